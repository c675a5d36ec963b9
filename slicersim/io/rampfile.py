"""Group-level raw-ramp files (HDF5), written in row blocks; no physics here.

Layout (one file per exposure)::

    /SCI            uint16  (nramps, ngroups, ny, nx)   group-averaged reads [ADU]
    /GROUPDQ        uint8   (nramps, ngroups, ny, nx)   JWST group flags (2 = SATURATED)
    /PIXELDQ        uint32  (ny, nx)                    JWST pixel flags (1 DO_NOT_USE, 1024 DEAD, 2048 HOT)
    /truth/rate     float32 (ny, nx)   optional         input rate [e-/s]
    /truth/<name>   truth of the detector effects (``effects=``): cosmic_rays (compound: ramp,
                    frame, y, x, electrons), nonlinearity/coefficients, ..., see
                    :mod:`slicersim.products.effects`
    root attributes NINTS NGROUPS NFRAMES GROUPGAP TFRAME TGROUP READPATT GAIN READNOISE
                    SEED BUNIT SOFTWARE VERSION CONFIG (JSON) COMPLETE

SCI and GROUPDQ are chunked one group × a row block.  The file is written
under a temporary name ``.NAME.tmp-PID-xxxx`` in the target directory and
linked to ``NAME`` only when complete (never replacing an existing file
unless asked); an interrupted writer leaves no file with the final name, and
its temporary is removed by the next writer in that directory.
"""
from __future__ import annotations

from slicersim.errors import RampFileError

import json
import os
import shutil

import numpy as np

from slicersim.io.atomic import _HDF5_MARGIN, AtomicH5File, is_temporary, one_line, remove_stale_temporaries

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


class RampWriter(AtomicH5File):
    """Stream a raw ramp to HDF5 in row blocks (context manager).

    Parameters
    ----------
    path : output file name
    nramps, ngroups : int;  shape : (ny, nx)
    attrs : dict of root attributes (values JSON-serialisable or scalars)
    row_block : rows per chunk;  compression : see :func:`compression_options`
    truth_rate : bool, reserve /truth/rate
    extra_bytes : further bytes (truth of detector effects) for the disk-space check
    overwrite : replace an existing ``path`` (default: refuse with :class:`RampFileError`)

    The file is written as ``.NAME.tmp-PID-xxxx`` in the target directory (created with the
    user's umask) and linked to ``NAME`` only when complete, which fails if ``NAME`` appeared
    meanwhile (two writers: one wins, the other gets a clear error).  Any error, SIGINT or
    exception inside the ``with`` block removes the temporary.  Temporaries of killed writers
    are removed by the next writer in the same directory.
    """

    error_class = RampFileError
    _dataset_names = ("sci", "groupdq", "pixdq", "truth")

    def __init__(self, path, nramps, ngroups, shape, attrs=None, row_block=64, compression=None,
                 truth_rate=False, pixeldq=True, overwrite=False, extra_bytes=0):
        super().__init__(path, overwrite)
        self.extra_bytes = int(extra_bytes)
        self.nramps, self.ngroups = int(nramps), int(ngroups)
        self.shape = tuple(int(s) for s in shape)
        self.attrs = dict(attrs or {})
        self.row_block = int(max(1, min(row_block, self.shape[0])))
        self.compression = compression_options(compression)
        self.truth_rate, self.pixeldq = truth_rate, pixeldq

    # ------------------------------------------------------------------ lifecycle
    def expected_bytes(self):
        """Uncompressed size of SCI + GROUPDQ (+ PIXELDQ, truth rate, ``extra_bytes``) [bytes]."""
        n = self.nramps * self.ngroups * self.shape[0] * self.shape[1]
        return n * 3 + self.shape[0] * self.shape[1] * (4 * self.pixeldq + 4 * self.truth_rate) + self.extra_bytes

    def check(self):
        """Refuse early (before any simulation or allocation): missing or read-only directory,
        existing file without ``overwrite``, not enough free disk space for an uncompressed file."""
        super().check()
        directory = os.path.dirname(self.path) or "."
        remove_stale_temporaries(directory)          # a killed writer's temporary holds disk space
        if not self.compression:
            need = self.expected_bytes() + _HDF5_MARGIN
            free = shutil.disk_usage(directory).free
            if need > free:
                raise RampFileError(f"not enough disk space in {directory}: need {need / 1e9:.3g} GB "
                                    f"for {self.path}, {free / 1e9:.3g} GB free")
        return self

    def _populate(self, file):
        dims = (self.nramps, self.ngroups) + self.shape
        chunks = (1, 1, self.row_block, self.shape[1])
        self.sci = file.create_dataset("SCI", dims, dtype="u2", chunks=chunks, **self.compression)
        self.groupdq = file.create_dataset("GROUPDQ", dims, dtype="u1", chunks=chunks,
                                                 **self.compression)
        if self.pixeldq:
            self.pixdq = file.create_dataset("PIXELDQ", self.shape, dtype="u4",
                                                   chunks=(self.row_block, self.shape[1]), **self.compression)
        if self.truth_rate:
            self.truth = file.create_dataset("truth/rate", self.shape, dtype="f4",
                                                   chunks=(self.row_block, self.shape[1]))
        for key, val in self.attrs.items():
            file.attrs[key] = val if not isinstance(val, (dict, list, tuple)) else json.dumps(val)
        file.attrs["COMPLETE"] = False

    # ------------------------------------------------------------------ writing
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

    def write_dataset(self, name, array, attrs=None):
        """Write ``truth/<name>`` (any array, structured arrays as compound datasets) with attributes.

        ``array`` may be a lazy (k, ny, nx) array-like (``shape``, ``dtype``, ``[:, y0:y1]``): it is
        then written in blocks of rows, never whole in memory."""
        lazy = not isinstance(array, np.ndarray) and hasattr(array, "shape") and len(getattr(array, "shape")) == 3
        if not lazy:
            array = np.asarray(array)

        def put():
            if lazy:
                k, ny, nx = array.shape
                rows = max(1, min(ny, (16 << 20) // max(1, k * nx * np.dtype(array.dtype).itemsize)))
                ds = self.file.create_dataset(f"truth/{name}", array.shape, dtype=array.dtype,
                                              chunks=(1, rows, nx))
                for y0 in range(0, ny, rows):
                    ds[:, y0:y0 + rows] = array[:, y0:y0 + rows]
            else:
                kwargs = _compression_for(array)
                ds = self.file.create_dataset(f"truth/{name}", data=array, **kwargs)
            for key, val in (attrs or {}).items():
                ds.attrs[key] = val if not isinstance(val, (dict, list, tuple)) else json.dumps(val)
        self._h5(put)


def _compression_for(array, probe_bytes=1 << 20, worth=0.75):
    """h5py options for a truth array: byte-shuffled gzip-1 when a zlib probe of its first
    ``probe_bytes`` (shuffled) compresses below ``worth`` of its size, else none (noise-like
    float maps barely compress and gzip would cost ~1 s per 64 MB)."""
    if array.size <= 4096 or array.dtype.kind not in "biufV":
        return {}
    import zlib
    flat = np.ascontiguousarray(array).reshape(-1)
    head = flat[:max(1, probe_bytes // flat.itemsize)]
    shuffled = head.view(np.uint8).reshape(-1, flat.itemsize).T.tobytes()
    if len(zlib.compress(shuffled, 1)) >= worth * len(shuffled):
        return {}
    return {"chunks": True, "compression": "gzip", "compression_opts": 1, "shuffle": True}


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
                            f"({one_line(exc)})") from exc
    with fh:
        if not fh.attrs.get("COMPLETE", False):
            raise RampFileError(f"{path}: incomplete file (no completion marker)")
        if "SCI" not in fh or "GROUPDQ" not in fh:
            raise RampFileError(f"{path}: not a slicersim ramp file (no SCI/GROUPDQ)")
        attrs = {k: fh.attrs[k] for k in fh.attrs}
        pix = fh["PIXELDQ"][...] if "PIXELDQ" in fh else None
        return fh["SCI"][...], fh["GROUPDQ"][...], pix, attrs
