"""Numerical hot loops with an OpenCL implementation and a NumPy twin.

Every public function takes ``backend="auto" | "opencl" | "numpy"``; "auto"
uses OpenCL when a device with double precision is available (see
:mod:`slicersim.backends.opencl`) and NumPy otherwise.  Both backends agree to about
1e-12 relative (they differ only in summation order and FMA contraction).
"""

from __future__ import annotations

import numpy as np

from slicersim import validation
from slicersim.backends import opencl
from slicersim.backends.dispatch import DEFAULT_MAX_BYTES, chunk_ranges
from slicersim.backends.opencl import check_vector_width
from slicersim.errors import ParameterError

__all__ = ["band_variance_table"]


def _check_inputs(Q, P2, A, B, Qsat, band):
    """The inputs of :func:`band_variance_table` as contiguous arrays of the kernel's types, their
    shapes consistent (ParameterError naming the array otherwise)."""
    Q = np.asarray(Q)                 # kept in its own dtype (read chunk by chunk: no copy of the whole)
    if Q.ndim != 3 or Q.dtype.kind not in "biuf":
        raise ParameterError(f"Q must be a real array of shape (N, nlbda, ncell), got {Q.dtype} {Q.shape}")
    N, nlbda, ncell = Q.shape
    P2 = np.ascontiguousarray(validation.array("P2", P2, ndim=2, finite=False))
    if P2.shape != (nlbda, ncell):
        raise ParameterError(f"P2 must have shape {(nlbda, ncell)}, got {P2.shape}")
    A, B, Qsat = (np.asarray(validation.array(name, x, finite=False)) for name, x in (("A", A), ("B", B), ("Qsat", Qsat)))
    if not A.shape == B.shape == Qsat.shape:
        raise ParameterError(f"A, B, Qsat must have the same length (shape), got {A.shape}, {B.shape}, {Qsat.shape}")
    if A.ndim == 2 and A.shape[0] == N:            # per-target candidates (N, K)
        A, B, Qsat = (np.ascontiguousarray(x) for x in (A, B, Qsat))
    else:
        A, B, Qsat = (np.ascontiguousarray(np.ravel(x)) for x in (A, B, Qsat))
    band = np.asarray(band)
    if band.shape != (N, 2) or not np.issubdtype(band.dtype, np.integer):
        raise ParameterError(f"band must be an integer array of shape {(N, 2)}, got {band.dtype} {band.shape}")
    band = np.ascontiguousarray(band, dtype=np.int32)
    if N and (band[:, 0].min() < 0 or band[:, 1].max() > nlbda or np.any(band[:, 1] < band[:, 0])):
        raise ParameterError(f"band ranges must satisfy 0 <= i0 <= i1 <= nlbda={nlbda}")
    return Q, P2, A, B, Qsat, band


def _bin_range(band):
    """Smallest bin range [lo, hi) covering all bands of a chunk (empty bands ignored)."""
    nonempty = band[:, 1] > band[:, 0]
    if not nonempty.any():
        return 0, 0
    return int(band[nonempty, 0].min()), int(band[nonempty, 1].max())


def band_variance_table(Q, P2, A, B, Qsat, band, backend="auto", *,
                        max_bytes=DEFAULT_MAX_BYTES, vector_width=None, precision=None):
    """Band-summed optimal-extraction variance for N targets x K candidate readouts.

    Parameters
    ----------
    Q : (N, nlbda, ncell) float array
        Electron rate per aperture cell (e-/s); NaN marks an invalid bin.
    P2 : (nlbda, ncell) float array
        Squared PSF extraction weights.
    A, B : (K,) float arrays, or (N, K): candidates of each target
        Cell variance of candidate k is ``A[k] + B[k] * Q`` (ADU^2) (``A[t, k] + B[t, k] * Q`` per target).
    Qsat : (K,) or (N, K) float array, as A
        Cells with ``Q > Qsat[k]`` are saturated (weight 0); +inf: none.
    band : (N, 2) int array
        Half-open bin range [i0, i1) of each target's band.
    backend : "auto", "opencl" or "numpy"
    max_bytes : int
        Approximate memory budget of the temporaries; targets are processed
        in chunks that fit in it (at least one target per chunk).
    vector_width : int, optional
        OpenCL only: candidates per work item (1, 2, 4, 8, 16); default
        from the device (1 on GPUs).
    precision : None (the ETC's: float64, the NumPy twin on a device without fp64), or
        "auto" | "double" | "single" (the batch ETC's dial, :mod:`slicersim.backends.precision`,
        product ``"batch_etc"``; single: float kernel with compensated sums, float64 results)

    Returns
    -------
    var_sum : (N, K) float64
        Sum over valid bins of the per-bin variance ``1 / w`` (+inf when
        a bin has all its cells saturated).
    nvalid : (N, K) int32
        Number of valid (non-NaN) bins; the band-mean variance is
        ``var_sum / nvalid``.
    """
    from slicersim.backends.precision import float64_kwargs, resolve_precision
    if precision is None:                                   # the single-target ETC: float64 on every device
        backend, precision = float64_kwargs(backend).values()
    else:
        backend, precision = resolve_precision(precision, backend, "batch_etc")
    Q, P2, A, B, Qsat, band = _check_inputs(Q, P2, A, B, Qsat, band)
    K = A.shape[-1]
    var_sum = np.zeros((Q.shape[0], K), np.float64)     # accumulated in place by either backend
    nvalid = np.zeros((Q.shape[0], K), np.int32)
    if var_sum.size == 0:
        return var_sum, nvalid
    if backend == "opencl":
        _band_variance_opencl(Q, P2, A, B, Qsat, band, max_bytes, vector_width, var_sum, nvalid, precision)
    else:
        _band_variance_numpy(Q, P2, A, B, Qsat, band, max_bytes, var_sum, nvalid)
    return var_sum, nvalid


def _band_variance_numpy(Q, P2, A, B, Qsat, band, max_bytes, var_sum, nvalid):
    N, nlbda, ncell = Q.shape
    K = A.shape[-1]
    per_target_cand = A.ndim == 2
    # per target: the float64 copy of its Q row plus ~4 (K, ncell) temporaries
    per_target = 8 * (nlbda * ncell + 4 * K * ncell + 2 * K)
    Ak, Bk, Sk = A[..., None], B[..., None], Qsat[..., None]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for t0, t1 in chunk_ranges(N, per_target, max_bytes):
            bd = band[t0:t1]
            lo, hi = _bin_range(bd)
            Qc = np.asarray(Q[t0:t1, lo:hi], dtype=np.float64)
            vs, nv = var_sum[t0:t1], nvalid[t0:t1]
            # loop over bins (sequential accumulation, as in the kernel);
            # vectorised over targets x candidates x cells
            for i in range(lo, hi):
                inband = (bd[:, 0] <= i) & (i < bd[:, 1])
                if inband.all():
                    inband = slice(None)
                elif not inband.any():
                    continue
                q = Qc[inband, i - lo][:, None, :]   # (n, 1, ncell)
                a, b, qs = (x[t0:t1][inband] for x in (Ak, Bk, Sk)) if per_target_cand else (Ak, Bk, Sk)
                term = P2[i] / (a + b * q)           # (n, K, ncell)
                term[q > qs] = 0.0                   # saturated cells: weight 0
                v = 1.0 / term.sum(axis=-1)          # (n, K); +inf if all saturated
                ok = ~np.isnan(v)
                vs[inband] += np.where(ok, v, 0.0)
                nv[inband] += ok
    return var_sum, nvalid


def nonzero_weights(P2):
    """CSR form of the non-zero extraction weights: (weight (nnz,) float64, cell (nnz,)
    int32, row_start (nlbda + 1,) int32), bin-major, cells in increasing order."""
    nz = P2 != 0
    row_start = np.zeros(P2.shape[0] + 1, np.int32)
    np.cumsum(nz.sum(axis=1), out=row_start[1:])
    bins, cells = np.nonzero(nz)
    if cells.size == 0:                    # keep the buffers non-empty for OpenCL
        return np.zeros(1), np.zeros(1, np.int32), row_start
    return np.ascontiguousarray(P2[bins, cells]), cells.astype(np.int32), row_start


def _pow2_at_most(n, cap):
    w = 1
    while w * 2 <= min(n, cap):
        w *= 2
    return w


def _band_variance_opencl(Q, P2, A, B, Qsat, band, max_bytes, vector_width, var_sum, nvalid, precision="double"):
    N, nlbda, ncell = Q.shape
    K = A.shape[-1]
    per_target_cand = A.ndim == 2
    real = np.float32 if precision == "single" else np.float64
    size = np.dtype(real).itemsize
    if precision == "double":
        opencl.require_fp64()
    dev = opencl.get_device()
    is_gpu = "GPU" in opencl.device_type(dev)
    if vector_width is None:
        vector_width = opencl.preferred_vector_width(16)
        # do not pad a handful of candidates up to a wide vector
        while vector_width > 1 and vector_width // 2 >= K:
            vector_width //= 2
    vector_width = check_vector_width(vector_width)
    VW = vector_width
    local = None
    mult = VW
    if is_gpu:  # pad to whole work groups along the candidate axis
        L = _pow2_at_most(-(-K // VW), min(64, int(dev.max_work_group_size)))
        local, mult = (L, 1), VW * L
    Kp = -(-K // mult) * mult
    # padded with the last candidate (of each target's row)
    pad = lambda x: np.ascontiguousarray(np.concatenate([x, np.repeat(x[..., -1:], Kp - K, axis=-1)], axis=-1),
                                         dtype=real)
    Ap, Bp, Sp = pad(A), pad(B), pad(Qsat)

    per_target = 2 * size * nlbda * ncell + 2 * 12 * Kp + 16 + (3 * size * Kp if per_target_cand else 0)
    nt_max = max(1, min(N, int(max_bytes // per_target)))
    # one kernel object and scratch buffers per thread, reused between calls (the batch ETC makes
    # several small calls per chunk of targets: creating them cost ~1 ms per call)
    kern = opencl.cached_kernel("band_variance.cl", "band_variance", (f"-DVW={VW}",) + opencl.precision_options(precision))
    weight, cell, row_start = nonzero_weights(P2)
    weight = np.ascontiguousarray(weight, dtype=real)
    # uploads are not blocking (in-order queue; every chunk ends with blocking reads, and the host
    # arrays of a chunk are kept in `held` until then)
    held = [weight, cell, row_start]
    d_w, d_c, d_r = (opencl.scratch_buffer(f"bv_{tag}", x.nbytes) for tag, x in zip("wcr", held))
    for x, d_x in zip(held, (d_w, d_c, d_r)):
        opencl.to_device_nowait(x, d_x)
    rows = nt_max if per_target_cand else 1                 # per target: uploaded chunk by chunk
    d_A, d_B, d_S = (opencl.scratch_buffer(f"bv_{tag}", size * rows * Kp) for tag in "ABS")
    if not per_target_cand:
        for x, d_x in ((Ap, d_A), (Bp, d_B), (Sp, d_S)):
            opencl.to_device_nowait(x, d_x)
    d_Q = opencl.scratch_buffer("bv_Q", size * nt_max * nlbda * ncell)
    d_band = opencl.scratch_buffer("bv_band", 8 * nt_max)
    d_vs = opencl.scratch_buffer("bv_vs", size * nt_max * Kp)
    d_nv = opencl.scratch_buffer("bv_nv", 4 * nt_max * Kp)
    h_vs = np.empty((nt_max, Kp), real)
    h_nv = np.empty((nt_max, Kp), np.int32)
    i32 = np.int32
    for t0, t1 in chunk_ranges(N, per_target, max_bytes):
        nt = t1 - t0
        bd = band[t0:t1]
        lo, hi = _bin_range(bd)
        nb = hi - lo
        chunk_held = [bd]
        if nb:
            chunk_held.append(np.ascontiguousarray(Q[t0:t1, lo:hi], dtype=real))
            opencl.to_device_nowait(chunk_held[-1], d_Q)
        opencl.to_device_nowait(bd, d_band)
        if per_target_cand:
            for x, d_x in ((Ap, d_A), (Bp, d_B), (Sp, d_S)):
                chunk_held.append(x[t0:t1])
                opencl.to_device_nowait(chunk_held[-1], d_x)
        opencl.launch(kern, (Kp // VW, nt), local, d_Q, d_w, d_c, d_r, d_A, d_B, d_S, d_band,
                      i32(Kp), i32(Kp if per_target_cand else 0), i32(nb), i32(ncell), i32(lo), d_vs, d_nv)
        opencl.from_device_nowait(h_vs[:nt], d_vs)
        opencl.from_device(h_nv[:nt], d_nv)         # blocking: the queue (in order) is done
        var_sum[t0:t1] = h_vs[:nt, :K]
        nvalid[t0:t1] = h_nv[:nt, :K]
    return var_sum, nvalid
