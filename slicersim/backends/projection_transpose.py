"""Transpose of the cube → detector deposit: detector image → cube cells, and the explicit
matrix of a range of cells.

The deposit (:func:`slicersim.backends.projection.deposit`) is linear, image = P · cube,
with P[pixel, cell] = Σ over the cell's sub-cells of scale · wx · wy (the stored tables).
This module applies its transpose with the same tables (``kernels/project_transpose.cl``
and a NumPy twin; ``backend="auto" | "opencl" | "numpy"``):

* :func:`gather` — Pᵀ · image (``power=1``), or (P∘P)ᵀ · image (``power=2``, squared
  weights: the variance of a pixel-to-cell sum Σ_p P[p, c] d_p of independent pixels);
* :func:`matrix_entries` — the non-zero entries (pixel, cell, weight) of P for a range of
  sub-cells, for callers that factorise PᵀWP (:mod:`slicersim.reduction.rectify`).

Kept apart from :mod:`~slicersim.backends.projection` (module size; the table cache keys on
that module's source, so adding the transpose there would have invalidated every cached
table).  Units: whatever the image holds per pixel, the output holds per cell.
"""

from __future__ import annotations

import numpy as np

from slicersim import validation
from slicersim.backends import opencl
from slicersim.backends.dispatch import resolve_backend
from slicersim.backends.projection import _options
from slicersim.backends.projection_deposit import parent_index as _parent_index, table_buffer as _table_buffer
from slicersim.errors import ParameterError

__all__ = ["gather", "matrix_entries"]

_KERNEL = "project_transpose.cl"
_GATHER_CHUNK = 1 << 13          # sub-cells per NumPy chunk (~ny·nx·8 bytes of temporaries each)


def _check_image(image, tables, band=False):
    """The rows of ``image`` the tables reach, as contiguous float64 (ParameterError naming ``image``
    for a wrong shape or a NaN/inf pixel there); ``band``: ``image`` is those rows already."""
    H, W = tables.detector_shape
    r0, r1 = tables.row_range
    image = np.asarray(image)
    want = (r1 - r0, W) if band else (H, W)
    if image.shape != want or image.dtype.kind not in "biuf":
        raise ParameterError(f"image must be a real array of shape {want} (the tables' detector"
                             f"{f', rows {r0}:{r1}' if band else ''}), got {image.dtype} {image.shape}")
    band = np.ascontiguousarray(image if band else image[r0:r1], dtype=np.float64)
    if not np.all(np.isfinite(band)):
        raise ParameterError("image must be finite where the tables reach (replace NaN pixels first)")
    return band


def gather(image, tables, power=1, backend="auto", band=False):
    """Transpose of the deposit: (S, E/ne, Q/nq) cube values of an (H, W) image.

    Parameters
    ----------
    image : (H, W) float array, finite on the rows the tables reach [any unit per pixel]; with
        ``band``, only those rows: (r1 − r0, W) for ``tables.row_range`` = (r0, r1)
    tables : :class:`~slicersim.backends.projection.DepositTables`
    power : 1 → Pᵀ·image; 2 → (P∘P)ᵀ·image (needs ``oversample == (1, 1)``: with sub-cells
        the square of a cell's summed weight is not the sum of the sub-cells' squares).
    band : ``image`` holds the tables' rows only (work on a field's band, not the detector)

    Pixels off the detector count as zero.  ⟨deposit(v), img⟩ = ⟨v, gather(img)⟩ to rounding.
    """
    t = tables
    validation.choice("power", power, (1, 2))
    if power == 2 and tuple(t.oversample) != (1, 1):
        raise ParameterError("power=2 (squared weights) needs tables without sub-cells (oversample (1, 1))")
    band = _check_image(image, t, band)
    S, E, Q = t.grid
    ne, nq = t.oversample
    out = np.zeros((S, E // ne, Q // nq), np.float64)
    r0, r1 = t.row_range
    if r1 <= r0 or t.ncell == 0:
        return out
    if resolve_backend(backend) == "opencl":
        _gather_opencl(band, t, power, out)
    else:
        _gather_numpy(band, t, power, out)
    return out


def _windows_of(t, c):
    """Per sub-cell of ``c``: window origin/size and its x and y weights (float64, zero padded)."""
    x0, y0, nx, ny = (t.meta[c, i].astype(np.int64) for i in range(4))
    nxp = -(-nx // t.vw) * t.vw
    jx, jy = np.arange(int(nx.max()))[None], np.arange(int(ny.max()))[None]
    off = t.offset[c][:, None]
    last = t.pool_size - 1
    wx = np.where(jx < nx[:, None], t.pool[np.minimum(off + jx, last)], 0).astype(np.float64)
    wy = np.where(jy < ny[:, None], t.pool[np.minimum(off + nxp[:, None] + jy, last)], 0).astype(np.float64)
    return x0, y0, jx, jy, wx, wy


def _gather_numpy(band, t, power, out):
    """Twin of ``gather_cells``: per chunk of sub-cells, their windows read with one fancy index."""
    t.host()
    H, W = t.detector_shape
    r0, r1 = t.row_range
    flat = out.ravel()
    for c0 in range(0, t.ncell, _GATHER_CHUNK):
        c = np.arange(c0, min(c0 + _GATHER_CHUNK, t.ncell))
        c = c[t.scale[c] != 0]
        if c.size == 0:
            continue
        x0, y0, jx, jy, wx, wy = _windows_of(t, c)
        if power == 2:
            wx, wy = wx * wx, wy * wy
        rows = y0[:, None] + jy - r0                                    # (n, NY) rows of the band
        cols = x0[:, None] + jx                                         # (n, NX)
        row_ok = (rows >= 0) & (rows < r1 - r0)
        col_ok = (cols >= 0) & (cols < W)
        pix = band[np.clip(rows, 0, r1 - r0 - 1)[:, :, None], np.clip(cols, 0, W - 1)[:, None, :]]
        pix = np.where(row_ok[:, :, None] & col_ok[:, None, :], pix, 0.0)
        line = np.einsum("nyx,nx->ny", pix, wx)
        s = t.scale[c] ** power * np.einsum("ny,ny->n", line, wy)
        np.add.at(flat, _parent_index(t, c), s)


def _device_tables(t):
    dev = t.device
    if "pool" not in dev:
        for name in ("meta", "offset", "pool", "scale"):
            dev[name] = _table_buffer(getattr(t, name))
    return dev


def _gather_opencl(band, t, power, out):
    opencl.require_fp64()
    dev = _device_tables(t)
    S, E, Q = t.grid
    ne, nq = t.oversample
    H, W = t.detector_shape
    r0, r1 = t.row_range
    d_img = opencl.to_device(band)
    d_out = opencl.device_buffer(out.nbytes)
    kern = opencl.get_kernel(_KERNEL, "gather_cells", _options(t))
    lsize = 32 if "GPU" in opencl.device_type() else 1
    gsize = -(-out.size // lsize) * lsize
    i32 = np.int32
    opencl.launch(kern, (gsize,), (lsize,), d_img, dev["meta"], dev["offset"], dev["pool"], dev["scale"],
                  np.int64(out.size), i32(E), i32(Q), i32(ne), i32(nq), i32(power), i32(W), i32(r0),
                  i32(r1 - r0), d_out)
    opencl.from_device(out, d_out)


def matrix_entries(tables, first, last):
    """Non-zero entries of P for the sub-cells ``first`` … ``last − 1`` (on-detector pixels).

    Returns ``(pixel, cell, weight)``: flat pixel index row·W + column (int64), cube-cell
    index in the (S, E/ne, Q/nq) order of :func:`gather` (int64; a cell with sub-cells appears
    once per sub-cell and pixel: sum duplicates) and weight scale·wx·wy (float64).  What a
    deposit puts on a pixel is Σ weight · value[cell] over its entries.
    """
    t = tables.host()
    H, W = t.detector_shape
    first = validation.integer("first (sub-cell)", first, low=0, high=t.ncell)
    last = validation.integer("last (sub-cell)", last, low=first, high=t.ncell)
    c = np.arange(first, last)
    c = c[t.scale[c] != 0]
    if c.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    x0, y0, jx, jy, wx, wy = _windows_of(t, c)
    rows = y0[:, None] + jy
    cols = x0[:, None] + jx
    weight = (t.scale[c][:, None, None] * wy[:, :, None]) * wx[:, None, :]
    ok = ((rows >= 0) & (rows < H))[:, :, None] & ((cols >= 0) & (cols < W))[:, None, :] & (weight != 0)
    pixel = rows[:, :, None] * W + cols[:, None, :]
    cell = np.broadcast_to(_parent_index(t, c)[:, None, None], ok.shape)
    return pixel[ok], cell[ok], weight[ok]
