"""User tables named by campaign specs: paths, digests, ECSV/CSV/Parquet reading; no physics."""
from __future__ import annotations

import hashlib
import os

import numpy as np

from slicersim import validation
from slicersim.errors import ConfigError

__all__ = ["resolve_path", "file_digest", "read_file_bytes", "read_table", "read_spectrum_table",
           "MAX_TEXT_BYTES", "MAX_TABLE_BYTES"]

#: largest text input read whole (configuration, campaign spec, effects config, curve) [bytes]
MAX_TEXT_BYTES = 64 << 20
#: largest table (spectrum, catalog) read [bytes]
MAX_TABLE_BYTES = 2 << 30

TABLE_FORMATS = {".ecsv": "ascii.ecsv", ".csv": "ascii.csv", ".parquet": "parquet", ".pq": "parquet"}


def read_file_bytes(path, error_class, what, max_bytes=MAX_TEXT_BYTES):
    """The bytes of ``path``, or one ``error_class`` line "cannot read <what> <path>: <reason>".

    ``path`` must be a regular file of at most ``max_bytes`` bytes (a FIFO, device or directory is
    refused before it is opened: reading ``/dev/zero`` or a FIFO would never end)."""
    path = validation.regular_file(what, path, error=error_class, max_bytes=max_bytes)
    try:
        with open(path, "rb") as fh:
            return fh.read()
    except OSError as exc:
        raise error_class(f"cannot read {what} {path}: {exc.strerror or exc}") from None


def resolve_path(path, base_dir, name):
    """Absolute path of an existing file named by spec key ``name`` (relative to ``base_dir``)."""
    if not isinstance(path, str) or not path:
        raise ConfigError(f"{name} must be a file path, got {path!r}")
    full = path if os.path.isabs(path) else os.path.normpath(os.path.join(base_dir, path))
    if not os.path.lexists(full):
        raise ConfigError(f"{name}: no such file {full}")
    return validation.regular_file(name, full, error=ConfigError, max_bytes=MAX_TABLE_BYTES)


def file_digest(path):
    """sha256 of a file's bytes (a regular file: a FIFO or device is refused, ConfigError)."""
    path = validation.regular_file("file", path, error=ConfigError)
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_table(path, name):
    """astropy Table from an .ecsv, .csv or .parquet file (one ConfigError naming ``name``)."""
    from astropy.table import Table
    path = validation.regular_file(name, path, error=ConfigError, max_bytes=MAX_TABLE_BYTES)
    fmt = TABLE_FORMATS.get(os.path.splitext(path)[1].lower())
    if fmt is None:
        raise ConfigError(f"{name}: {path} must be an .ecsv, .csv or .parquet file")
    try:
        if fmt == "parquet":                    # pyarrow directly (astropy's reader needs pandas)
            import pyarrow.parquet as pq
            return Table(pq.read_table(path).to_pydict())
        return Table.read(path, format=fmt)
    except Exception as exc:
        raise ConfigError(f"{name}: cannot read {path} ({type(exc).__name__}: {' '.join(str(exc).split())[:200]})") \
            from None


def read_spectrum_table(path, name):
    """(λ, F) float arrays from a table with columns lbda (or wavelength/wave/lambda) and flux
    (or flambda); the caller validates them."""
    tab = read_table(path, name)
    cols = {c.lower(): c for c in tab.colnames}
    lcol = next((cols[k] for k in ("lbda", "wavelength", "wave", "lambda") if k in cols), None)
    fcol = next((cols[k] for k in ("flux", "flambda", "f_lambda") if k in cols), None)
    if lcol is None or fcol is None:
        raise ConfigError(f"{name}: {path} needs columns lbda (Å) and flux (erg/s/cm²/Å), has {tab.colnames}")
    return _numeric(tab, lcol, path, name), _numeric(tab, fcol, path, name)


def _numeric(tab, col, path, name):
    """Column ``col`` as floats; ConfigError naming the file, the data row (its line in a CSV file)
    and the value of the first entry that is not a number (``5000,x``; a decimal comma ``1,5``)."""
    values = tab[col]
    try:
        out = np.asarray(values, dtype=float)
        if not np.any(getattr(values, "mask", False)):
            return out
    except (TypeError, ValueError):
        pass
    for i, value in enumerate(values):
        try:
            if np.ma.is_masked(value):
                raise ValueError  # internal: an empty entry, reported just below
            float(value)
        except (TypeError, ValueError):
            where = f"line {i + 2}" if path.lower().endswith(".csv") else f"data row {i + 1}"
            raise ConfigError(f"{name}: {path}, {where}: {col} = {validation.short_repr(str(value))} is not a number "
                              "(write numbers with a decimal point)") from None
    return np.asarray(values, dtype=float)
