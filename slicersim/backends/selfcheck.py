"""Per-device self-check: the selected OpenCL device's random streams against the NumPy twin.

Every noisy product (cubes, ramps, detector effects) draws through ``kernels/noise.cl`` /
``philox.cl``; a driver that computes or returns those draws wrongly must not be used silently
(seen on an NVIDIA H200, driver 580.159: uniforms, Gaussians and Poisson counts differed from the
twin and ramps came out 1e5 σ off).  :func:`device_selfcheck` launches the kernels the products
use, through the same kinds of buffers (host-mapped for the uniform/normal grid, device buffers for
Poisson), on a few hundred draws; :func:`slicersim.backends.dispatch.device_validated` runs it once
per device and process.  This module imports only :mod:`opencl` and :mod:`rng` (no cycle with
:mod:`dispatch`).
"""
from __future__ import annotations

import numpy as np

from slicersim.backends import opencl, rng

__all__ = ["device_selfcheck", "NOT_RUN"]

#: start of the message of a check that could not run (a build or launch failure): not a verdict
NOT_RUN = "OpenCL device self-check could not run"

_N_UNIFORM = 257                                  # odd: a partial work group
_POISSON_MEANS = np.tile([1e-3, 0.5, 3.0, 9.5, 30.0, 1e4], 50)    # inversion and PTRS branches
_SEED, _STREAM, _DRAW = 11, 3, 1


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
    to 1e-12 (a driver that contracts a·b + c into an FMA moves their last bits) and Poisson counts
    of means 1e-3 … 1e4 (≥ 98 % identical: a last-bit change moves a count only at a CDF step)."""
    try:
        dev = opencl.get_device().name.strip()
        uc, zc, kc = _opencl_draws()
    except Exception as exc:                        # a build or launch failure is a failed check
        return False, f"{NOT_RUN} ({type(exc).__name__}: {exc})"
    un, zn, kn = _numpy_draws()
    bad = []
    if not np.array_equal(uc, un):
        bad.append(f"{int(np.count_nonzero(uc != un))}/{un.size} uniforms differ")
    close = np.isclose(zc, zn, rtol=1e-12, atol=1e-12)
    if not close.all():
        bad.append(f"{int(np.count_nonzero(~close))}/{zn.size} Gaussians differ")
    if np.count_nonzero(kc != kn) > 0.02 * kn.size:
        bad.append(f"{int(np.count_nonzero(kc != kn))}/{kn.size} Poisson counts differ")
    if bad:
        return False, (f"OpenCL device {dev!r} fails the random-stream self-check against the NumPy twin "
                       f"({'; '.join(bad)}): its noisy products would be wrong")
    return True, f"OpenCL device {dev!r} passes the random-stream self-check"
