"""Reading slicersim's level-1b files back (:mod:`slicersim.io.uncal` writes them): the arrays, the
primary keywords and the TRUTH_* extensions, CHECKSUM / DATASUM verified."""
from __future__ import annotations

import json
import os

import numpy as np

from slicersim import validation
from slicersim.errors import RampFileError
from slicersim.io.atomic import one_line
from slicersim.io.fits_checksum import verify_datasums

__all__ = ["read_uncal", "read_uncal_truth"]


def _open(path):
    """The HDUList of a regular file (a FIFO or device refused before opening), its CHECKSUM /
    DATASUM verified where present (a mismatch is a RampFileError naming the extension)."""
    import warnings

    from astropy.io import fits
    path = os.fspath(path)
    if not os.path.lexists(path):
        raise RampFileError(f"{path}: no such file")
    path = validation.regular_file("level-1b file", path, error=RampFileError)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            hdul = fits.open(path, memmap=False, checksum=True, lazy_load_hdus=False)
            for hdu in hdul:
                hdu.data                                 # noqa: B018 (loaded: DATASUM verified)
    except OSError as exc:
        raise RampFileError(f"{path}: not a FITS file ({one_line(exc)})") from exc
    bad = [one_line(w.message) for w in caught if "checksum" in str(w.message).lower()]
    if bad:
        hdul.close()
        raise RampFileError(f"{path}: checksum mismatch ({bad[0]}): the file is corrupt")
    try:                    # astropy keeps a file cut inside a header (its warning) and a changed header byte
        verify_datasums(path, hdul, RampFileError)
    except BaseException:
        hdul.close()
        raise
    return hdul


def read_uncal(path):
    """(SCI uint16, GROUPDQ uint8 or None, PIXELDQ uint32 or None, primary header dict) of a
    level-1b file.  The slicersim root attributes are the header's ``SLICERSIM <NAME>`` keys."""
    with _open(path) as hdul:
        names = [h.name for h in hdul]
        if "SCI" not in names:
            raise RampFileError(f"{path}: no SCI extension")
        sci = np.asarray(hdul["SCI"].data, dtype=np.uint16)
        gdq = np.asarray(hdul["GROUPDQ"].data, dtype=np.uint8) if "GROUPDQ" in names else None
        pdq = np.asarray(hdul["PIXELDQ"].data, dtype=np.uint32) if "PIXELDQ" in names else None
        header = {k: v for k, v in hdul[0].header.items() if k not in ("COMMENT", "HISTORY", "")}
    return sci, gdq, pdq, header


def read_uncal_truth(path):
    """{HDF5 name: array} of the TRUTH_* extensions (images in their original dtype,
    tables as structured arrays)."""
    out = {}
    with _open(path) as hdul:
        for hdu in hdul[1:]:
            if not hdu.name.startswith("TRUTH_"):
                continue
            name = hdu.header.get("H5PATH", hdu.name)
            kind = hdu.header.get("H5DTYPE", "")
            if kind.startswith("["):
                dtype = np.dtype([tuple(f[:2]) + ((tuple(f[2]),) if len(f) > 2 else ()) for f in json.loads(kind)])
                table = np.zeros(len(hdu.data), dtype=dtype)
                for field in dtype.names:
                    table[field] = hdu.data[field]
                out[name] = table
            else:
                data = np.asarray(hdu.data)
                out[name] = data.astype(np.dtype(kind) if kind else data.dtype.newbyteorder("="))
    return out
