"""Raw ramps to read by row blocks: our HDF5 ramp files, JWST level-1b FITS files (recognised by
content, not by name) and in-memory arrays, with their readout keywords checked.

:func:`open_ramps` returns a reader with ``shape`` (nints, ngroups, ny, nx), ``attrs`` (the
file's keywords), ``integer`` (uint16 SCI), ``read(y0, y1, sci, gdq)`` (SCI [DN] and GROUPDQ of
rows y0:y1 into the caller's buffers), ``pixeldq(y0, y1)``, ``frame(i, g[, y0, y1])`` (rows of one group),
``truth(name)`` and
``rows`` (the row ranges of a file holding only some detector rows, else None).
:func:`ramp_readout` gives the validated readout (n, m, d), TFRAME [s], GAIN [DN/e-] and read
noise [e-/frame].  Every problem is a RampFileError naming the file and the keyword.
"""
from __future__ import annotations

import math
import os

import numpy as np

from slicersim.errors import ParameterError, RampFileError
from slicersim.io.atomic import is_temporary, one_line
from slicersim.validation import short_repr

__all__ = ["open_ramps", "check_source", "ramp_file_kind", "ramp_readout", "keyword_number"]

_HDF5_MAGIC, _FITS_MAGIC = b"\x89HDF\r\n\x1a\n", b"SIMPLE  ="


class _Ramps:
    """A raw ramp to read by row blocks: ``shape`` (nints, ngroups, ny, nx), ``attrs`` (keywords),
    ``integer`` (uint16 SCI), ``read(y0, y1, sci, gdq)``, ``pixeldq(y0, y1)``, ``frame(i, g)``,
    ``truth(name)`` (row-sliceable array or None), ``name``, ``kind``."""

    kind, name = "arrays", "<arrays>"
    #: row ranges [y0, y1) the source holds (a file of some detector rows), None: every row
    rows = None

    def close(self):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class _ArrayRamps(_Ramps):
    def __init__(self, arrays):
        if not isinstance(arrays, (tuple, list)) or len(arrays) != 4:
            raise RampFileError("arrays must be (SCI, GROUPDQ or None, PIXELDQ or None, attrs), as read_ramps returns")
        sci, gdq, pdq, attrs = arrays
        sci = np.asarray(sci)
        if sci.ndim != 4 or sci.dtype.kind not in "uif" or 0 in sci.shape:
            raise RampFileError(f"SCI must be a non-empty 4-D numeric array (nints, ngroups, ny, nx), got "
                                f"{sci.dtype} {sci.shape}")
        self.integer = sci.dtype == np.uint16
        self.sci = sci if self.integer else sci.astype(np.float64, copy=False)
        self.shape = sci.shape
        self.gdq = np.zeros(sci.shape, np.uint8) if gdq is None else np.asarray(gdq)
        self.pdq = np.zeros(sci.shape[2:], np.uint32) if pdq is None else np.asarray(pdq)
        if self.gdq.shape != sci.shape or self.pdq.shape != sci.shape[2:]:
            raise RampFileError(f"GROUPDQ {self.gdq.shape} and PIXELDQ {self.pdq.shape} do not match SCI {sci.shape}")
        if not isinstance(attrs, dict):
            raise RampFileError("attrs must be a dict of readout keywords (NFRAMES, GROUPGAP, TFRAME, ...)")
        self.attrs = dict(attrs)

    def read(self, y0, y1, sci, gdq):
        sci[...] = self.sci[:, :, y0:y1]
        gdq[...] = self.gdq[:, :, y0:y1]

    def pixeldq(self, y0, y1):
        return self.pdq[y0:y1].astype(np.uint32)

    def frame(self, i, g, y0=0, y1=None):
        return self.sci[i, g, y0:y1]

    def truth(self, name):
        return None


class _HDF5Ramps(_Ramps):
    kind = "hdf5"

    def __init__(self, path):
        import h5py
        try:
            import hdf5plugin  # noqa: F401  (registers lz4/zstd/bitshuffle: the campaigns' ramp compressions)
        except ImportError:
            pass
        self.name = path
        from slicersim.io.rampfile import READ_CHUNK_CACHE, metadata_errors
        try:
            with metadata_errors(path):
                self.fh = h5py.File(path, "r", **READ_CHUNK_CACHE)
        except RampFileError:
            raise
        except OSError as exc:
            raise RampFileError(f"{path}: not a readable HDF5 ramp file ({one_line(exc)})") from exc
        fh = self.fh
        from slicersim.io.rampfile import check_hdf5_input, simulated_rows
        try:              # no data from outside the file, a SCI whose declared shape (or rows) is stored
            check_hdf5_input(fh, path, ("SCI", "GROUPDQ", "PIXELDQ"), partial_rows=True)
            self.rows = simulated_rows(fh, path)
        except BaseException:
            self.close()
            raise
        if not fh.attrs.get("COMPLETE", False):
            self.close()
            raise RampFileError(f"{path}: incomplete file (no completion marker)")
        sci = fh.get("SCI")
        if sci is None or sci.ndim != 4 or sci.dtype != np.uint16:
            self.close()
            raise RampFileError(f"{path}: not a slicersim ramp file (needs SCI uint16 (nints, ngroups, ny, nx))")
        self.sci, self.gdq, self.shape, self.integer = sci, fh.get("GROUPDQ"), sci.shape, True
        pdq = fh.get("PIXELDQ")
        if (self.gdq is not None and self.gdq.shape != sci.shape) or (pdq is not None and pdq.shape != sci.shape[2:]):
            self.close()
            raise RampFileError(f"{path}: GROUPDQ/PIXELDQ shapes do not match SCI {sci.shape}")
        self.pdq = pdq
        self.attrs = {k: fh.attrs[k] for k in fh.attrs}
        self.chunk_rows = sci.chunks[2] if sci.chunks else 1

    def read(self, y0, y1, sci, gdq):
        from slicersim.io.rampfile import read_error
        for dset, out in ((self.sci, sci), (self.gdq, gdq)):
            if dset is None:
                out[...] = 0
                continue
            try:                              # a failed Fletcher-32 checksum: "checksum mismatch in dataset SCI of FILE"
                dset.read_direct(out, np.s_[:, :, y0:y1, :])
            except OSError as exc:
                raise read_error(exc, self.name, dset) from None

    def pixeldq(self, y0, y1):
        from slicersim.io.rampfile import read_dataset     # a failed checksum named, not h5py's words
        nx = self.shape[3]
        if self.pdq is None:
            return np.zeros((y1 - y0, nx), np.uint32)
        return read_dataset(self.pdq, self.name, np.s_[y0:y1]).astype(np.uint32)

    def frame(self, i, g, y0=0, y1=None):
        from slicersim.io.rampfile import read_dataset
        return read_dataset(self.sci, self.name, np.s_[i, g, y0:y1])

    def truth(self, name):
        try:
            return self.fh.get(f"truth/{name}")
        except (RuntimeError, KeyError, OSError) as exc:     # a soft link looping on itself
            raise RampFileError(f"{self.name}: truth/{name} is a soft link that does not resolve to an object "
                                f"({one_line(exc)})") from None

    def close(self):
        self.fh.close()


class _FitsImage:
    """Row-sliceable view of a FITS image extension (memory-mapped, BZERO applied)."""

    _TYPES = {8: ">u1", 16: ">i2", 32: ">i4", 64: ">i8", -32: ">f4", -64: ">f8"}

    def __init__(self, path, hdul, index):
        hdr = hdul[index].header
        bitpix, naxis = hdr["BITPIX"], hdr["NAXIS"]
        self.shape = tuple(int(hdr[f"NAXIS{naxis - a}"]) for a in range(naxis))
        self.bzero, bscale = hdr.get("BZERO", 0), hdr.get("BSCALE", 1)
        if bitpix not in self._TYPES or bscale != 1:
            raise RampFileError(f"{path}: extension {hdr.get('EXTNAME')} has BITPIX {bitpix}, BSCALE {bscale}")
        end = hdul.fileinfo(index)["datLoc"] + math.prod(self.shape) * abs(bitpix) // 8
        size = os.path.getsize(path)
        if end > size:
            raise RampFileError(f"{path}: truncated file: extension {hdr.get('EXTNAME')} ends at byte {end} "
                                f"(declared shape {self.shape}, BITPIX {bitpix}), the file has {size}")
        self.raw = np.memmap(path, dtype=self._TYPES[bitpix], mode="r", offset=hdul.fileinfo(index)["datLoc"],
                             shape=self.shape)
        unsigned = {(16, 32768): np.uint16, (32, 2**31): np.uint32, (8, 0): np.uint8}
        self.dtype = unsigned.get((bitpix, self.bzero), np.dtype(self._TYPES[bitpix]).newbyteorder("="))
        self.flip = bitpix in (16, 32) and self.dtype in (np.uint16, np.uint32)
        self.ndim = naxis

    def __getitem__(self, key):
        raw = np.asarray(self.raw[key])
        if self.flip:                               # v − BZERO stored in two's complement: flip the top bit
            u = raw.view(raw.dtype.str.replace("i", "u"))
            return (u ^ u.dtype.type(1 << (8 * u.dtype.itemsize - 1))).astype(self.dtype)
        out = raw.astype(self.dtype)
        return out + self.bzero if self.bzero else out


class _FitsRamps(_Ramps):
    kind = "jwst-uncal"

    def __init__(self, path):
        from astropy.io import fits
        self.name = path
        import warnings
        from astropy.utils.exceptions import AstropyWarning
        try:
            with warnings.catch_warnings():     # a truncated file or a damaged header: named below, in one line
                warnings.simplefilter("ignore", AstropyWarning)
                self.hdul = fits.open(path, memmap=False, lazy_load_hdus=False)
                for hdu in self.hdul:
                    hdu.header.tostring()                 # parsed here, where astropy's warnings are held back
        except OSError as exc:
            raise RampFileError(f"{path}: not a readable FITS file ({one_line(exc)})") from exc
        names = [h.name for h in self.hdul]
        if "SCI" not in names:
            self.close()
            raise RampFileError(f"{path}: not a level-1b ramp file (no SCI extension)")
        from slicersim.io.fits_checksum import verify_datasums
        try:
            verify_datasums(path, self.hdul, RampFileError)   # the DATASUM the writer streamed
        except BaseException:
            self.close()
            raise
        try:
            self.images = {n: _FitsImage(path, self.hdul, names.index(n)) for n in names
                           if n in ("SCI", "GROUPDQ", "PIXELDQ") or n.startswith("TRUTH_")
                           and self.hdul[n].header.get("XTENSION") == "IMAGE"}
        except BaseException:
            self.hdul.close()
            raise
        sci = self.images["SCI"]
        if sci.ndim != 4 or sci.dtype != np.uint16:
            self.close()
            raise RampFileError(f"{path}: SCI must be uint16 (nints, ngroups, ny, nx), got {sci.dtype} {sci.shape}")
        self.shape, self.integer = sci.shape, True
        gdq, pdq = self.images.get("GROUPDQ"), self.images.get("PIXELDQ")
        if (gdq is not None and gdq.shape != sci.shape) or (pdq is not None and pdq.shape != sci.shape[2:]):
            self.close()
            raise RampFileError(f"{path}: GROUPDQ/PIXELDQ shapes do not match SCI {sci.shape}")
        header = self.hdul[0].header
        attrs = {k[len("SLICERSIM "):]: v for k, v in header.items() if k.startswith("SLICERSIM ")}
        attrs.update({k: header[k] for k in ("NINTS", "NGROUPS", "NFRAMES", "GROUPGAP", "TFRAME", "TGROUP")
                      if k in header})
        self.attrs = attrs

    def read(self, y0, y1, sci, gdq):
        sci[...] = self.images["SCI"][:, :, y0:y1]
        gdq[...] = self.images["GROUPDQ"][:, :, y0:y1] if "GROUPDQ" in self.images else 0

    def pixeldq(self, y0, y1):
        pdq = self.images.get("PIXELDQ")
        return np.zeros((y1 - y0, self.shape[3]), np.uint32) if pdq is None else pdq[y0:y1].astype(np.uint32)

    def frame(self, i, g, y0=0, y1=None):
        return self.images["SCI"][i, g, y0:y1]

    def truth(self, name):
        from slicersim.io.uncal import truth_extname
        return self.images.get(truth_extname(name))

    def close(self):
        self.images = {}
        self.hdul.close()


def ramp_file_kind(path):
    """"hdf5", "fits" (by content) or None for a readable file; RampFileError for a writer's
    temporary or an unreadable file."""
    path = os.fspath(path)
    if is_temporary(path):
        raise RampFileError(f"{path}: incomplete file (temporary of an unfinished or killed writer)")
    try:
        with open(path, "rb") as fh:
            magic = fh.read(9)
    except OSError as exc:
        raise RampFileError(f"{path}: cannot read ({one_line(exc)})") from exc
    if magic.startswith(_HDF5_MAGIC):
        return "hdf5"
    if magic.startswith(_FITS_MAGIC):
        return "fits"
    return None


#: what :func:`open_ramps` accepts, said in its errors
ACCEPTED = ("a ramp file path (str or os.PathLike: an HDF5 file from `slicersim ramp` or a JWST level-1b FITS) "
            "or the arrays read_ramps returns: (SCI (nints, ngroups, ny, nx) [DN], GROUPDQ or None, PIXELDQ or "
            "None, attrs: a dict of the readout keywords NFRAMES, GROUPGAP, TFRAME, GAIN, READNOISE)")


def check_source(source, name="source"):
    """``source`` if it is a path (str, bytes, os.PathLike) or a sequence of four items (the arrays);
    else ParameterError naming ``name`` and saying what is accepted (:data:`ACCEPTED`)."""
    if isinstance(source, (str, bytes, os.PathLike)) or (isinstance(source, (tuple, list)) and len(source) == 4):
        return source
    got = f"a {type(source).__name__} of {len(source)} item(s)" if isinstance(source, (tuple, list)) else \
        short_repr(source)
    raise ParameterError(f"{name} must be {ACCEPTED}; got {got}")


def open_ramps(source, name="source"):
    """A raw ramp reader for a path (HDF5 or level-1b FITS, by content) or arrays
    (SCI, GROUPDQ, PIXELDQ, attrs); ParameterError naming ``name`` and what is accepted for another
    kind of value (a number, a bare array: :func:`check_source`), RampFileError for a file or arrays
    that are not ramps."""
    source = check_source(source, name)
    if isinstance(source, bytes):
        source = os.fsdecode(source)
    if isinstance(source, (str, os.PathLike)):
        path = os.fspath(source)
        kind = ramp_file_kind(path)
        if kind == "hdf5":
            return _HDF5Ramps(path)
        if kind == "fits":
            return _FitsRamps(path)
        raise RampFileError(f"{path}: neither an HDF5 ramp file nor a JWST level-1b FITS file")
    return _ArrayRamps(source)


# ----------------------------------------------------------------------------- readout
def keyword_number(attrs, key, where, kind=float):
    """The number of keyword ``key`` of a ramp file's ``attrs`` (bytes decoded); RampFileError naming the
    keyword when it is not a number (an integer with ``kind=int``)."""
    val = attrs[key]
    if isinstance(val, bytes):
        val = val.decode()
    try:
        num = kind(val) if kind is float else int(val)
        if kind is int and num != float(val):
            raise ValueError  # internal: caught just below, becomes a RampFileError naming the keyword
    except (TypeError, ValueError) as exc:
        raise RampFileError(f"{where}: keyword {key} = {val!r} is not {'an integer' if kind is int else 'a number'}") from exc
    return num


def ramp_readout(attrs, shape, gain, ron, where):
    """Validated (n, m, d), tframe [s], gain [DN/e-], read noise per frame [electron] of a ramp's keywords."""
    missing = [k for k in ("NFRAMES", "GROUPGAP", "TFRAME") if k not in attrs]
    if gain is None and "GAIN" not in attrs:
        missing.append("GAIN (or pass gain=)")
    if ron is None and "READNOISE" not in attrs:
        missing.append("READNOISE (or pass ron=)")
    if missing:
        raise RampFileError(f"{where}: readout keyword(s) missing: {', '.join(missing)}")
    nints, n = shape[:2]
    m, d = keyword_number(attrs, "NFRAMES", where, int), keyword_number(attrs, "GROUPGAP", where, int)
    tframe = keyword_number(attrs, "TFRAME", where)
    if m < 1 or d < 0 or not (math.isfinite(tframe) and tframe > 0):
        raise RampFileError(f"{where}: inconsistent readout keywords: NFRAMES = {m} (≥ 1), GROUPGAP = {d} (≥ 0), "
                            f"TFRAME = {tframe} s (> 0)")
    for key, val in (("NGROUPS", n), ("NINTS", nints)):
        if key in attrs and keyword_number(attrs, key, where, int) != val:
            raise RampFileError(f"{where}: inconsistent readout keywords: {key} = {attrs[key]} but SCI has {val}")
    if "TGROUP" in attrs and not math.isclose(keyword_number(attrs, "TGROUP", where), (m + d) * tframe, rel_tol=1e-6):
        raise RampFileError(f"{where}: inconsistent readout keywords: TGROUP = {attrs['TGROUP']} s but "
                            f"(NFRAMES + GROUPGAP)·TFRAME = {(m + d) * tframe:g} s")
    patt = attrs.get("READPATT", "")
    patt = patt.decode() if isinstance(patt, bytes) else str(patt)
    if patt.startswith("MACC(") and patt != f"MACC({n},{m},{d})":
        raise RampFileError(f"{where}: inconsistent readout keywords: READPATT = {patt} but NGROUPS, NFRAMES, "
                            f"GROUPGAP = {n}, {m}, {d}")
    if n < 2:
        raise RampFileError(f"{where}: {n} group(s) per integration: a slope needs at least 2")
    gain = keyword_number(attrs, "GAIN", where) if gain is None else float(gain)
    ron = keyword_number(attrs, "READNOISE", where) if ron is None else float(ron)
    if not (math.isfinite(gain) and gain > 0) or not (math.isfinite(ron) and ron >= 0):
        raise RampFileError(f"{where}: gain {gain} DN/e- must be > 0 and read noise {ron} electron ≥ 0")
    return (n, m, d), tframe, gain, ron
