"""NumPy ``.npy`` inputs we did not write: the header is checked before any data are read."""
from __future__ import annotations

import math
import os

import numpy as np

from slicersim import validation
from slicersim.errors import ParameterError

__all__ = ["load_npy"]


def _header(fh):
    """(shape, dtype) of an open ``.npy`` file, or None when it has no readable ``.npy`` header."""
    fmt = np.lib.format
    try:
        version = fmt.read_magic(fh)
        if version == (1, 0):
            shape, _, dtype = fmt.read_array_header_1_0(fh)
        elif version == (2, 0):
            shape, _, dtype = fmt.read_array_header_2_0(fh)
        else:                                     # (3, 0): utf-8 field names, no public reader
            shape, _, dtype = fmt._read_array_header(fh, version)
    except (ValueError, OSError, AttributeError, SyntaxError):
        return None
    return shape, dtype


def load_npy(name, path, *, error=ParameterError):
    """The array of the ``.npy`` file ``path`` (``allow_pickle=False``).  Before reading, its header:
    a declared shape whose bytes the file does not hold (a 200-byte file declaring 10⁵ × 10⁵ values)
    is ``error`` naming ``name``, the file and the shape; one larger than this machine's memory is a
    :class:`~slicersim.errors.ResourceError`.  A file without a ``.npy`` header is left to
    ``np.load`` (its ``ValueError``); an empty file is ``error``."""
    with open(path, "rb") as fh:
        header = _header(fh)
        start = fh.tell()
    if header is not None and not header[1].hasobject:
        shape, dtype = header
        nbytes = math.prod(shape) * dtype.itemsize
        held = os.path.getsize(path) - start
        if nbytes > held:
            raise error(f"{name}: {path} declares an array of shape {tuple(shape)} {dtype} ({nbytes / 2**30:.3g} "
                        f"GiB) but holds {held} bytes of data: a truncated or forged .npy file")
        validation.memory(f"{name}: {path} (shape {tuple(shape)} {dtype})", nbytes)
    try:
        return np.load(path, allow_pickle=False)
    except EOFError:                              # an empty file: NumPy's "No data left in file"
        raise error(f"{name}: {path} is empty: not a NumPy .npy file") from None
