"""Random draws on the device (``kernels/noise.cl``) with their NumPy twins (:mod:`slicersim.rng`).

Every element is keyed by (seed, stream, global element index), so results
are identical — bit for bit — whatever the backend, the chunking
(``max_bytes``) or the work-group size.

* :func:`noisy_cube` — expectation + √variance · N(0, 1) per voxel (ADU).
* :func:`poisson_draw` — Poisson counts (inversion below mean 10, PTRS above).
* :func:`uniform_normal_draw`, :func:`uniform_normal_grid`, :func:`philox_blocks` — raw streams (tests, other kernels);
  importing this module registers :func:`uniform_normal_grid` as the engine of
  :func:`slicersim.rng.uniform_normal_grid` (the draws of ``physics``).

Precision (:mod:`slicersim.backends.precision`, product ``"noise"``): :func:`noisy_cube` and
:func:`poisson_draw` take ``precision="auto" | "double" | "single"``.  Single runs the ``-DSINGLE``
build of ``noise.cl`` on float32 copies of the inputs, from the same Philox words: not bit-identical
to the twin but within a bounded fraction of σ (Gaussian) or mostly the same integers (Poisson),
with the same distribution (``tests/test_noise_precision.py``).  The raw streams stay double
(their users compare them bit for bit).
"""
from __future__ import annotations


import numpy as np

from slicersim import rng, validation
from slicersim.backends import opencl
from slicersim.backends.dispatch import DEFAULT_MAX_BYTES, resolve_backend
from slicersim.backends.opencl import check_vector_width
from slicersim.backends.precision import real_dtype, resolve_precision
from slicersim.errors import ParameterError

__all__ = ["noisy_cube", "poisson_draw", "uniform_normal_draw", "uniform_normal_grid", "philox_blocks", "seed_from",
           "DEFAULT_MAX_BYTES"]

MIN_CHUNK = 256          # elements: floor of a chunk whatever max_bytes (avoids absurd launch counts)
#: largest Poisson mean drawn in single precision: counts stay exact float integers (< 2^24 with 6σ to
#: spare) and the PTRS offset mu + 0.43 keeps a resolution of 2^-1 or finer
POISSON_SINGLE_MAX_MEAN = 2.0**22


def seed_from(seed):
    """Integer seed in [0, 2⁶⁴) from an int or a ``numpy.random.Generator`` (one 64-bit draw)."""
    if isinstance(seed, np.random.Generator):
        return int(seed.integers(0, 2**64, dtype=np.uint64))
    rng.seed_to_key(seed)  # validates
    return int(seed)


def _kernel(name, vector_width=1, precision="double"):
    """Kernel of noise.cl (which #includes philox.cl) for ``vector_width`` elements per work item,
    built for ``precision`` (reused by this thread between calls)."""
    return opencl.cached_kernel("noise.cl", name,
                                (f"-DRNG_VW={int(vector_width)}",) + opencl.precision_options(precision))


def _chunk_len(n, bytes_per_item, max_bytes, multiple):
    """Elements per chunk: within max_bytes, a multiple of ``multiple``, at least MIN_CHUNK."""
    step = max(MIN_CHUNK, int(max_bytes // bytes_per_item))
    step = min(max(n, 1), step, 2**31)
    return -(-step // multiple) * multiple


def _sizes(nitems, work_group):
    """(global, local) sizes for nitems work items, padded to whole work groups."""
    if work_group is None:
        return (nitems,), None
    wg = validation.integer("work_group", work_group, low=1, high=int(opencl.get_device().max_work_group_size))
    return (-(-nitems // wg) * wg,), (wg,)


def _stream(stream):
    return rng.check_stream(stream)


# --------------------------------------------------------------------------- Gaussian noise
def _check_out(out, shape, precision="double"):
    """``out`` checked (float64, or float32 for a single-precision draw), or a new float64 array."""
    if out is None:
        return np.empty(shape)
    dtypes = (np.float64, np.float32) if precision == "single" else (np.float64,)
    if not isinstance(out, np.ndarray) or out.shape != shape or out.dtype not in dtypes \
            or not out.flags.c_contiguous or not out.flags.writeable:
        kinds = "float64 or float32" if precision == "single" else "float64"
        raise ParameterError(f"out must be a writeable C-contiguous {kinds} array of shape {shape}")
    return out


def _any_negative(v):
    """Whether any element of the flat float64 ``v`` is < 0 (NaN is not), without a full-size
    temporary: fmin ignores NaN, so the smallest non-NaN value decides."""
    return v.size > 0 and bool(np.fmin.reduce(v) < 0)


def noisy_cube(expectation, variance, seed, backend="auto", max_bytes=DEFAULT_MAX_BYTES,
               work_group=None, *, stream=0, first_index=0, vector_width=None, out=None, precision="auto"):
    """One Gaussian realisation: expectation + √variance · N(0, 1) per element.

    expectation, variance : arrays of the same shape (e.g. ADU, ADU²); variance ≥ 0,
        non-finite variance (saturated voxel) → NaN, variance 0 → the expectation exactly.
    seed : int in [0, 2⁶⁴) or numpy Generator;  stream : int in [0, 2³²)
    first_index : global flat index of element 0 (to draw a slab of a larger cube consistently)
    Element i uses the Box–Muller cos branch of Philox block (first_index + i, stream, 0).
    OpenCL: max_bytes bounds the device buffers (3 float64 per element; on CPU devices the
    kernel reads and writes the arrays in place, no buffer); work_group is the local size
    (None: the runtime's); vector_width elements per work item (None: 1 on GPUs, the preferred
    double width on CPUs, twice it in single).  None of them changes the result.
    out : optional writeable C-contiguous array of the same shape receiving the result: float64, or
        float32 when the draw runs in single precision (no float64 temporary); default a new float64 array
    precision : "auto" (default), "double" or "single" (:mod:`slicersim.backends.precision`, product
        "noise"; resolved before any work).  Single draws in float32 from the same Philox words: within
        a few 1e-5 σ of the double draw (plus 2⁻²⁴ of the expectation, rounded to float32; variance 0
        still gives the float32 expectation exactly, non-finite variance NaN).  NumPy: always float64.
    """
    backend, precision = resolve_precision(precision, backend, "noise")
    real = real_dtype(precision)
    e, v = (_as_float(a, precision) for a in (expectation, variance))
    if e.shape != v.shape:
        raise ParameterError(f"expectation {e.shape} and variance {v.shape} must have the same shape")
    ef, vf = e.reshape(-1), v.reshape(-1)
    if _any_negative(vf):
        raise ParameterError(f"variance must be ≥ 0 ({np.count_nonzero(v < 0)} negative value(s))")
    seed, stream = seed_from(seed), _stream(stream)
    out = _check_out(out, e.shape, precision)
    of = out.reshape(-1)
    n = ef.size
    if n == 0:
        return out
    if backend == "opencl":
        vw = check_vector_width(vector_width, scale=2) if precision == "single" else check_vector_width(vector_width)
        args = (seed, stream, max_bytes, work_group, vw, precision)
        if ef.dtype == vf.dtype == of.dtype == real:
            _gaussian_noise_opencl(ef, vf, of, first_index, *args)
        else:
            _staged_single(ef, vf, of, first_index, *args)
        return out
    step = _chunk_len(n, 160, max_bytes, 1)       # ~20 float64 temporaries per element
    with np.errstate(invalid="ignore"):
        for i0 in range(0, n, step):
            i1 = min(n, i0 + step)
            z = rng.normal(seed, np.arange(first_index + i0, first_index + i1, dtype=np.uint64), stream)[:, 0]
            vv, ee = vf[i0:i1], ef[i0:i1]
            of[i0:i1] = np.where(~np.isfinite(vv), np.nan,
                                 np.where(vv == 0.0, ee, ee + np.sqrt(np.where(np.isfinite(vv), vv, 0.0)) * z))
    return out


_ZERO_COPY_LAUNCH = 2**26      # elements per launch when the kernel works on the arrays in place
_STAGE = 2**18                 # elements per float32 staging chunk of a single draw on float64 arrays


def _as_float(a, precision):
    """C-contiguous float array of ``a``: float64 for double; for single a float32 or float64 array
    as given (float64 ones are converted chunk by chunk while drawing, :func:`_staged_single`)."""
    a = np.asarray(a)
    if precision == "single" and a.dtype in (np.float32, np.float64):
        return np.ascontiguousarray(a)
    return np.ascontiguousarray(a, dtype=real_dtype(precision))


def _staged_single(ef, vf, of, first_index, seed, stream, max_bytes, work_group, vw, precision):
    """Single-precision draw with float64 inputs or output: chunks converted through float32 staging
    arrays small enough to stay in cache (no full-size float32 copies, whose first touch costs as much
    as the draw on a CPU), each drawn at its global index, so the result does not depend on them.  CPU
    devices: the kernel works in the staging arrays themselves (one host buffer each for all chunks;
    whole vectors, the padding lanes drawn and dropped); other devices: the device path per chunk."""
    n = ef.size
    stage = -(-min(n, _STAGE) // vw) * vw
    e32, v32, o32 = (np.empty(stage, np.float32) for _ in range(3))
    cpu = opencl.device_type() == "CPU"
    if cpu:
        key = rng.seed_to_key(seed)
        kern = _kernel("gaussian_noise", vw, precision)
        bufs = [opencl.host_buffer(a) for a in (e32, v32, o32)]
    for i0 in range(0, n, stage):
        k = min(n, i0 + stage) - i0
        e32[:k], v32[:k] = ef[i0:i0 + k], vf[i0:i0 + k]
        if not cpu:
            _gaussian_noise_opencl(e32[:k], v32[:k], o32[:k], first_index + i0, seed, stream, max_bytes,
                                   work_group, vw, precision)
        else:
            e32[k:], v32[k:] = 0.0, 0.0                     # padding lanes of the last vector
            gsize, lsize = _sizes(-(-k // vw), work_group)
            opencl.launch(kern, gsize, lsize, *bufs, np.uint64(first_index + i0), np.uint32(k),
                          np.uint32(key[0]), np.uint32(key[1]), np.uint32(stream))
            opencl.sync_to_host(bufs[2], o32)
        of[i0:i0 + k] = o32[:k]


def _gaussian_noise_opencl(ef, vf, of, first_index, seed, stream, max_bytes, work_group, vw, precision):
    """The draw on the device (``ef``, ``vf``, ``of`` of the precision's float type).  CPU devices
    (host memory): the kernel reads ``ef``, ``vf`` and writes ``of`` in place
    (``opencl.host_buffer``), whole vectors only, the last n mod vw elements through a small padded
    scratch; other devices: chunks through scratch buffers reused between calls.  Each element's
    draw depends on its global index only."""
    n = ef.size
    key = rng.seed_to_key(seed)
    kern = _kernel("gaussian_noise", vw, precision)
    size = ef.itemsize
    args = (np.uint32(key[0]), np.uint32(key[1]), np.uint32(stream))

    def launch(d_e, d_v, d_o, i0, count):
        gsize, lsize = _sizes(-(-count // vw), work_group)
        opencl.launch(kern, gsize, lsize, d_e, d_v, d_o, np.uint64(first_index + i0), np.uint32(count), *args)

    bulk = 0
    if opencl.device_type() == "CPU" and ef.flags.writeable and vf.flags.writeable:
        bulk = n // vw * vw
        for i0 in range(0, bulk, _ZERO_COPY_LAUNCH // vw * vw):
            i1 = min(bulk, i0 + _ZERO_COPY_LAUNCH // vw * vw)
            d_o = opencl.host_buffer(of[i0:i1])
            launch(opencl.host_buffer(ef[i0:i1]), opencl.host_buffer(vf[i0:i1]), d_o, i0, i1 - i0)
            opencl.sync_to_host(d_o, of[i0:i1])
    if bulk == n:
        return
    step = _chunk_len(n - bulk, 3 * size, max_bytes, vw)       # buffers hold whole vectors
    d_e, d_v, d_o = (opencl.scratch_buffer(f"noise.{name}", size * step) for name in "evo")
    for i0 in range(bulk, n, step):
        i1 = min(n, i0 + step)
        opencl.to_device(ef[i0:i1], d_e)
        opencl.to_device(vf[i0:i1], d_v)
        launch(d_e, d_v, d_o, i0, i1 - i0)
        opencl.from_device(of[i0:i1], d_o)


# --------------------------------------------------------------------------- Poisson
def poisson_draw(mean, seed, stream=0, backend="auto", max_bytes=DEFAULT_MAX_BYTES, work_group=None,
                 *, first_index=0, precision="auto"):
    """Poisson counts of expectation ``mean`` (≥ 0) as float64 (exact integers, NaN for non-finite mean).

    Same algorithm and keys as :func:`slicersim.rng.poisson` (element i: index first_index + i).
    precision : "auto" (default), "double" or "single" (:mod:`slicersim.backends.precision`, product
        "noise").  Single: the float build on float32 means, the same Philox words; most counts equal
        the double ones (a float rounding moves a CDF or floor decision, more often at large means:
        float32(mean) itself is within 2⁻²⁴ of the mean), the distribution is the same.  Means above
        :data:`POISSON_SINGLE_MAX_MEAN` are drawn in double under "auto" (ParameterError for "single",
        or for "auto" on a device without fp64).
    """
    requested = precision
    backend, precision = resolve_precision(precision, backend, "noise")
    m = np.ascontiguousarray(validation.array("Poisson mean", mean, finite=False))
    if np.any(m < 0):
        raise ParameterError(f"Poisson mean must be ≥ 0 ({np.count_nonzero(m < 0)} negative value(s))")
    seed, stream = seed_from(seed), _stream(stream)
    if backend != "opencl":
        index = np.arange(first_index, first_index + m.size, dtype=np.uint64).reshape(m.shape)
        return rng.poisson(m, seed, index, stream)
    if precision == "single" and np.any((m > POISSON_SINGLE_MAX_MEAN) & np.isfinite(m)):
        if requested != "auto" or not opencl.device_supports_fp64():
            way_out = "precision='double' or backend='numpy'" if opencl.device_supports_fp64() else \
                "backend='numpy' (this device has no fp64)"
            raise ParameterError(f"Poisson means above {POISSON_SINGLE_MAX_MEAN:.4g} cannot be drawn in single "
                                 f"precision (float counts): use {way_out}")
        precision = "double"
    real = real_dtype(precision)
    out = np.empty_like(m)
    mf, of = m.reshape(-1), out.reshape(-1)
    n = mf.size
    if n == 0:
        return out
    size = real.itemsize
    step = _chunk_len(n, 2 * size, max_bytes, 1)
    kern = _kernel("poisson_draw", 1, precision)
    d_m, d_o = opencl.device_buffer(size * step), opencl.device_buffer(size * step)
    o_real = of if real == np.float64 else np.empty(min(n, step), real)
    key = rng.seed_to_key(seed)
    for i0 in range(0, n, step):
        i1 = min(n, i0 + step)
        opencl.to_device(np.ascontiguousarray(mf[i0:i1], dtype=real), d_m)
        gsize, lsize = _sizes(i1 - i0, work_group)
        opencl.launch(kern, gsize, lsize, d_m, d_o, np.uint64(first_index + i0), np.uint32(i1 - i0),
                      np.uint32(key[0]), np.uint32(key[1]), np.uint32(stream))
        if o_real is of:
            opencl.from_device(of[i0:i1], d_o)
        else:
            opencl.from_device(o_real[:i1 - i0], d_o)
            of[i0:i1] = o_real[:i1 - i0]
    return out


# --------------------------------------------------------------------------- raw streams
def uniform_normal_draw(n, seed, stream=0, draw=0, backend="auto", work_group=None, *, first_index=0,
                        vector_width=None):
    """(uniforms, normals), each (n, 2) float64, for indices first_index … first_index + n − 1
    (the two uniforms of each Philox block and their two Box–Muller Gaussians)."""
    u, z = uniform_normal_grid(1, n, seed, stream, draw, backend, work_group, first_index=first_index,
                               vector_width=vector_width)
    return u[0], z[0]


def uniform_normal_grid(rows, ncols, seed, stream=0, draw=0, backend="auto", work_group=None, *,
                        first_index=0, row_stride=None, vector_width=None):
    """(uniforms, normals), each (rows, ncols, 2) float64: element (r, c) keyed by Philox index
    ``first_index + r·row_stride + c`` (row_stride default ncols) — e.g. a block of detector rows
    keyed ``y << 16 | x`` with first_index = y0 << 16 and row_stride = 2¹⁶.  Bit-identical to
    :func:`slicersim.rng.uniform` / :func:`~slicersim.rng.normal` of those indices."""
    seed, stream = seed_from(seed), _stream(stream)
    rows, ncols, first_index, row_stride = rng.check_grid(rows, ncols, first_index, row_stride)
    if resolve_backend(backend) != "opencl" or rows * ncols == 0:
        index = rng.grid_indices(rows, ncols, first_index, row_stride)
        return rng.uniform(seed, index, stream, draw), rng.normal(seed, index, stream, draw)
    opencl.require_fp64()
    vw = check_vector_width(vector_width)
    npad = -(-ncols // vw) * vw
    planes = np.empty((4, rows, npad))
    bufs = [opencl.host_buffer(plane) for plane in planes]              # zero-copy on CPU devices
    key = rng.seed_to_key(seed)
    (gx,), local = _sizes(npad // vw, work_group)
    opencl.launch(_kernel("uniform_normal", vw), (gx, rows), None if local is None else (local[0], 1), *bufs,
                  np.uint64(first_index), np.uint64(row_stride), np.uint32(npad), np.uint32(key[0]),
                  np.uint32(key[1]), np.uint32(stream), np.uint32(draw))
    for plane, buf in zip(planes, bufs):
        opencl.sync_to_host(buf, plane)
    planes = np.moveaxis(planes[:, :, :ncols], 0, -1)                   # views, no copy
    return planes[..., :2], planes[..., 2:]


def philox_blocks(counter, key, backend="auto"):
    """Philox4x32-10 of (n, 4) uint32 counters with (n, 2) uint32 keys → (n, 4) uint32."""
    counter = np.ascontiguousarray(counter, dtype=np.uint32).reshape(-1, 4)
    key = np.ascontiguousarray(np.broadcast_to(np.asarray(key, np.uint32), (counter.shape[0], 2)))
    if resolve_backend(backend) != "opencl":
        return rng.philox4x32(counter, key)
    out = np.empty_like(counter)
    n = counter.shape[0]
    if n == 0:
        return out
    d_o = opencl.device_buffer(out.nbytes)
    opencl.launch(_kernel("philox_words"), (n,), None, opencl.to_device(counter), opencl.to_device(key),
                  d_o, np.uint32(n))
    opencl.from_device(out, d_o)
    return out


def _device_grid(rows, ncols, seed, stream, draw, first_index, row_stride):
    """Engine of :func:`slicersim.rng.uniform_normal_grid`: this module's grid on the chosen backend."""
    return uniform_normal_grid(rows, ncols, seed, stream, draw, first_index=first_index, row_stride=row_stride)


rng.register_grid_engine(_device_grid)
