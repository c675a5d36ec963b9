"""Raw up-the-ramp H4RG reads: exact sampling of MACC(n, m, d) ramps.

Readout physics in small documented steps (cf. romanisim ``l1``):

1. :func:`frame_mean_charge` — mean charge collected per frame μ = (rate + dark
   + thermal dark)·t_f + ROIC glow  [e-/frame];
2. charge accumulation, a Poisson process sampled exactly by one of two paths
   chosen from μ only: *dense* — a Poisson increment in every frame; *sparse*
   (μ·(m+d) < ``sparse_max_group``, default ≈ μ < 0.75 e-/frame) — per group window
   (m reads + d dropped frames) a Poisson count and a uniform frame for each
   event, so a dark pixel costs one uniform and one Gaussian per group;
3. full-well clipping; group averaging of the m reads with read noise
   σ_r/√m per group; kTC reset noise once per ramp;
4. :func:`to_adu` — bias pedestal + gain, rounding and uint16 saturation;
   GROUPDQ flags (JWST SATURATED = 2).

Randomness is Philox4x32-10 keyed by (seed, ramp, pixel, frame or group): the
output is identical for any chunking, work-group size, vector width or device
count.  The OpenCL kernels are in ``kernels/ramp.cl``;
:func:`_simulate_block_numpy` is their bit-exact NumPy twin.
"""
from __future__ import annotations

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
                 full_well=None, sparse_max_group=None, gauss_min_mean=np.inf):
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
        if sparse_max_group is not None and not float(sparse_max_group) >= 0:
            raise ValueError(f"sparse_max_group must be ≥ 0 e-/group (or None), got {sparse_max_group}")
        self.sparse_max_group = None if sparse_max_group is None else float(sparse_max_group)
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
SPARSE_GROUP_CAP = 64.0        # e-/group: larger sparse_max_group values act as this (CDF inversion cost)
MAX_SPARSE_WINDOW = 4096       # frames per group window: event positions use (x·w) >> 52, x < 2⁵²


def sparse_threshold(p):
    """Expected e- per group below which a pixel takes the sparse path (0: never).

    ``p.sparse_max_group`` None: 0.9·(m + d) − 1, where the two kernels cost the same on a CPU
    (PoCL, AVX-512: a sparse event ≈ 3.8 ns, a dense frame ≈ 3.3 ns per pixel; ≈ 0.75 e-/frame
    for m + d = 8; never for m + d = 1); any value is capped at SPARSE_GROUP_CAP.  Both paths
    are exact: the choice changes the random numbers, not their distribution.
    """
    n, m, d = p.nmd
    smg = 0.9 * (m + d) - 1.0 if p.sparse_max_group is None else p.sparse_max_group
    if m + d > MAX_SPARSE_WINDOW or not smg > 0:
        return 0.0
    return min(smg, SPARSE_GROUP_CAP)


def _frame_increment(mu, exp_neg_mu, seed, pix, frame, stream, gauss_min_mean):
    """Poisson increments of one frame (twin of the dense path in ramp.cl)."""
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
    """Poisson(mu) by sequential search of the CDF from p = e^−mu with uniforms u."""
    return rng.inversion_search(mu, p, u)


def _frame_position(hi, lo, w):
    """Frame position in [0, w): (x·w) >> 52 with the 52-bit x of a uniform (exact integers)."""
    x = (hi.astype(np.uint64) << np.uint64(20)) | (lo.astype(np.uint64) >> np.uint64(12))
    return ((x * np.uint64(w)) >> np.uint64(52)).astype(np.float64)


def _event_words(seed, g, k, pix, stream):
    """Block of events k ≥ 1 of group g: draw 1 + (k−1)//2, words 0–1 for odd k, 2–3 for even k."""
    return rng.random_words(seed, (np.uint64(g) << np.uint64(32)) | pix, stream, 1 + ((k - 1) >> 1))


def _event_position(words, k, w):
    return _frame_position(words[:, 0], words[:, 1], w) if k & 1 else _frame_position(words[:, 2], words[:, 3], w)


def _events_seen(K, pos0, g, w, m, pix, seed, stream):
    """Σ over the K events of a group window of the reads that see them (m − position)."""
    seen = np.where((K > 0) & (pos0 < m), m - pos0, 0.0)
    words = np.empty((K.size, 4), np.uint32)
    sel, k = np.nonzero(K > 1)[0], 1
    while sel.size:
        if k & 1:
            words[sel] = _event_words(seed, g, k, pix[sel], stream)
        pos = _event_position(words[sel], k, w)
        seen[sel] = np.where(pos < m, seen[sel] + (m - pos), seen[sel])
        k += 1
        sel = sel[K[sel] > k]
    return seen


def _clipped_read_sum(before, K, pos0, g, w, m, full_well, pix, seed, stream):
    """Σ_j min(full well, before + #{events at positions ≤ j}) (windows over the full well; rare)."""
    kmax = int(K.max())
    pos = [pos0] + [_event_position(_event_words(seed, g, k, pix, stream), k, w) for k in range(1, kmax)]
    total = np.zeros(before.size)
    for j in range(m):
        cj = np.zeros(before.size)
        for k in range(kmax):
            cj = np.where((k < K) & (pos[k] <= j), cj + 1.0, cj)
        charge = before + cj
        total = total + np.where(charge >= full_well, full_well, charge)
    return total


def _sparse_group(mu, p_empty, before, g, w, m, full_well, pix, seed, stream):
    """(read sum, clipped charge after the window, window reached the full well) of group g.

    K ~ Poisson(mu·w) by inversion of the uniform of words 0–1 of block (g << 32 | pixel, stream,
    0); words 2–3 place event 0, later events use draws ≥ 1 (:func:`_event_words`)."""
    words = rng.random_words(seed, (np.uint64(g) << np.uint64(32)) | pix, stream, 0)
    K = _inversion(mu * float(w), p_empty, rng.words_to_uniform(words[:, 0], words[:, 1]))
    pos0 = _frame_position(words[:, 2], words[:, 3], w)
    seen = _events_seen(K, pos0, g, w, m, pix, seed, stream)
    total = before + K
    read_sum = float(m) * before + seen
    over = np.nonzero(total > full_well)[0]
    if over.size:
        read_sum[over] = _clipped_read_sum(before[over], K[over], pos0[over], g, w, m, full_well, pix[over],
                                           seed, stream)
    full = total >= full_well
    return read_sum, np.where(full, full_well, total), full


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
    sparse = mu * float(m + d) < sparse_threshold(p)
    sp, dn = np.nonzero(sparse)[0], np.nonzero(~sparse)[0]
    mu_sp, pix_sp, mu_dn, pix_dn = mu[sp], pix[sp], mu[dn], pix[dn]
    p_full, p_last = rng.rng_exp(-(mu_sp * float(m + d))), rng.rng_exp(-(mu_sp * float(m)))
    before = np.zeros(sp.size)
    exp_neg_mu = rng.rng_exp(-mu_dn)
    charge = np.zeros(dn.size)
    saturated = np.zeros(npix, dtype=bool)
    sci = np.empty((n, npix), np.uint16)
    gdq = np.empty((n, npix), np.uint8)
    read_sigma = p.ron / math.sqrt(m)
    frame = 0
    for g in range(n):
        w = m if g == n - 1 else m + d
        total = np.zeros(npix)
        pair = (np.uint64(g >> 1) << np.uint64(32)) | pix
        if g % 2 == 0:
            z_pair = rng.normal(seed, pair, sbase + P_READ, 0)
        if sp.size:
            total[sp], before, full = _sparse_group(mu_sp, p_last if g == n - 1 else p_full, before, g, w, m,
                                                    p.full_well, pix_sp, seed, sbase + P_SPARSE)
            saturated[sp] |= full
        if dn.size:
            sum_dn = np.zeros(dn.size)
            for j in range(w):
                charge = charge + _frame_increment(mu_dn, exp_neg_mu, seed, pix_dn, frame + j,
                                                   sbase + P_POISSON, p.gauss_min_mean)
                full = charge >= p.full_well
                charge[full] = p.full_well
                saturated[dn] |= full
                if j < m:
                    sum_dn = sum_dn + charge
            total[dn] = sum_dn
        frame += w
        mean = total / float(m) + read_sigma * z_pair[:, g & 1]
        adu = to_adu(mean, reset, p)
        saturated |= adu >= p.saturation
        sci[g] = adu.astype(np.uint16)
        gdq[g] = np.where(saturated, DQ["SATURATED"], 0).astype(np.uint8)
    return sci, gdq


# --------------------------------------------------------------------------- OpenCL
CPU_WORK_GROUP = 64        # work items per group on CPUs (PoCL's own choice can overflow the
MAX_CPU_WORK_GROUP = 1024  # thread stack with the private CDF tables: it is never left to it)


def _launch_geometry(vector_width, work_group):
    """(pixels per work item, work-group size or None) for the selected device.

    Pixels per work item: 1 on GPUs; on CPUs twice the preferred double vector width (≤ 16:
    two AVX-512 registers per operation give the out-of-order core independent Philox chains).
    """
    from . import opencl
    dev = opencl.get_device()
    gpu = "GPU" in opencl.device_type(dev)
    if vector_width is None:
        native = int(getattr(dev, "preferred_vector_width_double", 1) or 1)
        vector_width = 1 if gpu else max(w for w in (1, 2, 4, 8, 16) if w <= 2 * native)
    if vector_width not in (1, 2, 4, 8, 16):
        raise ValueError(f"vector_width must be 1, 2, 4, 8 or 16, got {vector_width}")
    limit = int(dev.max_work_group_size) if gpu else min(int(dev.max_work_group_size), MAX_CPU_WORK_GROUP)
    if work_group is None:
        work_group = None if gpu else CPU_WORK_GROUP
    elif not 1 <= int(work_group) <= limit:
        raise ValueError(f"work_group must be in [1, {limit}] on this device, got {work_group}")
    return vector_width, (int(work_group) if work_group else None)


def _ramp_kernel(name, vector_width):
    from . import opencl
    return opencl.get_kernel("ramp.cl", name, (f"-DRNG_VW={int(vector_width)}",))


def _pixel_lists(mu, p, vector_width):
    """(sparse, dense) uint32 pixel indices, each padded to a multiple of ``vector_width`` by
    repeating its last entry: sparse pixels in detector order (lanes of consecutive pixels load
    and store as vectors), dense pixels sorted by mean charge (lanes take the same branches)."""
    sparse = mu * float(p.nmd[1] + p.nmd[2]) < sparse_threshold(p)
    sp = np.flatnonzero(sparse).astype(np.uint32)
    dn = np.flatnonzero(~sparse).astype(np.uint32)
    dn = dn[np.argsort(mu[dn], kind="stable")]

    def pad(idx):
        extra = -idx.size % vector_width
        return np.concatenate([idx, np.full(extra, idx[-1], np.uint32)]) if extra and idx.size else idx
    return pad(sp), pad(dn)


def _buffer(workspace, name, nbytes):
    """Device buffer of ≥ nbytes, reused from ``workspace`` (a dict kept across row blocks)."""
    from . import opencl
    if workspace is None:
        return opencl.device_buffer(nbytes)
    buf, size = workspace.get(name, (None, 0))
    if size < nbytes:
        buf, size = opencl.device_buffer(nbytes), nbytes
        workspace[name] = (buf, size)
    return buf


def _simulate_block_opencl(mu_frame, dead, pixel0, ramp, seed, p, work_group=None, vector_width=None, *,
                           want_dq=True, sci_out=None, gdq_out=None, workspace=None):
    """OpenCL twin of :func:`_simulate_block_numpy`: sparse then dense pixels, ``vector_width``
    pixels per work item (see :func:`_launch_geometry`); the result does not depend on either.

    want_dq=False skips GROUPDQ (returned as None); sci_out / gdq_out: C-contiguous (n, npix)
    arrays to fill (default: new ones); workspace: dict reusing device buffers between blocks.
    """
    from . import opencl
    n, m, d = p.nmd
    npix = mu_frame.size
    vw, work_group = _launch_geometry(vector_width, work_group)
    key = rng.seed_to_key(seed)
    mu = np.ascontiguousarray(np.where(dead, 0.0, mu_frame), dtype=np.float64)
    lists = _pixel_lists(mu, p, vw)
    d_mu = opencl.to_device(mu, _buffer(workspace, "mu", mu.nbytes))
    d_sci = _buffer(workspace, "sci", 2 * n * npix)
    d_gdq = _buffer(workspace, "gdq", n * npix if want_dq else 1)
    common = (np.uint32(npix), np.uint32(pixel0), np.uint32(ramp), np.uint32(key[0]), np.uint32(key[1]),
              np.int32(n), np.int32(m), np.int32(d), np.float64(p.ron / math.sqrt(m)), np.float64(p.gain),
              np.float64(p.bias), np.float64(p.ktc_noise), np.float64(p.full_well), np.float64(p.saturation),
              np.int32(bool(want_dq)))
    for name, idx, extra in (("macc_ramp_sparse", lists[0], ()),
                             ("macc_ramp_dense", lists[1], (np.float64(p.gauss_min_mean),))):
        items = idx.size // vw
        if not items:
            continue
        gsize, lsize = (items,), None
        if work_group:
            gsize, lsize = (-(-items // work_group) * work_group,), (work_group,)
        d_idx = opencl.to_device(idx, _buffer(workspace, name, idx.nbytes))
        opencl.launch(_ramp_kernel(name, vw), gsize, lsize, d_mu, d_idx, np.uint32(items), d_sci, d_gdq,
                      *common, *extra)
    sci = np.empty((n, npix), np.uint16) if sci_out is None else sci_out
    opencl.from_device(sci, d_sci)
    gdq = None
    if want_dq:
        gdq = np.empty((n, npix), np.uint8) if gdq_out is None else gdq_out
        opencl.from_device(gdq, d_gdq)
    return sci, gdq


# --------------------------------------------------------------------------- driver
def _resolve_backend(backend):
    from .compute import resolve_backend
    return resolve_backend(backend)


def simulate(rate, nmd=(16, 8, 0), nramps=1, seed=0, out=None, tframe=2.83, ron=12.0, dark=2.8e-3,
             thermal_dark=0.0, roic_glow=3e-3, gain=1.0, saturation=65535, bias=DEFAULT_BIAS,
             ktc_noise=0.0, full_well=None, dead_pixels=None, pixeldq=None, sparse_max_group=None,
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
    sparse_max_group : expected e- per group below which the sparse sampler is used (None:
        0.9·(m+d) − 1, see :func:`sparse_threshold`; capped at 64).  Both samplers are exact:
        this only trades speed.
    gauss_min_mean : Poisson mean above which a rounded Gaussian replaces the exact draw
    memory_budget : bytes of host memory for the row blocks (default 1 GiB)
    work_group : OpenCL local size (None: 64 on CPUs, the runtime's on GPUs); never changes the result

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
    # bytes per pixel in flight: mu + dead + index list + SCI + GDQ (host and device copies)
    per_row = nx * (8 + 1 + 4 + 3 * n) * 2
    rows = int(max(1, min(ny, memory_budget // per_row)))
    if memory_budget < per_row:
        raise MemoryError(f"memory budget {memory_budget} B is smaller than one detector row "
                          f"({per_row} B for {n} groups)")
    full_bytes = p.nramps * n * ny * nx * 2
    if out is None and full_bytes > 8 * memory_budget:
        raise MemoryError(f"returning SCI in memory needs {full_bytes / 2**30:.1f} GiB: pass out=<file.h5>")
    backend = _resolve_backend(backend)
    block = _simulate_block_opencl if backend == "opencl" else _simulate_block_numpy
    kwargs = {}
    if backend == "opencl":
        kwargs = {"work_group": work_group, "want_dq": out is not None or return_dq, "workspace": {}}
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
            direct = {}
            if w is None and backend == "opencl" and y0 == 0 and y1 == ny:     # whole ramp: no copy
                direct = {"sci_out": result[ramp].reshape(n, -1)}
                if result_dq is not None:
                    direct["gdq_out"] = result_dq[ramp].reshape(n, -1)
            sci, gdq = block(mu[y0:y1].ravel(), dead[y0:y1].ravel(), y0 * nx, ramp, seed, p, **kwargs, **direct)
            if direct:
                continue
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
