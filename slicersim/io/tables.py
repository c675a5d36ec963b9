"""User tables named by campaign specs: paths, digests, ECSV/CSV/Parquet reading; no physics."""
from __future__ import annotations

import hashlib
import os

import numpy as np

from slicersim import validation
from slicersim.errors import ConfigError

__all__ = ["numeric_rows", "numeric_column", "parse_toml", "resolve_path", "file_digest", "read_file_bytes", "read_table", "read_spectrum_table",
           "data_line_numbers", "check_increasing", "MAX_TEXT_BYTES", "MAX_TABLE_BYTES"]

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


def data_line_numbers(text, nrows, comments="#"):
    """Line numbers (1-based, as a text editor shows them) of the ``nrows`` data rows of a CSV, ECSV
    or whitespace table's ``text``: the lines after the column-name line that are neither blank nor
    ``comments`` (ECSV's header; None: a CSV file, where astropy reads ``#`` lines as rows); None
    when the text does not have exactly that many."""
    lines = [n for n, line in enumerate(text.splitlines(), start=1)
             if line.strip() and not (comments and line.lstrip().startswith(comments))][1:]
    return lines if len(lines) == nrows else None


def check_increasing(values, where, *, error=ConfigError, lines=None, what="wavelength", label="row", first=1):
    """Refuse the first of ``values`` that is not above the one before it (rows out of order, a
    duplicate, NaN): one ``error`` line naming ``where`` (the file), the two rows and the two values.
    ``lines``: the rows' line numbers in the file, or a callable returning them (computed only on a
    refusal); without them, rows are named ``label`` and their position counted from ``first``."""
    values = np.asarray(values, dtype=float)
    bad = np.flatnonzero(~(np.diff(values) > 0))
    if bad.size == 0:
        return
    k = int(bad[0])
    lines = lines() if callable(lines) else lines
    at = (lambda i: f"line {lines[i]}") if lines is not None else (lambda i: f"{label} {i + first}")
    rule = f"{what}s must be finite and strictly increasing (rows are never sorted or dropped)"
    a, b = values[k], values[k + 1]
    if not np.isfinite(a) or not np.isfinite(b):
        i = k if not np.isfinite(a) else k + 1
        raise error(f"{where}, {at(i)}: {what} {values[i]:.10g} is not a finite number; {rule}")
    how = f"equals {a:.10g} on {at(k)} (a duplicate row)" if a == b else f"is below {a:.10g} on {at(k)}"
    raise error(f"{where}, {at(k + 1)}: {what} {b:.10g} {how}; {rule}")


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


def parse_toml(text, what, error=ConfigError):
    """The TOML document ``text`` (str) as a dict; one ``error`` line naming ``what`` for invalid TOML,
    including nesting too deep for the parser (a 100 000-deep array was a RecursionError)."""
    import tomllib
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{what} is not valid TOML: {exc}") from None
    except RecursionError:
        raise error(f"{what} is not valid TOML for slicersim: arrays or tables nested too deeply") from None


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
            arrow = pq.read_table(path)
            nested = [f"{f.name} ({f.type})" for f in arrow.schema if not _flat_arrow_type(f.type)]
            if nested:
                raise ConfigError(f"{name}: {path}: column {nested[0]} is not a column of numbers or text: a "
                                  "catalog holds one number or string per cell")
            return Table(arrow.to_pydict())
        return Table.read(path, format=fmt)
    except ConfigError:
        raise
    except Exception as exc:
        raise ConfigError(f"{name}: cannot read {path} ({type(exc).__name__}: {' '.join(str(exc).split())[:200]})") \
            from None


def _flat_arrow_type(kind):
    """Whether a pyarrow type holds one number, boolean or string per cell (not a list, struct or map)."""
    import pyarrow as pa
    return (pa.types.is_integer(kind) or pa.types.is_floating(kind) or pa.types.is_boolean(kind)
            or pa.types.is_string(kind) or pa.types.is_large_string(kind) or pa.types.is_null(kind))


def read_spectrum_table(path, name):
    """(λ, F) float arrays from a table with columns lbda (or wavelength/wave/lambda) and flux
    (or flambda); the caller validates them."""
    tab = read_table(path, name)
    cols = {c.lower(): c for c in tab.colnames}
    lcol = next((cols[k] for k in ("lbda", "wavelength", "wave", "lambda") if k in cols), None)
    fcol = next((cols[k] for k in ("flux", "flambda", "f_lambda") if k in cols), None)
    if lcol is None or fcol is None:
        raise ConfigError(f"{name}: {path} needs columns lbda (Å) and flux (erg/s/cm²/Å), has {tab.colnames}")
    lbda = numeric_column(tab, lcol, path, name)
    check_increasing(lbda, f"{name}: {path}", what=lcol, lines=lambda: _text_lines(path, len(tab)))
    return lbda, numeric_column(tab, fcol, path, name)


def _text_lines(path, nrows):
    """:func:`data_line_numbers` of a CSV/ECSV file (None for Parquet or a file not UTF-8)."""
    fmt = TABLE_FORMATS.get(os.path.splitext(path)[1].lower())
    if fmt == "parquet":
        return None
    try:
        with open(path, encoding="utf-8") as fh:
            return data_line_numbers(fh.read(), nrows, comments="#" if fmt == "ascii.ecsv" else None)
    except (OSError, UnicodeDecodeError):
        return None


def numeric_column(tab, col, path, name):
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
            lines = _text_lines(path, len(values))
            where = f"line {lines[i]}" if lines is not None else f"data row {i + 1}"
            raise ConfigError(f"{name}: {path}, {where}: {col} = {validation.short_repr(str(value))} is not a number "
                              "(write numbers with a decimal point)") from None
    return np.asarray(values, dtype=float)


def numeric_rows(path, ncols, *, skiprows=0, error=ConfigError, what="table"):
    """(n, ``ncols``) float array of a whitespace-separated text file after ``skiprows`` lines ('#'
    comments and blank lines skipped); a row with another count of numbers, or a word, is one
    ``error`` naming the file and its line (1-based, as an editor shows it)."""
    rows = []
    with open(path, encoding="utf-8", errors="replace") as fh:
        for number, line in enumerate(fh, start=1):
            fields = line.split("#", 1)[0].split()
            if number <= skiprows or not fields:
                continue
            try:
                values = [float(v) for v in fields]
            except ValueError:
                values = None
            if values is None or len(values) != ncols:
                got = "a word" if values is None else f"{len(values)} numbers"
                raise error(f"{path}, line {number}: {got} where a {what} row has {ncols} numbers")
            rows.append(values)
    return np.array(rows, dtype=float).reshape(-1, ncols)
