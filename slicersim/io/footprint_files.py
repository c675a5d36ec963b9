"""Files of detector footprints for pipelines: a FITS label image and a JSON description.

No physics here: the writers take an integer image and a JSON-able mapping (built by
:func:`slicersim.instrument.footprints.save_footprints`).  :func:`write_footprint_set`
publishes both files together (:func:`slicersim.io.file_set.write_files`: temporaries in the
directory, renamed in under a lock only when both are complete; a full disk or a killed
writer leaves neither, concurrent writers never a mixed pair); an existing file is refused
unless ``overwrite``.

* ``<name>_labels.fits``: primary HDU, the label image ``image[row, col]`` (int16 when the
  values fit, else int32), header cards given by the caller (keys ≤ 8 characters or
  HIERARCH).  FITS pixel (i, j) (1-based, i along NAXIS1) is ``image[j − 1, i − 1]``.
* ``<name>_outlines.json``: UTF-8 JSON, the mapping as given (keys sorted, no NaN).
"""
from __future__ import annotations

import io
import json
import math
import os

import numpy as np

from slicersim.errors import DatasetError, ParameterError
from slicersim.io.atomic import atomic_bytes
from slicersim.io.file_set import recover_interrupted, write_files

__all__ = ["write_label_image", "read_label_image", "write_outlines", "read_outlines", "footprint_paths",
           "check_outputs", "write_footprint_set", "label_image_bytes", "outlines_bytes"]


def footprint_paths(directory, name="footprints"):
    """(label image path, outlines path) of a footprint set ``name`` in ``directory``."""
    if not name or os.sep in name or name.startswith("."):
        raise ParameterError(f"footprint name must be a plain file stem, got {name!r}")
    directory = os.fspath(directory)
    return os.path.join(directory, f"{name}_labels.fits"), os.path.join(directory, f"{name}_outlines.json")


def check_outputs(paths, overwrite=False):
    """Refuse (ParameterError) outputs that exist (without ``overwrite``) or whose directory
    is missing or not writable, before anything is computed.  A set whose writer was killed
    while publishing it (first path: the label image) is completed first."""
    if paths and os.path.isdir(os.path.dirname(os.path.abspath(paths[0]))):
        recover_interrupted(paths[0])
    for path in paths:
        directory = os.path.dirname(os.path.abspath(path))
        if not os.path.isdir(directory):
            raise ParameterError(f"output directory does not exist: {directory}")
        if not os.access(directory, os.W_OK):
            raise ParameterError(f"output directory is not writable: {directory}")
        if os.path.isdir(path):
            raise ParameterError(f"output path is a directory: {path}")
        if os.path.lexists(path) and not overwrite:
            raise ParameterError(f"output file exists: {path} (pass overwrite=True / --overwrite to replace it)")


def label_image_bytes(image, header=()):
    """A FITS file (primary HDU) of an integer image, as bytes.

    ``header``: (key, value[, comment]) cards (str, int, float or bool values)."""
    from astropy.io import fits
    arr = np.asarray(image)
    if arr.ndim != 2 or not np.issubdtype(arr.dtype, np.integer):
        raise ParameterError(f"label image must be a 2-D integer array, got {arr.dtype} {arr.shape}")
    lo, hi = (int(arr.min()), int(arr.max())) if arr.size else (0, 0)
    dtype = np.int16 if -2**15 <= lo and hi < 2**15 else np.int32
    if not (-2**31 <= lo and hi < 2**31):
        raise ParameterError("label values do not fit in 32-bit integers")
    hdu = fits.PrimaryHDU(arr.astype(dtype))
    for card in header:
        key, value, *comment = card
        if not isinstance(value, (str, int, float, bool, np.integer, np.floating)):
            raise ParameterError(f"header value of {key} must be a str, int, float or bool, got {value!r}")
        if isinstance(value, (float, np.floating)) and not math.isfinite(value):
            raise ParameterError(f"header value of {key} must be finite, got {value!r}")
        key = key if len(key) <= 8 else f"HIERARCH {key}"
        hdu.header.append(fits.Card(key, value.item() if isinstance(value, np.generic) else value,
                                    comment[0] if comment else None), end=True)
    buf = io.BytesIO()
    hdu.writeto(buf)
    return buf.getvalue()


def write_label_image(path, image, header=(), overwrite=False):
    """Write an integer image to a FITS file (:func:`label_image_bytes`) atomically."""
    atomic_bytes(path, label_image_bytes(image, header), overwrite=overwrite, error_class=DatasetError)
    return os.fspath(path)


def read_label_image(path):
    """(image in native byte order, header dict) of a label image from :func:`write_label_image`."""
    from astropy.io import fits
    with fits.open(path, memmap=False) as hdul:
        data = np.asarray(hdul[0].data)
        header = {k: v for k, v in hdul[0].header.items() if k not in ("COMMENT", "")}
    return data.astype(data.dtype.newbyteorder("=")), header


def outlines_bytes(description):
    """A JSON-able mapping (polygons, ranges, metadata) as UTF-8 JSON bytes."""
    try:
        text = json.dumps(description, sort_keys=True, allow_nan=False, separators=(",", ":"))
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"footprint description is not plain JSON: {exc}") from exc
    return (text + "\n").encode("utf-8")


def write_outlines(path, description, overwrite=False):
    """Write a JSON-able mapping to ``path`` as JSON (:func:`outlines_bytes`) atomically."""
    atomic_bytes(path, outlines_bytes(description), overwrite=overwrite, error_class=DatasetError)
    return os.fspath(path)


def write_footprint_set(paths, image, header, description, overwrite=False, also=None):
    """Write the label image and the outlines (``paths`` from :func:`footprint_paths`) and the
    files ``also`` ({path: bytes or a callable writing to a binary file}, e.g. a figure),
    published together: all of them or none (:func:`~slicersim.io.file_set.write_files`).
    Everything is encoded before anything is written.  Returns the paths written."""
    absolute = [os.path.abspath(os.fspath(p)) for p in paths]
    files = {absolute[0]: label_image_bytes(image, header), absolute[1]: outlines_bytes(description)}
    for path, data in (also or {}).items():
        files[os.path.abspath(os.fspath(path))] = data
    if len(files) != 2 + len(also or {}):
        raise ParameterError(f"output paths must be distinct, got {list(files)}")
    write_files(files, overwrite=overwrite, error_class=DatasetError)
    return tuple(os.fspath(p) for p in paths) + tuple(os.fspath(p) for p in (also or {}))


def read_outlines(path):
    """The mapping written by :func:`write_outlines` (DatasetError naming ``path`` when the file is
    not UTF-8 JSON)."""
    with open(path, "rb") as fh:
        raw = fh.read()
    try:
        return json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{os.fspath(path)}: not a footprint outlines JSON file ({exc})") from None
