"""Cube → detector deposit: per-cell weight tables and the flux-conserving deposit.

Host side of ``kernels/project.cl`` with NumPy twins (``backend="auto" |
"opencl" | "numpy"``, see :mod:`slicersim.backends.band_variance`).  The geometry (which
box on the detector each cube cell covers, and its spot rms) comes from
:class:`slicersim.instrument.mapper.SlicerMapper`; this module only knows boxes.

Model of one (sub-)cell: a uniform axis-aligned box [ax, bx] × [ay, by] [px]
convolved with a Gaussian spot of rms (sx, sy) [px], integrated exactly over
each pixel [c, c+1) (closed form, see the kernel's header; the Gaussian
integrals come from a cubic Hermite table, absolute error < 4e-12).  The
window covers the box ± ``truncate`` rms; the weights are renormalised over
it, so every cell deposits exactly its value (cells are never split between
"lost" and "kept" except by the detector edge, where the part that falls off
is lost).  The deposit is separable: w(c_y, c_x) = scale · wx · wy.

Tables are cube-independent: build them once per (mapper, slices, λ grid)
and deposit any number of cubes.  Weights are stored as float32 by default
(half the memory and bandwidth); the per-cell ``scale`` is computed in
float64 from the *stored* weights, so flux conservation is exact to float64
rounding whatever the storage type.

Precision (``deposit(..., precision=)``, :mod:`slicersim.backends.precision`): the tables are
always built in double (box coordinates up to 4096 px); the deposit, which runs for every cube,
can run in single (:mod:`slicersim.backends.projection_deposit`).  On an OpenCL device without
fp64 the NumPy twin builds the tables and the deposit runs in single on the device.

Tables on disk (:func:`table_key`, :func:`store_tables`, :func:`load_tables`): a full Lazuli
field's tables take ~0.46 GB, so :class:`~slicersim.instrument.mapper.SlicerMapper` keeps them
in an :class:`~slicersim.io.table_cache.ArrayCache` (``$SLICERSIM_CACHE/projection``) under a
content key and reads them back memory-mapped; a hit is the built tables bit for bit.  Built
on the device, they are streamed to disk without a host copy; read back on a CPU device, the
kernels use the mapped file in place.
"""

from __future__ import annotations

import functools
import hashlib
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy
from scipy.special import erfc

from slicersim import validation
from slicersim.backends import opencl
from slicersim.backends.dispatch import resolve_backend
from slicersim.backends.precision import resolve_precision
from slicersim.backends.projection_deposit import deposit_numpy, deposit_opencl
from slicersim.errors import ParameterError
from slicersim.io.table_cache import ArrayCache, Chunks, TableCacheWarning, default_directory
from slicersim.memo import content_key

__all__ = ["DepositTables", "build_tables", "deposit", "table_key", "load_tables", "store_tables",
           "default_table_cache", "resolve_table_cache", "backend_tag", "table_builder", "TABLE_FORMAT", "footprint_windows"]

_KERNEL = "project.cl"
_INV_SQRT_2PI = 0.3989422804014327
TMAX, TINV = 8.5, 128.0          # Hermite table of the Gaussian integrals: range, nodes per unit
_NUMPY_CHUNK = 1 << 15          # cells per NumPy chunk (weights)
#: version of the on-disk table layout (part of every cache key, with this module's source)
TABLE_FORMAT = 1
_STREAM_BYTES = 8 << 20         # bytes per piece when streaming device tables to disk
_WEIGHTS_CHUNK = 1 << 18        # cells per cell_weights launch (12 MiB of boxes on the device)


@dataclass
class DepositTables:
    """Weight tables of N sub-cells on a (S, E, Q) grid (slice, λ row, φ column).

    ``meta[c] = (x0, y0, nx, ny)``: first pixel column/row of the window and
    its size; ``offset[c]``: start of the cell's weights in ``pool`` (``wx``
    padded to a multiple of ``vw``, then ``wy``); ``scale[c]``: value
    multiplier (1/(ne nq) over the stored weight sums).  ``oversample =
    (ne, nq)`` sub-cells per cube cell along λ and φ.  ``phases``: per
    launch, the (first, last) cell ranges of items that never share a pixel.
    """

    grid: tuple
    oversample: tuple
    vw: int
    weights_dtype: np.dtype
    detector_shape: tuple
    meta: np.ndarray
    offset: np.ndarray
    pool_size: int
    row_range: tuple
    phases: list
    scale: np.ndarray | None = None
    pool: np.ndarray | None = None
    device: dict = field(default_factory=dict, repr=False)

    @property
    def ncell(self):
        return int(self.meta.shape[0])

    def host(self):
        """Make sure ``pool`` and ``scale`` exist on the host (download if needed)."""
        if self.pool is None:
            pool = np.empty(self.pool_size, self.weights_dtype)
            scale = np.empty(self.ncell, np.float64)
            opencl.from_device(pool, self.device["pool"])
            opencl.from_device(scale, self.device["scale"])
            self.pool, self.scale = pool, scale
        return self

    def nbytes(self):
        n = self.meta.nbytes + self.offset.nbytes + self.ncell * 8
        return n + self.pool_size * np.dtype(self.weights_dtype).itemsize


# --------------------------------------------------------------------------- #
#  tables                                                                      #
# --------------------------------------------------------------------------- #
def footprint_windows(lo, hi, sigma, truncate):
    """(start, n) int32 [px]: the pixel windows of cell footprints [lo, hi] widened by ``truncate`` × ``sigma``."""
    start = np.floor(lo - truncate * sigma)
    stop = np.floor(hi + truncate * sigma)
    n = stop - start + 1
    if n.size and (not np.all(np.isfinite(n)) or n.max() > 4096):
        raise ParameterError("cell footprint or spot rms (optical model) is not finite or spans more than 4096 px")
    return start.astype(np.int32), n.astype(np.int32)


def table_builder(backend="auto"):
    """Who builds the weight tables: "opencl" (``cell_weights``, double only) where
    :func:`~slicersim.backends.dispatch.resolve_backend` picks OpenCL on a device with fp64, else
    "numpy" (the twin, also on an OpenCL device without fp64, whose deposit then runs in single)."""
    if resolve_backend(backend) == "opencl" and opencl.device_supports_fp64():
        return "opencl"
    return "numpy"


def default_block(backend="auto"):
    """Bins per deposit item: 16 on CPUs (few long work items), 2 on GPUs (many short ones;
    also on a GPU without fp64, where the deposit runs in single precision)."""
    on_device = resolve_backend(backend) == "opencl" or (
        backend != "numpy" and opencl.is_available() and not opencl.device_supports_fp64())
    if on_device and "GPU" in opencl.device_type():
        return 2
    return 16


def _item_bounds(grid, block):
    S, E, Q = grid
    e0 = np.arange(0, E, block)
    e1 = np.minimum(e0 + block, E)
    s = np.arange(S)[:, None]
    first = ((s * E + e0[None]) * Q).ravel()
    last = ((s * E + e1[None]) * Q).ravel()
    return first.astype(np.int64), last.astype(np.int64)


def _colour(first, last, meta, vw):
    """Greedy colouring of items whose padded pixel boxes overlap."""
    x0, y0, nx, ny = (meta[:, i].astype(np.int64) for i in range(4))
    x1 = x0 + -(-nx // vw) * vw
    y1 = y0 + ny
    xlo = np.minimum.reduceat(x0, first)
    xhi = np.maximum.reduceat(x1, first)
    ylo = np.minimum.reduceat(y0, first)
    yhi = np.maximum.reduceat(y1, first)
    colour = np.zeros(first.size, np.int64)
    for i in range(1, first.size):
        hit = (xlo[:i] < xhi[i]) & (xlo[i] < xhi[:i]) & (ylo[:i] < yhi[i]) & (ylo[i] < yhi[:i])
        used = np.bincount(colour[:i][hit], minlength=1)
        colour[i] = int(np.argmin(used)) if used.min() == 0 else used.size
    return [(first[colour == k].copy(), last[colour == k].copy()) for k in range(colour.max() + 1)]


def build_tables(box, grid, oversample=(1, 1), *, detector_shape=(4096, 4096), truncate=4.0,
                 weights_dtype=np.float32, vw=None, block=None, backend="auto"):
    """Weight tables for sub-cell boxes.

    Parameters
    ----------
    box : (N, 6) float array
        ax, bx, sx, ay, by, sy [px] of each sub-cell, in (s, e, q) order of ``grid``.
    grid : (S, E, Q)
        sub-cell grid; ``E`` and ``Q`` are multiples of ``oversample = (ne, nq)``.
    truncate : float
        window half-width beyond the box, in spot rms.
    weights_dtype : float32 or float64
    vw : int, optional
        x vector width (1, 2, 4, 8, 16); default 4 when most windows are ≤ 4 px, else 8.
    block : int, optional
        cube wavelength bins per deposit item (a work item loops over them);
        default :func:`default_block`.
    backend : "auto" | "opencl" | "numpy"
        the weights are computed in double by ``cell_weights`` or the NumPy twin
        (:func:`table_builder`: the twin on an OpenCL device without fp64).
    """
    box = np.ascontiguousarray(box, dtype=np.float64)
    S, E, Q = validation.shape("grid", grid, ndim=3, max_side=2**31 - 1)
    ne, nq = validation.shape("oversample", oversample, max_side=2**31 - 1)
    if box.shape != (S * E * Q, 6) or E % ne or Q % nq or box.shape[0] == 0:
        raise ParameterError(f"box must have shape ({S * E * Q}, 6) and grid {grid} be divisible by {oversample}")
    if np.any(box[:, [2, 5]] < 0) or np.any(box[:, 1] < box[:, 0]) or np.any(box[:, 4] < box[:, 3]):
        raise ParameterError("box: boxes need lo <= hi and rms >= 0")
    weights_dtype = np.dtype(validation.choice("weights_dtype", np.dtype(weights_dtype).name, ("float32", "float64")))
    x0, nx = footprint_windows(box[:, 0], box[:, 1], box[:, 2], truncate)
    y0, ny = footprint_windows(box[:, 3], box[:, 4], box[:, 5], truncate)
    if vw is None:
        vw = 4 if np.median(nx) <= 4 else 8
    vw = validation.choice("vw", vw, (1, 2, 4, 8, 16))
    meta = np.ascontiguousarray(np.stack([x0, y0, nx, ny], axis=1), dtype=np.int32)
    size = -(-nx.astype(np.int64) // vw) * vw + ny
    offset = np.zeros(size.size, np.int64)
    np.cumsum(size[:-1], out=offset[1:])
    pool_size = int(size.sum())
    H = int(detector_shape[0])
    r0 = int(np.clip(y0.min(), 0, H)) if y0.size else 0
    r1 = int(np.clip((y0.astype(np.int64) + ny).max(), r0, H)) if y0.size else 0
    block = default_block(backend) if block is None else int(block)
    first, last = _item_bounds((S, E, Q), max(1, block) * ne)
    phases = _colour(first, last, meta, vw)
    tables = DepositTables((S, E, Q), (ne, nq), vw, weights_dtype, tuple(detector_shape), meta,
                           offset, pool_size, (r0, r1), phases)
    factor = 1.0 / (ne * nq)
    if table_builder(backend) == "opencl":
        _weights_opencl(tables, box, factor)
    else:
        _weights_numpy(tables, box, factor)
    return tables


@functools.lru_cache(maxsize=1)
def hermite_table():
    """(TN, 8) cubic coefficients of Ht = t Φ(t) + φ(t) (cols 0–3) and Φ (cols 4–7).

    Interval k covers t ∈ [t_k, t_k + 1/TINV), t_k = −TMAX + k/TINV; with
    f = (t − t_k)·TINV the value is ((c3 f + c2) f + c1) f + c0: the cubic
    Hermite interpolant of the exact values and derivatives (Ht' = Φ,
    Φ' = φ) at both interval ends; absolute error < 4e-12 (h⁴/384 max|φ''|).
    """
    t = -TMAX + np.arange(int(round(2 * TMAX * TINV)) + 1) / TINV
    cdf = 0.5 * erfc(-t * np.sqrt(0.5))
    pdf = _INV_SQRT_2PI * np.exp(-0.5 * t * t)
    h = 1.0 / TINV
    cols = []
    for v, d in ((t * cdf + pdf, cdf), (cdf, pdf)):
        v0, v1, d0, d1 = v[:-1], v[1:], h * d[:-1], h * d[1:]
        cols += [v0, d0, -3 * v0 - 2 * d0 + 3 * v1 - d1, 2 * v0 + d0 - 2 * v1 + d1]
    return np.ascontiguousarray(np.stack(cols, axis=1))


def _hermite(u, s, which):
    """Ht (which=0) or Φ (which=1) at t = u/s, and the mask |t| < TMAX where it applies."""
    tab = hermite_table()
    inside = (s > 0) & (np.abs(u) < TMAX * s)
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.where(inside, (u / s + TMAX) * TINV, 0.0)
    k = np.floor(x)
    f = x - k
    base = k.astype(np.intp) * 8 + 4 * which
    flat = tab.ravel()
    return inside, ((flat[base + 3] * f + flat[base + 2]) * f + flat[base + 1]) * f + flat[base]


def _g_cdf_integral(u, s):
    """G(u) = ∫_{−∞}^{u} Φ(t/s) dt (s = 0 or |u| ≥ TMAX s: max(u, 0))."""
    inside, val = _hermite(u, s, 0)
    return np.where(inside, s * val, np.maximum(u, 0.0))


def _g_cdf(u, s):
    """Φ(u/s) (s = 0 or |u| ≥ TMAX s: step)."""
    inside, val = _hermite(u, s, 1)
    return np.where(inside, val, (u >= 0).astype(np.float64))


def box_weights_numpy(a, b, s, c0, n, nmax, dtype=np.float64):
    """(len(a), nmax) blurred-box pixel weights of pixels c0 + j (zero for j >= n).

    W(c) = (D(c+1) − D(c)) / (b − a), D(c) = G(c − a) − G(c − b); a point
    (b − a ≤ 1e-9): W(c) = Φ((c+1−a)/s) − Φ((c−a)/s).
    """
    a, b, s = (np.asarray(v, np.float64)[:, None] for v in (a, b, s))
    c = np.asarray(c0, np.float64)[:, None] + np.arange(nmax + 1)[None]
    width = b - a
    box = width > 1e-9
    with np.errstate(divide="ignore", invalid="ignore"):
        wbox = np.diff(_g_cdf_integral(c - a, s) - _g_cdf_integral(c - b, s), axis=1) / width
    wpt = np.diff(_g_cdf(c - a, s), axis=1) if not box.all() else 0.0
    w = np.maximum(np.where(box, wbox, wpt), 0.0).astype(dtype)
    w[np.arange(nmax)[None] >= np.asarray(n)[:, None]] = 0
    return w


def _weights_numpy(t, box, factor):
    x0, y0, nx, ny = (t.meta[:, i] for i in range(4))
    pool = np.zeros(t.pool_size, t.weights_dtype)
    scale = np.empty(t.ncell, np.float64)
    for c0 in range(0, t.ncell, _NUMPY_CHUNK):
        sl = slice(c0, min(c0 + _NUMPY_CHUNK, t.ncell))
        b = box[sl]
        nxp = -(-nx[sl] // t.vw) * t.vw
        wx = box_weights_numpy(b[:, 0], b[:, 1], b[:, 2], x0[sl], nx[sl], int(nxp.max()), t.weights_dtype)
        wy = box_weights_numpy(b[:, 3], b[:, 4], b[:, 5], y0[sl], ny[sl], int(ny[sl].max()), t.weights_dtype)
        jx = np.arange(wx.shape[1])[None]
        jy = np.arange(wy.shape[1])[None]
        off = t.offset[sl][:, None]
        mx = jx < nxp[:, None]
        my = jy < ny[sl][:, None]
        pool[(off + jx)[mx]] = wx[mx]
        pool[(off + nxp[:, None] + jy)[my]] = wy[my]
        sx = wx.astype(np.float64).sum(axis=1)
        sy = wy.astype(np.float64).sum(axis=1)
        with np.errstate(divide="ignore"):
            scale[sl] = np.where((sx > 0) & (sy > 0), factor / (sx * sy), 0.0)
    t.pool, t.scale = pool, scale


def _options(t, wtype=None):
    """Build options of project.cl for tables ``t`` (``wtype``: the weight type the kernel reads,
    default the tables' own)."""
    if wtype is None:
        wtype = "float" if t.weights_dtype == np.dtype(np.float32) else "double"
    return (f"-DVW={t.vw}", f"-DWTYPE={wtype}", f"-DTMAX={TMAX!r}", f"-DTINV={TINV!r}")


def _table_host_buffer(array):
    """Device buffer holding a host table: the array itself on CPU devices (no copy)."""
    if "CPU" in opencl.device_type() and array.flags.c_contiguous and array.flags.writeable:
        return opencl.host_buffer(array)
    return opencl.to_device(array)


def _weights_opencl(t, box, factor):
    """``cell_weights`` in launches of :data:`_WEIGHTS_CHUNK` cells: the boxes go to the
    device one chunk at a time (sub-buffers of meta, offset and scale; every cell is computed
    alone, so the result does not depend on the chunking)."""
    opencl.require_fp64()
    kern = opencl.get_kernel(_KERNEL, "cell_weights", _options(t))
    dev = t.device
    dev["meta"] = _table_host_buffer(t.meta)
    dev["offset"] = _table_host_buffer(t.offset)
    dev["pool"] = opencl.device_buffer(t.pool_size * t.weights_dtype.itemsize)
    dev["scale"] = opencl.device_buffer(8 * t.ncell)
    d_tab = opencl.to_device(hermite_table())
    chunk = min(_WEIGHTS_CHUNK, t.ncell)
    d_box = opencl.device_buffer(chunk * 6 * 8)
    lsize = 64
    for c0 in range(0, t.ncell, chunk):
        n = min(chunk, t.ncell - c0)
        opencl.to_device(box[c0:c0 + n], d_box)
        whole = n == t.ncell
        sub = (lambda buf, size: buf) if whole else (lambda buf, size: buf.get_sub_region(c0 * size, n * size))
        gsize = -(-n // lsize) * lsize
        opencl.launch(kern, (gsize,), None, d_box, sub(dev["meta"], 16), sub(dev["offset"], 8), np.int64(n),
                      np.float64(factor), d_tab, dev["pool"], sub(dev["scale"], 8))
    opencl.get_queue().finish()


# --------------------------------------------------------------------------- #
#  tables on disk                                                              #
# --------------------------------------------------------------------------- #
_CACHES: dict = {}


def default_table_cache():
    """The projection-table cache of this process: ``$SLICERSIM_CACHE/projection`` (else
    ``~/.cache/slicersim/projection``, see :func:`slicersim.io.table_cache.cache_root`), or
    None when ``$SLICERSIM_CACHE`` is "off".  Read at every call (the variable may change)."""
    directory = default_directory("projection")
    if directory is None:
        return None
    key = str(directory)
    if key not in _CACHES:
        _CACHES[key] = ArrayCache(directory)
    return _CACHES[key]


def resolve_table_cache(cache):
    """``"default"`` → :func:`default_table_cache`; None → no disk cache; a path → an
    :class:`~slicersim.io.table_cache.ArrayCache` there; an ArrayCache → itself."""
    if isinstance(cache, str) and cache == "default":
        return default_table_cache()
    if cache is None or isinstance(cache, ArrayCache):
        return cache
    if isinstance(cache, (str, Path)):
        key = str(Path(cache).expanduser().absolute())
        if key not in _CACHES:
            _CACHES[key] = ArrayCache(key)
        return _CACHES[key]
    raise ParameterError("table cache must be 'default', None, a path or an ArrayCache, got "
                         f"{validation.short_repr(cache)}")


@functools.lru_cache(maxsize=1)
def _code_version():
    """Digest of what the weights depend on besides their arguments: this module's source,
    the deposit kernel's source, NumPy and SciPy versions and :data:`TABLE_FORMAT`."""
    sha = hashlib.sha256(Path(__file__).read_bytes())
    for name in (_KERNEL, "vector_types.cl"):        # the deposit kernel and what it includes
        try:
            sha.update(opencl.kernel_source(name).encode("utf-8"))
        except FileNotFoundError:          # NumPy-only installation without the kernels
            sha.update(b"no kernel")
    sha.update(f"{TABLE_FORMAT} numpy {np.__version__} scipy {scipy.__version__}".encode())
    return sha.hexdigest()


def backend_tag(backend="auto"):
    """(table builder, OpenCL device fingerprint or None): what built tables depend on
    besides their arguments and the code (:func:`table_builder`: NumPy on a device without fp64)."""
    backend = table_builder(backend)
    # platform, device, vendor, driver; not the digest of every kernel source (other kernels
    # change independently: the deposit kernel's own sources are in _code_version)
    return backend, (tuple(opencl.device_fingerprint()[:4]) if backend == "opencl" else None)


def table_key(geometry, grid, oversample=(1, 1), *, detector_shape=(4096, 4096), truncate=4.0,
              weights_dtype=np.float32, vw=None, block=None, backend="auto"):
    """Hex cache key of the tables :func:`build_tables` makes from these arguments.

    ``geometry`` stands for the sub-cell boxes: the (N, 6) box array itself, or anything
    :func:`slicersim.memo.content_key` accepts that determines it (a mapper passes its
    nodes, spot values, slices, λ edges and the digest of its own code, so a hit needs no
    boxes).  The key is a SHA-256 of the content of that, the grid, detector shape,
    truncation, storage dtype, vector width and block, the resolved backend (the OpenCL and
    NumPy builders agree to float32 rounding, not bit for bit), on OpenCL the device
    (platform, name, vendor, driver) and the code version (:func:`_code_version`)."""
    if isinstance(geometry, np.ndarray):
        geometry = np.ascontiguousarray(geometry, dtype=np.float64)
    backend, device = backend_tag(backend)
    block = default_block(backend) if block is None else int(block)
    parts = {"geometry": geometry, "grid": tuple(int(v) for v in grid),
             "oversample": tuple(int(v) for v in oversample),
             "detector_shape": tuple(int(v) for v in detector_shape), "truncate": float(truncate),
             "weights_dtype": np.dtype(weights_dtype).str, "vw": None if vw is None else int(vw),
             "block": block, "backend": backend,
             "device": None if device is None else list(device),
             "code": _code_version()}
    return hashlib.sha256(repr(content_key(parts)).encode("utf-8")).hexdigest()


def _device_pieces(buffer, dtype, n):
    """C-order host pieces of a device buffer of ``n`` items (one bounded host block at a time)."""
    itemsize = np.dtype(dtype).itemsize
    step = max(1, _STREAM_BYTES // itemsize)
    for i0 in range(0, n, step):
        k = min(step, n - i0)
        host = np.empty(k, dtype)
        sub = buffer.get_sub_region(i0 * itemsize, k * itemsize) if (i0 or k < n) else buffer
        opencl.from_device(host, sub)
        yield host


def store_tables(cache, key, tables):
    """Write ``tables`` to ``cache`` under ``key`` and return them read back memory-mapped
    (the built arrays and device buffers can then be dropped); ``tables`` itself when the
    cache cannot be written (one warning, see :class:`~slicersim.io.table_cache.ArrayCache`).
    Tables that live on the device are streamed to disk in 8 MiB pieces (no host copy)."""
    t = tables
    if t.pool is None:
        pool = Chunks(t.weights_dtype, (t.pool_size,), _device_pieces(t.device["pool"], t.weights_dtype,
                                                                      t.pool_size))
        scale = Chunks(np.float64, (t.ncell,), _device_pieces(t.device["scale"], np.float64, t.ncell))
    else:
        pool, scale = t.pool, t.scale
    arrays = {"meta": t.meta, "offset": t.offset, "scale": scale, "pool": pool,
              "phase_first": np.concatenate([f for f, _ in t.phases]),
              "phase_last": np.concatenate([last for _, last in t.phases]),
              "phase_size": np.array([f.size for f, _ in t.phases], np.int64)}
    meta = {"grid": list(t.grid), "oversample": list(t.oversample), "vw": int(t.vw),
            "weights_dtype": np.dtype(t.weights_dtype).str, "detector_shape": list(t.detector_shape),
            "pool_size": int(t.pool_size), "row_range": list(t.row_range)}
    if not cache.store(key, arrays, meta):
        return tables
    return load_tables(cache, key) or tables


def load_tables(cache, key):
    """:class:`DepositTables` of entry ``key`` (arrays memory-mapped, read-only), or None when
    absent or damaged (a damaged entry is removed with a warning)."""
    found = cache.load(key)
    if found is None:
        return None
    a, m = found
    try:
        bounds = np.cumsum(a["phase_size"])[:-1]
        phases = list(zip(np.split(a["phase_first"], bounds), np.split(a["phase_last"], bounds)))
        t = DepositTables(tuple(m["grid"]), tuple(m["oversample"]), int(m["vw"]), np.dtype(m["weights_dtype"]),
                          tuple(m["detector_shape"]), a["meta"], a["offset"], int(m["pool_size"]),
                          tuple(m["row_range"]), phases, scale=a["scale"], pool=a["pool"])
        if (t.meta.shape != (t.ncell, 4) or t.offset.shape != (t.ncell,) or t.scale.shape != (t.ncell,)
                or t.pool.shape != (t.pool_size,) or t.pool.dtype != t.weights_dtype
                or int(np.prod(t.grid)) != t.ncell):
            raise ValueError("array shapes do not match the metadata")  # internal: caught below, tables rebuilt
    except (KeyError, TypeError, ValueError) as exc:
        warnings.warn(f"projection tables {key} in {cache.directory} are inconsistent ({exc}); rebuilt",
                      TableCacheWarning, stacklevel=2)
        cache.remove(key)
        return None
    return t


# --------------------------------------------------------------------------- #
#  deposit                                                                     #
# --------------------------------------------------------------------------- #
def deposit(value, tables, out=None, backend="auto", precision="auto"):
    """Deposit cube values into a detector image.

    Parameters
    ----------
    value : (S, E/ne, Q/nq) float array
        value of each cube cell (any unit per cell per bin; the image is in the
        same unit per pixel); finite (a NaN would spread over its padded window).
    tables : DepositTables
    out : (H, W) float64 array, optional
        accumulated into in place (a new zero image when None).
    backend : "auto" | "opencl" | "numpy"
    precision : "auto" (default), "double" or "single" (:mod:`slicersim.backends.precision`):
        single deposits value × scale × weights into a float32 image band (≤ 1e-5 of the image
        peak against double, :data:`~slicersim.backends.precision.SINGLE_PRECISION_ERRORS`
        ["projection"]), then adds it to ``out`` in float64; the tables are the same.  Checked
        before any work.

    Returns the (H, W) float64 image.
    """
    backend, precision = resolve_precision(precision, backend, "projection")
    t = tables
    S, E, Q = t.grid
    ne, nq = t.oversample
    value = np.asarray(value)
    if value.shape != (S, E // ne, Q // nq):
        raise ParameterError(f"value must have shape {(S, E // ne, Q // nq)}, got {value.shape}")
    H, W = t.detector_shape
    if out is None:
        out = np.zeros((H, W), np.float64)
    elif out.shape != (H, W) or out.dtype != np.float64 or not out.flags.c_contiguous:
        raise ParameterError(f"out must be a C-contiguous float64 array of shape {(H, W)}")
    r0, r1 = t.row_range
    if r1 <= r0 or t.ncell == 0:
        return out
    if backend == "opencl":
        single = precision == "single"
        deposit_opencl(value, t, out, _options(t, "float" if single else None), precision)
    else:
        deposit_numpy(np.ascontiguousarray(value, dtype=np.float64), t, out)
    return out
