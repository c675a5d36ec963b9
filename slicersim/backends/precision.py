"""Precision as a dial: which floating type a kernel family runs in on the selected device.

Every kernel-backed entry point that has single-precision kernels takes
``precision="auto" | "double" | "single"``:

* ``"double"``: float64 kernels (or the NumPy twin).  On an OpenCL device without fp64 this is
  refused with one clear error (the NumPy twin is still reached with ``backend="numpy"``).
* ``"single"``: float32 kernels, built from the same sources with ``-DSINGLE``
  (:func:`slicersim.backends.opencl.precision_options`).  Their error against the float64 twin is
  measured and bounded per product (:data:`SINGLE_PRECISION_ERRORS`, tested).  The NumPy backend
  has no single-precision twin: ``backend="numpy"`` computes in float64 whatever is asked.
* ``"auto"`` (default): single where the product's measured error stays below its documented
  tolerance *and* the device lacks fast fp64 (no fp64 at all, or on a GPU an fp64 FMA throughput
  below 1/:data:`FAST_FP64_RATIO` of fp32, measured once per device: :func:`fp64_throughput_ratio`);
  double otherwise.  CPUs (fp64 at ½ the fp32 rate: half the SIMD lanes; not timed, since shared
  cores make such timings unreliable) and data-centre GPUs keep double, so their results do not
  change; consumer and integrated GPUs (1/16–1/64) get single.

Before single kernels run, the device passes a single-precision self-check
(:func:`~slicersim.backends.selfcheck.device_selfcheck_single`: float noise draws and the
self-check's ramp blocks through the float samplers, no fp64 needed), once per device and process; on failure ``backend="auto"``
falls back to NumPy with a warning and ``backend="opencl"`` raises.

The ETC, the reference reproduction and everything compared at 1e-6 stay double: they do not take
this argument.
"""
from __future__ import annotations

import threading
import time
import warnings
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from slicersim.backends import opencl
from slicersim.backends.dispatch import BACKENDS, device_validated, resolve_backend
from slicersim.errors import OpenCLUnavailableError, ParameterError
from slicersim.validation import choice, short_repr

__all__ = ["PRECISIONS", "SINGLE_PRECISION_ERRORS", "DOUBLE_ONLY_PRODUCTS", "FAST_FP64_RATIO", "products",
           "check_product", "check_precision", "resolve_precision",
           "float64_kwargs", "storage_dtype",
           "fp64_throughput_ratio", "real_dtype"]

PRECISIONS = ("auto", "double", "single")
#: fp64 counts as fast when its FMA throughput is at least 1/FAST_FP64_RATIO of fp32's
FAST_FP64_RATIO = 4.0


@dataclass(frozen=True)
class SingleError:
    """Measured max error of a product in single precision against its float64 twin, and the
    tolerance that ``precision="auto"`` requires (both in ``unit``)."""
    measured: float
    tolerance: float
    unit: str
    measured_on: str

    @property
    def acceptable(self) -> bool:
        return self.measured <= self.tolerance


#: products with single-precision kernels: measured error (``benchmarks/precision.py`` and the
#: tests that bound it) and tolerance
SINGLE_PRECISION_ERRORS = {
    "psf": SingleError(3.9e-7, 1e-5, "of the PSF peak",
                       "Lazuli narrow field, Airy, jitter, blur, source in the field; PoCL CPU (a source hundreds of "
                       "cells off the field leaves only far wings in it: 1.6e-5 of their peak at 600 cells)"),
    "lsf": SingleError(1.5e-7, 1e-5, "of the peak", "Lazuli point-source cube (photons), its LSF; PoCL CPU"),
    "convolution": SingleError(1.7e-6, 1e-5, "of each plane's peak",
                               "Sersic host ⊛ Airy kernels, direct and FFT; PoCL CPU"),
    "cube": SingleError(2.0e-7, 1e-5, "of the signal peak",
                        "Lazuli narrow-field Airy cube (jitter, blur, LSF); PoCL CPU"),
    "ramp": SingleError(1.2e-3, 1e-2, "of the SCI values differing from double (integers: same Philox words)",
                        "μ from 0 to 3e4 e-/frame, MACC(16, 8, 2), kTC and read noise; PoCL CPU (values differ by "
                        "1 ADU where a float rounding moves rint, by more where it moves a Poisson decision: "
                        "6e-5 of the values with 10-3000 e-/frame)"),
    "batch_etc": SingleError(1.2e-7, 1e-5, "relative, of the band variance (SNR: half of it)",
                             "random tables, 400 targets × 256 readouts, saturated cells and NaN bins (1.1e-7), "
                             "a 300-SN survey plan z = 0.05-1.5 (SNR 5.5e-8, same readouts); PoCL CPU"),
    "noise": SingleError(8.1e-5, 1e-3, "of σ (max |Δ| of a Gaussian draw, voxels with variance > 0)",
                         "noisy_cube of the Lazuli narrow-field Airy cube (3.4e6 voxels, seed 12345); PoCL CPU.  Same "
                         "Philox words, float uniform of 24 bits ≥ 2^-32: the max grows with the draws (radii near 0, "
                         "tails: above 1e-3 only beyond 5.8 σ, ~2e-8 of them), plus 2^-24 |expectation|.  Poisson: "
                         "1.1e-4 of the counts differ (by 1), means log-uniform in [1e-3, 1e5]; same distribution"),
    "projection": SingleError(1.7e-7, 1e-5, "of the detector image peak",
                              "Lazuli SN z = 0.5 detector image, both fields (510 λ, 6.9e6 cells, ≤ 9 cell windows "
                              "per pixel), float accumulation in a fixed order; image sum vs cube sum 3e-9; PoCL CPU"),
}


#: products without single-precision kernels (always double; "single" is refused for them)
DOUBLE_ONLY_PRODUCTS: tuple = ()


def products() -> tuple:
    """The registered product names of the precision dial: those with single-precision kernels
    (:data:`SINGLE_PRECISION_ERRORS`) and :data:`DOUBLE_ONLY_PRODUCTS`."""
    return tuple(SINGLE_PRECISION_ERRORS) + tuple(p for p in DOUBLE_ONLY_PRODUCTS if p not in SINGLE_PRECISION_ERRORS)


def check_product(product) -> str:
    """``product`` if it is a registered product name (:func:`products`), else a ParameterError
    naming it, with a "did you mean" and the valid names (a typo must not silently mean "no single
    kernels")."""
    return choice("product", product, products(), what="precision product")


def check_precision(precision):
    """``precision``: one of :data:`PRECISIONS`, or a mapping product → one of them whose product
    names are registered (:func:`check_product`); else one clear ParameterError."""
    if isinstance(precision, Mapping):
        checked = {}
        for product, value in precision.items():
            checked[check_product(product)] = choice(f"precision[{product!r}]", value, PRECISIONS,
                                                     what=f"precision of {product!r}")
        return checked
    if not isinstance(precision, str):
        raise ParameterError(f"precision must be one of {', '.join(map(repr, PRECISIONS))} or a mapping "
                             f"product → precision, got {short_repr(precision)}")
    return choice("precision", precision, PRECISIONS)


def real_dtype(precision: str):
    """NumPy dtype of a resolved precision ("double" → float64, "single" → float32)."""
    return np.dtype(np.float32 if precision == "single" else np.float64)


def storage_dtype(dtype, *, name="dtype"):
    """``dtype`` as ``np.dtype``: float64 or float32 (the storage of the cube's outputs), else
    ParameterError naming ``name``."""
    try:
        dtype = np.dtype(dtype)
    except TypeError:
        raise ParameterError(f"{name} must be float64 or float32, got {short_repr(dtype)}") from None
    if dtype not in (np.float64, np.float32):
        raise ParameterError(f"{name} must be float64 or float32, got {dtype}")
    return dtype


_ratios: dict = {}
_warned_single: set = set()             # devices that failed the single-precision self-check (warned once)
_ratio_lock = threading.Lock()


#: fp32 / fp64 throughput assumed for CPU devices: SIMD registers hold half as many doubles
CPU_RATIO = 2.0


def fp64_throughput_ratio() -> float:
    """fp32 / fp64 FMA throughput of the selected device: inf without fp64, :data:`CPU_RATIO` on a
    CPU, else measured once per device and process (``kernels/precision.cl``: independent FMA
    chains; single and double launches alternated, the median of 5 pairs)."""
    if not opencl.device_supports_fp64():
        return float("inf")
    if opencl.device_type() == "CPU":
        return CPU_RATIO
    key = opencl.device_fingerprint()
    with _ratio_lock:
        if key not in _ratios:
            _ratios[key] = _measure_ratio()
        return _ratios[key]


def _measure_ratio() -> float:
    """Median over 5 alternated (single, double) launch pairs of t_double / t_single (a burst of
    other work then hits both of a pair alike).  ``kernels/precision.cl`` with VW-lane vectors
    (8 on CPUs, where a scalar chain is latency-bound and hides the SIMD width; 1 on GPUs, SIMT)."""
    dev = opencl.get_device()
    gpu = "GPU" in opencl.device_type()
    items, steps, vw = int(dev.max_compute_units) * (2048 if gpu else 1024), (4096 if gpu else 256), (1 if gpu else 8)
    runs = {}
    for name, dtype in (("single", np.float32), ("double", np.float64)):
        kern = opencl.get_kernel("precision.cl", "fma_chains", opencl.precision_options(name) + (f"-DVW={vw}",))
        buf = opencl.device_buffer(np.dtype(dtype).itemsize * items)
        runs[name] = (kern, buf)

    def once(name):
        kern, buf = runs[name]
        t0 = time.perf_counter()
        opencl.launch(kern, (items,), None, np.int32(steps), buf)
        opencl.get_queue().finish()
        return time.perf_counter() - t0
    once("single"), once("double")                      # builds and first touches
    ratios = [once("double") / max(once("single"), 1e-9) for _ in range(5)]
    return float(np.median(ratios))


def resolve_precision(precision, backend="auto", product="cube"):
    """(backend, precision) resolved for ``product`` (a registered name, :func:`products`; a
    mapping ``precision`` gives that product's entry, "auto" if absent): backend "opencl" or
    "numpy", precision "double" or "single" (always "double" on NumPy).  Raises one clear error
    (ParameterError) for an unknown precision, product or backend name, for
    ``"double"`` on an OpenCL device without fp64, and for ``"single"`` on a product that has no
    single-precision kernels."""
    product = check_product(product)
    precision = check_precision(precision)
    if isinstance(precision, dict):                     # per product; the others "auto"
        precision = precision.get(product, "auto")
    choice("backend", backend, BACKENDS)
    single_ok = product in SINGLE_PRECISION_ERRORS
    if precision == "single" and not single_ok:
        raise ParameterError(f"precision='single' is not available for {product!r} (single-precision kernels: "
                             f"{', '.join(SINGLE_PRECISION_ERRORS)}); use 'auto' or 'double'")
    if backend == "numpy":
        return "numpy", "double"
    opencl.check_process()               # a forked child must not silently change backend
    device = opencl.is_available()
    if not device:
        if backend == "opencl":
            try:
                opencl.get_device()                      # its own clear error (disabled, no platform…)
            except OpenCLUnavailableError:
                raise
            except Exception as exc:
                raise OpenCLUnavailableError(f"backend='opencl' asked for, but no OpenCL device is usable: {exc}") \
                    from None
            raise OpenCLUnavailableError("backend='opencl' asked for, but no OpenCL device is usable")
        return "numpy", "double"
    fp64 = opencl.device_supports_fp64()
    name = opencl.get_device().name.strip()
    if precision == "double":
        if not fp64:
            raise OpenCLUnavailableError(
                f"precision 'double' needs fp64, which OpenCL device {name!r} lacks: use precision 'single' or "
                "'auto' (--precision), the NumPy backend (backend='numpy', --backend numpy where the command has "
                "it), or another device (SLICERSIM_DEVICE)")
        return resolve_backend(backend), "double"
    if precision == "single" or (single_ok and SINGLE_PRECISION_ERRORS[product].acceptable
                                 and (not fp64 or fp64_throughput_ratio() > FAST_FP64_RATIO)):
        if fp64:
            chosen = resolve_backend(backend)          # the fp64 self-check decides, as for double
            if chosen != "opencl":
                return chosen, "double"
        ok, msg = device_validated("single")           # the float builds' own check (no fp64 needed)
        if ok:
            return "opencl", "single"
        if backend == "opencl":
            raise OpenCLUnavailableError(f"{msg}; use backend='numpy' or 'auto' (falls back to NumPy), or pick "
                                         "another device (SLICERSIM_DEVICE)")
        if opencl.device_fingerprint() not in _warned_single:
            _warned_single.add(opencl.device_fingerprint())
            warnings.warn(f"{msg}; using the NumPy twins (float64)", RuntimeWarning, stacklevel=2)
        return "numpy", "double"
    if not fp64:
        if backend == "opencl":
            raise OpenCLUnavailableError(f"OpenCL device {name!r} lacks fp64 and {product!r} has no "
                                         "single-precision kernels: use backend='numpy' or 'auto'")
        return "numpy", "double"
    return resolve_backend(backend), "double"


def float64_kwargs(backend="auto"):
    """``backend`` and ``precision`` keywords for computations that stay float64 on every device (the
    reduction's projections, whose noiseless round trips are checked to ~1e-15): OpenCL where the
    device has fp64 (and passes its self-check), else the NumPy twin — never the single kernels that
    "auto" may pick on a device without fast fp64."""
    return {"backend": resolve_backend(backend), "precision": "double"}
