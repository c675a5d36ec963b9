"""Backend choice, memory budget and chunking shared by every kernel family.

Every kernel-backed function takes ``backend="auto" | "opencl" | "numpy"``:
"auto" uses OpenCL when a device with double precision is available (see
:mod:`slicersim.backends.opencl`) and the NumPy twin otherwise.
"""
from __future__ import annotations

import os
import threading
import warnings

from slicersim import validation
from slicersim.backends import opencl
from slicersim.backends.selfcheck import NOT_RUN, device_selfcheck, device_selfcheck_single
from slicersim.errors import OpenCLUnavailableError

__all__ = ["BACKENDS", "DEFAULT_MAX_BYTES", "resolve_backend", "chunk_ranges"]

#: memory budget [bytes] of the temporaries of one call, unless the caller gives max_bytes
DEFAULT_MAX_BYTES = 256 * 2**20
BACKENDS = ("auto", "opencl", "numpy")


#: device fingerprint → (passed, message) of the self-check (:func:`device_validated`)
_SELFCHECK = {}
_selfcheck_lock = threading.Lock()
_warned = set()                                   # devices already warned about (once per process)
_TRUE, _FALSE = ("1", "true", "yes", "on"), ("", "0", "false", "no", "off")


def _trust_device() -> bool:
    value = os.environ.get("SLICERSIM_TRUST_DEVICE", "").strip().lower()
    if value not in _TRUE + _FALSE:
        warnings.warn(f"SLICERSIM_TRUST_DEVICE={value!r} is not one of {_TRUE + _FALSE[1:]}: the device "
                      "self-check runs", RuntimeWarning, stacklevel=3)
    return value in _TRUE


def device_validated(precision: str = "double") -> tuple:
    """(passed, message): whether the selected OpenCL device gives the NumPy twin's random
    draws and ramps (:func:`slicersim.backends.selfcheck.device_selfcheck`; with
    ``precision="single"`` the float builds' noise draws and ramps within their documented deviation,
    :func:`~slicersim.backends.selfcheck.device_selfcheck_single`), checked once per device,
    precision and process (a check that could not run is not kept: the next call tries again).
    Every noisy product goes through these kernels: a driver that computes or returns them wrongly
    (seen on an NVIDIA H200: uniforms, Gaussians and Poisson counts differed from the twin) must not
    be used silently.  ``SLICERSIM_TRUST_DEVICE=1`` skips the check."""
    if _trust_device():
        return True, "not checked (SLICERSIM_TRUST_DEVICE)"
    key = opencl.device_fingerprint()
    if precision == "single":
        key = (key, "single")
    with _selfcheck_lock:
        if key not in _SELFCHECK:
            result = device_selfcheck_single() if precision == "single" else device_selfcheck()
            if not result[0] and result[1].startswith(NOT_RUN):
                return result
            _SELFCHECK[key] = result
        return _SELFCHECK[key]


def resolve_backend(backend: str = "auto") -> str:
    """Return "opencl" or "numpy" for *backend* (raises on unknown names).

    "auto" uses OpenCL only on a device with fp64 that passes the self-check
    (:func:`device_validated`; a warning names a device that fails it); an explicit "opencl"
    on a device that fails it raises :class:`OpenCLUnavailableError`."""
    validation.choice("backend", backend, BACKENDS)
    if backend == "numpy":
        return backend
    if backend == "opencl":
        if opencl.is_available() and opencl.device_supports_fp64():
            ok, msg = device_validated()
            if not ok:
                raise OpenCLUnavailableError(
                    f"{msg}; use backend='numpy' (--backend numpy) or 'auto' (falls back to NumPy), or pick "
                    f"another device with {opencl.ENV_VAR}; SLICERSIM_TRUST_DEVICE=1 skips the check (diagnosis only)")
        return backend
    opencl.check_process()  # a forked child must not silently change backend
    if opencl.is_available() and opencl.device_supports_fp64():
        ok, msg = device_validated()
        if ok:
            return "opencl"
        key = opencl.device_fingerprint()
        with _selfcheck_lock:
            first = key not in _warned
            _warned.add(key)
        if first:
            warnings.warn(f"{msg}; using the NumPy twins", RuntimeWarning, stacklevel=2)
    return "numpy"


def chunk_ranges(n, bytes_per_item, max_bytes=DEFAULT_MAX_BYTES, multiple=1):
    """Half-open ranges [i0, i1) covering 0…n, each within ``max_bytes`` for items of
    ``bytes_per_item`` bytes, a multiple of ``multiple`` items long (at least one multiple)."""
    step = max(multiple, int(max_bytes // max(bytes_per_item, 1)) // multiple * multiple)
    for i0 in range(0, n, step):
        yield i0, min(n, i0 + step)


