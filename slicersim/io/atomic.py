"""Atomic files: written under a temporary name in the target directory, published
under the final name only when complete; no physics here.

Temporaries are ``.NAME.tmp-PID-HOSTxxxx``; an interrupted writer leaves no file with the
final name, and its temporary is removed by the next writer in that directory
(:func:`remove_stale_temporaries`, only for dead processes of this host).  HDF5 files are
written through :class:`GuardedFile` so that a full disk gives one clear error instead of a
crash inside HDF5.
"""
from __future__ import annotations

import errno
import hashlib
import os
import re
import shutil
import secrets
import signal
import threading

import numpy as np

from slicersim.errors import DatasetError
from slicersim.io.output_paths import check_output_path, output_path, refuse_special

__all__ = ["AtomicH5File", "flush_chunks", "GuardedFile", "is_temporary", "remove_stale_temporaries", "atomic_bytes",
           "publish", "sha256_file", "one_line", "check_output_path", "output_path",
           "refuse_special"]

#: HDF5 file-format versions of every file written here: the 1.8 format (readable by HDF5 ≥ 1.8) with
#: version-2 object headers, which carry a checksum of their metadata — attributes (GAIN, READNOISE, CONFIG,
#: truth parameters), dataset layouts and filters — verified by HDF5 on every read: one flipped bit in an
#: attribute is a read error, not a silently different gain (the data chunks carry Fletcher-32)
HDF5_LIBVER = ("v108", "v108")

#: temporaries are ``.<final name>.tmp-<pid>-<host tag><random>`` (the host tag keeps a writer from
#: removing the temporary of a live process on another machine sharing the directory)
_TMP_TAG = ".tmp-"
_TMP_RE = re.compile(r"^\.(?P<final>.+)\.tmp-(?P<pid>\d+)-(?P<host>[0-9a-f]{6})[0-9a-f]+$")


def _host_tag():
    import socket
    return hashlib.sha1(socket.gethostname().encode("utf-8", "replace")).hexdigest()[:6]
#: bytes of HDF5 metadata allowed for beyond the raw data when checking free space
_HDF5_MARGIN = 1 << 20


def is_temporary(path):
    """True when ``path`` names a writer's temporary (``.NAME.tmp-PID-xxxx``)."""
    return _TMP_RE.match(os.path.basename(os.fspath(path))) is not None


def _pid_alive(pid):
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:          # exists, owned by someone else
        return True
    return True


def remove_stale_temporaries(directory, final=None, folders=False):
    """Remove temporaries left in ``directory`` by writers that no longer run; returns their paths.

    Parameters
    ----------
    directory : str or path-like
        The folder searched (not recursively).
    final : str, optional
        Only the temporaries of this final name (None: every one).
    folders : bool, optional
        Also remove temporary folders (a writer that builds a folder and renames it), never following
        a link; files only by default.

    Returns
    -------
    list of str
        The paths removed.
    """
    removed, host = [], _host_tag()
    try:
        names = os.listdir(directory)
    except OSError:
        return removed
    for name in names:
        match = _TMP_RE.match(name)
        if (match is None or match["host"] != host or int(match["pid"]) == os.getpid()
                or (final is not None and match["final"] != final) or _pid_alive(int(match["pid"]))):
            continue
        path = os.path.join(directory, name)
        try:
            if folders and os.path.isdir(path) and not os.path.islink(path):
                shutil.rmtree(path)
            else:
                os.remove(path)
            removed.append(path)
        except OSError:
            pass
    return removed


def one_line(exc):
    """Short one-line text of an OSError (HDF5 messages span lines), with the file it names."""
    if isinstance(exc, OSError) and exc.strerror:
        text = f"[Errno {exc.errno}] {exc.strerror}" if exc.errno else exc.strerror
        return f"{text}: {exc.filename}" if exc.filename is not None else text
    return " ".join(str(exc).split())


class GuardedFile:
    """File object for h5py's ``fileobj`` driver that never reports a failed write to HDF5.

    HDF5 (2.0, via h5py 3.16) leaves its objects in a state that crashes the process (SIGSEGV)
    when a write fails while it flushes or closes a file, e.g. on a full disk.  This object
    records the first OSError instead, keeps later writes in memory (so HDF5 reads back what it
    believes it wrote) and lets HDF5 close cleanly; :class:`RampWriter` then raises the recorded
    error and removes the temporary.
    """

    _OVERLAY_MAX = 64 << 20

    def __init__(self, fd):
        self.fd, self.pos, self.size = fd, 0, 0
        self.error = None
        self._overlay, self._overlay_bytes = [], 0

    def _fail(self, exc):
        if self.error is None:
            self.error = exc

    # io protocol used by h5py ----------------------------------------------------------
    def seek(self, offset, whence=0):
        self.pos = offset if whence == 0 else (self.pos + offset if whence == 1 else self.size + offset)
        return self.pos

    def tell(self):
        return self.pos

    def write(self, buf):
        view = memoryview(buf).cast("B")
        n = len(view)
        if self.error is None:
            try:
                done = 0
                while done < n:
                    done += os.pwrite(self.fd, view[done:], self.pos + done)
            except OSError as exc:
                self._fail(exc)
        if self.error is not None and (self._overlay_bytes < self._OVERLAY_MAX or n <= 65536):
            self._overlay.append((self.pos, bytes(view)))
            self._overlay_bytes += n
        self.pos += n
        self.size = max(self.size, self.pos)
        return n

    def readinto(self, buf):
        view = memoryview(buf).cast("B")
        n = len(view)
        try:
            data = os.pread(self.fd, n, self.pos)
        except OSError as exc:
            self._fail(exc)
            data = b""
        got = len(data)
        view[:got] = data
        for off, chunk in self._overlay:
            lo, hi = max(off, self.pos), min(off + len(chunk), self.pos + n)
            if lo < hi:
                if lo - self.pos > got:
                    view[got:lo - self.pos] = bytes(lo - self.pos - got)
                view[lo - self.pos:hi - self.pos] = chunk[lo - off:hi - off]
                got = max(got, hi - self.pos)
        self.pos += got
        return got

    def read(self, n=-1):
        n = max(0, self.size - self.pos) if n is None or n < 0 else n
        buf = bytearray(n)
        return bytes(buf[:self.readinto(buf)])

    def truncate(self, size=None):
        size = self.pos if size is None else int(size)
        if self.error is None:
            try:
                os.ftruncate(self.fd, size)
            except OSError as exc:
                self._fail(exc)
        self.size = size
        return size

    def flush(self):
        pass

    def readable(self):
        return True

    def writable(self):
        return True

    def seekable(self):
        return True



def publish(tmp, path, overwrite=False, error_class=DatasetError):
    """Give the complete temporary ``tmp`` its final name ``path``: replaced when ``overwrite``,
    else a hard link that fails if ``path`` appeared meanwhile (two writers: one wins).  Only a
    regular file (or a link to one) is ever replaced (:func:`refuse_special`)."""
    if overwrite:
        refuse_special(path, error_class)
        os.replace(tmp, path)
        return
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise error_class(f"output file exists: {path} (another writer finished first; "
                          "pass overwrite=True / --overwrite to replace it)") from None
    except OSError as exc:             # no hard links here (FAT, some network file systems)
        if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK,
                             errno.ENOSYS):
            raise
        if os.path.lexists(path):
            raise error_class(f"output file exists: {path} (pass overwrite=True / --overwrite "
                              "to replace it)") from None
        os.rename(tmp, path)
        return
    os.remove(tmp)


def temporary_path(path):
    """A new temporary name for ``path`` in its directory (not created)."""
    directory, base = os.path.split(os.path.abspath(os.fspath(path)))
    return os.path.join(directory, f".{base}{_TMP_TAG}{os.getpid()}-{_host_tag()}{secrets.token_hex(4)}")


def atomic_bytes(path, data, overwrite=False, error_class=DatasetError):
    """Write ``data`` (bytes) to ``path`` atomically (temporary, fsync, publish); ``path`` must
    be a file path (:func:`output_path`), an existing one a regular file (:func:`refuse_special`)."""
    path = output_path(path, error_class)
    refuse_special(path, error_class)
    tmp = temporary_path(path)
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666)
        try:
            view, done = memoryview(data), 0
            while done < len(view):
                done += os.write(fd, view[done:])
            os.fsync(fd)
        finally:
            os.close(fd)
        publish(tmp, path, overwrite, error_class)
    except OSError as exc:
        raise error_class(f"cannot write {path}: {one_line(exc)}") from exc
    finally:
        if os.path.lexists(tmp):
            os.remove(tmp)


def sha256_file(path, block=1 << 22):
    """Hex SHA-256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(block), b""):
            digest.update(chunk)
    return digest.hexdigest()


def flush_chunks(dset):
    """Write ``dset``'s cached chunks to the file now (H5Dflush), so that where they land does
    not depend on when the last handle to it is closed: a Dask worker's profiler, a traceback
    or a debugger holding a frame would otherwise move them, and the same data would give a
    file with different bytes."""
    if dset.chunks is not None:
        dset.flush()


class AtomicH5File:
    """Write one HDF5 file atomically (context manager yielding itself; ``.file`` is the h5py File).

    Subclasses create their datasets in :meth:`_populate`.  The file is published (hard link,
    so an existing file is never replaced unless ``overwrite``) only when the ``with`` block
    ends without error; any error, SIGINT or exception removes the temporary.  SIGINT while
    HDF5 runs is held back until HDF5 returns.  Errors are raised as ``error_class``.
    """

    error_class = DatasetError
    #: attributes holding h5py datasets, dropped when the file closes
    _dataset_names = ()
    #: fsync the file before publishing it (durable against an OS crash); a subclass whose
    #: files are checksummed elsewhere (campaign products) may skip it
    durable = True

    def __init__(self, path, overwrite=False):
        self.path = output_path(path, self.error_class)
        self.overwrite = bool(overwrite)
        self._file = self._fh = self._fd = self._tmp = None
        self._busy = 0
        self._busy_lock = threading.Lock()     # _h5 runs in background writer threads too
        self._pending_signal = self._old_handler = None

    @property
    def file(self):
        return self._file

    def check(self):
        """Refuse early (:func:`check_output_path`): missing or read-only directory, a directory,
        FIFO, device or socket at ``path`` (or a link to one), an existing file without ``overwrite``."""
        check_output_path(self.path, self.overwrite, self.error_class)
        return self

    def _populate(self, file):
        """Create the datasets (subclasses)."""

    def write(self, name, data, attrs=None, **options):
        """Create dataset ``name`` holding ``data`` (h5py ``create_dataset`` options), with ``attrs``.
        Non-empty numeric arrays get a Fletcher-32 checksum per chunk (verified by HDF5 on read)."""
        arr = np.asarray(data) if not isinstance(data, (str, bytes)) else None
        if arr is not None and arr.ndim > 0 and arr.size > 0 and arr.dtype.kind in "biuf":
            options.setdefault("fletcher32", True)

        def put():
            dset = self._file.create_dataset(name, data=data, **options)
            for key, val in (attrs or {}).items():
                dset.attrs[key] = val
            flush_chunks(dset)
        self._h5(put)

    def set_attrs(self, attrs):
        """Root attributes (scalars, strings or arrays)."""
        self._h5(lambda: self._file.attrs.update(attrs))

    def __enter__(self):
        self.check()
        directory = os.path.dirname(self.path) or "."
        remove_stale_temporaries(directory)
        self._install_signal_handler()
        self._busy += 1
        try:
            self._create(directory)
        except BaseException:
            self._busy -= 1
            self._abort()
            self._restore_signal_handler()
            self._pending_signal = None
            raise
        self._busy -= 1
        if self._pending_signal is not None:           # SIGINT while creating: abort now
            self._abort()
            self._restore_signal_handler(deliver=True)
        return self

    def _create(self, directory):
        import h5py
        for _ in range(100):
            tmp = temporary_path(self.path)
            try:
                self._fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0),
                                   0o666)        # the umask applies, as for any new file
            except FileExistsError:
                continue
            except OSError as exc:
                raise self.error_class(f"cannot create {self.path}: {one_line(exc)}") from exc
            self._tmp = tmp
            break
        else:  # pragma: no cover
            raise self.error_class(f"cannot create a temporary file in {directory}")
        try:
            self._fh = GuardedFile(self._fd)
            self._file = h5py.File(self._fh, "w", libver=HDF5_LIBVER)
            self._populate(self._file)
        except Exception as exc:
            raise self.error_class(f"cannot create {self.path}: {one_line(exc)}") from exc
        self._raise_io_error("cannot create")

    def __exit__(self, exc_type, exc, tb):
        self._busy += 1                      # SIGINT from here on is delivered after the cleanup
        try:
            if exc_type is not None or self._pending_signal is not None:
                self._abort()
                return False
            try:
                self._file.attrs["COMPLETE"] = True
                self._close_file()
                self._raise_io_error("cannot finish")
                if self.durable:
                    os.fsync(self._fd)
                os.close(self._fd)
                self._fd = None
                if self._pending_signal is not None:
                    self._abort()
                    return False
                self._publish()
            except BaseException as err:
                self._abort()
                if isinstance(err, self.error_class):
                    raise
                if isinstance(err, Exception):
                    raise self.error_class(f"cannot finish {self.path}: {one_line(err)}") from err
                raise
            return False
        finally:
            self._busy -= 1
            self._restore_signal_handler(deliver=exc_type is None or not issubclass(exc_type, KeyboardInterrupt))

    def _publish(self):
        """Give the complete temporary its final name (never replacing a file unless overwrite)."""
        tmp, self._tmp = self._tmp, None
        try:
            publish(tmp, self.path, self.overwrite, self.error_class)
        except BaseException:
            self._tmp = tmp
            raise

    def _close_file(self):
        file, self._file = self._file, None
        for name in self._dataset_names:        # h5py objects must not outlive the file
            self.__dict__.pop(name, None)
        if file is not None:
            file.close()

    def _abort(self):
        try:
            self._close_file()
        except Exception:
            pass
        if self._fd is not None:
            try:
                os.close(self._fd)
            except OSError:
                pass
            self._fd = None
        if self._tmp is not None:
            try:
                os.remove(self._tmp)
            except FileNotFoundError:
                pass
            self._tmp = None

    def _raise_io_error(self, what):
        if self._fh is not None and self._fh.error is not None:
            raise self.error_class(f"{what} {self.path}: {one_line(self._fh.error)}") from self._fh.error

    # ------------------------------------------------------------------ SIGINT
    def _install_signal_handler(self):
        """SIGINT while HDF5 runs is held back until HDF5 returns (an exception raised inside
        HDF5's I/O callbacks could leave it in a crashing state); elsewhere it is immediate."""
        if threading.current_thread() is not threading.main_thread():
            return
        try:
            old = signal.getsignal(signal.SIGINT)
        except (ValueError, AttributeError):  # pragma: no cover
            return
        if not callable(old):                # SIG_IGN / SIG_DFL / not set from Python
            return

        def handler(signum, frame):
            if self._busy:
                self._pending_signal = (signum, frame)
            else:
                old(signum, frame)
        self._old_handler = old
        signal.signal(signal.SIGINT, handler)

    def _restore_signal_handler(self, deliver=False):
        """Put the previous SIGINT handler back and (``deliver``) call it for a held-back SIGINT."""
        old, self._old_handler = self._old_handler, None
        pending, self._pending_signal = self._pending_signal, None
        if old is not None:
            signal.signal(signal.SIGINT, old)
        if deliver and pending is not None:
            (old or signal.default_int_handler)(*pending)

    def _deliver_pending(self):
        """Act on a SIGINT held back while HDF5 ran (between blocks: the caller aborts the file)."""
        pending, self._pending_signal = self._pending_signal, None
        if pending is not None:
            (self._old_handler or signal.default_int_handler)(*pending)

    def _h5(self, func, *args):
        """``func(*args)`` with SIGINT held back; callable from several threads at once (the count
        of running HDF5 calls is updated under a lock; a held-back SIGINT is delivered when the
        last of them returns, as KeyboardInterrupt in that thread)."""
        with self._busy_lock:
            self._busy += 1
        try:
            func(*args)
        except OSError as exc:
            raise self.error_class(f"writing {self.path} failed: {one_line(exc)}") from exc
        finally:
            with self._busy_lock:
                self._busy -= 1
                idle = self._busy == 0
        self._raise_io_error("cannot write")
        if idle:
            self._deliver_pending()
