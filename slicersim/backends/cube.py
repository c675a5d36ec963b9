"""Fused detector cube of a point source: OpenCL host wrapper (``kernels/cube.cl``) and NumPy twin.

One λ chunk of the cube (output bins i0 … i1 − 1 of a grid of nl bins) from
small inputs, without materialising the product cube G·P:

    C[i, y, x] = Σ_t w_t (G_j P_j[y, x] + H_j[y, x]) + U_i,  j = reflect(i + t − h)   [ph/s/cell]
    e = QE_i C                                  [e-/s/cell]
    signal   = e · t_int g r                    [ADU]    (NaN where saturated)
    variance = r A + r B e                      [ADU²]   (+inf where saturated)
    saturated ⇔ e > p (saturation/(t_int g) − D_eff)   (``Simulation.cell_variance``'s test)

P is a separable Gaussian (:class:`GaussianPSF`, whose erf cell fractions are
computed on the host, or given factors (fy, fx): P = fy[:, :, None]·fx[:, None, :])
or a full block P[j, y, x] (e.g. Airy); H an optional extended source already
blurred by the PSF.  "reflect" mirrors about the outer edges of the whole
grid (scipy's mode), so a chunk only needs the input bins lo … lo + nb − 1
that its taps reach (the LSF halo).  The variance is Rauscher07's, linear in
e (:func:`slicersim.etc.readout_variance_coefficients`).  Saturated voxels are
exactly those with variance = +inf (NaN fluxes give NaN signal and variance).

Backends agree to a few 1e-16 of the peak (summation order and FMA contraction
only); each voxel's arithmetic does not depend on the chunking.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slicersim.backends import opencl
from slicersim.backends.precision import real_dtype, resolve_precision, storage_dtype
from slicersim.backends.psf import DevicePSF
from slicersim.errors import ParameterError
from slicersim.physics.psf import cell_edges, erf_cell_fractions

__all__ = ["ReadoutConstants", "GaussianPSF", "DetectorChunk", "detector_block", "detector_chunk",
           "reflect_indices", "release_buffers", "default_vector_width"]

_KERNEL_FILE = "cube.cl"
_LAUNCH_BYTES = 1 << 30        # output bytes per kernel launch (cache-sized launches were not faster)


@dataclass(frozen=True)
class ReadoutConstants:
    """Detector constants of one readout (per ramp, r ramps summed).

    tint [s], gain [ADU/e-], nramps r, var_a [ADU²] and var_b [ADU² per e-/s] of the per-ramp cell
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

    @property
    def signal_scale(self):
        """t_int g r [ADU per e-/s]: signal = e · signal_scale."""
        return self.tint * self.gain * self.nramps

    @property
    def saturation_rate(self):
        """Cell electron rate above which a cell saturates, p (saturation/(t_int g) − D_eff) [e-/s/cell]:
        the test (e/p + D_eff) t_int g > saturation of ``Simulation.cell_variance`` solved for e."""
        return self.pixels_per_cell * (self.saturation / (self.tint * self.gain) - self.dark)

    def signal_variance(self, electrons):
        """(signal [ADU], variance [ADU²]) of r ramps for cell electron rates e [e-/s/cell]: e t_int g r
        and r (A + B e), NaN and +inf where e exceeds :attr:`saturation_rate` (the kernel's test)."""
        saturated = electrons > self.saturation_rate
        return (np.where(saturated, np.nan, electrons * self.signal_scale),
                np.where(saturated, np.inf, self.var_a * self.nramps + self.var_b * self.nramps * electrons))


@dataclass(frozen=True)
class GaussianPSF:
    """Separable Gaussian PSF of the input bins: σ_y, σ_x (nb,) [cells], source position (x0, y0)
    [cells from the field centre], field shape (ny, nx); P = fy[:, :, None] · fx[:, None, :]."""
    sig_y: np.ndarray
    sig_x: np.ndarray
    position: tuple
    shape: tuple

    def factors(self):
        """(fy (nb, ny), fx (nb, nx)) erf cell fractions, bit-identical to the factors of
        :func:`slicersim.physics.psf.gaussian_psf_fractions`."""
        (ny, nx), (x0, y0) = self.shape, self.position
        return _cell_fractions(cell_edges(ny), y0, self.sig_y), _cell_fractions(cell_edges(nx), x0, self.sig_x)


def _cell_fractions(edges, centre, sigma):
    """``slicersim.physics.psf.erf_cell_fractions`` (erf near the centre, erfc differences in the
    tails; erfc is not evaluated where it underflows to 0)."""
    return erf_cell_fractions(edges, centre, sigma)


def reflect_indices(bins, nl, halo):
    """(nc, 2h + 1) input bins j = reflect(i + t − h) of output bins i in ``bins`` = (i0, i1)
    on a grid of nl bins (mirror about the outer edges, period 2 nl: scipy's "reflect")."""
    i0, i1 = bins
    return _reflect(np.arange(i0, i1)[:, None] + np.arange(-halo, halo + 1)[None, :], nl)


def _reflect(j, nl):
    j = np.mod(j, 2 * nl)
    return np.where(j >= nl, 2 * nl - 1 - j, j)


def _as_f64(x):
    return np.ascontiguousarray(x, dtype=np.float64)


@dataclass(frozen=True)
class DetectorChunk:
    """The inputs of one λ chunk of the fused detector cube: output bins ``bins`` = (i0, i1) of a
    grid of ``nl`` bins computed from input bins lo … lo + nb − 1.

    taps (2h + 1,) LSF weights; rate (nb,) point-source photons G = F f2p [ph/s] or None;
    uniform (i1 − i0,) LSF'd uniform photons U [ph/s/cell]; qe (i1 − i0,) [e-/ph]; psf: a
    :class:`GaussianPSF`, factors (fy (nb, ny), fx (nb, nx)), P (nb, ny, nx) or a
    :class:`~slicersim.backends.psf.DevicePSF` (None without rate); host (nb, ny, nx) extended
    photons before the LSF [ph/s/cell] or None."""
    taps: np.ndarray
    rate: np.ndarray | None
    uniform: np.ndarray
    qe: np.ndarray
    bins: tuple
    nl: int
    lo: int
    psf: object = None
    host: np.ndarray | None = None


def _check_psf(psf):
    """→ (kind, payload, (nb, ny, nx)); kind "gaussian" | "factors" | "full"."""
    if isinstance(psf, GaussianPSF):
        sig_y, sig_x = _as_f64(psf.sig_y).ravel(), _as_f64(psf.sig_x).ravel()
        if sig_y.shape != sig_x.shape:
            raise ValueError(f"sig_y and sig_x must have the same length, got {sig_y.shape}, {sig_x.shape}")  # internal: built by a PSF profile
        ny, nx = (int(n) for n in psf.shape)
        gauss = GaussianPSF(sig_y, sig_x, tuple(float(p) for p in psf.position), (ny, nx))
        return "gaussian", gauss, (sig_y.size, ny, nx)
    if isinstance(psf, tuple):
        fy, fx = (_as_f64(f) for f in psf)
        if fy.ndim != 2 or fx.ndim != 2 or fy.shape[0] != fx.shape[0]:
            raise ValueError(f"PSF factors must be fy (nb, ny) and fx (nb, nx), got {fy.shape}, {fx.shape}")  # internal: built by a PSF profile
        return "factors", (fy, fx), (fy.shape[0], fy.shape[1], fx.shape[1])
    if isinstance(psf, DevicePSF):
        if len(psf.shape) != 3:
            raise ValueError(f"a DevicePSF must be (nb, ny, nx), got shape {psf.shape}")  # internal: built by backends.psf
        return "full", psf, tuple(int(n) for n in psf.shape)
    psf = _as_f64(psf)
    if psf.ndim != 3:
        raise ValueError(f"psf must be (nb, ny, nx), (fy, fx) or a GaussianPSF, got shape {psf.shape}")  # internal: built by a PSF profile
    return "full", psf, psf.shape


def _check_spectra(chunk):
    """taps, bins, uniform and qe of ``chunk`` as float64 arrays and ints (internal consistency)."""
    taps = _as_f64(chunk.taps).ravel()
    if taps.size % 2 != 1:
        raise ValueError(f"taps must have an odd length 2h + 1, got {taps.size}")  # internal: from lsf_weights
    i0, i1 = (int(b) for b in chunk.bins)
    if not 0 <= i0 <= i1 <= chunk.nl:
        raise ValueError(f"bins {chunk.bins} must satisfy 0 <= i0 <= i1 <= nl = {chunk.nl}")  # internal: the builder's chunks
    uniform, qe = _as_f64(chunk.uniform).ravel(), _as_f64(chunk.qe).ravel()
    if uniform.shape != (i1 - i0,) or qe.shape != (i1 - i0,):
        raise ValueError(f"uniform and qe must have {i1 - i0} values, got {uniform.shape}, {qe.shape}")  # internal: the builder's slices
    return taps, (i0, i1), uniform, qe


def _check_sources(chunk):
    """(kind, psf, rate, host, (nb, ny, nx)) of the point source and host blocks of ``chunk``."""
    rate, psf, host = chunk.rate, chunk.psf, chunk.host
    if (rate is None) != (psf is None):
        raise ValueError("a point source needs both rate and psf (or neither, with a host block)")  # internal: the builder pairs them
    if rate is None and host is None:
        raise ValueError("give a point source (rate and psf), a host block, or both")  # internal: uniform scenes need no block
    kind, shape = None, None
    if psf is not None:
        kind, psf, shape = _check_psf(psf)
        rate = _as_f64(rate).ravel()
        if rate.shape != shape[:1]:
            raise ValueError(f"rate must have nb = {shape[0]} values, got {rate.shape}")  # internal: the builder's slices
    if host is not None:
        host = _as_f64(host)
        if host.ndim != 3 or (shape is not None and host.shape != shape):
            raise ValueError(f"host must be (nb, ny, nx) = {shape or '(nb, ny, nx)'}, got {host.shape}")  # internal: the builder's blocks
        shape = host.shape
    return kind, psf, rate, host, shape


def _checked(chunk):
    """(chunk with float64 arrays, PSF kind, (nb, ny, nx)); the LSF of the output bins must stay
    within the input bins."""
    taps, (i0, i1), uniform, qe = _check_spectra(chunk)
    kind, psf, rate, host, shape = _check_sources(chunk)
    if i1 > i0:
        j = _reflect(np.arange(i0 - taps.size // 2, i1 + taps.size // 2), chunk.nl)   # every bin a tap reaches
        if j.min() < chunk.lo or j.max() >= chunk.lo + shape[0]:
            raise ValueError(f"input blocks hold bins {chunk.lo}…{chunk.lo + shape[0] - 1} but the LSF of bins "  # internal: the builder's halo
                             f"{i0}…{i1 - 1} reaches {j.min()}…{j.max()}")
    return DetectorChunk(taps, rate, uniform, qe, (i0, i1), int(chunk.nl), int(chunk.lo), psf, host), kind, shape


def detector_block(taps, rate, uniform, qe, readout, *, bins, nl, lo, psf=None, host=None, **options):
    """Signal [ADU] and variance [ADU²] of output bins ``bins`` = (i0, i1); saturated ⇔ variance = +inf.

    The keyword form of :func:`detector_chunk`: ``taps, rate, uniform, qe, bins, nl, lo, psf, host``
    are the fields of :class:`DetectorChunk`; ``options`` (``out``, ``dtype``, ``backend``,
    ``precision``, ``vector_width``, ``row_per_item``) those of :func:`detector_chunk`.
    """
    return detector_chunk(DetectorChunk(taps, rate, uniform, qe, bins, nl, lo, psf, host), readout, **options)


def detector_chunk(chunk, readout, *, out=None, dtype=np.float64, backend="auto", precision="auto",
                   vector_width=None, row_per_item=None):
    """Signal [ADU] and variance [ADU²] of one :class:`DetectorChunk`; saturated ⇔ variance = +inf.

    Parameters
    ----------
    chunk : :class:`DetectorChunk` (the LSF of the output bins must stay within the input bins)
    readout : :class:`ReadoutConstants` (linear variance, both backends) or, NumPy only, any object
        with ``signal_variance(e) -> (signal, variance)`` of r ramps (e.g. a non-linear model)
    out : optional (signal, variance) C-contiguous arrays (i1 − i0, ny, nx) of ``dtype``
    dtype : float64 or float32 storage (arithmetic is float64 unless ``precision`` is "single")
    backend : "auto" | "opencl" | "numpy" (the NumPy twin: the same steps in float64)
    precision : "double", "single" (OpenCL: every input and operation in float32: ≤ 1e-5 of the
        signal peak against double, measured ~2e-7; voxels within that of the saturation rate may
        flip) or "auto" (:mod:`slicersim.backends.precision`; NumPy computes in float64)
    vector_width, row_per_item : OpenCL layout, no effect on the result: cells per vector (1, 2, 4,
        8, 16) and whole rows per work item (default: the device's preferred double width and rows
        on CPUs; 1 and one cell per work item on GPUs)
    """
    chunk, kind, (nb, ny, nx) = _checked(chunk)
    dtype = storage_dtype(dtype)
    shape = (chunk.bins[1] - chunk.bins[0], ny, nx)
    if out is None:
        out = (np.empty(shape, dtype), np.empty(shape, dtype))
    if any(a.shape != shape or a.dtype != dtype or not a.flags.c_contiguous for a in out):
        raise ValueError(f"out arrays must be C-contiguous {shape} of {dtype}")  # internal: the builder's slices
    backend, precision = resolve_precision(precision, backend, "cube")
    if not (shape[0] and ny and nx):
        return out
    if backend == "opencl":
        if not isinstance(readout, ReadoutConstants):
            raise ValueError("the OpenCL kernel needs ReadoutConstants (a linear variance)")  # internal: builder picks NumPy
        _detector_block_opencl(chunk, kind, readout, out, (vector_width, row_per_item), precision)
    else:
        _detector_block_numpy(chunk, kind, readout, out)
    return out


# --------------------------------------------------------------------------- NumPy twin
def _photons_in(chunk, kind):
    """Photons of the input bins before the LSF, G P + H [ph/s/cell] (nb, ny, nx) (or 0.0)."""
    photons, psf = 0.0, chunk.psf
    if kind is not None:
        if kind == "gaussian":
            psf = psf.factors()
        if kind != "full":
            psf = psf[0][:, :, None] * psf[1][:, None, :]
        elif isinstance(psf, DevicePSF):
            psf = psf.to_host()
        photons = chunk.rate[:, None, None] * psf
    if chunk.host is not None:
        photons = photons + chunk.host
    return photons


def _lsf_electrons(chunk, photons_in, ny, nx):
    """e = QE_i (Σ_t w_t photons_in[j] + U_i) [e-/s/cell] of the output bins, j = reflect(i + t − h)."""
    j = reflect_indices(chunk.bins, chunk.nl, chunk.taps.size // 2) - chunk.lo
    electrons = np.empty((j.shape[0], ny, nx))
    for c in range(j.shape[0]):                                        # one output plane at a time
        electrons[c] = (np.tensordot(chunk.taps, photons_in[j[c]], axes=1) + chunk.uniform[c]) * chunk.qe[c]
    return electrons


def _detector_block_numpy(chunk, kind, readout, out):
    """The NumPy twin of the kernel: photons, LSF, QE, then ``readout.signal_variance``."""
    signal, variance = out
    electrons = _lsf_electrons(chunk, _photons_in(chunk, kind), signal.shape[1], signal.shape[2])
    signal[...], variance[...] = readout.signal_variance(electrons)


# --------------------------------------------------------------------------- OpenCL
def release_buffers():
    """Free this thread's cached device buffers and kernels (re-created on demand)."""
    opencl.release_thread_resources()


def _kernel(file, name, options=()):
    """Kernel object reused between calls (creating one costs ~1 ms of pyopencl set-up)."""
    return opencl.cached_kernel(file, name, tuple(options))


def _buffer(name, nbytes):
    """Device buffer ``name`` of at least ``nbytes``, reused between calls: allocating and
    first-touching ~60 MB of output buffers per cube costs as much as the kernel on PoCL."""
    return opencl.scratch_buffer(f"cube.{name}", nbytes)


def default_vector_width():
    """Cells per vector: 1 on GPUs, the preferred double width (≤ 16) on CPUs."""
    return opencl.preferred_vector_width(16)


def _host_memory_device():
    """True on CPU devices: buffers over the NumPy outputs (``opencl.host_buffer``) are used in
    place, saving the device → host copies of signal and variance (2 × 28 MB for Lazuli)."""
    return opencl.device_type() == "CPU"


def _psf_on_device(kind, psf, nxp, real=np.dtype(np.float64)):
    """(buffer a, buffer b) for the kernel's psf_a, psf_b arguments, in the kernel's ``real``; fx
    rows padded with zeros to nxp cells (whole vectors).  Gaussian erf factors are computed on the
    host: scipy's erf takes ~1 ms for the Lazuli cube, PoCL's double erf ~10 ms."""
    if kind == "full":
        if isinstance(psf, DevicePSF):
            if np.dtype(psf.dtype) == real:            # already on the device: no round trip
                return psf.buffer, _buffer("unused", 8)
            psf = psf.to_host()
        psf = np.ascontiguousarray(psf, real)
        return opencl.to_device(psf, _buffer("psf", psf.nbytes)), _buffer("unused", 8)
    fy, fx = psf.factors() if kind == "gaussian" else psf
    fx_padded = np.zeros((fx.shape[0], nxp), real)
    fx_padded[:, :fx.shape[1]] = fx
    return opencl.to_device(np.ascontiguousarray(fy, real)), opencl.to_device(fx_padded)


def _kernel_layout(layout, real):
    """(vector width, whole rows per work item) of the kernel launch; ``layout`` = (vector_width,
    row_per_item), None for the device's defaults."""
    vw, rows = layout
    rows = "GPU" not in opencl.device_type() if rows is None else bool(rows)
    vw = min(16, default_vector_width() * (2 if real.itemsize == 4 else 1) if vw is None else int(vw))
    if vw not in (1, 2, 4, 8, 16):
        raise ParameterError(f"vector_width must be 1, 2, 4, 8 or 16, got {vw}")
    return vw, rows


def _detector_block_opencl(chunk, kind, ro, out, layout=(None, None), precision="double"):
    """The fused kernel over ``out`` = (signal, variance), in launches of ≤ :data:`_LAUNCH_BYTES`."""
    signal, variance = out
    real = real_dtype(precision)
    if signal.dtype == np.float64 and real == np.float32 and not opencl.device_supports_fp64():
        tmp = (np.empty(signal.shape, np.float32), np.empty(signal.shape, np.float32))   # no double stores
        _detector_block_opencl(chunk, kind, ro, tmp, layout, precision)
        signal[...], variance[...] = tmp
        return
    nc, ny, nx = signal.shape
    vw, rows = _kernel_layout(layout, real)
    options = (f"-DVW={vw}", f"-DOUT={'double' if signal.dtype == np.float64 else 'float'}",
               f"-DSEPARABLE={int(kind != 'full')}", f"-DHAS_POINT={int(kind is not None)}",
               f"-DHAS_HOST={int(chunk.host is not None)}", f"-DNTAPS={chunk.taps.size}") \
        + opencl.precision_options(precision)
    kern = _kernel(_KERNEL_FILE, "pointsource_cube", options)
    unused = _buffer("unused", 8)
    nvec = -(-nx // vw)                   # vectors per row
    d_a, d_b = (unused, unused) if kind is None else _psf_on_device(kind, chunk.psf, nvec * vw, real)
    host = None if chunk.host is None else np.ascontiguousarray(chunk.host, real)
    d_host = unused if host is None else opencl.to_device(host, _buffer("host", host.nbytes))
    d_rate = unused if chunk.rate is None else opencl.to_device(chunk.rate.astype(real))
    d_u, d_qe, d_w = (opencl.to_device(a.astype(real)) for a in (chunk.uniform, chunk.qe, chunk.taps))
    plane_bytes = signal.itemsize * ny * nx
    step = max(1, min(nc, _LAUNCH_BYTES // (2 * plane_bytes)))    # output planes per launch
    zero_copy = _host_memory_device()
    if not zero_copy:
        d_s, d_v = _buffer("signal", step * plane_bytes), _buffer("variance", step * plane_bytes)
    per_item = nvec if rows else 1        # CPU: a whole row per work item; GPU: one vector (cell)
    i32, f64 = np.int32, real.type
    for c0 in range(0, nc, step):
        c1 = min(nc, c0 + step)
        if zero_copy:     # the kernel writes (and first-touches) the output arrays themselves
            d_s, d_v = opencl.host_buffer(signal[c0:c1]), opencl.host_buffer(variance[c0:c1])
        opencl.launch(kern, (-(-nvec // per_item), ny, c1 - c0), None, d_a, d_b, d_host, d_rate, d_u, d_qe,
                      d_w, i32(chunk.nl), i32(chunk.lo), i32(chunk.bins[0]), i32(c0), i32(ny), i32(nx),
                      i32(nvec * vw), i32(per_item),
                      f64(ro.signal_scale), f64(ro.var_a * ro.nramps), f64(ro.var_b * ro.nramps),
                      f64(ro.saturation_rate), d_s, d_v)
        if zero_copy:
            opencl.sync_to_host(d_s, signal[c0:c1])
            opencl.sync_to_host(d_v, variance[c0:c1])
        else:
            opencl.from_device(signal[c0:c1], d_s)
            opencl.from_device(variance[c0:c1], d_v)
