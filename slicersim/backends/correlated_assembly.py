"""Assembly of one group of the correlated read noise of :class:`~slicersim.backends.correlated_noise.CorrelatedNoise`.

The group-mean noise [e-] of pixel (row, x) of output o at scan position j is the sum of

* the high part: the windowed segment streams (common + output o) of the row's segment and of
  its overlap neighbour (sin/cos tapers whose squares sum to one);
* the low part: A + (A' − A)·j/row_len (common + output streams at the row and the next row,
  linear interpolation along the scan), plus the alternating (even/odd) term ± the same of the
  alternating stream;
* the pedestal of output o and the picture frame pf·(e_y(row) + e_x(x)).

``assemble_group`` (``kernels/correlated_noise.cl``) and its NumPy twin :func:`assemble_numpy`
compute it from :class:`GroupInputs`; ``gen`` is the generator (its geometry and segment layout).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slicersim.backends import opencl

__all__ = ["GroupInputs", "assemble_numpy", "assemble_opencl", "assembly_kernel"]


@dataclass(frozen=True)
class GroupInputs:
    """The inputs of ``assemble_group`` for one group of rows y0 … y0 + rows − 1: segment streams
    ``seg`` and windows ``win`` (first segment ``s_first``), the low-part terms at the rows and the
    next rows (``la``, ``la2``: common + output; ``aa``, ``aa2``: alternating) (rows, n_outputs),
    the pedestal ``ped`` (n_outputs,), the picture-frame amplitude ``pf`` and its row / column
    profiles ``ey`` (rows,), ``ex`` (nx,) [e-]."""
    seg: np.ndarray
    win: np.ndarray
    s_first: int
    y0: int
    la: np.ndarray
    la2: np.ndarray
    aa: np.ndarray
    aa2: np.ndarray
    ped: np.ndarray
    pf: float
    ey: np.ndarray
    ex: np.ndarray


def _group_inputs(args):
    """A :class:`GroupInputs` from one, or from its fields in order."""
    if len(args) == 1 and isinstance(args[0], GroupInputs):
        return args[0]
    return GroupInputs(*args)


def _segment_part(gen, inp, row, s, x_index):
    """Windowed segment stream ``s`` (rows, nx) at ``row``: its common plus output parts."""
    g = gen.geometry
    S, h = gen._segment_geometry()[:2]
    o, j = x_index
    i = s - inp.s_first
    p = (row - s * S + h) * g.row_len + j
    return inp.win[i, p] * (inp.seg[i, 0, p] + inp.seg[i, 1 + o, p])


def assemble_numpy(gen, *inputs, out):
    """NumPy twin of ``assemble_group`` (kernels/correlated_noise.cl): writes out (rows, nx);
    ``inputs``: a :class:`GroupInputs` or its fields in order."""
    inp = _group_inputs(inputs)
    g = gen.geometry
    S, h, nseg = gen._segment_geometry()[:3]
    x = np.arange(g.nx)
    o, j = x // g.ncol, g.scan_index(x)
    row = inp.y0 + np.arange(out.shape[0])[:, None]
    s1 = row // S                                          # the row's segment and its overlap neighbour
    r1 = row - s1 * S
    s2 = np.where(r1 < h, s1 - 1, np.where(r1 >= S - h, s1 + 1, -1))
    ok2 = (s2 >= 0) & (s2 < nseg)
    s2 = np.where(ok2, s2, s1)
    v1, v2 = _segment_part(gen, inp, row, s1, (o, j)), _segment_part(gen, inp, row, s2, (o, j))
    t = (j.astype(np.float32) / np.float32(g.row_len))
    a, a2, c, c2 = inp.la[:, o], inp.la2[:, o], inp.aa[:, o], inp.aa2[:, o]
    low = a + t * (a2 - a)
    alt = c + t * (c2 - c)
    v = v1 + np.where(ok2, v2, np.float32(0.0))
    v = v + low + np.where(j % 2 == 1, -alt, alt)
    out[:] = v + inp.ped[o] + np.float32(inp.pf) * (inp.ey[:, None] + inp.ex[None, :])
    return out


def assembly_kernel(ncol):
    """(``assemble_group`` kernel, columns per work item, device is a GPU): explicit float lanes on
    CPUs (the largest of 16, 8, 4, 1 dividing an output's ``ncol`` columns), one column on GPUs."""
    gpu = "GPU" in opencl.device_type(opencl.get_device())
    vw = 1 if gpu else next(v for v in (16, 8, 4, 1) if ncol % v == 0)
    return opencl.cached_kernel("correlated_noise.cl", "assemble_group", (f"-DFVW={vw}",)), vw, gpu


def assemble_opencl(gen, *inputs, out):
    """OpenCL ``assemble_group`` of one group into ``out`` (C-contiguous float32 (rows, nx)), with the
    inputs of :func:`assemble_numpy` (the kernel's group-indexed arrays holding one group)."""
    inp = _group_inputs(inputs)
    g = gen.geometry
    S, h, nseg, span, length = gen._segment_geometry()
    rows = out.shape[0]
    kern, vw, gpu = assembly_kernel(g.ncol)
    bufs = [opencl.to_device(np.ascontiguousarray(a, np.float32)) for a in (inp.seg, inp.win)]
    small = [opencl.to_device(np.ascontiguousarray(a, np.float32)) for a in
             (inp.la, inp.la2, inp.aa, inp.aa2, inp.ped, np.array([inp.pf], np.float32), inp.ey, inp.ex)]
    d_out = opencl.workspace_buffer(None, "cn_out", out.nbytes)
    opencl.launch(kern, (g.nx // vw, rows), None, *bufs, np.int32(inp.s_first), np.int32(inp.seg.shape[0]),
                  np.int32(nseg), np.int32(S), np.int32(h), np.int32(span), np.int32(length), np.int32(inp.y0),
                  np.int32(g.row_len), np.int32(g.ncol), np.int32(g.n_outputs), np.int32(g.nx), *small, d_out,
                  np.int32(0), np.int32(rows))
    opencl.from_device(out, d_out)
    return out
