"""Up-the-ramp fitting of MACC group means: the kernel ``kernels/ramp_fit.cl`` and its NumPy twin.

Per pixel, over all integrations of a flat block (group means g_k [DN], gain g [DN/e-]):

* differences D_j = (g_{j+1} − g_j)/g [e-] of consecutive usable groups (not SATURATED, not
  DO_NOT_USE; a group at or above ``satlim`` and every later group are SATURATED); a JUMP_DET
  flag on group j+1 drops D_j, and so does a non-finite D_j (a NaN or infinite group mean);
* jumps (two-point differences, as stcal's): the used difference farthest from their median
  is a jump while |D_j − med| > ``jump_threshold``·σ, σ² = 2σ_g² + (max(med, 0)/τ)(τ − 2c) the
  exact variance of a difference (at least 3 differences are needed);
* the runs of used differences are the segments.  Their covariance is tridiagonal Toeplitz:
  Var D = 2σ_g² + λ(τ − 2c), Cov(D_j, D_j+1) = λc − σ_g², with σ_g² the read (and rounding)
  variance of a group mean [e-²], τ = (m + d) t_f and c = t_f (m² − 1)/(6m);
* ``ols``: unweighted least squares per segment, segments (and integrations) combined with
  read-noise weights (stcal's combination; per-run sums in closed form); ``gls``: generalised
  least squares with the exact covariance at the OLS rate λ₀ (one iteration), w = T⁻¹1 per
  segment through the leading minors of T (no division in the recurrences), which is the
  inverse-variance combination of the segments' GLS slopes.  Either way rate = Σw·D/(τΣw) and
  the variance is wᵀTw/(τΣw)², split exactly into read and Poisson parts.
* the jump test brackets the median by counting and stops as soon as the bracket decides it
  (kernel; lanes that use every one of ≤ 64 differences sort them all at once by a network);
  the twin sorts.  The decisions are the same.
* the kernel fits ``vector_width`` pixels per work item (lanes of vector types, 8 on CPUs unless
  the work group's private memory calls for fewer, 1 on GPUs) in the scalar operation order:
  every width gives the same bits.

Both backends follow the same operation order (FP contraction off in the kernel); they agree
to rounding (≈1e-15 relative) and make the same jump decisions.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slicersim.backends import opencl
from slicersim.errors import ParameterError

__all__ = ["FitConstants", "fit_constants", "fit_block_numpy", "fit_block_opencl", "check_launch", "WEIGHTINGS",
           "JUMP_MIN_DIFFS", "DQ_DO_NOT_USE", "DQ_SATURATED", "DQ_JUMP_DET"]

WEIGHTINGS = ("gls", "ols")
JUMP_MIN_DIFFS = 3                 # used differences needed to test for a jump
DQ_DO_NOT_USE, DQ_SATURATED, DQ_JUMP_DET = 1, 2, 4
MAX_GROUPS = 512                   # leading minors of the GLS recurrences stay ≥ n/2ⁿ (no underflow)


@dataclass(frozen=True)
class FitConstants:
    """Validated scalars of a fit (see :func:`fit_constants`)."""

    ngroups: int
    inv_gain: float        # e- per DN
    sg2: float             # variance of one group mean [e-²]
    tau: float             # group time (m + d) t_f [s]
    ccorr: float           # t_f (m² − 1)/(6m) [s]
    satlim: float          # DN at and above which a group is saturated (inf: never)
    jump_thr: float        # σ; 0: no jump detection
    weighting: str


def fit_constants(nmd, tframe, gain, read_noise, quantization=0.0, saturation=math.inf, jump_threshold=4.0,
                  weighting="gls"):
    """FitConstants of a MACC(n, m, d) readout.

    tframe [s]; gain [DN/e-]; read_noise [electron] per frame; quantization [DN²] added to the variance
    of each group mean (1/12 for integer data); saturation [DN]; jump_threshold [σ] (None or 0:
    off); weighting ``"gls"`` or ``"ols"``."""
    n, m, d = (int(v) for v in nmd)
    if n < 2 or n > MAX_GROUPS or m < 1 or d < 0:
        raise ParameterError(f"readout (n, m, d) = {nmd}: need 2 ≤ n ≤ {MAX_GROUPS}, m ≥ 1, d ≥ 0")
    for name, val, low in (("tframe", tframe, 0.0), ("gain", gain, 0.0)):
        if not (math.isfinite(val) and val > low):
            raise ParameterError(f"{name} must be finite and > 0, got {val}")
    for name, val in (("read_noise", read_noise), ("quantization", quantization)):
        if not (math.isfinite(val) and val >= 0):
            raise ParameterError(f"{name} must be finite and ≥ 0, got {val}")
    thr = 0.0 if jump_threshold is None else float(jump_threshold)
    if not (math.isfinite(thr) and thr >= 0):
        raise ParameterError(f"jump_threshold must be finite and ≥ 0 σ (or None), got {jump_threshold}")
    if weighting not in WEIGHTINGS:
        raise ParameterError(f"weighting must be one of {WEIGHTINGS}, got {weighting!r}")
    sat = math.inf if saturation is None else float(saturation)
    if math.isnan(sat):
        raise ParameterError("saturation must be a number of DN (or None)")
    sg2 = read_noise ** 2 / m + quantization / gain ** 2
    return FitConstants(n, 1.0 / gain, sg2, (m + d) * tframe, tframe * (m * m - 1) / (6.0 * m), sat, thr, weighting)


def _check_block(sci, gdq, pixeldq, k):
    if sci.ndim != 3 or sci.shape[1] != k.ngroups or gdq.shape != sci.shape:
        raise ValueError(f"sci and gdq must be (nints, {k.ngroups}, npix) alike, got {sci.shape} and {gdq.shape}")  # internal: blocks of fit_ramps
    if sci.dtype not in (np.uint16, np.float64) or gdq.dtype != np.uint8:
        raise ValueError(f"sci must be uint16 or float64 and gdq uint8, got {sci.dtype} and {gdq.dtype}")  # internal: blocks of fit_ramps
    if pixeldq.shape != (sci.shape[2],) or pixeldq.dtype != np.uint32:
        raise ValueError(f"pixeldq must be uint32 ({sci.shape[2]},), got {pixeldq.dtype} {pixeldq.shape}")  # internal: blocks of fit_ramps


# ----------------------------------------------------------------------------- NumPy twin
def _differences(sci_i, flags, inv_gain):
    """D (N, npix) [e-] and used (N, npix) of one integration from its flags."""
    raw = sci_i.astype(np.float64, copy=False)
    usable = (flags & (DQ_SATURATED | DQ_DO_NOT_USE)) == 0
    used = usable[:-1] & usable[1:] & ((flags[1:] & DQ_JUMP_DET) == 0)
    with np.errstate(invalid="ignore", over="ignore"):
        D = (raw[1:] - raw[:-1]) * inv_gain
    used &= np.isfinite(D)                       # a NaN or infinite difference is never used
    return D, used


def _detect_jumps(D, used, flags, njump, k, pois_diag):
    """Flag jumps in place (used, flags, njump), as the kernel's loop, for all pixels at once."""
    idx = np.arange(D.shape[1])
    while idx.size:
        u, d = used[:, idx], D[:, idx]
        nv = u.sum(axis=0)
        keep = nv >= JUMP_MIN_DIFFS
        idx, u, d, nv = idx[keep], u[:, keep], d[:, keep], nv[keep]
        if not idx.size:
            break
        cols = np.arange(idx.size)
        ordered = np.sort(np.where(u, d, np.inf), axis=0)
        med = 0.5 * (ordered[(nv - 1) // 2, cols] + ordered[nv // 2, cols])
        limit = k.jump_thr * np.sqrt(2.0 * k.sg2 + (np.maximum(med, 0.0) / k.tau) * pois_diag)
        dev = np.where(u, np.abs(d - med), -1.0)
        jbest = np.argmax(dev, axis=0)
        hit = dev[jbest, cols] > limit
        idx, jbest = idx[hit], jbest[hit]
        used[jbest, idx] = False
        flags[jbest + 1, idx] |= DQ_JUMP_DET
        njump[idx] += 1


def _ols_sums(D, used, sums):
    """Add the OLS sums of each run of L used differences to sums = [P, S, W2, Q] (in place):
    P = Σ p(L+1−p) D_p, S = L(L+1)(L+2)/6, Σw² = L(L+1)(L+2)(L²+2L+2)/30, Q = L(L+1)(L+2)/3."""
    N, npix = D.shape
    s1, s2, pos = np.zeros(npix), np.zeros(npix), np.zeros(npix)
    for j in range(N):
        u = used[j]
        pos = np.where(u, pos + 1.0, pos)
        s1 = np.where(u, s1 + pos * D[j], s1)
        s2 = np.where(u, s2 + pos * pos * D[j], s2)
        end = u & (used[j + 1] == 0) if j + 1 < N else u
        if end.any():
            L = pos[end]
            L3 = L * (L + 1.0) * (L + 2.0)
            sums[0][end] += (L + 1.0) * s1[end] - s2[end]
            sums[1][end] += L3 / 6.0
            sums[2][end] += L3 * (L * L + 2.0 * L + 2.0) / 30.0
            sums[3][end] += L3 / 3.0
            s1[end], s2[end], pos[end] = 0.0, 0.0, 0.0


def _gls_sums(D, used, a, r, sums):
    """Add Σw·D, Σw, Σw², Σw_j·w_j+1, Σ(w_j − w_j−1)² (sums, in place) for w = T'⁻¹1 per run,
    T' = tridiag(r, 1, r) (leading-minor recurrences, as the kernel; equal weights where a ≤ 0)."""
    N, npix = D.shape
    A, B, C = np.zeros((N, npix)), np.zeros((N, npix)), np.zeros((N, npix))
    r2 = r * r
    mq, mq1, e = np.ones(npix), np.ones(npix), np.zeros(npix)
    for j in range(N):
        u = used[j]
        e = np.where(u, mq - r * e, 0.0)
        B[j], C[j], A[j] = e, r * mq, 1.0 / mq1
        nxt = mq1 - r2 * mq
        mq, mq1 = np.where(u, mq1, 1.0), np.where(u, nxt, 1.0)
    P, S, W2, WW, Q = sums
    positive = a > 0.0
    wnext = np.zeros(npix)
    for j in range(N - 1, -1, -1):
        w = np.where(used[j], np.where(positive, (B[j] - C[j] * wnext) * A[j], 1.0), 0.0)
        P += w * D[j]
        S += w
        W2 += w * w
        WW += w * wnext
        step = w - wnext
        Q += step * step
        wnext = w
    Q += wnext * wnext


def fit_block_numpy(sci, gdq, pixeldq, k):
    """NumPy twin of the ``ramp_fit`` kernel.

    sci (nints, n, npix) uint16 [DN] or float64 [DN]; gdq uint8 alike; pixeldq uint32 (npix,);
    k : :class:`FitConstants`.  Returns fit (4, npix) float64 = rate [e-/s], variance, Poisson
    and read variance [e-²/s²]; dq uint32 (npix,); njump int32 (npix,); gdq_out uint8 like gdq."""
    _check_block(sci, gdq, pixeldq, k)
    nints, n, npix = sci.shape
    pois_diag = k.tau - 2.0 * k.ccorr
    gdq_out = np.empty_like(gdq)
    anysat = np.zeros(npix, bool)
    njump = np.zeros(npix, np.int32)
    ols = [np.zeros(npix) for _ in range(4)]                 # P, S, W2, Q
    for i in range(nints):
        raw = sci[i].astype(np.float64, copy=False)
        flags = gdq_out[i]
        sat = np.logical_or.accumulate(((gdq[i] & DQ_SATURATED) != 0) | (raw >= k.satlim), axis=0)
        flags[...] = gdq[i] | np.where(sat, DQ_SATURATED, 0).astype(np.uint8)
        usable = (flags & (DQ_SATURATED | DQ_DO_NOT_USE)) == 0
        njump += (usable[:-1] & usable[1:] & ((flags[1:] & DQ_JUMP_DET) != 0)).sum(axis=0, dtype=np.int32)
        anysat |= sat[-1]
        D, used = _differences(sci[i], flags, k.inv_gain)
        if k.jump_thr > 0.0:
            _detect_jumps(D, used, flags, njump, k, pois_diag)
        _ols_sums(D, used, ols)
    P, S, W2, Q = ols
    with np.errstate(divide="ignore", invalid="ignore"):
        lam0 = np.where(S > 0.0, np.fmax(P / (k.tau * S), 0.0), 0.0)     # fmax: as the kernel's (NaN → 0)
    WW = W2 - 0.5 * Q
    if k.weighting == "gls":
        a = 2.0 * k.sg2 + lam0 * pois_diag
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.where(a > 0.0, (lam0 * k.ccorr - k.sg2) / a, 0.0)
        P, S, W2, WW, Q = sums = [np.zeros(npix) for _ in range(5)]
        for i in range(nints):
            _gls_sums(*_differences(sci[i], gdq_out[i], k.inv_gain), a, r, sums)
    dq = pixeldq | np.where(anysat, DQ_SATURATED, 0).astype(np.uint32) \
        | np.where(njump > 0, DQ_JUMP_DET, 0).astype(np.uint32)
    fit = np.full((4, npix), np.nan)
    ok = S > 0.0
    norm = k.tau * S[ok]
    n2 = norm * norm
    var_read = k.sg2 * Q[ok] / n2
    var_pois = lam0[ok] * (pois_diag * W2[ok] + 2.0 * k.ccorr * WW[ok]) / n2
    fit[0, ok] = P[ok] / norm
    fit[1, ok] = var_read + var_pois
    fit[2, ok] = var_pois
    fit[3, ok] = var_read
    dq[~ok] |= np.uint32(DQ_DO_NOT_USE)
    return fit, dq, njump, gdq_out


# ----------------------------------------------------------------------------- OpenCL
CPU_WORK_GROUP = 64


def _check_out(out, npix, inputs):
    """ValueError unless ``out`` is six writeable C-contiguous (npix,) arrays (float64 ×4, uint32, int32)
    sharing no memory with one another or with ``inputs``: the kernel writes each output as it reads
    the inputs, so shared images overwrite one another (rate is variance: the variance returned as
    the rate, silently)."""
    dtypes = (np.float64,) * 4 + (np.uint32, np.int32)
    if len(out) != 6 or any(not isinstance(a, np.ndarray) or a.shape != (npix,) or a.dtype != dt
                            or not a.flags.c_contiguous or not a.flags.writeable for a, dt in zip(out, dtypes)):
        raise ValueError(f"out must be six writeable C-contiguous ({npix},) arrays (float64 x4, uint32, int32)")  # internal: fit_ramps's images
    if any(np.may_share_memory(a, b) for i, a in enumerate(out) for b in (*out[i + 1:], *inputs)):
        raise ValueError("out must be six arrays sharing no memory with one another or with sci, gdq, pixeldq")  # internal: fit_ramps's images




#: private memory of one work group of the kernel on CPUs [bytes]: PoCL keeps the work items' private
#: arrays (≈ 49 bytes per group and lane) on a thread's stack; 16 lanes × 65 groups × 256 work items
#: (13 MB) crashed the process
CPU_PRIVATE_BUDGET = 6 << 20


def _lanes(vector_width, gpu, ngroups, work_group):
    """Pixels per work item: ``vector_width`` (1, 2, 4, 8 or 16) or by default 1 on GPUs and on CPUs the
    widest of 8, 4, 2, 1 whose work group's private arrays fit :data:`CPU_PRIVATE_BUDGET`; on CPUs an
    explicit width or work group beyond it is a ParameterError."""
    if vector_width is not None and (isinstance(vector_width, bool) or not isinstance(vector_width, (int, np.integer))
                                     or vector_width not in (1, 2, 4, 8, 16)):
        raise ParameterError(f"vector_width must be 1, 2, 4, 8 or 16, got {vector_width!r}")
    if gpu:
        return 1 if vector_width is None else int(vector_width)

    def private(width):
        return 49 * ngroups * width * work_group
    if vector_width is None:
        vector_width = next((w for w in (8, 4, 2, 1) if private(w) <= CPU_PRIVATE_BUDGET), 1)
    if private(vector_width) > CPU_PRIVATE_BUDGET:
        raise ParameterError(f"work_group {work_group} x vector_width {vector_width} x {ngroups} groups needs "
                             f"{private(vector_width) / 2**20:.1f} MiB of private memory per work group on this CPU "
                             f"device (at most {CPU_PRIVATE_BUDGET >> 20} MiB): use a smaller work_group or vector_width")
    return int(vector_width)


def check_launch(ngroups, work_group=None, vector_width=None):
    """The kernel's launch on this device, checked before any data are read: ParameterError for a
    work group outside [1, the device's maximum] or beyond :data:`CPU_PRIVATE_BUDGET` with the lanes.

    Parameters
    ----------
    ngroups : int
        Groups per integration.
    work_group, vector_width : int or None
        As :func:`fit_block_opencl`'s (None: the defaults).

    Returns
    -------
    gpu : bool
        Whether the device is a GPU.
    work_group : int or None
        The work group used (None: the GPU driver's choice).
    lanes : int
        Pixels per work item.
    """
    dev = opencl.get_device()
    gpu = "GPU" in opencl.device_type(dev)
    if work_group is not None and not 1 <= int(work_group) <= int(dev.max_work_group_size):
        raise ParameterError(f"work_group must be in [1, {int(dev.max_work_group_size)}] on this device, got {work_group}")
    if work_group is None:
        work_group = None if gpu else CPU_WORK_GROUP
    return gpu, work_group, _lanes(vector_width, gpu, ngroups, int(work_group or CPU_WORK_GROUP))


def fit_block_opencl(sci, gdq, pixeldq, k, *, work_group=None, workspace=None, want_gdq=True, wait=True,
                     out=None, vector_width=None):
    """OpenCL version of :func:`fit_block_numpy` (same arguments and results).

    workspace : dict reusing device buffers between blocks;  want_gdq=False : GROUPDQ out is None;
    wait=False : return at once a function that waits for the kernel and returns the results, so
    that the caller can read the next block meanwhile;  out : (rate, variance, var_poisson,
    var_rnoise, dq, njump), C-contiguous writeable (npix,) arrays (float64 ×4, uint32, int32) the
    results are written into (the caller's images: no copy, no fresh memory), returned as the
    tuple (rate, variance, var_poisson, var_rnoise) in place of fit.  On CPU devices the kernel
    works on the arrays in place (zero-copy): ``sci``, ``gdq`` and ``pixeldq`` must then stay
    untouched until the results are fetched;  vector_width : pixels per work item (lanes of the
    kernel's vector types; default on CPUs the widest of 8, 4, 2, 1 within :data:`CPU_PRIVATE_BUDGET`,
    1 on GPUs), which does not change the results."""
    _check_block(sci, gdq, pixeldq, k)
    opencl.require_fp64()
    nints, n, npix = sci.shape
    sci, gdq = np.ascontiguousarray(sci), np.ascontiguousarray(gdq)
    pixeldq = np.ascontiguousarray(pixeldq)
    gpu, work_group, lanes = check_launch(n, work_group, vector_width)
    if npix == 0 or nints == 0:          # nothing to launch (a zero-size buffer is an OpenCL error): the twin's results
        fit0, dq0, nj0, g0 = fit_block_numpy(sci, gdq, pixeldq, k)
        if out is not None:
            _check_out(out, npix, (sci, gdq, pixeldq))
            for a, b in zip(out, (*fit0, dq0, nj0)):
                a[...] = b
            fit0, dq0, nj0 = tuple(out[:4]), out[4], out[5]
        result = (fit0, dq0, nj0, g0 if want_gdq else None)
        return result if wait else (lambda: result)
    options = (f"-DNGROUPS={n}", f"-DWEIGHTING={WEIGHTINGS.index(k.weighting)}",
               f"-DSCI_DOUBLE={int(sci.dtype == np.float64)}", f"-DWANT_GDQ={int(bool(want_gdq))}",
               f"-DVW={lanes}")
    kernel = opencl.cached_kernel("ramp_fit.cl", "ramp_fit", options)
    if out is None:
        fit = np.empty((4, npix))
        rate, var, vpois, vread = fit
        dq, njump = np.empty(npix, np.uint32), np.empty(npix, np.int32)
    else:
        _check_out(out, npix, (sci, gdq, pixeldq))
        rate, var, vpois, vread, dq, njump = out
        fit = (rate, var, vpois, vread)
    gdq_out = np.empty_like(gdq) if want_gdq else np.empty(1, np.uint8)
    outputs = (rate, var, vpois, vread, dq, njump, gdq_out)
    names = ("rate", "var", "vpois", "vread", "dq", "njump", "gdq_out")
    zero_copy = not gpu and all(a.flags.writeable for a in (sci, gdq, pixeldq))
    if zero_copy:                    # PoCL: the kernel reads and writes the host arrays themselves
        d_sci, d_gdq, d_pdq = (opencl.host_buffer(a) for a in (sci, gdq, pixeldq))
        d_out = [opencl.host_buffer(a) for a in outputs]
    else:
        d_sci = opencl.to_device(sci, opencl.workspace_buffer(workspace, "sci", sci.nbytes))
        d_gdq = opencl.to_device(gdq, opencl.workspace_buffer(workspace, "gdq", gdq.nbytes))
        d_pdq = opencl.to_device(pixeldq, opencl.workspace_buffer(workspace, "pdq", pixeldq.nbytes))
        d_out = [opencl.workspace_buffer(workspace, name, a.nbytes) for name, a in zip(names, outputs)]
    nwords = -(-(n - 1) // 64)
    d_bits = opencl.workspace_buffer(workspace, "bits", 8 * nints * nwords * npix if nints > 1 and k.weighting == "gls" else 8)
    items = -(-npix // lanes)
    gsize, lsize = (items,), None
    if work_group:
        gsize, lsize = (-(-items // int(work_group)) * int(work_group),), (int(work_group),)
    d_gout = d_out[-1]
    opencl.launch(kernel, gsize, lsize, d_sci, d_gdq, d_gout, d_bits, d_pdq, *d_out[:6], np.uint32(npix),
                  np.uint32(nints), np.float64(k.inv_gain), np.float64(k.sg2), np.float64(k.tau),
                  np.float64(k.ccorr), np.float64(k.satlim), np.float64(k.jump_thr))

    inputs = (sci, gdq, pixeldq)                 # alive until the kernel is done with them
    # Device copies (GPUs): the results are read back by copies enqueued now, right behind this kernel.
    # The output buffers belong to ``workspace``: the next block's kernel, launched before this
    # block's finish() (wait=False, as fit_ramps pipelines its blocks), overwrites them, and a copy
    # enqueued in finish() would read that block's results (seen on an H200: every row block but
    # the last got the rates of the next one; pulls -945 +- 60780 on a 4096² ramp).
    wanted = [(d_buf, host) for d_buf, host in zip(d_out, outputs) if want_gdq or host is not gdq_out]
    reads = [] if zero_copy else [opencl.from_device_nowait(host, d_buf) for d_buf, host in wanted]

    def finish():
        assert inputs
        if not zero_copy:
            for event in reads:
                event.wait()
        else:
            for d_buf, host in wanted:
                opencl.sync_to_host(d_buf, host)
        return fit, dq, njump, (gdq_out if want_gdq else None)
    return finish() if wait else finish
