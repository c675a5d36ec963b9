"""The cube → detector deposit of :mod:`slicersim.backends.projection`: the ``deposit_cells``
launches (``kernels/project.cl``) in double or single precision, and the NumPy twin.

Kept apart from :mod:`~slicersim.backends.projection` (module size; the table cache keys on that
module's source, and nothing here changes a table).  :func:`slicersim.backends.projection.deposit`
validates its arguments and calls :func:`deposit_opencl` or :func:`deposit_numpy`.

Single precision (``precision="single"``, :mod:`slicersim.backends.precision`): the same kernel
built with ``-DSINGLE`` and float weights; value, scale and the image band are float32.  The
band starts at zero and is added to the float64 ``out`` on the host, so an image accumulated
over several calls (both fields, several cubes) keeps float64 between calls.  float32 copies of
the per-cell scales (and of float64 weights) are made once per tables object and kept with its
device buffers.  The tables themselves are built in double (NumPy twin on a device without
fp64) whatever precision deposits them.
"""
from __future__ import annotations

import numpy as np

from slicersim.backends import opencl

__all__ = ["deposit_numpy", "deposit_opencl", "parent_index", "table_buffer"]

_KERNEL = "project.cl"
_DEPOSIT_CHUNK = 1 << 15        # cells per NumPy chunk (deposit: ~ny*nxp temporaries each)


def parent_index(t, c):
    """Cube cell of sub-cells ``c`` of tables ``t`` (flat index into the (S, E/ne, Q/nq) values)."""
    S, E, Q = t.grid
    ne, nq = t.oversample
    s, rem = np.divmod(c, E * Q)
    e, q = np.divmod(rem, Q)
    return (s * (E // ne) + e // ne) * (Q // nq) + q // nq


def deposit_numpy(value, t, out):
    """Twin of ``deposit_cells`` (float64): per chunk of cells, one bincount on the chunk's bounding box."""
    t.host()
    H, W = t.detector_shape
    flat = value.ravel()
    for c0 in range(0, t.ncell, _DEPOSIT_CHUNK):
        c = np.arange(c0, min(c0 + _DEPOSIT_CHUNK, t.ncell))
        v = flat[parent_index(t, c)]
        keep = v != 0
        c, v = c[keep], v[keep] * t.scale[c[keep]]
        if c.size == 0:
            continue
        x0, y0, nx, ny = (t.meta[c, i].astype(np.int64) for i in range(4))
        nxp = -(-nx // t.vw) * t.vw
        NX, NY = int(nx.max()), int(ny.max())
        jx, jy = np.arange(NX)[None], np.arange(NY)[None]
        off = t.offset[c][:, None]
        wx = np.where(jx < nx[:, None], t.pool[np.minimum(off + jx, t.pool_size - 1)], 0).astype(np.float64)
        wy = np.where(jy < ny[:, None], t.pool[np.minimum(off + nxp[:, None] + jy, t.pool_size - 1)], 0)
        f = v[:, None] * wy.astype(np.float64)                         # (n, NY)
        rlo, rhi = int(y0.min()), int(y0.max()) + NY
        clo, chi = int(x0.min()), int(x0.max()) + NX
        width = chi - clo
        idx = ((y0 - rlo) * width + (x0 - clo))[:, None, None] + (jy * width)[:, :, None] + jx[:, None, :]
        contrib = f[:, :, None] * wx[:, None, :]
        acc = np.bincount(idx.ravel(), weights=contrib.ravel(), minlength=(rhi - rlo) * width)
        acc = acc.reshape(rhi - rlo, width)
        r_a, r_b, c_a, c_b = max(rlo, 0), min(rhi, H), max(clo, 0), min(chi, W)
        if r_a < r_b and c_a < c_b:                     # what falls off the detector is lost
            out[r_a:r_b, c_a:c_b] += acc[r_a - rlo:r_b - rlo, c_a - clo:c_b - clo]


def table_buffer(array):
    """Device buffer of a table array.  On CPU devices a memory-mapped table (read from the
    cache) is used in place: a copy-on-write mapping of its file (the kernels only read it),
    so no copy of the tables is made in host memory."""
    if (isinstance(array, np.memmap) and array.size and array.filename is not None
            and "CPU" in opencl.device_type()):
        private = np.memmap(array.filename, dtype=array.dtype, mode="c", offset=array.offset, shape=array.shape)
        return opencl.host_buffer(private)
    return opencl.to_device(np.ascontiguousarray(array))


def _host_table(t, name, dtype, n):
    """Table ``name`` of ``t`` on the host (downloaded when the tables live on the device only)."""
    array = getattr(t, name)
    if array is None:
        array = np.empty(n, dtype)
        opencl.from_device(array, t.device[name])
    return array


def _table_buffers(t, single):
    """(meta, offset, pool, scale) device buffers of the deposit: the tables' own, or in single
    precision float32 copies of scale (and of float64 weights), made once per tables object."""
    dev = t.device
    pool_name = "pool32" if single and t.weights_dtype != np.dtype(np.float32) else "pool"
    scale_name = "scale32" if single else "scale"
    for name in ("meta", "offset", pool_name, scale_name):
        if name in dev:
            continue
        if name.endswith("32"):
            source, dtype, n = (("pool", t.weights_dtype, t.pool_size) if name == "pool32"
                                else ("scale", np.dtype(np.float64), t.ncell))
            copy = np.array(_host_table(t, source, dtype, n), np.float32)        # own, writeable memory
            dev[name] = opencl.host_buffer(copy) if "CPU" in opencl.device_type() else opencl.to_device(copy)
        else:
            dev[name] = table_buffer(getattr(t, name))
    return dev["meta"], dev["offset"], dev[pool_name], dev[scale_name]


def deposit_opencl(value, t, out, options, precision="double"):
    """``deposit_cells`` over every colour phase of ``t``, accumulated into ``out`` (float64).
    ``value``: (S, E/ne, Q/nq) array of any float dtype and layout (converted in one pass);
    ``options``: the tables' build options (vector width, weight type, table constants) for
    this precision.  On CPU devices the kernels read ``value`` and write the image band in place
    (no device copies)."""
    single = precision == "single"
    if not single:
        opencl.require_fp64()
    real = np.dtype(np.float32 if single else np.float64)
    d_meta, d_offset, d_pool, d_scale = _table_buffers(t, single)
    dev = t.device
    if "phases" not in dev:
        dev["phases"] = [(opencl.to_device(f), opencl.to_device(l), f.size) for f, l in t.phases]
    is_gpu = "GPU" in opencl.device_type()
    S, E, Q = t.grid
    ne, nq = t.oversample
    H, W = t.detector_shape
    r0, r1 = t.row_range
    if single:            # a zero float band, added to out afterwards: out keeps float64 between calls
        band = np.zeros((r1 - r0, W), np.float32)
    else:
        band = out[r0:r1]                               # contiguous rows of a C array
    zero_copy = "CPU" in opencl.device_type()      # the kernels write the band's own memory
    d_img = opencl.host_buffer(band) if zero_copy else opencl.to_device(band, opencl.device_buffer(band.nbytes))
    value = np.ascontiguousarray(value, real)        # one pass from the caller's (strided) view
    d_val = (opencl.host_buffer(value) if zero_copy and value.flags.writeable and value.size
             else opencl.to_device(value))
    kern = opencl.get_kernel(_KERNEL, "deposit_cells", tuple(options) + opencl.precision_options(precision))
    i32 = np.int32
    for d_first, d_last, n in dev["phases"]:
        lsize = 32 if is_gpu else 1
        gsize = -(-n // lsize) * lsize
        opencl.launch(kern, (gsize,), (lsize,), d_val, d_meta, d_offset, d_pool, d_scale, d_first, d_last,
                      i32(n), i32(E), i32(Q), i32(ne), i32(nq), d_img, i32(W), i32(r0), i32(r1 - r0))
    if zero_copy:
        opencl.sync_to_host(d_img, band)
    else:
        opencl.from_device(band, d_img)
    if single:
        out[r0:r1] += band
