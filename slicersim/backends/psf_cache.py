"""PSF blocks cached across targets: :func:`psf_cube`, :func:`psf_cube_device` and
:func:`psf_cells` of :mod:`slicersim.backends.psf`, memoised in one process-wide LRU bounded in
bytes (:data:`PSF_CACHE_MAX_BYTES`, :func:`clear_psf_cache`).

A Monte Carlo loop builds a new target (a new model) per draw, but the PSF of a point source
depends on the instrument only, so every draw after the first reuses the same blocks.  The key
is the content of *every* input of the computation (:func:`slicersim.memo.content_key`): the
wavelengths' bytes, the field shape, the source position, the profile, σ_ref, the spatial
scale, guiding and instrumental σ, diameter and obscuration, the oversampling, the grid, the
memory budget, the cells (``psf_cells``), the resolved backend and precision and, on OpenCL, the device
(platform, name, driver) and the kernel sources' digest.  Any change gives another key: a
cached block is the uncached one, bit for bit.

Host blocks are returned as read-only views of the cached array (copy before writing).  Blocks
left on the device (:class:`~slicersim.backends.psf.DevicePSF`) share the cached buffer: device
consumers only read it (never write into a DevicePSF buffer); they are cached per OpenCL
context (a context created later, e.g. after ``opencl.reset()``, computes its own).
"""
from __future__ import annotations

import contextlib
import dataclasses
import inspect
import os
import threading

import numpy as np

from slicersim.backends import opencl, psf as _psf
from slicersim.backends.dispatch import resolve_backend
from slicersim.backends.precision import resolve_precision
from slicersim.errors import SlicersimError
from slicersim.memo import ByteLRU, content_key, read_only

__all__ = ["psf_cube", "psf_cube_device", "psf_cells", "clear_psf_cache", "psf_cache_info",
           "set_psf_cache_limit", "bypass", "PSF_CACHE_MAX_BYTES", "PSF_CACHE"]

#: bytes of PSF blocks kept per process (env SLICERSIM_PSF_CACHE_BYTES overrides; 0 disables)
PSF_CACHE_MAX_BYTES = 256 * 2**20
_ENV = "SLICERSIM_PSF_CACHE_BYTES"


def _limit_from_env():
    text = os.environ.get(_ENV, "").strip()
    if not text:
        return PSF_CACHE_MAX_BYTES
    try:
        value = int(float(text))
    except ValueError:
        raise SlicersimError(f"{_ENV}={text!r} is not a number of bytes") from None
    if value < 0:
        raise SlicersimError(f"{_ENV} must be >= 0, got {value}")
    return value


PSF_CACHE = ByteLRU("psf", _limit_from_env())
_SIGNATURES = {name: inspect.signature(getattr(_psf, name)) for name in ("psf_cube", "psf_cube_device", "psf_cells")}


def clear_psf_cache():
    """Drop every cached PSF block (host arrays and device buffers)."""
    PSF_CACHE.clear()


def psf_cache_info():
    """entries, nbytes, max_bytes, hits, misses, evictions of the PSF cache."""
    return PSF_CACHE.info()


def set_psf_cache_limit(max_bytes):
    """Bound the PSF cache to ``max_bytes`` (0 disables it); evicts at once if needed."""
    PSF_CACHE.max_bytes = max_bytes


_bypass = threading.local()


@contextlib.contextmanager
def bypass():
    """Within the block, this thread computes every PSF afresh (no lookup, nothing stored)."""
    depth = getattr(_bypass, "depth", 0)
    _bypass.depth = depth + 1
    try:
        yield
    finally:
        _bypass.depth = depth


def _device_identity():
    return opencl.device_fingerprint()


def _key(func, args, kwargs):
    """(content key of every argument, defaults filled in) + resolved backend (+ device)."""
    bound = _SIGNATURES[func].bind(*args, **kwargs)
    bound.apply_defaults()
    params = dict(bound.arguments)
    params.pop("out_buffer", None)
    optics = _psf.psf_optics(params.pop("optics"), **params.pop("optics_keywords"))   # one key per optics
    params.update(dataclasses.asdict(optics))
    if params.get("grid") == "reference":          # NumPy, double, whatever was asked
        backend = resolve_backend(params["backend"])
    else:
        backend, params["precision"] = resolve_precision(params["precision"], params["backend"], "psf")
    params["backend"] = backend
    device = _device_identity() if backend == "opencl" else None
    return (func, content_key(params), device)


def _nbytes(value):
    return value.nbytes


def _cached(func, args, kwargs):
    if PSF_CACHE.max_bytes == 0 or getattr(_bypass, "depth", 0):
        return getattr(_psf, func)(*args, **kwargs)
    try:
        key = _key(func, args, kwargs)
    except (TypeError, SlicersimError):
        # an argument without content key, a bad call, or a backend/precision that cannot be resolved
        # for the key (e.g. "double" without fp64 for a NumPy-only Gaussian psf_cells): computed (or
        # refused) exactly as uncached, not cached
        return getattr(_psf, func)(*args, **kwargs)
    hit = PSF_CACHE.get(key)
    if hit is not None:
        ctx, value = hit
        if ctx is None or ctx is opencl.get_context():
            return read_only(value) if isinstance(value, np.ndarray) else value
        PSF_CACHE.discard(key)                       # a buffer of an older context
    value = getattr(_psf, func)(*args, **kwargs)
    ctx = opencl.get_context() if isinstance(value, _psf.DevicePSF) else None
    if isinstance(value, np.ndarray):
        value = read_only(value)
    PSF_CACHE.put(key, (ctx, value), _nbytes(value))
    return read_only(value) if isinstance(value, np.ndarray) else value


def psf_cube(*args, **kwargs):
    """:func:`slicersim.backends.psf.psf_cube`, cached; returns a read-only array."""
    return _cached("psf_cube", args, kwargs)


def psf_cube_device(*args, **kwargs):
    """:func:`slicersim.backends.psf.psf_cube_device`, cached: a DevicePSF sharing the cached
    buffer (read it only), or the read-only array of :func:`psf_cube` when the block is not
    computed on a device.  With an ``out_buffer`` the block is computed into it, uncached."""
    if kwargs.get("out_buffer") is not None:
        return _psf.psf_cube_device(*args, **kwargs)
    return _cached("psf_cube_device", args, kwargs)


def psf_cells(*args, **kwargs):
    """:func:`slicersim.backends.psf.psf_cells`, cached; returns a read-only array."""
    return _cached("psf_cells", args, kwargs)
