"""Content-keyed cache of named arrays on disk, read back memory-mapped; no physics here.

Each entry is a directory ``<cache dir>/<key>/`` holding one ``.npy`` file per array and a
``manifest.json`` (format, key, the caller's metadata, and for every array its file name,
dtype, shape, byte size and SHA-256).  Guarantees:

* **atomic**: an entry is written under a temporary name (``.<key>.tmp-PID-HOSTxxxx``) and
  published by one ``rename`` of the directory; a reader sees a complete entry or none.  Two
  writers of the same key are safe: the first rename wins, the second finds the entry there
  and discards its own copy.  Temporaries of dead writers are removed by the next writer.
* **never trusted silently**: :meth:`ArrayCache.load` checks every file's size and SHA-256
  against the manifest (a file is checksummed once per process while its inode, size and
  mtime stay the same); a missing, truncated or corrupt file, or an unreadable manifest,
  gives one :class:`TableCacheWarning`, the entry is removed and the caller rebuilds.  Files
  are not fsynced: the checksums catch what a crash leaves behind.
* **memory-mapped**: arrays come back from ``np.load(mmap_mode="r")`` (read-only); their
  pages are file-backed and leave resident memory when the arrays are dropped.
* **bounded**: after a store, least-recently-used entries are removed until the directory
  holds at most ``max_bytes`` (the entry just written is kept).
* **best effort**: a directory that cannot be created or written, or a full disk, gives one
  warning per directory and process; :meth:`ArrayCache.store` then returns False and the
  caller keeps its arrays in memory.

Arrays can be stored from memory or streamed (:class:`Chunks`: dtype, shape and an iterable of
C-order pieces), so an array that lives on an accelerator never needs a full host copy.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import threading
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slicersim import validation
from slicersim.io.atomic import _TMP_RE, _host_tag, _pid_alive, temporary_path

__all__ = ["ArrayCache", "Chunks", "TableCacheWarning", "cache_root", "default_directory", "CACHE_ENV",
           "DEFAULT_MAX_BYTES", "FORMAT"]

#: environment variable naming slicersim's cache root ("off", "none", "0" or "": no disk cache)
CACHE_ENV = "SLICERSIM_CACHE"
_OFF = {"off", "none", "0", "no", "false", "disable", "disabled"}
#: bytes an :class:`ArrayCache` directory may hold by default (least recently used entries go)
DEFAULT_MAX_BYTES = 8 * 2**30
#: manifest format version
FORMAT = 1
_MANIFEST = "manifest.json"
_READ_BLOCK = 1 << 22
_FREE_MARGIN = 64 << 20          # bytes left free on the disk beyond the entry
_ALIGN = 4096                    # .npy data offset (one page)
_NPY_MAGIC = b"\x93NUMPY\x01\x00"


class TableCacheWarning(RuntimeWarning):
    """A cache entry was corrupt (and rebuilt) or the cache directory cannot be used."""


@dataclass(frozen=True)
class Chunks:
    """An array given as C-order pieces (streamed to disk, never held whole)."""

    dtype: np.dtype
    shape: tuple
    pieces: object       # iterable of arrays whose concatenated ravel() is the array

    @property
    def nbytes(self):
        return int(np.prod(self.shape, dtype=np.int64)) * np.dtype(self.dtype).itemsize


def cache_root():
    """slicersim's cache root: ``$SLICERSIM_CACHE``, else ``$XDG_CACHE_HOME/slicersim``, else
    ``~/.cache/slicersim``; None when ``$SLICERSIM_CACHE`` is "off" / "none" / "0"."""
    env = os.environ.get(CACHE_ENV)
    if env is not None:
        env = env.strip()
        if env.lower() in _OFF or not env:
            return None
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME", "").strip()
    return (Path(xdg) if xdg else Path.home() / ".cache") / "slicersim"


def default_directory(name):
    """``cache_root() / name`` (None when the disk cache is off)."""
    root = cache_root()
    return None if root is None else root / name


# files checksummed by this process: path -> (inode, size, mtime_ns, sha256)
_VERIFIED: dict = {}
_VERIFIED_LOCK = threading.Lock()
_WARNED: set = set()


def _stat_key(st):
    return (st.st_ino, st.st_size, st.st_mtime_ns)


def _file_sha256(path):
    """SHA-256 of a file read in blocks (page cache only: nothing is mapped into the process)."""
    digest = hashlib.sha256()
    buf = bytearray(_READ_BLOCK)
    view = memoryview(buf)
    with open(path, "rb", buffering=0) as fh:
        while True:
            n = fh.readinto(buf)
            if not n:
                break
            digest.update(view[:n])
    return digest.hexdigest()


class _CorruptEntry(Exception):
    pass


class ArrayCache:
    """Named arrays on disk under content keys (see the module docstring).

    Parameters
    ----------
    directory : path of the cache directory (created on the first store)
    max_bytes : bound on the bytes of all entries (least recently used ones are removed)
    verify : check sizes and SHA-256 of every file on load (default True)
    """

    def __init__(self, directory, *, max_bytes=DEFAULT_MAX_BYTES, verify=True):
        if max_bytes is not None:
            max_bytes = validation.integer("max_bytes (table cache)", max_bytes, low=0)
        self.directory = Path(directory).expanduser().absolute()
        self.max_bytes = None if max_bytes is None else int(max_bytes)
        self.verify = bool(verify)

    def __repr__(self):
        return f"ArrayCache({str(self.directory)!r}, max_bytes={self.max_bytes})"

    def path(self, key):
        """Directory of entry ``key`` (hex digest: letters, digits, '-' and '_' only)."""
        key = str(key)
        if not key or not all(c.isalnum() or c in "-_" for c in key):
            raise ValueError(f"cache key must be hex/alphanumeric, got {key!r}")  # internal: keys are digests
        return self.directory / key

    # ------------------------------------------------------------------ read
    def load(self, key):
        """``(arrays, meta)`` of entry ``key`` (arrays read-only, memory-mapped), or None when
        absent.  A damaged entry is removed with one :class:`TableCacheWarning` (None)."""
        entry = self.path(key)
        try:
            with open(entry / _MANIFEST, "rb") as fh:
                raw = fh.read()
        except (FileNotFoundError, NotADirectoryError):
            return None
        except OSError as exc:
            self._warn_unusable(f"cannot read {entry / _MANIFEST}: {exc}")
            return None
        try:
            manifest = json.loads(raw.decode("utf-8"))
            try:
                arrays = self._open(entry, key, manifest)
            except FileNotFoundError as exc:
                if not (entry / _MANIFEST).exists():     # removed meanwhile by another process: a miss
                    return None
                raise _CorruptEntry(f"{exc.filename} is missing") from None
        except (_CorruptEntry, ValueError, KeyError, TypeError, OSError) as exc:
            warnings.warn(f"cache entry {entry} is damaged ({exc}); it is removed and rebuilt",
                          TableCacheWarning, stacklevel=3)
            self.remove(key)
            return None
        try:
            os.utime(entry / _MANIFEST)         # least-recently-used order
        except OSError:
            pass
        return arrays, manifest.get("meta", {})

    def _open(self, entry, key, manifest):
        if manifest.get("format") != FORMAT or manifest.get("key") != key:
            raise _CorruptEntry(f"manifest format {manifest.get('format')!r} / key do not match")
        arrays = {}
        for name, info in manifest["arrays"].items():
            path = entry / info["file"]
            st = os.stat(path)
            if st.st_size != info["file_bytes"]:
                raise _CorruptEntry(f"{info['file']} has {st.st_size} bytes, expected {info['file_bytes']}")
            if self.verify:
                with _VERIFIED_LOCK:
                    known = _VERIFIED.get(str(path))
                if known is None or known[:3] != _stat_key(st) or known[3] != info["sha256"]:
                    digest = _file_sha256(path)
                    if digest != info["sha256"]:
                        raise _CorruptEntry(f"{info['file']} checksum mismatch")
                    with _VERIFIED_LOCK:
                        _VERIFIED[str(path)] = _stat_key(st) + (digest,)
            shape = tuple(info["shape"])
            mode = "r" if int(np.prod(shape, dtype=np.int64)) > 0 else None
            arr = np.load(path, mmap_mode=mode, allow_pickle=False)
            if arr.dtype != np.dtype(info["dtype"]) or arr.shape != shape:
                raise _CorruptEntry(f"{info['file']} holds {arr.dtype}{arr.shape}, expected "
                                    f"{info['dtype']}{shape}")
            arrays[name] = arr
        return arrays

    # ------------------------------------------------------------------ write
    def store(self, key, arrays, meta=None):
        """Write entry ``key``: ``arrays`` {name: ndarray or :class:`Chunks`}, ``meta`` a
        JSON-able dict.  True when the entry is on disk (written here or by another writer),
        False (one warning per directory) when the directory cannot be used."""
        entry = self.path(key)
        for name in arrays:
            if not name.isidentifier():
                raise ValueError(f"array name {name!r} must be an identifier")  # internal: names set by the package
        nbytes = sum(int(a.nbytes) for a in arrays.values())
        tmp = None
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            free = shutil.disk_usage(self.directory).free
            if nbytes + _FREE_MARGIN > free:
                raise OSError(f"{nbytes / 2**20:.0f} MiB needed, {free / 2**20:.0f} MiB free")
            self._remove_stale()
            if (entry / _MANIFEST).exists():
                return True
            tmp = Path(temporary_path(entry))
            tmp.mkdir()
            files = {}
            for name, arr in arrays.items():
                files[name] = _write_npy(tmp / f"{name}.npy", arr)
            manifest = {"format": FORMAT, "key": str(key), "meta": meta or {}, "arrays": files}
            (tmp / _MANIFEST).write_text(json.dumps(manifest, indent=1), encoding="utf-8")
            try:
                os.rename(tmp, entry)
            except OSError:
                if (entry / _MANIFEST).exists():         # another writer won: keep theirs
                    pass
                elif entry.is_dir() and self.remove(key):     # a foreign, incomplete directory
                    os.rename(tmp, entry)
                else:
                    raise
            if not tmp.exists():
                tmp = None
                with _VERIFIED_LOCK:                     # written here: no need to read it back
                    for name, info in files.items():
                        st = os.stat(entry / info["file"])
                        _VERIFIED[str(entry / info["file"])] = _stat_key(st) + (info["sha256"],)
        except OSError as exc:
            self._warn_unusable(f"cannot write {entry}: {exc}")
            return False
        finally:
            if tmp is not None:
                shutil.rmtree(tmp, ignore_errors=True)
        self._evict(keep=entry.name)
        return True

    def _warn_unusable(self, why):
        tag = str(self.directory)
        if tag not in _WARNED:
            _WARNED.add(tag)
            warnings.warn(f"array cache {tag} is not usable ({why}); results are kept in memory",
                          TableCacheWarning, stacklevel=4)

    # ------------------------------------------------------------------ housekeeping
    def remove(self, key):
        """Remove entry ``key`` (renamed aside first, so readers never see half of it)."""
        entry = self.path(key)
        aside = Path(temporary_path(entry))
        try:
            os.rename(entry, aside)
        except OSError:
            return False
        shutil.rmtree(aside, ignore_errors=True)
        return True

    def entries(self):
        """``[(key, bytes, last use [s since epoch])]`` of the complete entries."""
        out = []
        try:
            names = os.listdir(self.directory)
        except OSError:
            return out
        for name in names:
            if name.startswith("."):
                continue
            try:
                st = os.stat(self.directory / name / _MANIFEST)
                size = sum(f.stat().st_size for f in (self.directory / name).iterdir())
            except OSError:
                continue
            out.append((name, size, st.st_mtime))
        return out

    def size(self):
        """Bytes held by the complete entries."""
        return sum(e[1] for e in self.entries())

    def clear(self):
        """Remove every entry."""
        for key, _, _ in self.entries():
            self.remove(key)

    def _evict(self, keep):
        if self.max_bytes is None:
            return
        entries = sorted(self.entries(), key=lambda e: e[2])
        total = sum(e[1] for e in entries)
        for key, size, _ in entries:
            if total <= self.max_bytes:
                break
            if key != keep and self.remove(key):
                total -= size

    def _remove_stale(self):
        """Remove temporaries of writers of this host that no longer run."""
        host = _host_tag()
        for name in os.listdir(self.directory):
            match = _TMP_RE.match(name)
            if (match is None or match["host"] != host or int(match["pid"]) == os.getpid()
                    or _pid_alive(int(match["pid"]))):
                continue
            shutil.rmtree(self.directory / name, ignore_errors=True)


def _write_npy(path, arr):
    """Write one ``.npy`` (format 1.0) from an array or :class:`Chunks`, hashing as it goes;
    returns its manifest record."""
    if isinstance(arr, Chunks):
        dtype, shape, pieces = np.dtype(arr.dtype), tuple(int(v) for v in arr.shape), arr.pieces
    else:
        arr = np.asarray(arr)
        dtype, shape = arr.dtype, arr.shape
        pieces = (np.ascontiguousarray(arr),)
    if dtype.hasobject:
        raise ValueError("object arrays cannot be cached")  # internal: the package caches numeric tables only
    header = _npy_header(dtype, shape)
    digest = hashlib.sha256(header)
    expected = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    written = 0
    with open(path, "wb") as fh:
        fh.write(header)
        for piece in pieces:
            piece = np.ascontiguousarray(piece, dtype=dtype)
            view = memoryview(piece).cast("B")
            digest.update(view)
            fh.write(view)
            written += len(view)
    if written != expected:
        raise ValueError(f"{path.name}: {written} bytes given, {expected} expected")  # internal: bad Chunks
    return {"file": path.name, "dtype": dtype.str, "shape": list(shape),
            "file_bytes": len(header) + written, "sha256": digest.hexdigest()}


def _npy_header(dtype, shape):
    """``.npy`` format 1.0 header padded to :data:`_ALIGN` bytes, so that the data of a mapped
    file starts on a page boundary (usable in place by devices that need aligned host memory)."""
    text = "{'descr': %r, 'fortran_order': False, 'shape': %r, }" % (np.lib.format.dtype_to_descr(dtype),
                                                                     tuple(shape))
    pad = -(len(_NPY_MAGIC) + 2 + len(text) + 1) % _ALIGN
    body = (text + " " * pad + "\n").encode("latin1")
    return _NPY_MAGIC + len(body).to_bytes(2, "little") + body
