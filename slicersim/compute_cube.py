"""Fused detector cube of a point source: OpenCL host wrapper (``kernels/cube.cl``) and NumPy twin.

One λ chunk of the cube (output bins i0 … i1 − 1 of a grid of nl bins) from
small inputs, without materialising the product cube G·P:

    C[i, y, x] = Σ_t w_t (G_j P_j[y, x] + H_j[y, x]) + U_i,  j = reflect(i + t − h)   [ph/s/cell]
    e = QE_i C                                  [e-/s/cell]
    signal   = e t_int g r                      [ADU]    (NaN where saturated)
    variance = (A + B e) r                      [ADU²]   (+inf where saturated)
    saturated ⇔ (e/p + D_eff) t_int g > saturation  (the test of ``Simulation.cell_variance``)

P is the separable Gaussian erf product fy[j, y]·fx[j, x] (``psf_y``,
``psf_x``) or a full block P[j, y, x] (``psf``, e.g. Airy); H an optional
extended source already blurred by the PSF (``host``).  "reflect" mirrors
about the outer edges of the whole grid (scipy's mode), so a chunk only needs
the input bins lo … lo + nb − 1 that its taps reach (the LSF halo).  The
variance is Rauscher07's, linear in e (:func:`slicersim.etc.readout_variance_coefficients`).

Backends agree to ~1e-15 of the peak (summation order and FMA contraction
only); each voxel's arithmetic does not depend on the chunking.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slicersim import opencl
from slicersim.compute import resolve_backend

__all__ = ["ReadoutConstants", "detector_block", "reflect_indices", "release_buffers"]

_KERNEL_FILE = "cube.cl"
_OUT_DTYPES = (np.float64, np.float32)


@dataclass(frozen=True)
class ReadoutConstants:
    """Detector constants of one readout (per ramp, r ramps summed).

    tint [s], gain [ADU/e-], nramps r, var_a [ADU²] and var_b [ADU² per e-/s] of the cell
    variance V = A + B e, pixels_per_cell p, dark = D_eff [e-/s/px], saturation [ADU] (inf: none).
    """
    tint: float
    gain: float
    nramps: int
    var_a: float
    var_b: float
    pixels_per_cell: float
    dark: float
    saturation: float


def reflect_indices(bins, nl, half):
    """(nc, 2h + 1) input bins j = reflect(i + t − h) of output bins i in ``bins`` = (i0, i1)
    on a grid of nl bins (mirror about the outer edges, period 2 nl: scipy's "reflect")."""
    i0, i1 = bins
    j = np.arange(i0, i1)[:, None] + np.arange(-half, half + 1)[None, :]
    j = np.mod(j, 2 * nl)
    return np.where(j >= nl, 2 * nl - 1 - j, j)


def _as_f64(x):
    return np.ascontiguousarray(x, dtype=np.float64)


def _check(taps, rate, uniform, qe, bins, nl, lo, psf, psf_y, psf_x, host, dtype):
    taps = _as_f64(taps).ravel()
    if taps.size % 2 != 1:
        raise ValueError(f"taps must have an odd length 2h + 1, got {taps.size}")
    half = taps.size // 2
    i0, i1 = (int(b) for b in bins)
    if not 0 <= i0 <= i1 <= nl:
        raise ValueError(f"bins {bins} must satisfy 0 <= i0 <= i1 <= nl = {nl}")
    nc = i1 - i0
    uniform, qe = _as_f64(uniform).ravel(), _as_f64(qe).ravel()
    if uniform.shape != (nc,) or qe.shape != (nc,):
        raise ValueError(f"uniform and qe must have {nc} values, got {uniform.shape}, {qe.shape}")
    separable = psf is None
    if rate is None:
        if host is None:
            raise ValueError("give a point source (rate and a PSF), a host block, or both")
        psf = psf_y = psf_x = None
        separable = False
    elif separable:
        if psf_y is None or psf_x is None:
            raise ValueError("a point source needs psf (nb, ny, nx) or psf_y (nb, ny) and psf_x (nb, nx)")
        psf_y, psf_x = _as_f64(psf_y), _as_f64(psf_x)
        if psf_y.ndim != 2 or psf_x.ndim != 2 or psf_y.shape[0] != psf_x.shape[0]:
            raise ValueError(f"psf_y (nb, ny) and psf_x (nb, nx) mismatch: {psf_y.shape}, {psf_x.shape}")
    else:
        psf = _as_f64(psf)
        if psf.ndim != 3:
            raise ValueError(f"psf must be (nb, ny, nx), got {psf.shape}")
    if host is not None:
        host = _as_f64(host)
        if host.ndim != 3:
            raise ValueError(f"host must be (nb, ny, nx), got {host.shape}")
    blocks = [a for a in (psf, host) if a is not None]
    if blocks:
        nb, ny, nx = blocks[0].shape
    else:
        nb, ny, nx = psf_y.shape[0], psf_y.shape[1], psf_x.shape[1]
    if any(b.shape != (nb, ny, nx) for b in blocks) or (psf_y is not None and psf_y.shape[0] != nb):
        raise ValueError("psf / psf_y / psf_x / host blocks must cover the same bins and cells")
    if rate is not None:
        rate = _as_f64(rate).ravel()
        if rate.shape != (nb,):
            raise ValueError(f"rate must have nb = {nb} values, got {rate.shape}")
    if nc:
        j = reflect_indices((i0, i1), nl, half)
        if j.min() < lo or j.max() >= lo + nb:
            raise ValueError(f"input blocks hold bins {lo}…{lo + nb - 1} but the LSF of bins {i0}…{i1 - 1} "
                             f"reaches {j.min()}…{j.max()}")
    dtype = np.dtype(dtype)
    if dtype.type not in _OUT_DTYPES:
        raise ValueError(f"dtype must be float64 or float32, got {dtype}")
    return taps, rate, uniform, qe, (i0, i1), psf, psf_y, psf_x, host, separable, (nb, ny, nx), dtype


def detector_block(taps, rate, uniform, qe, readout, *, bins, nl, lo, psf=None, psf_y=None, psf_x=None,
                   host=None, out=None, dtype=np.float64, backend="auto"):
    """Signal [ADU], variance [ADU²] and saturated mask of output bins ``bins`` = (i0, i1).

    Parameters
    ----------
    taps : (2h + 1,) LSF weights for offsets −h … h
    rate : (nb,) point-source photon rate G = F f2p [ph/s] of input bins lo … lo + nb − 1, or None
    uniform : (i1 − i0,) LSF'd uniform photons U [ph/s/cell];  qe : (i1 − i0,) [e-/ph]
    readout : :class:`ReadoutConstants`
    bins, nl, lo : output bin range, grid size, first input bin
    psf : (nb, ny, nx) PSF fractions, or psf_y (nb, ny) and psf_x (nb, nx) of a separable PSF
    host : (nb, ny, nx) extended-source photons before the LSF [ph/s/cell], or None
    out : optional (signal, variance, saturated) C-contiguous arrays (nc, ny, nx) of dtype, dtype, bool
    dtype : float64 or float32 storage of signal and variance (arithmetic is float64)
    backend : "auto" | "opencl" | "numpy"
    """
    (taps, rate, uniform, qe, bins, psf, psf_y, psf_x, host, separable, (nb, ny, nx),
     dtype) = _check(taps, rate, uniform, qe, bins, nl, lo, psf, psf_y, psf_x, host, dtype)
    shape = (bins[1] - bins[0], ny, nx)
    if out is None:
        out = (np.empty(shape, dtype), np.empty(shape, dtype), np.empty(shape, bool))
    for arr, dt in zip(out, (dtype, dtype, np.dtype(bool))):
        if arr.shape != shape or arr.dtype != dt or not arr.flags.c_contiguous:
            raise ValueError(f"out arrays must be C-contiguous {shape} of {dtype}, {dtype}, bool")
    if shape[0] == 0 or ny == 0 or nx == 0:
        return out
    args = (taps, rate, uniform, qe, readout, bins, nl, lo, psf, psf_y, psf_x, host, separable, out)
    if resolve_backend(backend) == "opencl":
        _detector_block_opencl(*args)
    else:
        _detector_block_numpy(*args)
    return out


# --------------------------------------------------------------------------- NumPy twin
def _detector_block_numpy(taps, rate, uniform, qe, ro, bins, nl, lo, psf, psf_y, psf_x, host, separable,
                          out):
    signal, variance, saturated = out
    j = reflect_indices(bins, nl, taps.size // 2) - lo
    if rate is not None:
        if separable:
            psf = psf_y[:, :, None] * psf_x[:, None, :]
        photons_in = rate[:, None, None] * psf
        if host is not None:
            photons_in = photons_in + host
    else:
        photons_in = host
    for c in range(j.shape[0]):                                        # one output plane at a time
        photons = np.tensordot(taps, photons_in[j[c]], axes=1) + uniform[c]
        e = photons * qe[c]
        sat = (e / ro.pixels_per_cell + ro.dark) * ro.tint * ro.gain > ro.saturation
        signal[c] = np.where(sat, np.nan, e * ro.tint * ro.gain * ro.nramps)
        variance[c] = np.where(sat, np.inf, (ro.var_a + ro.var_b * e) * ro.nramps)
        saturated[c] = sat


# --------------------------------------------------------------------------- OpenCL
_pool: dict = {}


def release_buffers():
    """Free the device buffers kept between calls (they are re-created on demand)."""
    _pool.clear()


def _pooled(name, nbytes):
    """Device buffer ``name`` of at least ``nbytes``, reused between calls (allocating and
    first-touching ~60 MB of output buffers per cube costs more than the kernel on PoCL)."""
    ctx = opencl.get_context()
    hit = _pool.get(name)
    if hit is None or hit[0] is not ctx or hit[1] < nbytes:
        hit = (ctx, max(int(nbytes), 1), opencl.device_buffer(nbytes))
        _pool[name] = hit
    return hit[2]


def vector_width():
    """Cells per work item: 1 on GPUs (coalesced rows), the preferred double width (≤ 8) on CPUs."""
    dev = opencl.get_device()
    if "GPU" in opencl.device_type(dev):
        return 1
    native = int(getattr(dev, "preferred_vector_width_double", 1) or 1)
    vw = 1
    while vw * 2 <= min(native, 8):
        vw *= 2
    return vw


def _detector_block_opencl(taps, rate, uniform, qe, ro, bins, nl, lo, psf, psf_y, psf_x, host, separable,
                           out, vw=None):
    signal, variance, saturated = out
    nc, ny, nx = signal.shape
    vw = vector_width() if vw is None else vw
    out_type = "double" if signal.dtype == np.float64 else "float"
    options = (f"-DVW={vw}", f"-DOUT={out_type}", f"-DSEPARABLE={int(separable)}",
               f"-DHAS_POINT={int(rate is not None)}", f"-DHAS_HOST={int(host is not None)}")
    kern = opencl.get_kernel(_KERNEL_FILE, "pointsource_cube", options)
    unused = _pooled("unused", 8)
    if rate is None:
        d_a = d_b = unused
    elif separable:
        d_a, d_b = opencl.to_device(psf_y), opencl.to_device(psf_x)
    else:
        d_a, d_b = opencl.to_device(psf, _pooled("psf", psf.nbytes)), unused
    d_host = unused if host is None else opencl.to_device(host, _pooled("host", host.nbytes))
    d_rate = unused if rate is None else opencl.to_device(rate)
    d_u, d_qe, d_w = opencl.to_device(uniform), opencl.to_device(qe), opencl.to_device(taps)
    d_s, d_v = _pooled("signal", signal.nbytes), _pooled("variance", variance.nbytes)
    d_m = _pooled("saturated", saturated.nbytes)
    i32, f64 = np.int32, np.float64
    opencl.launch(kern, (-(-nx // vw), ny, nc), None, d_a, d_b, d_host, d_rate, d_u, d_qe, d_w,
                  i32(taps.size // 2), i32(nl), i32(lo), i32(bins[0]), i32(ny), i32(nx),
                  f64(ro.tint), f64(ro.gain), f64(ro.nramps), f64(ro.var_a), f64(ro.var_b),
                  f64(ro.pixels_per_cell), f64(ro.dark), f64(ro.saturation), d_s, d_v, d_m)
    opencl.from_device(signal, d_s)
    opencl.from_device(variance, d_v)
    opencl.from_device(saturated.view(np.uint8), d_m)
