"""User tables named by campaign specs: paths, digests, ECSV/CSV/Parquet reading; no physics."""
from __future__ import annotations

import hashlib
import os

import numpy as np

from slicersim.errors import ConfigError

__all__ = ["resolve_path", "file_digest", "read_file_bytes", "read_table", "read_spectrum_table"]

TABLE_FORMATS = {".ecsv": "ascii.ecsv", ".csv": "ascii.csv", ".parquet": "parquet", ".pq": "parquet"}


def read_file_bytes(path, error_class, what):
    """The bytes of ``path``, or one ``error_class`` line "cannot read <what> <path>: <reason>"."""
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
    if not os.path.isfile(full):
        raise ConfigError(f"{name}: no such file {full}")
    return full


def file_digest(path):
    """sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_table(path, name):
    """astropy Table from an .ecsv, .csv or .parquet file (one ConfigError naming ``name``)."""
    from astropy.table import Table
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
    try:
        return np.asarray(tab[lcol], dtype=float), np.asarray(tab[fcol], dtype=float)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{name}: {path}: non-numeric lbda / flux ({exc})") from None
