"""Reference-pixel correction of NIR ramps: JWST's ``refpix`` algorithm as its documentation
describes it (jwst docs, refpix step, "NIR detector data"; arguments odd_even_columns,
use_side_ref_pixels, side_smoothing_length, side_gain).

For every integration and group:

1. top/bottom correction: for each output (amplifier) the mean of the reference pixels in
   the top and bottom ``border`` rows of its columns, separately for even and odd detector
   columns (odd_even_columns), is subtracted from every pixel of those columns;
2. side correction (use_side_ref_pixels): per row, the mean of the left and right reference
   columns (after step 1), smoothed by a running median over ``side_smoothing_length`` rows
   and multiplied by ``side_gain``, is subtracted from the whole row.

Differences from the pipeline: plain means where JWST uses sigma-clipped means (our
reference pixels have no outliers unless asked for), and no reordering (our data are in
detector coordinates already).
"""
from __future__ import annotations

import numpy as np
from scipy.ndimage import median_filter

from slicersim.errors import EffectsError

__all__ = ["refpix_correct", "refpix_offsets"]


def refpix_correct(sci, n_outputs=32, border=4, odd_even_columns=True, use_side_ref_pixels=True,
                   side_smoothing_length=11, side_gain=1.0):
    """Reference-pixel corrected copy of SCI (nints, ngroups, ny, nx) as float64 [same units]."""
    data = np.array(sci, dtype=np.float64, copy=True)
    if data.ndim != 4:
        raise EffectsError(f"reference-pixel correction: SCI must be 4-D (nints, ngroups, ny, nx), got shape {data.shape}")
    nints, ngroups, ny, nx = data.shape
    check_refpix_layout((ny, nx), n_outputs, border, side_smoothing_length=side_smoothing_length)
    for i in range(nints):
        for g in range(ngroups):
            frame = data[i, g]
            col, row = refpix_offsets(np.concatenate([frame[:border], frame[-border:]], axis=0),
                                      np.concatenate([frame[:, :border], frame[:, -border:]], axis=1),
                                      n_outputs, border, odd_even_columns, use_side_ref_pixels,
                                      side_smoothing_length, side_gain)
            frame -= col[None, :]
            frame -= row[:, None]
    return data


def check_refpix_layout(shape, n_outputs=32, border=4, odd_even_columns=True, use_side_ref_pixels=True,
                        side_smoothing_length=11, side_gain=1.0):
    """Refuse (EffectsError) a correction impossible on a (ny, nx) detector: nx not divisible by the
    outputs, a border that leaves no pixel, a smoothing length < 1."""
    ny, nx = shape
    if n_outputs < 1 or nx % n_outputs:
        raise EffectsError(f"reference-pixel correction of this file: its width nx = {nx} is not divisible by its "
                           f"n_outputs = {n_outputs} (the file's EFFECTS ask for the correction; refpix=False in Python, "
                           "--no-refpix on the command line, skips it)")
    if border < 1 or ny <= 2 * border or nx <= 2 * border:
        raise EffectsError(f"reference-pixel correction of this file: a border of {border} reference pixels is "
                           f"impossible for its {ny}×{nx} detector (the file's EFFECTS ask for the correction; "
                           "refpix=False in Python, --no-refpix on the command line, skips it)")
    if side_smoothing_length < 1:
        raise EffectsError(f"reference-pixel correction: side_smoothing_length must be ≥ 1, got {side_smoothing_length}")


def refpix_offsets(refrows, refcols, n_outputs=32, border=4, odd_even_columns=True, use_side_ref_pixels=True,
                   side_smoothing_length=11, side_gain=1.0):
    """The correction of one frame from its reference pixels alone: corrected = frame − col[x] − row[y].

    Parameters
    ----------
    refrows : numpy.ndarray of shape (2·border, nx)
        The frame's top ``border`` rows then its bottom ``border`` rows [DN].
    refcols : numpy.ndarray of shape (ny, 2·border)
        The frame's left ``border`` columns then its right ``border`` columns [DN].
    n_outputs, border, odd_even_columns, use_side_ref_pixels, side_smoothing_length, side_gain
        As :func:`refpix_correct`.

    Returns
    -------
    col : numpy.ndarray of shape (nx,)
        Top/bottom term of every column [DN]: the mean of its output's (and parity's) reference rows.
    row : numpy.ndarray of shape (ny,)
        Side term of every row [DN] (zeros without ``use_side_ref_pixels``).
    """
    refrows = np.asarray(refrows, np.float64)
    refcols = np.asarray(refcols, np.float64)
    nx, ny = refrows.shape[1], refcols.shape[0]
    ncol = nx // n_outputs
    col = np.empty(nx)
    x = np.arange(nx)
    for o in range(n_outputs):
        x0 = o * ncol
        for par in ((0, 1) if odd_even_columns else (None,)):
            cols = x[x0:x0 + ncol]
            if par is not None:
                cols = cols[cols % 2 == par]
            col[cols] = refrows[:, cols].mean()
    row = np.zeros(ny)
    if use_side_ref_pixels:
        side_x = np.concatenate([x[:border], x[-border:]])
        side = (refcols - col[side_x][None, :]).mean(axis=1)          # after the top/bottom step
        row = side_gain * median_filter(side, size=int(side_smoothing_length), mode="nearest")
    return col, row
