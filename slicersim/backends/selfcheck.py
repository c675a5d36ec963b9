"""Per-device self-check: the selected OpenCL device's random streams against the NumPy twin.

Every noisy product (cubes, ramps, detector effects) draws through ``kernels/noise.cl`` /
``philox.cl``; a driver that computes or returns those draws wrongly must not be used silently
(seen on an NVIDIA H200, driver 580.159: uniforms, Gaussians and Poisson counts differed from the
twin and ramps came out 1e5 σ off).  :func:`device_selfcheck` launches the kernels the products
use, through the same kinds of buffers (host-mapped for the uniform/normal grid, device buffers for
Poisson), on a few hundred draws, and then the ramp sampler (``kernels/ramp.cl``, both kernels) on
two small blocks whose mean charges take every path of the kernels (see :func:`_ramp_cases`), bit for
bit against its twin (SCI and GROUPDQ): the streams alone do not vouch for the kernels built on them
(on the H200 they passed while a 4096² reduction was still wrong — there the ramp kernel turned out
right and the fit's read-back wrong, see gpu_h200.md run 7 — but a ramp-kernel miscompilation is
exactly what such a check must catch).  Cost on PoCL (2 cores, kernels built): ≈ 0.15 s for the
streams, + 0.15–0.2 s for the ramp blocks (kernel ≈ 0.07 s, twin ≈ 0.1–0.15 s); building ramp.cl
without a binary cache adds ≈ 4 s once (a ramp product builds it anyway); H200: 2.2 s with builds.
:func:`slicersim.backends.dispatch.device_validated` runs it once per device and process.  This
module imports only :mod:`opencl` and :mod:`rng` at import time (the ramp backend, which imports
:mod:`dispatch`, is imported when the check runs).
"""
from __future__ import annotations

import numpy as np

from slicersim import rng
from slicersim.backends import opencl

__all__ = ["device_selfcheck", "device_selfcheck_single", "NOT_RUN"]

#: start of the message of a check that could not run (a build or launch failure): not a verdict
NOT_RUN = "OpenCL device self-check could not run"

_N_UNIFORM = 257                                  # odd: a partial work group
_POISSON_MEANS = np.tile([1e-3, 0.5, 3.0, 9.5, 30.0, 1e4], 50)    # inversion and PTRS branches
_SEED, _STREAM, _DRAW = 11, 3, 1

# Ramp blocks of the self-check: mean charge per frame [e-/frame] of each pixel class (0 = dead).
# Block A (default sparse threshold: sparse below 0.57 e-/frame for m + d = 3; gauss_min_mean 5e3):
# sparse windows with 0, 1 and several events (past the 3 tabulated CDF terms), dense inversion
# (< 10; 9.99 and 10 on either side of the switch), PTRS (10 … 3e3, unsaturated), the rounded
# Gaussian (≥ 5e3), ADU clipped at 65535 from frame 6 … 1 (9e3 … 1e6), the full well (8e4 e-, above
# the ADU range) reached by 3e4 … 1e6; kTC noise, gain ≠ 1; pixel indices of the last rows of a
# 4096² detector, ramp 3.  Block B (sparse_max_group 64: sparse up to
# 21 e-/frame; full well 150 e-): sparse windows crossing the full well (the clipped read sum), many
# events per window, ADU clipped at 0 (bias 5 ADU), saturation flags by ADU; pixel indices above
# 2³¹ (64-bit counters with the top bit of the low word set).  Classes are shuffled (dense lists
# sorted by charge, sparse lanes not contiguous); 97 + 61 pixels: partial vectors and work groups.
_RAMP_MU_A = [0.0, 1e-3, 0.02, 0.3, 0.55, 0.6, 1.0, 3.0, 9.99, 10.0, 30.0, 300.0, 3e3, 5e3, 9e3, 3e4,
              3e5, 1e6]
_RAMP_MU_B = [0.0, 1e-3, 0.3, 2.0, 7.0, 15.0, 21.0, 25.0, 300.0, 2e4, 3e5]
_RAMP_NMD = (4, 2, 1)
_RAMP_SEED = 2**63 + 977


def _ramp_cases():
    """[(mu (npix,), dead (npix,), pixel0, ramp, RampParameters)] of the two ramp blocks."""
    from slicersim.physics.ramp import RampParameters
    gen = np.random.default_rng(5)
    cases = []
    for mu_classes, npix, pixel0, ramp, kw in (
            (_RAMP_MU_A, 97, 4090 * 4096 + 37, 3,
             dict(ron=12.0, ktc_noise=25.0, gain=1.3, bias=2000.0, saturation=65535.0, full_well=80000.0,
                  gauss_min_mean=5e3)),
            (_RAMP_MU_B, 61, 2**31 + 4093, 0,
             dict(ron=12.0, gain=1.0, bias=5.0, saturation=120.0, full_well=150.0, sparse_max_group=64.0))):
        mu = np.resize(np.asarray(mu_classes, float), npix)[gen.permutation(npix)]
        dead = np.zeros(npix, bool)
        dead[gen.choice(npix, 3, replace=False)] = True
        cases.append((mu, dead, pixel0, ramp, RampParameters(nmd=_RAMP_NMD, **kw)))
    return cases


def _ramp_blocks(simulate_block):
    """[(SCI, GROUPDQ)] of the ramp blocks by ``simulate_block`` (the kernel or its twin)."""
    return [simulate_block(mu, dead, pixel0, ramp, _RAMP_SEED, p) for mu, dead, pixel0, ramp, p in _ramp_cases()]


def _ramp_mismatch(got, want, max_fraction=0.0):
    """'' when the ramp blocks agree (SCI and GROUPDQ differing in at most ``max_fraction`` of the
    values: 0, identical, for the float64 kernels), else what differs."""
    bad = []
    for name, (sc, qc), (sn, qn) in zip("AB", got, want):
        nsci = int(np.count_nonzero(sc != sn)) if sc.shape == sn.shape else sn.size
        ndq = int(np.count_nonzero(qc != qn)) if qc.shape == qn.shape else qn.size
        if max(nsci, ndq) > max_fraction * sn.size:
            bad.append(f"ramp block {name}: {nsci}/{sn.size} SCI and {ndq}/{qn.size} GROUPDQ values differ")
    return "; ".join(bad)


def _uniform_normal(vw):
    """(uniforms, Gaussians) of the uniform_normal kernel at vector width ``vw`` (host-mapped buffers)."""
    key = rng.seed_to_key(_SEED)
    npad = -(-_N_UNIFORM // vw) * vw
    planes = np.zeros((4, 1, npad))
    bufs = [opencl.host_buffer(plane) for plane in planes]
    kern = opencl.cached_kernel("noise.cl", "uniform_normal", (f"-DRNG_VW={vw}",))
    opencl.launch(kern, (npad // vw, 1), None, *bufs, np.uint64(0), np.uint64(npad), np.uint32(npad),
                  np.uint32(key[0]), np.uint32(key[1]), np.uint32(_STREAM), np.uint32(_DRAW))
    for plane, buf in zip(planes, bufs):
        opencl.sync_to_host(buf, plane)
    grid = np.moveaxis(planes[:, 0, :_N_UNIFORM], 0, -1)
    return grid[:, :2], grid[:, 2:]


def _opencl_draws():
    """(uniforms (n, 2), Gaussians (n, 2), Poisson counts) from the device's noise.cl kernels: the
    uniform/normal grid at width 1 and at the device's preferred width (the products' on CPUs) —
    the second must equal the first — and Poisson counts."""
    u, z = _uniform_normal(1)
    vw = opencl.preferred_vector_width()
    if vw > 1:
        uv, zv = _uniform_normal(vw)
        if not (np.array_equal(uv, u) and np.array_equal(zv, z)):
            u, z = uv, zv                          # reported against the twin below
    mu = np.ascontiguousarray(_POISSON_MEANS)
    counts = np.zeros_like(mu)
    d_m, d_o = opencl.to_device(mu), opencl.device_buffer(counts.nbytes)
    pkey = rng.seed_to_key(_SEED + 2)
    kern = opencl.cached_kernel("noise.cl", "poisson_draw", ("-DRNG_VW=1",))
    opencl.launch(kern, (mu.size,), None, d_m, d_o, np.uint64(0), np.uint32(mu.size), np.uint32(pkey[0]),
                  np.uint32(pkey[1]), np.uint32(_STREAM))
    opencl.from_device(counts, d_o)
    return u, z, counts


def _numpy_draws():
    index = np.arange(_N_UNIFORM, dtype=np.uint64)
    mu = _POISSON_MEANS
    return (rng.uniform(_SEED, index, _STREAM, _DRAW), rng.normal(_SEED, index, _STREAM, _DRAW),
            rng.poisson(mu, _SEED + 2, np.arange(mu.size, dtype=np.uint64), _STREAM))


def device_selfcheck():
    """(passed, message) for the selected device: uniforms exactly (integer arithmetic), Gaussians
    to 1e-12 (a driver that contracts a·b + c into an FMA moves their last bits), Poisson counts
    of means 1e-3 … 1e4 (≥ 98 % identical: a last-bit change moves a count only at a CDF step),
    and two small ramp blocks through every path of ``ramp.cl``, bit for bit (SCI and GROUPDQ)."""
    from slicersim.backends import ramp as ramp_backend
    try:
        dev = opencl.get_device().name.strip()
        uc, zc, kc = _opencl_draws()
        rc = _ramp_blocks(ramp_backend.simulate_block_opencl)
    except Exception as exc:                        # a build or launch failure is a failed check
        return False, f"{NOT_RUN} ({type(exc).__name__}: {exc})"
    un, zn, kn = _numpy_draws()
    rn = _ramp_blocks(ramp_backend.simulate_block_numpy)
    bad = []
    if not np.array_equal(uc, un):
        bad.append(f"{int(np.count_nonzero(uc != un))}/{un.size} uniforms differ")
    close = np.isclose(zc, zn, rtol=1e-12, atol=1e-12)
    if not close.all():
        bad.append(f"{int(np.count_nonzero(~close))}/{zn.size} Gaussians differ")
    return _verdict(dev, bad, kc, kn, rc, rn, 0.0, "random-stream and ramp self-check against the NumPy twin",
                    "its noisy products")


def _verdict(dev, bad, counts, counts_twin, ramps, ramps_twin, max_fraction, check, products):
    """(passed, message) of a self-check: ``bad`` (what already differs) plus the Poisson counts (≤ 2 %
    or ``max_fraction`` may differ: a last-bit change moves a count only at a CDF step) and the ramp
    blocks (≤ ``max_fraction`` of their values)."""
    ndiff = int(np.count_nonzero(counts != counts_twin))
    if ndiff > max(0.02, max_fraction) * counts_twin.size:
        bad.append(f"{ndiff}/{counts_twin.size} Poisson counts differ")
    ramp_bad = _ramp_mismatch(ramps, ramps_twin, max_fraction)
    if ramp_bad:
        bad.append(ramp_bad)
    if bad:
        return False, f"OpenCL device {dev!r} fails the {check} ({'; '.join(bad)}): {products} would be wrong"
    return True, f"OpenCL device {dev!r} passes the {check}"


#: largest fraction of the ramp blocks' SCI (and GROUPDQ) values that the single-precision samplers
#: may change against the float64 twin: a float rounding moves a value by 1 ADU in ~1e-3 of them
#: (0 of the 632 values here on PoCL), a broken device changes most of them
SINGLE_MAX_FRACTION = 0.02


#: largest |Δ| [σ] of a single-precision Gaussian draw against the twin's (the "noise" tolerance)
SINGLE_MAX_GAUSS_SIGMA = 1e-3
_N_GAUSS_SINGLE = 256                             # a multiple of every vector width


def _single_noise_draws():
    """(Gaussians, Poisson counts) of noise.cl's float builds: ``gaussian_noise`` of (0, 1) at width 1
    and at the device's preferred width, ``poisson_draw`` of the self-check's means (kernels launched
    here: no precision resolution, hence no re-entry into the check)."""
    n, key = _N_GAUSS_SINGLE, rng.seed_to_key(_SEED)
    options = opencl.precision_options("single")
    z = []
    for vw in dict.fromkeys((1, opencl.preferred_vector_width())):
        kern = opencl.cached_kernel("noise.cl", "gaussian_noise", (f"-DRNG_VW={vw}",) + options)
        d_e, d_v = opencl.to_device(np.zeros(n, np.float32)), opencl.to_device(np.ones(n, np.float32))
        d_o, out = opencl.device_buffer(4 * n), np.empty(n, np.float32)
        opencl.launch(kern, (n // vw,), None, d_e, d_v, d_o, np.uint64(0), np.uint32(n), np.uint32(key[0]),
                      np.uint32(key[1]), np.uint32(_STREAM))
        opencl.from_device(out, d_o)
        z.append(out.astype(np.float64))
    mu = np.ascontiguousarray(_POISSON_MEANS, np.float32)
    counts = np.zeros_like(mu)
    d_m, d_o = opencl.to_device(mu), opencl.device_buffer(counts.nbytes)
    pkey = rng.seed_to_key(_SEED + 2)
    opencl.launch(opencl.cached_kernel("noise.cl", "poisson_draw", ("-DRNG_VW=1",) + options), (mu.size,), None,
                  d_m, d_o, np.uint64(0), np.uint32(mu.size), np.uint32(pkey[0]), np.uint32(pkey[1]),
                  np.uint32(_STREAM))
    opencl.from_device(counts, d_o)
    return z, counts.astype(np.float64)


def device_selfcheck_single():
    """(passed, message) for the single-precision builds (``-DSINGLE``), which a device without fp64
    runs unchecked by :func:`device_selfcheck` (its kernels are fp64): Gaussian draws of
    ``noise.cl`` within :data:`SINGLE_MAX_GAUSS_SIGMA` of the twin's, Poisson counts (≤
    :data:`SINGLE_MAX_FRACTION` differ), and the same two ramp blocks through the float samplers
    (Philox words, float uniforms, log/exp/sin/cos, PTRS with ``rng_log_poisson``) against the
    float64 twin, allowed to differ in ≤ :data:`SINGLE_MAX_FRACTION` of the SCI and of the GROUPDQ
    values (float roundings, not bit-identical by design)."""
    from slicersim.backends import ramp as ramp_backend
    try:
        dev = opencl.get_device().name.strip()
        zc, kc = _single_noise_draws()
        got = _ramp_blocks(lambda *a: ramp_backend.simulate_block_opencl(*a, precision="single"))
    except Exception as exc:                        # a build or launch failure is a failed check
        return False, f"{NOT_RUN} ({type(exc).__name__}: {exc})"
    want = _ramp_blocks(ramp_backend.simulate_block_numpy)
    zn = rng.normal(_SEED, np.arange(_N_GAUSS_SINGLE, dtype=np.uint64), _STREAM)[:, 0]
    kn = _numpy_draws()[2]
    bad = []
    for vw_z in zc:
        err = float(np.max(np.abs(vw_z - zn)))
        if not err <= SINGLE_MAX_GAUSS_SIGMA:
            bad.append(f"Gaussians off by up to {err:.2g} σ")
            break
    return _verdict(dev, bad, kc, kn, got, want, SINGLE_MAX_FRACTION,
                    "single-precision noise and ramp self-check against the float64 twin",
                    "its single-precision products")
