"""Raw up-the-ramp H4RG reads: per-frame sampling of MACC(n, m, d) ramps.

Readout physics in small documented steps (cf. romanisim ``l1``):

1. :func:`frame_mean_charge` — mean charge collected per frame μ = (rate + dark
   + thermal dark)·t_f + ROIC glow  [e-/frame];
2. charge accumulation — exact Poisson increments per frame (dense path) or,
   for pixels whose expected charge per group is below ``sparse_max_group``,
   an exact count-then-place sampler (sparse path);
3. full-well clipping; group averaging of the m reads with read noise
   σ_r/√m per group; kTC reset noise once per ramp;
4. :func:`to_adu` — bias pedestal + gain, rounding and uint16 saturation;
   GROUPDQ flags (JWST SATURATED = 2).

Randomness is Philox4x32-10 keyed by (seed, ramp, pixel, frame): the output is
identical for any chunking, work-group size or device count.  The OpenCL
kernel is ``kernels/ramp.cl``; :func:`_simulate_block_numpy` is its bit-exact
NumPy twin.
"""
from __future__ import annotations

import hashlib
import math
import os

import numpy as np

from . import rng
from .detector import ReadoutError, readout_times
from .rampio import DQ, RampWriter

__all__ = ["simulate", "RampParameters", "frame_mean_charge", "macc_frame_schedule", "readpatt",
           "fit_slopes", "DEFAULT_BIAS"]

DEFAULT_BIAS = 2000.0          # ADU pedestal: read noise never clips at 0
P_POISSON, P_READ, P_KTC, P_SPARSE = 0, 1, 2, 3


class RampParameters:
    """Validated readout and detector parameters of a ramp simulation."""

    def __init__(self, nmd, nramps=1, tframe=2.83, ron=12.0, dark=2.8e-3, thermal_dark=0.0,
                 roic_glow=3e-3, gain=1.0, saturation=65535, bias=DEFAULT_BIAS, ktc_noise=0.0,
                 full_well=None, sparse_max_group=0.1, gauss_min_mean=np.inf):
        try:
            n, m, d = (int(v) for v in nmd)
        except Exception as exc:
            raise ReadoutError(f"readout mode must be (n, m, d) integers, got {nmd!r}") from exc
        if m < 1:
            raise ReadoutError(f"readout mode {nmd}: m (frames per group) must be ≥ 1")
        if d < 0:
            raise ReadoutError(f"readout mode {nmd}: d (dropped frames) must be ≥ 0")
        if n < 2:
            raise ReadoutError(f"readout mode {nmd}: n must be ≥ 2 groups to measure a slope")
        if int(nramps) != nramps or nramps < 1:
            raise ReadoutError(f"nramps must be an integer ≥ 1, got {nramps!r}")
        for name, val in (("tframe", tframe), ("gain", gain)):
            if not (np.isfinite(val) and val > 0):
                raise ValueError(f"{name} must be > 0, got {val}")
        for name, val in (("ron", ron), ("roic_glow", roic_glow), ("ktc_noise", ktc_noise),
                          ("thermal_dark", thermal_dark), ("bias", bias)):
            if not (np.isfinite(val) and val >= 0):
                raise ValueError(f"{name} must be finite and ≥ 0, got {val}")
        if not 0 < saturation <= 65535:
            raise ValueError(f"saturation must be in (0, 65535] ADU, got {saturation}")
        self.nmd, self.nramps = (n, m, d), int(nramps)
        self.tframe, self.ron, self.gain = float(tframe), float(ron), float(gain)
        self.dark, self.thermal_dark, self.roic_glow = dark, float(thermal_dark), float(roic_glow)
        self.saturation, self.bias, self.ktc_noise = float(saturation), float(bias), float(ktc_noise)
        self.full_well = float((saturation - bias) / gain if full_well is None else full_well)
        self.sparse_max_group = float(sparse_max_group)
        self.gauss_min_mean = float(gauss_min_mean)
        t = readout_times(self.nmd, self.tframe)
        self.nframes, self.tgroup = t["nframes"], t["group_time"]

    def attrs(self, seed):
        """Root attributes of the raw file (JWST-like names)."""
        n, m, d = self.nmd
        return {"NINTS": self.nramps, "NGROUPS": n, "NFRAMES": m, "GROUPGAP": d, "TFRAME": self.tframe,
                "TGROUP": self.tgroup, "READPATT": readpatt(self.nmd), "GAIN": self.gain,
                "READNOISE": self.ron, "SEED": int(seed), "BUNIT": "ADU", "BIAS": self.bias,
                "SATURATION": self.saturation, "FULLWELL": self.full_well}


def readpatt(nmd):
    """Readout pattern name, e.g. ``MACC(16,8,0)``."""
    return "MACC({},{},{})".format(*nmd)


def macc_frame_schedule(nmd):
    """(group index or −1 for dropped, is_read) per frame of one ramp."""
    n, m, d = nmd
    groups, reads = [], []
    for g in range(n):
        last = m if g == n - 1 else m + d
        for j in range(last):
            groups.append(g if j < m else -1)
            reads.append(j < m)
    return np.array(groups), np.array(reads)


def frame_mean_charge(rate, dark, thermal_dark, roic_glow, tframe):
    """Mean charge per frame μ = (rate + dark + thermal dark)·t_f + ROIC glow [e-/frame].

    rate, dark : e-/s (arrays or scalars);  roic_glow : e-/frame (also during dropped frames).
    """
    return (np.asarray(rate, dtype=float) + dark + thermal_dark) * tframe + roic_glow


def to_adu(charge_mean, reset, p):
    """rint(bias + gain·(reset + mean charge)) clipped to the uint16 range (float64 out)."""
    adu = np.rint(p.bias + p.gain * (reset + charge_mean))
    return np.clip(adu, 0.0, 65535.0)


# --------------------------------------------------------------------------- NumPy twin
def _frame_increment(mu, exp_neg_mu, seed, pix, frame, stream, gauss_min_mean):
    """Poisson increments of one frame (twin of ``frame_increment`` in ramp.cl)."""
    out = np.zeros_like(mu)
    gauss = (mu > 0) & (mu >= gauss_min_mean)
    ptrs = (mu >= rng.PTRS_MIN_MEAN) & ~gauss
    inv = (mu > 0) & ~gauss & ~ptrs
    pair = (np.uint64(frame >> 1) << np.uint64(32))
    if gauss.any():
        z = rng.normal(seed, pair | pix[gauss], stream, 1)[..., frame & 1]
        out[gauss] = np.maximum(np.rint(mu[gauss] + np.sqrt(mu[gauss]) * z), 0.0)
    if ptrs.any():
        idx = (np.uint64(frame) << np.uint64(32)) | pix[ptrs]
        out[ptrs] = rng._poisson_ptrs(mu[ptrs], seed, idx, stream + 0x80000000)
    if inv.any():
        u = rng.uniform(seed, pair | pix[inv], stream, 0)[..., frame & 1]
        out[inv] = _inversion(mu[inv], exp_neg_mu[inv], u)
    return out


def _inversion(mu, p, u):
    p = p.copy()
    cdf = p.copy()
    k = np.zeros_like(mu)
    todo = np.nonzero((u > cdf) & (p > 0.0))[0]
    while todo.size:
        k[todo] += 1.0
        p[todo] = p[todo] * mu[todo] / k[todo]
        cdf[todo] = cdf[todo] + p[todo]
        todo = todo[(u[todo] > cdf[todo]) & (p[todo] > 0.0)]
    return k


def _binomial_inversion(R, p, u):
    """Binomial(R, p) by CDF inversion (vectorised twin of ramp.cl)."""
    out = np.where(p >= 1.0, R, 0.0)
    todo = np.nonzero(p < 1.0)[0]
    if not todo.size:
        return out
    q = 1.0 - p[todo]
    prob = rng.rng_exp(R[todo] * rng.rng_log(q))
    cdf = prob.copy()
    x = np.zeros_like(prob)
    ratio = p[todo] / q
    Rt, ut = R[todo], u[todo]
    act = np.nonzero((ut > cdf) & (x < Rt))[0]
    while act.size:
        prob[act] = prob[act] * ((Rt[act] - x[act]) / (x[act] + 1.0)) * ratio[act]
        x[act] = x[act] + 1.0
        cdf[act] = cdf[act] + prob[act]
        act = act[(ut[act] > cdf[act]) & (x[act] < Rt[act])]
    out[todo] = x
    return out


def _simulate_block_numpy(mu_frame, dead, pixel0, ramp, seed, p):
    """SCI (ngroups, npix) uint16 and GROUPDQ uint8 for one ramp of a flat pixel block."""
    n, m, d = p.nmd
    npix = mu_frame.size
    pix = np.arange(pixel0, pixel0 + npix, dtype=np.uint64)
    mu = np.where(dead, 0.0, mu_frame)
    sbase = 4 * ramp
    reset = np.zeros(npix)
    if p.ktc_noise > 0:
        reset = p.ktc_noise * rng.normal(seed, pix, sbase + P_KTC, 0)[..., 0]
    sparse = mu * (m + d) < p.sparse_max_group
    dense = np.nonzero(~sparse)[0]
    exp_neg_mu = rng.rng_exp(-mu)
    remaining = np.zeros(npix)
    sp = np.nonzero(sparse & (mu > 0))[0]
    if sp.size:
        remaining[sp] = rng.poisson(mu[sp] * p.nframes, seed, pix[sp], sbase + P_SPARSE)
    charge = np.zeros(npix)
    saturated = np.zeros(npix, dtype=bool)
    sci = np.empty((n, npix), np.uint16)
    gdq = np.empty((n, npix), np.uint8)
    read_sigma = p.ron / math.sqrt(m)
    frame = 0
    for g in range(n):
        total = np.zeros(npix)
        for j in range(m if g == n - 1 else m + d):
            inc = np.zeros(npix)
            if dense.size:
                inc[dense] = _frame_increment(mu[dense], exp_neg_mu[dense], seed, pix[dense], frame,
                                              sbase + P_POISSON, p.gauss_min_mean)
            live = np.nonzero(remaining > 0)[0]
            if live.size:
                idx = (np.uint64(frame + 1) << np.uint64(32)) | pix[live]
                u = rng.uniform(seed, idx, sbase + P_SPARSE, 1)[..., 0]
                pr = np.full(live.size, 1.0 / (p.nframes - frame))
                got = _binomial_inversion(remaining[live], pr, u)
                inc[live] = got
                remaining[live] = remaining[live] - got
            charge = charge + inc
            full = charge >= p.full_well
            charge[full] = p.full_well
            saturated |= full
            if j < m:
                total = total + charge
            frame += 1
        idx = (np.uint64(g >> 1) << np.uint64(32)) | pix
        z = rng.normal(seed, idx, sbase + P_READ, 0)[..., g & 1]
        mean = total / float(m) + read_sigma * z
        adu = to_adu(mean, reset, p)
        saturated |= adu >= p.saturation
        sci[g] = adu.astype(np.uint16)
        gdq[g] = np.where(saturated, DQ["SATURATED"], 0).astype(np.uint8)
    return sci, gdq


# --------------------------------------------------------------------------- OpenCL
def _ramp_kernel():
    from . import opencl
    from .compute_noise import _kernel_dir
    src_dir = _kernel_dir()
    digest = hashlib.sha1((opencl.kernel_source("philox.cl") + opencl.kernel_source("noise.cl"))
                          .encode()).hexdigest()[:16]
    return opencl.get_kernel("ramp.cl", "macc_ramp", (f"-I{src_dir}", f"-DSLICERSIM_RNG_SHA=0x{digest}"))


def _simulate_block_opencl(mu_frame, dead, pixel0, ramp, seed, p, work_group=None):
    from . import opencl
    n, m, d = p.nmd
    npix = mu_frame.size
    key = rng.seed_to_key(seed)
    kern = _ramp_kernel()
    d_mu = opencl.to_device(np.ascontiguousarray(mu_frame, dtype=np.float64))
    d_dead = opencl.to_device(np.ascontiguousarray(dead, dtype=np.uint8))
    d_sci = opencl.device_buffer(2 * n * npix)
    d_gdq = opencl.device_buffer(n * npix)
    local = None
    gsize = npix
    if work_group:
        gsize = -(-npix // work_group) * work_group
        local = (work_group,)
    opencl.launch(kern, (gsize,), local, d_mu, d_dead, d_sci, d_gdq, np.uint32(npix), np.uint32(pixel0),
                  np.uint32(ramp), np.uint32(key[0]), np.uint32(key[1]), np.int32(n), np.int32(m), np.int32(d), np.float64(p.ron),
                  np.float64(p.gain), np.float64(p.bias), np.float64(p.ktc_noise), np.float64(p.full_well),
                  np.float64(p.saturation), np.float64(p.sparse_max_group), np.float64(p.gauss_min_mean))
    sci = np.empty((n, npix), np.uint16)
    gdq = np.empty((n, npix), np.uint8)
    opencl.from_device(sci, d_sci)
    opencl.from_device(gdq, d_gdq)
    return sci, gdq


# --------------------------------------------------------------------------- driver
def _resolve_backend(backend):
    from .compute import resolve_backend
    return resolve_backend(backend)


def simulate(rate, nmd=(16, 8, 0), nramps=1, seed=0, out=None, tframe=2.83, ron=12.0, dark=2.8e-3,
             thermal_dark=0.0, roic_glow=3e-3, gain=1.0, saturation=65535, bias=DEFAULT_BIAS,
             ktc_noise=0.0, full_well=None, dead_pixels=None, pixeldq=None, sparse_max_group=0.1,
             gauss_min_mean=np.inf, compression=None, memory_budget=2**30, truth=True,
             config=None, backend="auto", progress=None, work_group=None, return_dq=False):
    """Simulate raw MACC ramps of a rate image.

    Parameters
    ----------
    rate : (ny, nx) photo-electron rate [e-/s] (detector terms are added here)
    nmd : (n, m, d) readout;  nramps : ramps between resets;  seed : int in [0, 2⁶⁴)
    out : HDF5 path (group-level file, see :mod:`slicersim.rampio`) or None
    tframe [s], ron [e-/read], dark [e-/s, scalar or image], thermal_dark [e-/s],
    roic_glow [e-/frame], gain [ADU/e-], saturation [ADU], bias [ADU], ktc_noise [e-],
    full_well [e-] (default (saturation − bias)/gain)
    dead_pixels : bool (ny, nx) pixels collecting no charge;  pixeldq : uint32 (ny, nx) flags
    sparse_max_group : expected e- per group below which the exact sparse sampler is used
    gauss_min_mean : Poisson mean above which a rounded Gaussian replaces the exact draw
    memory_budget : bytes of host memory for the row blocks (default 1 GiB)

    Returns
    -------
    SCI (nramps, ngroups, ny, nx) uint16 when ``out`` is None (and GROUPDQ with
    ``return_dq``), else the path written.
    """
    rate = np.asarray(rate, dtype=float)
    if rate.ndim != 2 or rate.size == 0:
        raise ValueError(f"rate must be a non-empty 2-D image (ny, nx), got shape {rate.shape}")
    if not np.all(np.isfinite(rate)):
        raise ValueError(f"rate contains {np.count_nonzero(~np.isfinite(rate))} NaN/inf pixel(s)")
    if np.any(rate < 0):
        raise ValueError(f"rate contains {np.count_nonzero(rate < 0)} negative pixel(s) [e-/s]")
    dark_arr = np.asarray(dark, dtype=float)
    if np.any(~np.isfinite(dark_arr)) or np.any(dark_arr < 0):
        raise ValueError("dark must be finite and ≥ 0")
    seed = int(rng.seed_to_key(seed).astype(np.uint64)[0] | (rng.seed_to_key(seed).astype(np.uint64)[1] << np.uint64(32)))
    p = RampParameters(nmd, nramps, tframe, ron, 0.0, thermal_dark, roic_glow, gain, saturation, bias,
                       ktc_noise, full_well, sparse_max_group, gauss_min_mean)
    ny, nx = rate.shape
    if ny * nx >= 2**32:
        raise ValueError("image too large: pixel indices must fit in 32 bits")
    n = p.nmd[0]
    mu = frame_mean_charge(rate, dark_arr, thermal_dark, roic_glow, tframe)
    dead = np.zeros(rate.shape, bool) if dead_pixels is None else np.asarray(dead_pixels, bool)
    if dead.shape != rate.shape:
        raise ValueError("dead_pixels must have the shape of rate")
    # bytes per pixel in flight: mu + dead + SCI + GDQ (host and device copies)
    per_row = nx * (8 + 1 + 3 * n) * 2
    rows = int(max(1, min(ny, memory_budget // per_row)))
    if memory_budget < per_row:
        raise MemoryError(f"memory budget {memory_budget} B is smaller than one detector row "
                          f"({per_row} B for {n} groups)")
    full_bytes = p.nramps * n * ny * nx * 2
    if out is None and full_bytes > 8 * memory_budget:
        raise MemoryError(f"returning SCI in memory needs {full_bytes / 2**30:.1f} GiB: pass out=<file.h5>")
    backend = _resolve_backend(backend)
    block = _simulate_block_opencl if backend == "opencl" else _simulate_block_numpy
    kwargs = {"work_group": work_group} if backend == "opencl" else {}
    steps = [(r, y0) for r in range(p.nramps) for y0 in range(0, ny, rows)]
    if progress is None:
        progress = len(steps) > 4
    iterator = steps
    if progress:
        from tqdm.auto import tqdm
        iterator = tqdm(steps, desc="ramps", unit="block")
    attrs = p.attrs(seed)
    attrs.update({"SOFTWARE": "slicersim", "VERSION": _version(), "BACKEND": backend,
                  "CONFIG": config if config is not None else {}, "DARK": float(np.mean(dark_arr)),
                  "THERMAL_DARK": thermal_dark, "ROIC_GLOW": roic_glow, "KTC_NOISE": ktc_noise})
    result = None if out is not None else np.empty((p.nramps, n, ny, nx), np.uint16)
    result_dq = np.empty((p.nramps, n, ny, nx), np.uint8) if (out is None and return_dq) else None
    writer = RampWriter(out, p.nramps, n, (ny, nx), attrs=attrs, row_block=min(rows, 256),
                        compression=compression, truth_rate=truth) if out is not None else None

    def run(w):
        if w is not None:
            w.write_pixeldq(_pixeldq(pixeldq, dead, rate.shape))
            if truth:
                w.write_truth(rate)
        for ramp, y0 in iterator:
            y1 = min(ny, y0 + rows)
            sci, gdq = block(mu[y0:y1].ravel(), dead[y0:y1].ravel(), y0 * nx, ramp, seed, p, **kwargs)
            sci = sci.reshape(n, y1 - y0, nx)
            if w is not None:
                w.write_block(ramp, y0, sci, gdq.reshape(n, y1 - y0, nx))
            else:
                result[ramp, :, y0:y1] = sci
                if result_dq is not None:
                    result_dq[ramp, :, y0:y1] = gdq.reshape(n, y1 - y0, nx)
    if writer is None:
        run(None)
        return (result, result_dq) if return_dq else result
    with writer as w:
        run(w)
    return os.path.abspath(out)


def _pixeldq(pixeldq, dead, shape):
    flags = np.zeros(shape, np.uint32) if pixeldq is None else np.asarray(pixeldq, np.uint32).copy()
    flags[dead] |= DQ["DEAD"] | DQ["DO_NOT_USE"]
    return flags


def _version():
    from . import __version__
    return __version__


def fit_slopes(sci, nmd, tframe, gain=1.0, groupdq=None):
    """Unweighted least-squares slopes over group means [e-/s] of SCI (ngroups, ...) ADU.

    Groups flagged in ``groupdq`` are excluded; pixels with < 2 good groups give NaN.
    """
    n, m, d = nmd
    t = ((np.arange(n) * (m + d)) + (m + 1) / 2.0) * tframe          # mean time of each group
    y = np.asarray(sci, dtype=float) / gain
    good = np.ones(y.shape, bool) if groupdq is None else (np.asarray(groupdq) == 0)
    tt = np.broadcast_to(t.reshape((n,) + (1,) * (y.ndim - 1)), y.shape)
    w = good.astype(float)
    sw = w.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        tm = (w * tt).sum(0) / sw
        ym = (w * y).sum(0) / sw
        num = (w * (tt - tm) * (y - ym)).sum(0)
        den = (w * (tt - tm) ** 2).sum(0)
        slope = num / den
    return np.where(sw >= 2, slope, np.nan)
