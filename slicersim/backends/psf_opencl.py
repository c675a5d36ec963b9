"""OpenCL host side of the point-source PSF cubes of :mod:`slicersim.backends.psf` (``kernels/psf.cl``).

:func:`gaussian_opencl`: 1-D erf cell fractions per axis, then their outer product.
:func:`airy_window_opencl`: the Airy profile of a window of output cells, blurred and binned by
banded row and column taps; the intensity depends on |dx|, |dy| only, so sub-sample blocks, rows
and output blocks that mirror each other about the source are computed once
(:func:`mirror_blocks`, :func:`shared_rows`, :func:`output_mirror_blocks`; offsets compared as
integers of 2⁻⁴⁴ cell).  ``airy`` is the validated parameter object of :mod:`slicersim.backends.psf`
(k [rad/cell], prefactor, ε, blur σ [cells], oversampling, grid, ``axis``).
"""
from __future__ import annotations

import numpy as np

from slicersim.backends import opencl
from slicersim.backends.dispatch import chunk_ranges
from slicersim.backends.precision import real_dtype
from slicersim.physics.psf import blur_bin_taps, blur_margin, cell_quadrature

__all__ = ["KERNELS", "gaussian_opencl", "airy_window_opencl", "mirror_blocks", "output_mirror_blocks",
           "shared_rows"]

KERNELS = "psf.cl"
_FUSED_MAX_ROWS = 17      # jitter margins up to 8 cells: Airy + row blur in one kernel
_COL_ROWS_CPU = 4         # blur_bin_cols rows per work item on CPUs: 4 independent FMA chains
_CHUNK_LBDA = 16          # wavelengths per OpenCL launch: the intermediate rows stay in cache (~3 MB)


def _offset_keys(d):
    """|d| [cells] as integers (units of 2^-44 cell): equal keys, equal Airy intensity to ~1e-14."""
    return np.round(np.abs(d) * 2.0**44).astype(np.int64)


def mirror_blocks(dx, vw):
    """(nw, 2) int32: x blocks of VW sub-samples to evaluate, and the block holding the
    same |dx| in reverse order (its values are the reversed block's) or -1."""
    keys = _offset_keys(dx).reshape(-1, vw)
    seen, rows = {}, []
    for w in range(keys.shape[0]):
        partner = seen.pop(tuple(keys[w][::-1]), None)
        if partner is not None:
            rows[partner][1] = w
        else:
            seen.setdefault(tuple(keys[w]), len(rows))
            rows.append([w, -1])
    return np.ascontiguousarray(rows, dtype=np.int32).reshape(-1, 2)


def _x_layout(c0, nxo_p, mx, nx, x0, t, vw):
    """De-interleaved x sub-samples for output cells [c0, c0 + nxo_p) [window indices]:
    (xoff, ncx, dx, xblocks).  The window starts mx + xoff cells before c0; xoff < VW is
    the shift that pairs the most mirror blocks (a centred source: half of them)."""
    best = None
    for xoff in range(vw):
        ncx = -(-(nxo_p + 2 * mx + xoff) // vw) * vw
        cells = np.arange(c0 - mx - xoff, c0 - mx - xoff + ncx, dtype=float) - nx / 2.0
        dx = np.ascontiguousarray((t[:, None] + cells[None, :] - x0).ravel())
        blocks = mirror_blocks(dx, vw)
        if best is None or blocks.shape[0] < best[3].shape[0]:
            best = (xoff, ncx, dx, blocks)
        if 2 * blocks.shape[0] <= ncx * t.size // vw + 1:      # every block paired: done
            break
    return best


def output_mirror_blocks(c0, nxo_p, nx, x0, kx, vw):
    """(nwo, 2) int32: output blocks of VW cells to compute and the block whose cells
    mirror them about the source in reverse order (or -1).  Mirroring needs symmetric
    taps kx (to 1e-15) and cell centres at exactly opposite offsets (keys to 2^-44 cell)."""
    nb = nxo_p // vw
    centres = np.arange(c0, c0 + nxo_p, dtype=float) + 0.5 - nx / 2.0 - x0
    keys = np.round(centres * 2.0**44).astype(np.int64).reshape(nb, vw)
    symmetric = np.abs(kx - kx[::-1]).max() <= 1e-15 * np.abs(kx).max()
    where = {tuple(keys[w]): w for w in range(nb)}
    rows, covered = [], set()
    for w in range(nb):
        if w in covered:
            continue
        partner = where.get(tuple(-keys[w][::-1])) if symmetric else None
        if partner is not None and partner != w and partner not in covered and partner > w:
            covered.add(partner)
            rows.append([w, partner])
        else:
            rows.append([w, -1])
    return np.ascontiguousarray(rows, dtype=np.int32).reshape(-1, 2)


def shared_rows(dy):
    """int32 code per sub-sample row: -1 evaluate; 2 s evaluate and keep in slot s;
    2 s + 1 read slot s (an earlier row with the same |dy|)."""
    keys = _offset_keys(dy)
    first, counts = {}, {}
    for i, k in enumerate(keys):
        counts[k] = counts.get(k, 0) + 1
    code = np.full(keys.size, -1, dtype=np.int32)
    for i, k in enumerate(keys):
        if counts[k] < 2:
            continue
        if k in first:
            code[i] = 2 * first[k] + 1
        else:
            first[k] = len(first)
            code[i] = 2 * first[k]
    return code


def gaussian_opencl(sig_y, sig_x, shape, position, max_bytes, precision="double"):
    """Two kernels: 1-D erf cell fractions per axis, then their outer product."""
    ny, nx = shape
    nl = sig_y.size
    real = real_dtype(precision)
    out = np.empty((nl, ny, nx), real)
    opts = opencl.precision_options(precision)
    k_frac = opencl.get_kernel(KERNELS, "gaussian_cell_fractions", opts)
    k_outer = opencl.get_kernel(KERNELS, "outer_product", opts)
    size = real.itemsize
    per = size * (ny * nx + ny + nx + 2)
    step = max(1, min(nl, int(max_bytes // per)))
    d_fy, d_fx = opencl.device_buffer(size * step * ny), opencl.device_buffer(size * step * nx)
    d_out = opencl.device_buffer(size * step * ny * nx)
    for l0, l1 in chunk_ranges(nl, per, max_bytes):
        n = l1 - l0
        d_sy = opencl.to_device(np.ascontiguousarray(sig_y[l0:l1], real))
        d_sx = opencl.to_device(np.ascontiguousarray(sig_x[l0:l1], real))
        opencl.launch(k_frac, (ny, n), None, d_sy, real.type(position[1]), d_fy)
        opencl.launch(k_frac, (nx, n), None, d_sx, real.type(position[0]), d_fx)
        opencl.launch(k_outer, (nx, ny, n), None, d_fy, d_fx, d_out)
        opencl.from_device(out[l0:l1], d_out)
    return out.astype(np.float64, copy=False)


def airy_window_opencl(airy, shape, position, window, max_bytes, out_buffer=None, precision="double"):
    """OpenCL twin of :func:`slicersim.backends.psf` ``_airy_window_numpy``.

    y: ``airy_rows`` evaluates the Airy sub-samples of VW columns walking down
    the rows and applies the row taps on the fly (``airy_subsamples`` +
    ``blur_bin_rows`` when the jitter margin is too wide for registers);
    x: ``blur_bin_cols`` on sub-samples stored de-interleaved (node b of window
    cell c at b·ncx + c) so that VW consecutive output cells read contiguous
    vectors.  Output blocks of VW cells are padded symmetrically (padding is
    not stored).  The intensity depends on |dx|, |dy| only: x blocks and rows
    with the same offsets, and output blocks that mirror each other about the
    source, are computed once (a source at the centre of the narrow field:
    ¼ of the J1 evaluations, ~½ of the column contractions; 2.7× faster).
    ``out_buffer``: device buffer of ≥ 8 nλ nyo nxo bytes (single: 4) to receive the
    whole window (returned, nothing is copied to the host); None: a float64 NumPy array.
    ``precision`` "single": every kernel in float32 (sub-sample offsets, tap weights,
    accumulators), the host geometry in float64 rounded once to float32.
    """
    ny, nx = shape
    x0, y0 = position
    j0, j1_, k0, k1 = window
    real = real_dtype(precision)
    size = real.itemsize
    # the same number of lanes per vector register: twice as many floats as doubles
    oy, ox, vw = airy.o_y, airy.o_x, opencl.preferred_vector_width(16 if size == 4 else 8, 8 // size)
    dy, ky = airy.axis(j0, j1_, ny, y0, airy.sigma_y, oy)
    nyo, nxo, nys = j1_ - j0, k1 - k0, dy.size
    mx = blur_margin(airy.sigma_x)
    nxo_p = -(-nxo // vw) * vw
    pad = (nxo_p - nxo) // 2          # output cells [k0 - pad, k0 - pad + nxo_p): symmetric padding
    t, _ = cell_quadrature(ox, airy.grid)
    kx = blur_bin_taps(ox, airy.grid, airy.sigma_x)
    xoff, ncx, dx, xblocks = _x_layout(k0 - pad, nxo_p, mx, nx, x0, t, vw)
    oblocks = output_mirror_blocks(k0 - pad, nxo_p, nx, x0, kx, vw)
    nxs, nl = ox * ncx, airy.lbda.size
    na_y = 2 * blur_margin(airy.sigma_y) + 1
    fused = na_y <= _FUSED_MAX_ROWS
    yslot = shared_rows(dy)
    nslot = int(np.count_nonzero((yslot >= 0) & (yslot % 2 == 0))) if fused else 0
    nw = xblocks.shape[0]
    per_lbda = size * ((nslot * nw * vw) if fused else nys * nxs) + size * (nyo * nxs + nyo * nxo_p) + 2 * size
    step = max(1, min(nl, int(max_bytes // per_lbda), _CHUNK_LBDA))
    jr = 1 if vw == 1 else _COL_ROWS_CPU       # rows per blur_bin_cols work item (GPUs: 1)
    opts = (f"-DVW={vw}", f"-DJR={jr}") + ((f"-DNA={na_y}",) if fused else ()) + opencl.precision_options(precision)
    if fused:
        k_rows = opencl.get_kernel(KERNELS, "airy_rows", opts)
        d_xb, d_ys = opencl.to_device(xblocks), opencl.to_device(yslot)
        d_t = opencl.device_buffer(size * step * nslot * nw * vw)
    else:
        k_sub = opencl.get_kernel(KERNELS, "airy_subsamples", opts)
        k_rows = opencl.get_kernel(KERNELS, "blur_bin_rows", opts)
        d_s = opencl.device_buffer(size * step * nys * nxs)
    k_cols = opencl.get_kernel(KERNELS, "blur_bin_cols", opts)
    d_dx, d_dy = opencl.to_device(dx.astype(real)), opencl.to_device(np.ascontiguousarray(dy, real))
    d_ky, d_kx = opencl.to_device(ky.astype(real)), opencl.to_device(kx.astype(real))
    d_ob = opencl.to_device(oblocks)
    d_u = opencl.device_buffer(size * step * nyo * nxs)
    on_device = out_buffer is not None
    d_out = out_buffer if on_device else opencl.device_buffer(size * step * nyo * nxo)
    out = None if on_device else np.empty((nl, nyo, nxo), real)
    i32, f64 = np.int32, real.type
    for l0 in range(0, nl, step):
        l1 = min(nl, l0 + step)
        n = l1 - l0
        d_k = opencl.to_device(np.ascontiguousarray(airy.kwave[l0:l1], real))
        d_p = opencl.to_device(np.ascontiguousarray(airy.pref[l0:l1], real))
        if fused:
            opencl.launch(k_rows, (nw, n), None, d_dx, d_dy, d_k, d_p, d_ky, d_xb, d_ys, f64(airy.eps),
                          i32(oy), i32(nyo), i32(nxs), i32(nslot), d_t, d_u)
        else:
            opencl.launch(k_sub, (nxs // vw, nys, n), None, d_dx, d_dy, d_k, d_p, f64(airy.eps),
                          i32(nxs), d_s)
            opencl.launch(k_rows, (nxs // vw, nyo, n), None, d_s, d_ky, i32(ky.size), i32(oy),
                          i32(nys), i32(nxs), d_u)
        opencl.launch(k_cols, (oblocks.shape[0], -(-nyo // jr), n), None, d_u, d_kx, d_ob, i32(2 * mx + 1),
                      i32(ox), i32(ncx), i32(xoff), i32(pad), i32(nxo), i32(l0 if on_device else 0),
                      i32(nyo), d_out)
        if not on_device:
            opencl.from_device(out[l0:l1], d_out)
    return out_buffer if on_device else out.astype(np.float64, copy=False)
