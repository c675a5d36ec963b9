"""Group-level raw-ramp files (HDF5), written in row blocks; no physics here.

Layout (one file per exposure)::

    /SCI            uint16  (nramps, ngroups, ny, nx)   group-averaged reads [ADU]
    /GROUPDQ        uint8   (nramps, ngroups, ny, nx)   JWST group flags (2 = SATURATED)
    /PIXELDQ        uint32  (ny, nx)                    JWST pixel flags (1 DO_NOT_USE, 1024 DEAD, 2048 HOT)
    /truth/rate     float32 (ny, nx)   optional         input rate [e-/s]
    root attributes NINTS NGROUPS NFRAMES GROUPGAP TFRAME TGROUP READPATT GAIN READNOISE
                    SEED BUNIT SOFTWARE VERSION CONFIG (JSON) COMPLETE

SCI and GROUPDQ are chunked one group × a row block.  The file is written
under a temporary name in the target directory and renamed only when
complete; an interrupted writer leaves no file with the final name.
"""
from __future__ import annotations

from slicersim.errors import RampFileError  # noqa: F401  (re-exported)

import json
import os
import shutil
import tempfile

import numpy as np

__all__ = ["RampWriter", "RampFileError", "compression_options", "read_ramps", "DQ"]

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


class RampWriter:
    """Stream a raw ramp to HDF5 in row blocks (context manager).

    Parameters
    ----------
    path : output file name
    nramps, ngroups : int;  shape : (ny, nx)
    attrs : dict of root attributes (values JSON-serialisable or scalars)
    row_block : rows per chunk;  compression : see :func:`compression_options`
    truth_rate : bool, reserve /truth/rate
    """

    def __init__(self, path, nramps, ngroups, shape, attrs=None, row_block=64, compression=None,
                 truth_rate=False, pixeldq=True):
        self.path = os.path.abspath(path)
        self.nramps, self.ngroups = int(nramps), int(ngroups)
        self.shape = tuple(int(s) for s in shape)
        self.attrs = dict(attrs or {})
        self.row_block = int(max(1, min(row_block, self.shape[0])))
        self.compression = compression_options(compression)
        self.truth_rate, self.pixeldq = truth_rate, pixeldq
        self._file = None
        self._tmp = None

    # ------------------------------------------------------------------ lifecycle
    def expected_bytes(self):
        """Uncompressed size of SCI + GROUPDQ (+ PIXELDQ, truth) [bytes]."""
        n = self.nramps * self.ngroups * self.shape[0] * self.shape[1]
        return n * 3 + self.shape[0] * self.shape[1] * (4 * self.pixeldq + 4 * self.truth_rate)

    def __enter__(self):
        import h5py
        directory = os.path.dirname(self.path) or "."
        if not os.path.isdir(directory):
            raise RampFileError(f"output directory does not exist: {directory}")
        if not os.access(directory, os.W_OK):
            raise RampFileError(f"output directory is not writable: {directory}")
        free = shutil.disk_usage(directory).free
        if not self.compression and self.expected_bytes() > free:
            raise RampFileError(f"not enough disk space in {directory}: need "
                                f"{self.expected_bytes() / 1e9:.2f} GB, {free / 1e9:.2f} GB free")
        fd, self._tmp = tempfile.mkstemp(prefix=".partial-", suffix=".h5", dir=directory)
        os.close(fd)
        try:
            self._file = h5py.File(self._tmp, "w")
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
            self._abort()
            raise RampFileError(f"cannot create {self.path}: {exc}") from exc
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is not None:
            self._abort()
            return False
        try:
            self._file.attrs["COMPLETE"] = True
            self._file.close()
            self._file = None
            os.replace(self._tmp, self.path)
        except Exception as err:
            self._abort()
            raise RampFileError(f"cannot finish {self.path}: {err}") from err
        return False

    def _abort(self):
        try:
            if self._file is not None:
                self._file.close()
        except Exception:
            pass
        self._file = None
        if self._tmp and os.path.exists(self._tmp):
            os.remove(self._tmp)

    # ------------------------------------------------------------------ writing
    def write_block(self, ramp, row0, sci, groupdq=None):
        """Write groups (ngroups, nrows, nx) of one ramp starting at detector row ``row0``."""
        rows = slice(row0, row0 + sci.shape[1])
        try:
            self.sci[ramp, :, rows, :] = sci
            if groupdq is not None:
                self.groupdq[ramp, :, rows, :] = groupdq
        except OSError as exc:
            raise RampFileError(f"writing {self.path} failed (disk full?): {exc}") from exc

    def write_pixeldq(self, pixeldq):
        self.pixdq[...] = np.asarray(pixeldq, dtype=np.uint32)

    def write_truth(self, rate):
        self.truth[...] = np.asarray(rate, dtype=np.float32)


def read_ramps(path):
    """(SCI, GROUPDQ, PIXELDQ or None, attrs) of a complete ramp file."""
    import h5py
    with h5py.File(path, "r") as fh:
        if not fh.attrs.get("COMPLETE", False):
            raise RampFileError(f"{path} is incomplete")
        attrs = {k: fh.attrs[k] for k in fh.attrs}
        pix = fh["PIXELDQ"][...] if "PIXELDQ" in fh else None
        return fh["SCI"][...], fh["GROUPDQ"][...], pix, attrs
