"""Reading tabulated instrument curves (ECSV / CSV) and turning them into callables.

File I/O only: no physics here.  Wavelengths are returned in Angstrom.

Parsed curves are cached by the SHA-256 of the file's bytes (plus the arguments), so building
many models from the same files parses each file once per process while an edited file is
parsed again; callers get fresh copies (:data:`CURVE_CACHE`, ``slicersim.memo.clear_caches``).
"""
from __future__ import annotations

import hashlib
import io
import os

import numpy as np

from slicersim.errors import CurveError
from slicersim.io.tables import check_increasing, data_line_numbers, read_file_bytes
from slicersim.memo import ByteLRU

__all__ = ["read_curve", "CurveError", "CURVE_CACHE"]

#: parsed curve files, keyed by content digest (a few kB each)
CURVE_CACHE = ByteLRU("curves", 16 * 2**20)

_UNIT_TO_AA = {"angstrom": 1.0, "aa": 1.0, "a": 1.0, "nm": 10.0, "nanometer": 10.0,
               "micron": 1e4, "um": 1e4, "µm": 1e4, "micrometer": 1e4, "m": 1e10}


def _to_angstrom(values, unit, default_unit):
    unit = (str(unit) if unit is not None else default_unit).strip().lower()
    if unit not in _UNIT_TO_AA:
        raise CurveError(f"unknown wavelength unit {unit!r}")
    return np.asarray(values, dtype=float) * _UNIT_TO_AA[unit]


def read_curve(path, columns=None, wavelength_unit=None):
    """Read a tabulated curve.

    Parameters
    ----------
    path : str
        ECSV (astropy, units read from the header) or CSV/whitespace text file
        with a header line; the first column is the wavelength.
    columns : list of str, optional
        value columns to return (default: every column after the wavelength).
    wavelength_unit : str, optional
        unit of the wavelength column when the file does not say; default
        micron for ECSV and Angstrom for CSV.

    Returns
    -------
    lbda : ndarray  [AA], strictly increasing
    values : dict  column name -> ndarray
    """
    if not os.path.lexists(path):
        raise CurveError(f"curve file not found: {path}")
    raw = read_file_bytes(path, CurveError, "curve file")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    text = text.replace("\r\n", "\n").replace("\r", "\n")         # universal newlines, as open()
    ecsv = path.lower().endswith(".ecsv")
    key = (hashlib.sha256(raw).hexdigest(), ecsv, wavelength_unit)
    hit = CURVE_CACHE.get(key)
    if hit is None:
        hit = _parse(text, path, ecsv, wavelength_unit)
        CURVE_CACHE.put(key, hit, hit[0].nbytes + sum(a.nbytes for a in hit[1].values()) + len(raw))
    lbda, data = hit[0].copy(), {n: a.copy() for n, a in hit[1].items()}
    if columns is not None:
        missing = [c for c in columns if c not in data]
        if missing:
            raise CurveError(f"curve file {path} has no column(s) {missing}; it has {list(data)}")
        data = {c: data[c] for c in columns}
    if lbda.size < 2 or np.any(~np.isfinite(lbda)) or np.any(np.diff(lbda) <= 0):
        raise CurveError(f"curve file {path}: wavelengths must be finite and strictly increasing")
    return lbda, data


def _parse_error(exc):
    """The first problem NumPy's table reader reports, as one short clause."""
    import re
    text = " ".join(str(exc).split())
    bad = re.search(r"Line #(\d+) \(got (\d+) columns instead of (\d+)\)", text)
    if bad:
        line, got, want = bad.groups()
        return f"line {line} has {got} columns where the header has {want}"
    return text if len(text) <= 120 else text[:117] + "..."


def _parse(text, path, ecsv, wavelength_unit):
    """(lbda [Å], {column: values}) of a curve file's text (``path`` for messages only)."""
    try:
        if ecsv:
            from astropy.table import Table
            tab = Table.read(text.splitlines(), format="ascii.ecsv")
            names = tab.colnames
            wcol = tab[names[0]]
            unit = wavelength_unit or (str(wcol.unit) if wcol.unit is not None else "micron")
            lbda = _to_angstrom(np.asarray(wcol), unit, "micron")
            data = {n: np.asarray(tab[n], dtype=float) for n in names[1:]}
        else:
            first = text.split("\n", 1)[0]
            delim = "," if "," in first else None
            raw = np.genfromtxt(io.StringIO(text), delimiter=delim, names=True, dtype=float, comments="#")
            names = list(raw.dtype.names)
            lbda = _to_angstrom(raw[names[0]], wavelength_unit, "angstrom")
            data = {n: np.asarray(raw[n], dtype=float) for n in names[1:]}
    except CurveError:
        raise
    except Exception as exc:
        raise CurveError(f"cannot read curve file {path}: {_parse_error(exc)} (a curve file is a header line of "
                         "column names, then rows of numbers)") from None
    check_increasing(lbda, f"curve file {path}", error=CurveError, lines=lambda: data_line_numbers(text, lbda.size))
    return np.array(lbda, dtype=float), {n: np.array(a, dtype=float) for n, a in data.items()}
