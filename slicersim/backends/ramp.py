"""Ramp samplers: the OpenCL kernels of ``kernels/ramp.cl`` and their bit-exact NumPy twin.

:func:`simulate_block_numpy` and :func:`simulate_block_opencl` sample one ramp of
a flat block of pixels from the mean charge per frame (dense path: a Poisson
increment per frame; sparse path: per group window a Poisson count and a frame
for each event), with Philox4x32-10 keyed by (seed, ramp, pixel, frame or
group), so both return the same integers for any chunking, work-group size or
vector width.  The readout physics is in :mod:`slicersim.physics.ramp`; the
driver is :func:`slicersim.products.ramps.simulate`.
"""
from __future__ import annotations

import math

import numpy as np

from slicersim import rng
from slicersim.backends import opencl
from slicersim.backends.opencl import check_vector_width
from slicersim.errors import ParameterError
from slicersim.io.rampfile import DQ
from slicersim.physics.ramp import P_KTC, P_POISSON, P_READ, P_SPARSE, RAMP_PTRS_MIN_MEAN, sparse_threshold, to_adu

__all__ = ["simulate_block_numpy", "simulate_block_opencl", "charge_groups", "CPU_WORK_GROUP", "MAX_CPU_WORK_GROUP"]

def _frame_increment(mu, exp_neg_mu, seed, pix, frame, stream, gauss_min_mean):
    """Poisson increments of one frame (twin of the dense path in ramp.cl)."""
    out = np.zeros_like(mu)
    gauss = (mu > 0) & (mu >= gauss_min_mean)
    ptrs = (mu >= RAMP_PTRS_MIN_MEAN) & ~gauss
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


#: draw of the block whose word 0 holds a sparse count's low 32 bits (counter (g << 32 | pixel, stream))
REFINE_DRAW = 0xFFFFFFFF


def _frame_position32(x, w):
    """Frame position in [0, w): (x·w) >> 32 with a 32-bit word x (exact integers)."""
    return ((np.asarray(x, np.uint64) * np.uint64(w)) >> np.uint64(32)).astype(np.float64)


def _inversion_state(mu, p0, u):
    """:func:`rng.inversion_search` that also returns the term and CDF value where each search stopped."""
    p = np.array(p0, dtype=np.float64, copy=True)
    cdf = p.copy()
    k = np.zeros_like(mu)
    todo = np.nonzero((u > cdf) & (p > 0.0))[0]
    while todo.size:
        k[todo] += 1.0
        p[todo] = p[todo] * mu[todo] / k[todo]
        cdf[todo] = cdf[todo] + p[todo]
        todo = todo[(u[todo] > cdf[todo]) & (p[todo] > 0.0)]
    return k, p, cdf


def sparse_count(lam, p_empty, hi, low_words):
    """K ~ Poisson(lam) by inversion of the 52-bit uniform of :func:`rng.words_to_uniform` whose top
    32 bits are ``hi``; its low bits come from ``low_words()`` (called with the lanes that need them)
    only where a CDF value falls between the smallest and the largest uniform with those top bits,
    so the counts are those of full 52-bit uniforms while nearly all pixels use 32 random bits.

    Parameters
    ----------
    lam, p_empty : (npix,) float64
        Poisson mean and e^−lam.
    hi : (npix,) uint32
        Top 32 bits of the uniform.
    low_words : callable
        ``low_words(sel)`` → (sel.size,) uint32: the low 32 bits of the lanes ``sel``.

    Returns
    -------
    (npix,) float64 counts."""
    hi = np.asarray(hi, np.uint32)
    K, p, cdf = _inversion_state(lam, p_empty, rng.words_to_uniform(hi, np.uint32(0)))
    # the search of the largest uniform with these top bits goes on past K iff it exceeds the CDF
    # value that stopped this one (and the term is not 0): the kernel's second search, in one test
    amb = np.nonzero((rng.words_to_uniform(hi, np.uint32(0xFFFFFFFF)) > cdf) & (p > 0.0))[0]
    if amb.size:
        u = rng.words_to_uniform(hi[amb], low_words(amb))
        K[amb] = rng.inversion_search(lam[amb], p_empty[amb], u)
    return K


def _sparse_group(mu, p_empty, before, g, w, m, full_well, pix, seed, stream, fx=None):
    """(read sum, clipped charge after the window, window reached the full well) of group g.

    One block (g//2 << 32 | pixel, stream, 0) serves windows g = 2i (words 0, 1) and 2i + 1 (words
    2, 3): K ~ Poisson(mu·w) by inversion (:func:`sparse_count`) of a uniform with top bits word 0
    (2), low bits word 0 of block (g << 32 | pixel, stream, REFINE_DRAW) where needed; word 1 (3)
    places event 0 (:func:`_frame_position32`); later events use draws ≥ 1
    (:func:`_event_words`).  ``fx`` (effects twin, :mod:`slicersim.backends.ramp_effects`) adds the
    window's deposits and the nonlinear read values."""
    words = rng.random_words(seed, (np.uint64(g >> 1) << np.uint64(32)) | pix, stream, 0)
    hi, pw = words[:, 2 * (g & 1)], words[:, 2 * (g & 1) + 1]
    gidx = np.uint64(g) << np.uint64(32)
    K = sparse_count(mu * float(w), p_empty, hi,
                     lambda sel: rng.random_words(seed, gidx | pix[sel], stream, REFINE_DRAW)[:, 0])
    pos0 = _frame_position32(pw, w)
    seen = _events_seen(K, pos0, g, w, m, pix, seed, stream)
    total = before + K
    dsum = None
    if fx is not None:
        dsum = fx.window_deposits(w)
        total = total + dsum
    read_sum = float(m) * before + seen
    over = np.nonzero(total > full_well)[0]
    if over.size:
        read_sum[over] = _clipped_read_sum(before[over], K[over], pos0[over], g, w, m, full_well, pix[over],
                                           seed, stream)
    if fx is not None:
        read_sum = fx.window_read_sum(read_sum, before, K, pos0, g, w, m, full_well, pix, seed, stream)
    full = total >= full_well
    return read_sum, np.where(full, full_well, total), full


def charge_groups(mu_frame, dead, pixel0, ramp, seed, p, fx=None):
    """Yield (g, read sum over the m reads of group g [e-] (npix,), sticky saturation flags (npix,)).

    The flags array is shared between groups: a consumer may OR further flags into it.  ``fx``:
    the effects twin (deposits, nonlinearity), None for the plain ramp."""
    n, m, d = p.nmd
    npix = mu_frame.size
    pix = np.arange(pixel0, pixel0 + npix, dtype=np.uint64)
    mu = np.where(dead, 0.0, mu_frame)
    sbase = 4 * ramp
    sparse = mu * float(m + d) < sparse_threshold(p)
    sp, dn = np.nonzero(sparse)[0], np.nonzero(~sparse)[0]
    mu_sp, pix_sp, mu_dn, pix_dn = mu[sp], pix[sp], mu[dn], pix[dn]
    p_full, p_last = rng.rng_exp(-(mu_sp * float(m + d))), rng.rng_exp(-(mu_sp * float(m)))
    before = np.zeros(sp.size)
    exp_neg_mu = rng.rng_exp(-mu_dn)
    charge = np.zeros(dn.size)
    saturated = np.zeros(npix, dtype=bool)
    fx_sp = fx_dn = None
    if fx is not None:
        fx_sp, fx_dn = fx.subset(sp), fx.subset(dn)
    frame = 0
    for g in range(n):
        w = m if g == n - 1 else m + d
        total = np.zeros(npix)
        if sp.size:
            if fx_sp is not None:
                fx_sp.start_window(frame)
            total[sp], before, full = _sparse_group(mu_sp, p_last if g == n - 1 else p_full, before, g, w, m,
                                                    p.full_well, pix_sp, seed, sbase + P_SPARSE, fx_sp)
            saturated[sp] |= full
        if dn.size:
            sum_dn = np.zeros(dn.size)
            for j in range(w):
                charge = charge + _frame_increment(mu_dn, exp_neg_mu, seed, pix_dn, frame + j,
                                                   sbase + P_POISSON, p.gauss_min_mean)
                if fx_dn is not None:
                    charge = fx_dn.frame_deposits(charge, frame + j)
                full = charge >= p.full_well
                charge[full] = p.full_well
                saturated[dn] |= full
                if j < m:
                    sum_dn = sum_dn + (charge if fx_dn is None else fx_dn.read_value(charge))
            total[dn] = sum_dn
        frame += w
        yield g, total, saturated


def simulate_block_numpy(mu_frame, dead, pixel0, ramp, seed, p):
    """SCI (ngroups, npix) uint16 and GROUPDQ uint8 for one ramp of a flat pixel block."""
    n, m, d = p.nmd
    npix = mu_frame.size
    pix = np.arange(pixel0, pixel0 + npix, dtype=np.uint64)
    sbase = 4 * ramp
    reset = np.zeros(npix)
    if p.ktc_noise > 0:
        reset = p.ktc_noise * rng.normal(seed, pix, sbase + P_KTC, 0)[..., 0]
    sci = np.empty((n, npix), np.uint16)
    gdq = np.empty((n, npix), np.uint8)
    read_sigma = p.ron / math.sqrt(m)
    for g, total, saturated in charge_groups(mu_frame, dead, pixel0, ramp, seed, p):
        if g % 2 == 0:
            z_pair = rng.normal(seed, (np.uint64(g >> 1) << np.uint64(32)) | pix, sbase + P_READ, 0)
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
    dev = opencl.get_device()
    gpu = "GPU" in opencl.device_type(dev)
    vector_width = check_vector_width(vector_width, 16, scale=2)
    limit = int(dev.max_work_group_size) if gpu else min(int(dev.max_work_group_size), MAX_CPU_WORK_GROUP)
    if work_group is None:
        work_group = None if gpu else CPU_WORK_GROUP
    elif not 1 <= int(work_group) <= limit:
        raise ParameterError(f"work_group must be in [1, {limit}] on this device, got {work_group}")
    return vector_width, (int(work_group) if work_group else None)


def block_arguments(npix, pixel0, ramp, key, p, want_dq, real=np.float64):
    """Scalar arguments of the two samplers after the output buffers (RAMP_KERNEL_ARGS); ``real``:
    the kernels' floating type (float32 for the ``-DSINGLE`` build)."""
    n, m, d = p.nmd
    return (np.uint32(npix), np.uint32(pixel0), np.uint32(ramp), np.uint32(key[0]), np.uint32(key[1]),
            np.int32(n), np.int32(m), np.int32(d), real(p.ron / math.sqrt(m)), real(p.gain),
            real(p.bias), real(p.ktc_noise), real(p.full_well), real(p.saturation),
            np.int32(bool(want_dq)))


def launch_samplers(kernel_of, lists, vw, work_group, workspace, head, outputs, scalars, gauss_min_mean,
                    tail=(), real=np.float64):
    """Launch ``macc_ramp_sparse`` then ``macc_ramp_dense`` (``kernel_of(name, vw)``) on their pixel
    lists; arguments: ``head`` (mu), the list and its item count, ``outputs``, ``scalars``
    (:func:`block_arguments`), ``tail`` (the effects build's), then gauss_min_mean (dense only)."""
    for name, idx in (("macc_ramp_sparse", lists[0]), ("macc_ramp_dense", lists[1])):
        items = idx.size // vw
        if not items:
            continue
        gsize, lsize = (items,), None
        if work_group:
            gsize, lsize = (-(-items // work_group) * work_group,), (work_group,)
        d_idx = opencl.to_device(idx, opencl.workspace_buffer(workspace, name, idx.nbytes))
        extra = (real(gauss_min_mean),) if name == "macc_ramp_dense" else ()
        opencl.launch(kernel_of(name, vw), gsize, lsize, *head, d_idx, np.uint32(items), *outputs, *scalars,
                      *tail, *extra)


def _ramp_kernel(name, vector_width, precision="double"):
    return opencl.get_kernel("ramp.cl", name, (f"-DRNG_VW={int(vector_width)}",) + opencl.precision_options(precision))


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




def device_block(mu_frame, dead, p, vector_width, work_group, workspace, real=np.float64):
    """Setup shared by the OpenCL samplers of a flat pixel block: (vw, work_group, pixel lists,
    device buffer of μ [e-/frame] with 0 for dead pixels, as ``real``).  The lists (which pixel takes
    which path) are chosen from the float64 μ whatever the kernels' precision."""
    vw, work_group = _launch_geometry(vector_width, work_group)
    mu = np.where(dead, 0.0, mu_frame)
    lists = _pixel_lists(mu, p, vw)
    mu = np.ascontiguousarray(mu, dtype=real)
    return vw, work_group, lists, opencl.to_device(mu, opencl.workspace_buffer(workspace, "mu", mu.nbytes))


def simulate_block_opencl(mu_frame, dead, pixel0, ramp, seed, p, work_group=None, vector_width=None, *,
                          want_dq=True, out=None, workspace=None, precision="double"):
    """OpenCL twin of :func:`simulate_block_numpy`: sparse then dense pixels, ``vector_width``
    pixels per work item (see :func:`_launch_geometry`); the result does not depend on either.

    want_dq=False skips GROUPDQ (returned as None); out: (sci, gdq) C-contiguous (n, npix) arrays to
    fill (either may be None: a new one); workspace: dict reusing device buffers between blocks.
    precision="single": the float build (same Philox words; equal to the twin's integers except
    where a float rounding moves a decision, see ``kernels/philox.cl`` and
    :data:`slicersim.backends.precision.SINGLE_PRECISION_ERRORS`).
    """
    n = p.nmd[0]
    npix = mu_frame.size
    real = np.float32 if precision == "single" else np.float64
    vw, work_group, lists, d_mu = device_block(mu_frame, dead, p, vector_width, work_group, workspace, real)
    key = rng.seed_to_key(seed)
    d_sci = opencl.workspace_buffer(workspace, "sci", 2 * n * npix)
    d_gdq = opencl.workspace_buffer(workspace, "gdq", n * npix if want_dq else 1)
    launch_samplers(lambda name, width: _ramp_kernel(name, width, precision), lists, vw, work_group, workspace,
                    (d_mu,), (d_sci, d_gdq), block_arguments(npix, pixel0, ramp, key, p, want_dq, real),
                    p.gauss_min_mean, real=real)
    sci_out, gdq_out = (None, None) if out is None else out
    sci = np.empty((n, npix), np.uint16) if sci_out is None else sci_out
    opencl.from_device(sci, d_sci)
    gdq = None
    if want_dq:
        gdq = np.empty((n, npix), np.uint8) if gdq_out is None else gdq_out
        opencl.from_device(gdq, d_gdq)
    return sci, gdq
