"""The per-pixel part of a simulated detector's dark, as a pipeline's dark reference file holds it.

A ramp file records its detector's uniform dark as ``DARK_RATE`` (dark + thermal dark + ROIC glow /
t_frame) and, when it has bad pixels, their extra dark (warm and hot pixels) in
``truth/bad_pixels/extra_dark``: together they are the per-pixel dark of the reference files
``slicersim reffiles`` writes for the same ramps (:func:`slicersim.products.reference.reference_arrays`),
the calibration a pipeline subtracts.
"""
from __future__ import annotations

import os

import numpy as np

from slicersim.errors import RampFileError
from slicersim.reduction.checks import _DARK_MAX

__all__ = ["extra_dark", "ipc_kernel_seen"]


def extra_dark(raw_path, shape, ipc_kernel=None, rows=None):
    """The bad pixels' extra dark a ramp file records, as the rates see it.

    Parameters
    ----------
    raw_path : str or path-like
        The ramp file (HDF5); anything else (a level-1b FITS file, ramps in memory) has no map.
    shape : (ny, nx)
        The detector's shape [px]: a map of another shape is not this detector's.
    ipc_kernel : numpy.ndarray of shape (3, 3), optional
        The IPC kernel the rates are seen through (dark charge is coupled to the neighbours like any
        other charge); None: none.
    rows : sequence of (int, int), optional
        Row ranges [y0, y1) to read (a ramp file of some rows): the map elsewhere is 0, and IPC couples
        the rows of each range among themselves.

    Returns
    -------
    numpy.ndarray of shape (ny, nx) or None
        The extra dark [e-/s] (float64, 0 where the file has none or a non-finite value), or None when the
        file records no map.

    Raises
    ------
    RampFileError
        The file's map is damaged: not a dataset of real numbers, or a value no detector has (negative,
        above 1e6 e-/s), or corrupt (a failed checksum).
    """
    if not isinstance(raw_path, (str, os.PathLike)):
        return None
    import h5py
    try:
        fh = h5py.File(raw_path, "r")
    except OSError:                                   # not HDF5 (a level-1b FITS file): no map
        return None
    where = f"truth/bad_pixels/extra_dark of {os.fspath(raw_path)}"
    with fh:
        node = fh.get("truth/bad_pixels/extra_dark")
        if node is None:
            return None
        if not isinstance(node, h5py.Dataset) or node.dtype.kind not in "iuf":
            raise RampFileError(f"{where} is not a map of real rates [e-/s] "
                                f"({'a group' if not isinstance(node, h5py.Dataset) else node.dtype}): "
                                "the file is damaged (give dark= a rate or an image, or dark=None)")
        if tuple(node.shape) != tuple(shape):
            return None
        from slicersim.io.rampfile import read_dataset      # a failed checksum named, not "no map"
        ranges = ((0, shape[0]),) if rows is None else rows
        extra = np.zeros(shape)
        for y0, y1 in ranges:
            extra[y0:y1] = read_dataset(node, os.fspath(raw_path), np.s_[y0:y1])
    extra[~np.isfinite(extra)] = 0.0
    if np.any(extra < 0) or np.any(extra > _DARK_MAX):
        bad = float(extra[(extra < 0) | (extra > _DARK_MAX)].flat[0])
        raise RampFileError(f"{where} holds {bad:g} e-/s, not a dark rate (≥ 0 and ≤ {_DARK_MAX:g} e-/s): "
                            "the file is damaged (give dark= a rate or an image, or dark=None)")
    if ipc_kernel is not None:
        from slicersim.physics.ipc import apply_ipc
        for y0, y1 in ranges:
            extra[y0:y1] = apply_ipc(extra[y0:y1], ipc_kernel)
    return extra


def ipc_kernel_seen(attrs):
    """The IPC kernel a ramp file's rates are seen through, for :func:`extra_dark` when the reduction does
    not deconvolve them (``ipc=False``: the charge coupling is in the rates all the same); None where the
    file records none or its EFFECTS keyword cannot be read (``ipc=False`` is the way to reduce such a
    file)."""
    from slicersim.reduction.ipc_correction import ipc_kernel_of
    try:
        return ipc_kernel_of(attrs)
    except RampFileError:
        return None
