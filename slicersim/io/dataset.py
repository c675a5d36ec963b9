"""Campaign dataset directories: layout, per-target records, checksums, a lock; no physics.

Layout::

    DIR/spec.toml             the spec exactly as given
    DIR/spec.json             the canonical spec (sorted JSON) and its sha256: the dataset's identity
    DIR/versions.json         software versions that made the dataset
    DIR/catalog.ecsv          one row per target (parameters, readout, seeds, products + sha256)
    DIR/products/tNNNNNN/     products of one target (HDF5 files, each written atomically)
    DIR/records/tNNNNNN.json  the target's record, written last: status "done" with every
                              product's file name, size and sha256, or "failed" with its error
    DIR/.lock                 held (flock) by the client running the campaign
    DIR/.timings/tNNNNNNN.json  the wall time of the target's task (hidden: not part of the content)

A target is *done* when its record says so and every product listed there exists with the
recorded size and sha256; anything else (no record, a missing, truncated or corrupted
product) is *missing* and is computed again.  Every file is written under a temporary name
and published complete (:mod:`slicersim.io.atomic`).

Nothing outside the directory is touched: ``products/``, ``records/`` and every
``products/tNNNNNNN/`` must be real directories inside it (a symbolic link, or anything but a
directory, is refused with :class:`DatasetError` naming it), the lock is opened without
following a link, and removing a target's or the dataset's files (a rerun, ``force``) removes
only files its records name or that have the dataset's own names (``tNNNNNNN.json``,
``products/tNNNNNNN/NAME.h5``) inside those verified directories.
"""
from __future__ import annotations

import fcntl
import hashlib
import json
import os
import re
import stat

from slicersim.errors import DatasetError
from slicersim.validation import short_repr
from slicersim.io.atomic import (AtomicH5File, atomic_bytes, is_temporary, one_line, remove_stale_temporaries,
                                 sha256_file)

__all__ = ["Dataset", "ProductFile", "canonical_json", "spec_digest", "target_key", "changed_keys", "real_dir",
           "not_a_dataset_directory"]

SPEC_TOML, SPEC_JSON, VERSIONS, CATALOG, LOCK = "spec.toml", "spec.json", "versions.json", "catalog.ecsv", ".lock"
PRODUCTS, RECORDS = "products", "records"
#: wall times of the targets' tasks (hidden: they vary from run to run, the dataset's content does not)
TIMINGS = ".timings"
#: names the dataset gives its own files and folders (nothing else is ever removed)
_TARGET_RE = re.compile(r"^t\d{7,}$")
_RECORD_RE = re.compile(r"^t\d{7,}\.json$")
_PRODUCT_RE = re.compile(r"^[a-z][a-z0-9_]*\.h5$")
_NOTHING = re.compile(r"(?!)")
_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)


def not_a_dataset_directory(path, hint=""):
    """The :class:`DatasetError` for a dataset path that is not a directory: missing, a file (a campaign
    spec, when it ends with .toml: ``hint`` says what to do with it), or a FIFO, device or socket."""
    if not os.path.lexists(path):
        return DatasetError(f"no such dataset directory: {path}")
    if os.path.isfile(path):
        spec = f" ({path} looks like a campaign spec{'; ' + hint if hint else ''})" \
            if path.lower().endswith(".toml") else ""
        return DatasetError(f"{path} is a file, not a dataset directory{spec}")
    return DatasetError(f"{path} is not a directory (a FIFO, device or socket), not a dataset directory")


def real_dir(path, make=False):
    """``path`` when it is a real directory (not a symbolic link); created (one level) when
    missing and ``make``; :class:`DatasetError` naming it otherwise."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        if not make:
            raise DatasetError(f"dataset folder {path} is missing") from None
        try:
            os.mkdir(path)
        except FileExistsError:
            pass
        except OSError as exc:
            raise DatasetError(f"cannot create the dataset folder {path}: {one_line(exc)}") from None
        st = os.lstat(path)
    if stat.S_ISLNK(st.st_mode):
        raise DatasetError(f"{path} is a symbolic link: a dataset's folders must be real folders inside it "
                           "(nothing outside the dataset is written or removed); replace the link by a folder")
    if not stat.S_ISDIR(st.st_mode):
        raise DatasetError(f"{path} is not a folder: a dataset's folders must be real folders inside it")
    return path


def _unlink_own(directory, pattern, names=(), follow=False):
    """Remove from the real directory ``directory`` the entries (regular files or links, never
    folders) whose names match ``pattern`` or are in ``names``, and dead writers' temporaries;
    returns the names removed.  The directory is opened without following a link (unless
    ``follow``: the dataset's own root may be a link)."""
    fd = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) | (0 if follow else _NOFOLLOW))
    removed = []
    try:
        for name in os.listdir(fd):
            if not (pattern.match(name) or name in names):
                continue
            st = os.lstat(name, dir_fd=fd)
            if stat.S_ISREG(st.st_mode) or stat.S_ISLNK(st.st_mode):
                os.unlink(name, dir_fd=fd)
                removed.append(name)
    finally:
        os.close(fd)
    remove_stale_temporaries(directory)
    return removed


def canonical_json(obj):
    """Canonical JSON text (sorted keys, no spaces variation) of a JSON-able object."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)


def spec_digest(spec_dict):
    """sha256 of the canonical JSON of a spec."""
    return hashlib.sha256(canonical_json(spec_dict).encode()).hexdigest()


def target_key(target_id):
    """Directory / record name of a target: ``t`` + zero-padded id."""
    return f"t{int(target_id):07d}"


class ProductFile(AtomicH5File):
    """One HDF5 product file written atomically (datasets via :meth:`write`).

    Not fsynced: the target's record (written durably, last) holds the product's size and
    sha256, which every resume verifies, so a product an OS crash lost or tore is found
    and computed again, like one a ``kill -9`` interrupted."""

    durable = False


class Dataset:
    """A campaign dataset directory (see the module docstring)."""

    def __init__(self, path):
        self.path = os.path.abspath(os.fspath(path))
        self._lock_fd = None

    # ------------------------------------------------------------------ paths
    def file(self, name):
        return os.path.join(self.path, name)

    def product_dir(self, target_id):
        return os.path.join(self.path, PRODUCTS, target_key(target_id))

    def target_dir(self, target_id, make=False):
        """The target's products folder, checked to be a real folder inside the dataset (as are
        ``products/``); created when missing and ``make``."""
        real_dir(self.file(PRODUCTS), make=make)
        return real_dir(self.product_dir(target_id), make=make)

    def check_folders(self, make=False):
        """Refuse (:class:`DatasetError` naming it) a ``products/``, ``records/`` or
        ``products/tNNNNNNN`` that is a symbolic link or not a folder; ``make`` creates the two
        top folders (and the dataset's own) when missing."""
        if make:
            os.makedirs(self.path, exist_ok=True)
        real_dir(self.file(PRODUCTS), make=make)
        self.records_dir(make=make)
        for name in sorted(os.listdir(self.file(PRODUCTS))):
            if _TARGET_RE.match(name):
                real_dir(os.path.join(self.file(PRODUCTS), name))

    def records_dir(self, make=False):
        """``records/``, checked to be a real folder inside the dataset."""
        return real_dir(self.file(RECORDS), make=make)

    def record_path(self, target_id):
        return os.path.join(self.path, RECORDS, target_key(target_id) + ".json")

    @property
    def exists(self):
        return os.path.isfile(self.file(SPEC_JSON))

    # ------------------------------------------------------------------ creation
    @staticmethod
    def check_path(path, force=False):
        """Refuse an output path that is a file, or whose parent does not exist or is read-only;
        a directory that is not a dataset is refused, a damaged one (records or products but
        no spec.json) only without ``force``."""
        try:
            path = os.path.abspath(os.fspath(path))
        except TypeError:
            raise DatasetError(f"the dataset directory must be a path (str or os.PathLike), got "
                               f"{short_repr(path)}") from None
        if os.path.exists(path) and not os.path.isdir(path):
            raise DatasetError(f"output path is a file, not a dataset directory: {path}")
        parent = os.path.dirname(path)
        if not os.path.isdir(parent):
            raise DatasetError(f"parent directory does not exist: {parent}")
        if os.path.isdir(path):
            if not os.access(path, os.W_OK):
                raise DatasetError(f"dataset directory is not writable: {path}")
            holder = _lock_holder(os.path.join(path, LOCK))
            if holder is not None:                  # another run is creating or running it: not damaged
                raise DatasetError(f"{path} is in use by another process ({holder or 'a slicersim run'}): "
                                   "wait for it or stop it")
            if os.listdir(path) and not os.path.isfile(os.path.join(path, SPEC_JSON)):
                names = [n for n in os.listdir(path) if n != LOCK]
                damaged = set(names) <= {SPEC_TOML, VERSIONS, CATALOG, PRODUCTS, RECORDS} and \
                    bool(set(names) & {SPEC_TOML, PRODUCTS, RECORDS}) and _only_own(path)
                if damaged and not force:
                    raise DatasetError(f"{path} is a damaged slicersim dataset ({SPEC_JSON} is missing); "
                                       "--force discards its products and starts it again")
                if names and not damaged:
                    raise DatasetError(f"{path} exists and is not a slicersim dataset (no {SPEC_JSON}); "
                                       "choose a new or empty directory")
        elif not os.access(parent, os.W_OK):
            raise DatasetError(f"directory is not writable: {parent}")
        return path

    def create(self):
        """Create the dataset folder if it does not exist; True when this call created it (an atomic
        ``mkdir``: of two runs started on one new folder exactly one gets True, and only that one may
        remove it again, :meth:`remove_new`)."""
        try:
            os.mkdir(self.path)
            return True
        except FileExistsError:
            return False
        except OSError as exc:
            raise DatasetError(f"cannot create the dataset folder {self.path}: {one_line(exc)}") from None

    def remove_new(self):
        """Remove a dataset folder this run created (:meth:`create`) when it failed before any target was
        recorded (a failed run leaves nothing new behind): only the dataset's own files and empty folders,
        and only under the dataset's lock — a folder another run holds, or has filled, is left as it is."""
        if self._lock_fd is None:
            try:
                self.lock()
            except DatasetError:                     # in use by another run: it is theirs now
                return
        try:
            self._remove_own_empty()
        finally:
            self.unlock()

    def _remove_own_empty(self):
        try:
            for sub in (RECORDS, PRODUCTS):
                path = self.file(sub)
                if os.path.lexists(path):
                    real_dir(path)
                    os.rmdir(path)                   # only when empty: nothing computed
            _unlink_own(self.path, _NOTHING, (SPEC_TOML, SPEC_JSON, VERSIONS, CATALOG, LOCK), follow=True)
            os.rmdir(self.path)
        except (OSError, DatasetError):
            pass

    def stored_spec(self):
        """(canonical spec dict, digest) stored in the dataset, or None."""
        try:
            with open(self.file(SPEC_JSON), encoding="utf-8") as fh:
                doc = json.load(fh)
            return doc["spec"], doc["sha256"]
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError) as exc:
            raise DatasetError(f"{self.file(SPEC_JSON)} is unreadable ({one_line(exc)}): the directory is "
                               "not a valid dataset; use --force to start it again") from exc

    def check_spec(self, spec_dict, force=False):
        """Refuse (:class:`DatasetError`) a dataset made from another spec unless ``force``;
        writes nothing.  Returns the spec's digest."""
        digest = spec_digest(spec_dict)
        stored = self.stored_spec()
        if stored is not None and stored[1] != digest and not force:
            changed = sorted(changed_keys(stored[0], spec_dict))
            raise DatasetError(f"{self.path} was made from a different spec (changed: "
                               f"{', '.join(changed[:6]) or 'content'}); use a new directory, or "
                               "--force to discard its products and start again")
        return digest

    def initialise(self, spec_text, spec_dict, versions, force=False):
        """Create the dataset or check that it was made from the same spec.

        A different spec is refused (:class:`DatasetError`) unless ``force``, which deletes
        the old records and products before writing the new spec."""
        digest = self.check_spec(spec_dict, force)
        stored = self.stored_spec()
        if (stored is not None and stored[1] != digest) or (stored is None and force):
            self.discard()
        self.check_folders(make=True)
        for directory in (self.path, self.file(RECORDS)):   # left by a killed client or worker
            remove_stale_temporaries(directory)
        if stored is None or stored[1] != digest:
            atomic_bytes(self.file(SPEC_TOML), spec_text.encode(), overwrite=True)
            atomic_bytes(self.file(VERSIONS), (json.dumps(versions, indent=1, sort_keys=True) + "\n").encode(),
                         overwrite=True)
            doc = {"sha256": digest, "spec": spec_dict}
            atomic_bytes(self.file(SPEC_JSON), (json.dumps(doc, indent=1, sort_keys=True) + "\n").encode(),
                         overwrite=True)
        else:
            self._compare_versions(versions)
        return digest

    def _compare_versions(self, versions):
        """Warn when a dataset is resumed with other software versions (products may differ)."""
        import warnings
        try:
            with open(self.file(VERSIONS), encoding="utf-8") as fh:
                old = json.load(fh)
        except (OSError, ValueError):
            return
        changed = sorted(k for k in set(old) | set(versions) if old.get(k) != versions.get(k))
        if changed:
            warnings.warn(f"{self.path} was started with other software versions ("
                          + ", ".join(f"{k} {old.get(k)} → {versions.get(k)}" for k in changed[:5])
                          + "): products computed now may differ bit for bit from the earlier ones",
                          stacklevel=3)

    def discard(self):
        """Remove the dataset's own records, products, catalog and spec (``--force``): the files
        its records name and the files with its own names inside its verified folders; anything
        else (an unrelated file or folder in ``products/``) stays."""
        for name in (RECORDS, PRODUCTS):
            if os.path.lexists(self.file(name)):
                real_dir(self.file(name))          # a link: refused, its target untouched
        if os.path.isdir(self.file(PRODUCTS)):
            for name in os.listdir(self.file(PRODUCTS)):
                if _TARGET_RE.match(name):
                    self.clean_target(int(name[1:]))
        for name in (RECORDS, TIMINGS):
            if os.path.isdir(self.file(name)) and not os.path.islink(self.file(name)):
                _unlink_own(self.file(name), _RECORD_RE)
        for name in (RECORDS, PRODUCTS, TIMINGS):
            try:
                os.rmdir(self.file(name))          # only when nothing else is left in it
            except OSError:
                pass
        _unlink_own(self.path, _NOTHING, (CATALOG, SPEC_JSON, SPEC_TOML, VERSIONS), follow=True)

    # ------------------------------------------------------------------ lock
    def lock(self):
        """Hold the dataset's lock (one running client per dataset); released on exit or death."""
        os.makedirs(self.path, exist_ok=True)
        try:                                        # never through a link: the lock is truncated
            fd = os.open(self.file(LOCK), os.O_RDWR | os.O_CREAT | _NOFOLLOW | getattr(os, "O_CLOEXEC", 0), 0o666)
        except OSError as exc:
            raise DatasetError(f"cannot open the dataset lock {self.file(LOCK)} ({one_line(exc)}; a symbolic "
                               "link is refused)") from None
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            os.close(fd)
            raise DatasetError(f"the dataset lock {self.file(LOCK)} is not a regular file")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                holder = os.pread(fd, 64, 0).decode(errors="replace").strip()
            finally:
                os.close(fd)
            raise DatasetError(f"dataset {self.path} is in use by another slicersim campaign "
                               f"({holder or 'unknown process'}); wait for it or stop it") from None
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"pid {os.getpid()} on {os.uname().nodename}\n".encode(), 0)
        except OSError as exc:                      # a full disk: name the file, not only errno 28
            os.close(fd)
            raise DatasetError(f"cannot write the dataset lock {self.file(LOCK)} ({one_line(exc)})") from None
        self._lock_fd = fd
        return self

    def unlock(self):
        if self._lock_fd is not None:
            try:
                os.ftruncate(self._lock_fd, 0)
            except OSError:
                pass
            os.close(self._lock_fd)          # closing releases the flock
            self._lock_fd = None

    def __enter__(self):
        return self.lock()

    def __exit__(self, *exc):
        self.unlock()
        return False

    # ------------------------------------------------------------------ records
    def write_record(self, target_id, record):
        """Write the target's record atomically into the verified ``records/``."""
        self.records_dir()
        atomic_bytes(self.record_path(target_id),
                     (json.dumps(record, indent=1, sort_keys=True) + "\n").encode(), overwrite=True)

    def write_timing(self, target_id, seconds):
        """Record the wall time [s] a target's task took in ``.timings/tNNNNNNN.json`` (outside the
        dataset's content: hidden, never checksummed; a failure to write it is ignored)."""
        try:
            directory = real_dir(self.file(TIMINGS), make=True)
            atomic_bytes(os.path.join(directory, target_key(target_id) + ".json"),
                         json.dumps({"target_id": int(target_id), "seconds": float(seconds)}).encode(), overwrite=True)
        except (OSError, DatasetError):
            pass

    def read_timing(self, target_id):
        """The wall time [s] recorded by :meth:`write_timing`, or NaN."""
        try:
            with open(os.path.join(self.file(TIMINGS), target_key(target_id) + ".json"), encoding="utf-8") as fh:
                return float(json.load(fh)["seconds"])
        except (OSError, ValueError, KeyError, TypeError):
            return float("nan")

    def read_record(self, target_id):
        """The target's record, or None when absent or unreadable (a torn file counts as absent)."""
        try:
            with open(self.record_path(target_id), encoding="utf-8") as fh:
                rec = json.load(fh)
        except (OSError, ValueError):
            return None
        return rec if isinstance(rec, dict) and rec.get("target_id") == int(target_id) else None

    def verify(self, record, deep=True):
        """'' when every product of a done record is intact, else the reason it is not."""
        products = record.get("products")
        if not isinstance(products, dict) or not all(
                isinstance(i, dict) and isinstance(i.get("file"), str) and isinstance(i.get("bytes"), int)
                and isinstance(i.get("sha256"), str) and os.path.basename(i["file"]) == i["file"]
                for i in products.values()):
            return "malformed record (products)"
        for name, info in sorted(products.items()):
            path = os.path.join(self.product_dir(record["target_id"]), info["file"])
            try:
                self.target_dir(record["target_id"])
                st = os.lstat(path)
            except (OSError, DatasetError):
                return f"{name}: missing"
            if not stat.S_ISREG(st.st_mode):
                return f"{name}: not a regular file"
            size = st.st_size
            if size != info["bytes"]:
                return f"{name}: {size} bytes, expected {info['bytes']} (truncated?)"
            if deep and sha256_file(path) != info["sha256"]:
                return f"{name}: checksum mismatch (corrupted)"
        return ""

    def state(self, target_ids, deep=True):
        """{target_id: ("done" | "failed" | "missing", record or None, reason)}."""
        out = {}
        if os.path.lexists(self.file(RECORDS)):
            self.records_dir()                    # a link: refused, never read
        for tid in target_ids:
            tid = int(tid)
            rec = self.read_record(tid)
            if rec is None:
                out[tid] = ("missing", None, "no record")
            elif rec.get("status") == "failed":
                out[tid] = ("failed", rec, rec.get("error", ""))
            elif rec.get("status") == "done":
                why = self.verify(rec, deep)
                out[tid] = ("done", rec, "") if not why else ("missing", rec, why)
            else:
                out[tid] = ("missing", rec, f"unknown status {rec.get('status')!r}")
        return out

    def clean_target(self, target_id):
        """Remove a target's record and products before it is computed again: the files its
        record names and those with the dataset's own product names (``NAME.h5``, temporaries),
        in its verified folder; a link there is refused (:class:`DatasetError`), its target
        untouched."""
        rec = self.read_record(target_id) if os.path.isdir(self.file(RECORDS)) else None
        if os.path.lexists(self.file(RECORDS)):
            self.records_dir()
            try:
                os.remove(self.record_path(target_id))
            except FileNotFoundError:
                pass
        pdir = self.product_dir(target_id)
        if not os.path.lexists(pdir):
            return
        self.target_dir(target_id)
        named = [i.get("file") for i in ((rec or {}).get("products") or {}).values() if isinstance(i, dict)]
        _unlink_own(pdir, _PRODUCT_RE, {n for n in named if isinstance(n, str) and os.path.basename(n) == n})
        try:
            os.rmdir(pdir)                          # recreated by the writer; kept when not empty
        except OSError:
            pass

    def write_catalog(self, table):
        """Write ``catalog.ecsv`` atomically (astropy Table)."""
        import io
        buf = io.StringIO()
        table.write(buf, format="ascii.ecsv")
        atomic_bytes(self.file(CATALOG), buf.getvalue().encode(), overwrite=True)


def _lock_holder(path):
    """The text a running client wrote into the lock file ``path`` while it holds the lock ("" when it wrote
    nothing yet); None when the lock is free, absent or not a regular file."""
    try:
        fd = os.open(path, os.O_RDONLY | _NOFOLLOW | getattr(os, "O_CLOEXEC", 0))
    except OSError:
        return None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return None
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return os.pread(fd, 64, 0).decode(errors="replace").strip()
        return None
    finally:
        os.close(fd)


def _only_own(path):
    """True when ``products/`` and ``records/`` of ``path`` (where present, real folders) hold only
    the dataset's own names: a folder holding an unrelated ``products/`` is not a damaged dataset."""
    for sub, pattern in ((PRODUCTS, _TARGET_RE), (RECORDS, _RECORD_RE)):
        full = os.path.join(path, sub)
        if not os.path.lexists(full):
            continue
        if os.path.islink(full) or not os.path.isdir(full):
            return False
        if any(not (pattern.match(n) or is_temporary(n)) for n in os.listdir(full)):
            return False
    return True


def product_info(path):
    """{file, bytes, sha256} of a written product."""
    return {"file": os.path.basename(path), "bytes": os.path.getsize(path), "sha256": sha256_file(path)}


def changed_keys(old, new, prefix=""):
    """Dotted keys whose values differ between two nested dicts."""
    keys = set(old) | set(new) if isinstance(old, dict) and isinstance(new, dict) else set()
    if not keys:
        return {prefix or "spec"} if old != new else set()
    out = set()
    for key in keys:
        name = f"{prefix}.{key}" if prefix else str(key)
        if key not in old or key not in new:
            out.add(name)
        elif old[key] != new[key]:
            out |= changed_keys(old[key], new[key], name)
    return out
