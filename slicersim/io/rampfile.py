"""Group-level raw-ramp files (HDF5), written in row blocks; no physics here.

Layout (one file per exposure)::

    /SCI            uint16  (nramps, ngroups, ny, nx)   group-averaged reads [ADU]
    /GROUPDQ        uint8   (nramps, ngroups, ny, nx)   JWST group flags (2 = SATURATED)
    /PIXELDQ        uint32  (ny, nx)                    JWST pixel flags (1 DO_NOT_USE, 1024 DEAD, 2048 HOT)
    /truth/rate     float32 (ny, nx)   optional         input rate [e-/s]
    root attributes NINTS NGROUPS NFRAMES GROUPGAP TFRAME TGROUP READPATT GAIN READNOISE
                    SEED BUNIT SOFTWARE VERSION CONFIG (JSON) COMPLETE

SCI and GROUPDQ are chunked one group × a row block.  The file is written
under a temporary name ``.NAME.tmp-PID-xxxx`` in the target directory and
linked to ``NAME`` only when complete (never replacing an existing file
unless asked); an interrupted writer leaves no file with the final name, and
its temporary is removed by the next writer in that directory.
"""
from __future__ import annotations

from slicersim.errors import RampFileError  # noqa: F401  (re-exported)

import errno
import json
import os
import re
import secrets
import shutil
import signal
import threading

import numpy as np

__all__ = ["RampWriter", "RampFileError", "compression_options", "read_ramps", "DQ", "is_temporary",
           "remove_stale_temporaries"]

#: JWST data-quality bit values
DQ = {"GOOD": 0, "DO_NOT_USE": 1, "SATURATED": 2, "JUMP_DET": 4, "DEAD": 1024, "HOT": 2048}




def compression_options(compression):
    """h5py dataset keyword arguments for ``compression``.

    None (default, uncompressed), ``"gzip"`` or ``"gzip:<level>"``, ``"lz4"``
    (Blosc2/LZ4 with bit-shuffle, via hdf5plugin), ``"zstd"`` (Blosc2/Zstd with
    bit-shuffle), ``"bitshuffle-lz4"`` (bitshuffle filter with LZ4).
    """
    if compression in (None, "none", False):
        return {}
    if str(compression).startswith("gzip"):
        level = int(str(compression).split(":")[1]) if ":" in str(compression) else 4
        return {"compression": "gzip", "compression_opts": level, "shuffle": True}
    try:
        import hdf5plugin
    except ImportError as exc:
        raise RampFileError(f"compression {compression!r} needs the 'hdf5plugin' package") from exc
    if compression == "lz4":
        return dict(hdf5plugin.Blosc2(cname="lz4", clevel=5, filters=hdf5plugin.Blosc2.BITSHUFFLE))
    if compression == "zstd":
        return dict(hdf5plugin.Blosc2(cname="zstd", clevel=3, filters=hdf5plugin.Blosc2.BITSHUFFLE))
    if compression == "bitshuffle-lz4":
        return dict(hdf5plugin.Bitshuffle(cname="lz4"))
    raise RampFileError(f"unknown compression {compression!r}: None, 'gzip[:level]', 'lz4', 'zstd', "
                        "'bitshuffle-lz4'")


#: temporaries are ``.<final name>.tmp-<pid>-<host tag><random>`` (the host tag keeps a writer from
#: removing the temporary of a live process on another machine sharing the directory)
_TMP_TAG = ".tmp-"
_TMP_RE = re.compile(r"^\.(?P<final>.+)\.tmp-(?P<pid>\d+)-(?P<host>[0-9a-f]{6})[0-9a-f]+$")


def _host_tag():
    import hashlib
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


def remove_stale_temporaries(directory):
    """Remove temporaries left in ``directory`` by writers that no longer run; returns their paths."""
    removed, host = [], _host_tag()
    try:
        names = os.listdir(directory)
    except OSError:
        return removed
    for name in names:
        match = _TMP_RE.match(name)
        if (match is None or match["host"] != host or int(match["pid"]) == os.getpid()
                or _pid_alive(int(match["pid"]))):
            continue
        path = os.path.join(directory, name)
        try:
            os.remove(path)
            removed.append(path)
        except OSError:
            pass
    return removed


def _one_line(exc):
    """Short one-line text of an OSError (HDF5 messages span lines)."""
    if isinstance(exc, OSError) and exc.strerror:
        return f"[Errno {exc.errno}] {exc.strerror}" if exc.errno else exc.strerror
    return " ".join(str(exc).split())


class _GuardedFile:
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


class RampWriter:
    """Stream a raw ramp to HDF5 in row blocks (context manager).

    Parameters
    ----------
    path : output file name
    nramps, ngroups : int;  shape : (ny, nx)
    attrs : dict of root attributes (values JSON-serialisable or scalars)
    row_block : rows per chunk;  compression : see :func:`compression_options`
    truth_rate : bool, reserve /truth/rate
    overwrite : replace an existing ``path`` (default: refuse with :class:`RampFileError`)

    The file is written as ``.NAME.tmp-PID-xxxx`` in the target directory (created with the
    user's umask) and linked to ``NAME`` only when complete, which fails if ``NAME`` appeared
    meanwhile (two writers: one wins, the other gets a clear error).  Any error, SIGINT or
    exception inside the ``with`` block removes the temporary.  Temporaries of killed writers
    are removed by the next writer in the same directory.
    """

    def __init__(self, path, nramps, ngroups, shape, attrs=None, row_block=64, compression=None,
                 truth_rate=False, pixeldq=True, overwrite=False):
        self.path = os.path.abspath(os.fspath(path))
        self.nramps, self.ngroups = int(nramps), int(ngroups)
        self.shape = tuple(int(s) for s in shape)
        self.attrs = dict(attrs or {})
        self.row_block = int(max(1, min(row_block, self.shape[0])))
        self.compression = compression_options(compression)
        self.truth_rate, self.pixeldq = truth_rate, pixeldq
        self.overwrite = bool(overwrite)
        self._file = None
        self._fh = None
        self._fd = None
        self._tmp = None
        self._busy = 0
        self._pending_signal = None
        self._old_handler = None

    # ------------------------------------------------------------------ lifecycle
    def expected_bytes(self):
        """Uncompressed size of SCI + GROUPDQ (+ PIXELDQ, truth) [bytes]."""
        n = self.nramps * self.ngroups * self.shape[0] * self.shape[1]
        return n * 3 + self.shape[0] * self.shape[1] * (4 * self.pixeldq + 4 * self.truth_rate)

    def check(self):
        """Refuse early (before any simulation or allocation): missing or read-only directory,
        existing file without ``overwrite``, not enough free disk space for an uncompressed file."""
        directory = os.path.dirname(self.path) or "."
        if not os.path.isdir(directory):
            raise RampFileError(f"output directory does not exist: {directory}")
        if not os.access(directory, os.W_OK):
            raise RampFileError(f"output directory is not writable: {directory}")
        if os.path.isdir(self.path):
            raise RampFileError(f"output path is a directory: {self.path}")
        if not self.overwrite and os.path.lexists(self.path):
            raise RampFileError(f"output file exists: {self.path} (pass overwrite=True / --overwrite "
                                "to replace it)")
        if not self.compression:
            need = self.expected_bytes() + _HDF5_MARGIN
            free = shutil.disk_usage(directory).free
            if need > free:
                raise RampFileError(f"not enough disk space in {directory}: need {need / 1e9:.3g} GB "
                                    f"for {self.path}, {free / 1e9:.3g} GB free")
        return self

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
        base = os.path.basename(self.path)
        for _ in range(100):
            tmp = os.path.join(directory, f".{base}{_TMP_TAG}{os.getpid()}-{_host_tag()}{secrets.token_hex(4)}")
            try:
                self._fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0),
                                   0o666)        # the umask applies, as for any new file
            except FileExistsError:
                continue
            except OSError as exc:
                raise RampFileError(f"cannot create {self.path}: {_one_line(exc)}") from exc
            self._tmp = tmp
            break
        else:  # pragma: no cover
            raise RampFileError(f"cannot create a temporary file in {directory}")
        try:
            self._fh = _GuardedFile(self._fd)
            self._file = h5py.File(self._fh, "w")
            dims = (self.nramps, self.ngroups) + self.shape
            chunks = (1, 1, self.row_block, self.shape[1])
            self.sci = self._file.create_dataset("SCI", dims, dtype="u2", chunks=chunks, **self.compression)
            self.groupdq = self._file.create_dataset("GROUPDQ", dims, dtype="u1", chunks=chunks,
                                                     **self.compression)
            if self.pixeldq:
                self.pixdq = self._file.create_dataset("PIXELDQ", self.shape, dtype="u4",
                                                       chunks=(self.row_block, self.shape[1]), **self.compression)
            if self.truth_rate:
                self.truth = self._file.create_dataset("truth/rate", self.shape, dtype="f4",
                                                       chunks=(self.row_block, self.shape[1]))
            for key, val in self.attrs.items():
                self._file.attrs[key] = val if not isinstance(val, (dict, list, tuple)) else json.dumps(val)
            self._file.attrs["COMPLETE"] = False
        except Exception as exc:
            raise RampFileError(f"cannot create {self.path}: {_one_line(exc)}") from exc
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
                os.fsync(self._fd)
                os.close(self._fd)
                self._fd = None
                if self._pending_signal is not None:
                    self._abort()
                    return False
                self._publish()
            except BaseException as err:
                self._abort()
                if isinstance(err, RampFileError):
                    raise
                if isinstance(err, Exception):
                    raise RampFileError(f"cannot finish {self.path}: {_one_line(err)}") from err
                raise
            return False
        finally:
            self._busy -= 1
            self._restore_signal_handler(deliver=exc_type is None or not issubclass(exc_type, KeyboardInterrupt))

    def _publish(self):
        """Give the complete temporary its final name (never replacing a file unless overwrite)."""
        if self.overwrite:
            os.replace(self._tmp, self.path)
            self._tmp = None
            return
        try:
            os.link(self._tmp, self.path)
        except FileExistsError:
            raise RampFileError(f"output file exists: {self.path} (another writer finished first; "
                                "pass overwrite=True / --overwrite to replace it)") from None
        except OSError as exc:             # no hard links here (FAT, some network file systems)
            if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK,
                                 errno.ENOSYS):
                raise
            if os.path.lexists(self.path):
                raise RampFileError(f"output file exists: {self.path} (pass overwrite=True / --overwrite "
                                    "to replace it)") from None
            os.rename(self._tmp, self.path)
            self._tmp = None
            return
        os.remove(self._tmp)
        self._tmp = None

    def _close_file(self):
        file, self._file = self._file, None
        for name in ("sci", "groupdq", "pixdq", "truth"):
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
            raise RampFileError(f"{what} {self.path}: {_one_line(self._fh.error)}") from self._fh.error

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

    # ------------------------------------------------------------------ writing
    def _h5(self, func, *args):
        self._busy += 1
        try:
            func(*args)
        except OSError as exc:
            raise RampFileError(f"writing {self.path} failed: {_one_line(exc)}") from exc
        finally:
            self._busy -= 1
        self._raise_io_error("cannot write")
        self._deliver_pending()

    def write_block(self, ramp, row0, sci, groupdq=None):
        """Write groups (ngroups, nrows, nx) of one ramp starting at detector row ``row0``."""
        rows = slice(row0, row0 + sci.shape[1])

        def put():
            self.sci[ramp, :, rows, :] = sci
            if groupdq is not None:
                self.groupdq[ramp, :, rows, :] = groupdq
        self._h5(put)

    def write_pixeldq(self, pixeldq):
        self._h5(self.pixdq.__setitem__, Ellipsis, np.asarray(pixeldq, dtype=np.uint32))

    def write_truth(self, rate):
        self._h5(self.truth.__setitem__, Ellipsis, np.asarray(rate, dtype=np.float32))


def read_ramps(path):
    """(SCI, GROUPDQ, PIXELDQ or None, attrs) of a complete ramp file."""
    import h5py
    path = os.fspath(path)
    if is_temporary(path):
        raise RampFileError(f"{path}: incomplete file (temporary of an unfinished or killed writer)")
    try:
        fh = h5py.File(path, "r")
    except FileNotFoundError as exc:
        raise RampFileError(f"{path}: no such file") from exc
    except OSError as exc:
        raise RampFileError(f"{path}: incomplete file or not an HDF5 ramp file "
                            f"({_one_line(exc)})") from exc
    with fh:
        if not fh.attrs.get("COMPLETE", False):
            raise RampFileError(f"{path}: incomplete file (no completion marker)")
        if "SCI" not in fh or "GROUPDQ" not in fh:
            raise RampFileError(f"{path}: not a slicersim ramp file (no SCI/GROUPDQ)")
        attrs = {k: fh.attrs[k] for k in fh.attrs}
        pix = fh["PIXELDQ"][...] if "PIXELDQ" in fh else None
        return fh["SCI"][...], fh["GROUPDQ"][...], pix, attrs
