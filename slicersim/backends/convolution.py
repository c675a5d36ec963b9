"""LSF along λ and 2-D convolution of cube planes: OpenCL kernels and NumPy/SciPy twins.

* :func:`apply_lsf` — Gaussian line-spread function along the wavelength axis,
  σ in bins, constant or varying with λ (kernel ``kernels/lsf.cl``).
* :func:`convolve_cube` — linear 2-D convolution of every λ-plane of a cube with
  its own (or a shared) PSF kernel, direct (``kernels/convolve.cl``) or by FFT
  (own mixed-radix 2/3/4/5 Stockham FFT, ``kernels/fft.cl``).

Every function takes ``backend="auto" | "opencl" | "numpy"`` (see
:func:`slicersim.backends.band_variance.resolve_backend`).  Non-finite input raises
:class:`ValueError`: callers validate spectra and cubes, a NaN would otherwise
spread over the LSF or PSF footprint (or, with the FFT, the whole plane).
"""
from __future__ import annotations

import numpy as np
import scipy.ndimage
import scipy.sparse

from slicersim import validation
from slicersim.backends import opencl
from slicersim.backends.dispatch import DEFAULT_MAX_BYTES, chunk_ranges, resolve_backend
from slicersim.backends.precision import check_precision, real_dtype, resolve_precision
from slicersim.errors import ParameterError
from slicersim.physics import lsf

__all__ = ["apply_lsf", "convolve_cube", "choose_convolution_method",
           "fft_good_size", "fft_radix_plan", "FFT_COST_PER_DIRECT_TAP"]

#: FFT batches on CPU devices: a few MiB of planes stay in cache between the passes
#: (measured on PoCL, 2 cores: 4–8 MiB batches ~2× faster than one 256 MiB batch)
CPU_FFT_CHUNK_BYTES = 8 * 2**20


def _finite_array(values, name):
    """``values`` as a float64 array with no NaN/inf (ParameterError naming ``name``: a NaN would
    spread over the convolution footprint)."""
    a = validation.array(name, values, finite=False)
    if not np.all(np.isfinite(a)):
        raise ParameterError(f"{name} contains {np.count_nonzero(~np.isfinite(a))} NaN/inf value(s); "
                             "validate the input first (NaN would spread over the convolution footprint)")
    return a


# --------------------------------------------------------------------------- #
#  line-spread function along λ                                                #
# --------------------------------------------------------------------------- #
def _band_form(M):
    """(band (n, bw), jlo (n,), nband (n,)) of a CSR matrix whose rows are all non-empty
    (true for LSF matrices: bin k always keeps part of its own content)."""
    n = M.shape[0]
    indptr, idx = M.indptr, M.indices
    jlo, jhi = idx[indptr[:-1]], idx[indptr[1:] - 1]
    nband = (jhi - jlo + 1).astype(np.int32)
    band = np.zeros((n, max(1, int(nband.max()))))
    row = np.repeat(np.arange(n), np.diff(indptr))
    band[row, idx - jlo[row]] = M.data
    return band, jlo.astype(np.int32), nband


def apply_lsf(values, sigma_bins, axis=0, truncate=4.0, backend="auto", *, max_bytes=DEFAULT_MAX_BYTES,
              precision="auto"):
    """Gaussian LSF along ``axis`` (λ) of ``values`` (a spectrum or a (nλ, ny, nx) cube).

    sigma_bins : float or (nλ,) array, Gaussian σ [bins].
        A float reproduces ``scipy.ndimage.gaussian_filter1d(values, σ, axis,
        mode="reflect", truncate=truncate)`` (weights exp(−k²/2σ²), |k| ≤
        int(truncate σ + 0.5), normalised; edges reflected … x1 x0 | x0 x1 …).
        An array gives σ per input bin in the flux-conserving scatter form of
        :func:`lsf_matrix` (each input bin spreads its content with its own σ;
        edge reflections folded back), so the sum over λ is conserved exactly.
        For a constant σ both forms are the same matrix.  σ = 0 returns the
        input; σ much larger than the spectrum folds repeatedly and tends to a
        flat spectrum with the same total.
    precision : "auto", "double" or "single" (OpenCL kernel in float32: ≤ 1e-5 of the peak against
        double, :mod:`slicersim.backends.precision`); the result is float64 either way.
    Raises ParameterError (a ValueError) on NaN/inf values and negative or non-finite σ.
    """
    check_precision(precision)
    x = _finite_array(values, "values")
    if x.ndim == 0:
        raise ParameterError("values must have at least one dimension")
    axis = validation.integer("axis", axis, low=-x.ndim, high=x.ndim - 1) % x.ndim
    n = x.shape[axis]
    sig = lsf.check_sigma(sigma_bins, n, truncate)
    constant = np.ndim(sigma_bins) == 0
    if n == 0 or x.size == 0 or not np.any(sig > 0):
        return x.copy()
    backend, precision = resolve_precision(precision, backend, "lsf")
    if backend == "numpy":
        return lsf.apply_lsf(x, sig[0] if constant else sig, axis=axis, truncate=truncate)
    moved = np.moveaxis(x, axis, 0)
    x2 = np.ascontiguousarray(moved.reshape(n, -1))
    out = _lsf_opencl(x2, lsf.lsf_matrix(sig, n, truncate), max_bytes, precision)
    return np.moveaxis(out.reshape(moved.shape), 0, axis)


def _lsf_opencl(x2, M, max_bytes, precision="double"):
    real = real_dtype(precision)
    if real == np.float64:
        opencl.require_fp64()
    size = real.itemsize
    n, npix = x2.shape
    band, jlo, nband = _band_form(M)
    VW = opencl.preferred_vector_width(16 if size == 4 else 8, 8 // size)
    step = max(VW, int(max_bytes // (2 * size * n)) // VW * VW)
    step = min(step, -(-npix // VW) * VW)
    kern = opencl.get_kernel("lsf.cl", "lsf_band_apply", (f"-DVW={VW}",) + opencl.precision_options(precision))
    d_band, d_jlo, d_nb = opencl.to_device(band.astype(real)), opencl.to_device(jlo), opencl.to_device(nband)
    d_x, d_out = opencl.device_buffer(size * n * step), opencl.device_buffer(size * n * step)
    out = np.empty_like(x2)
    for p0 in range(0, npix, step):
        p1 = min(npix, p0 + step)
        cp = -(-(p1 - p0) // VW) * VW
        h = np.zeros((n, cp), real)
        h[:, :p1 - p0] = x2[:, p0:p1]
        opencl.to_device(h, d_x)
        opencl.launch(kern, (cp // VW, n), None, d_x, d_band, d_jlo, d_nb,
                      np.int32(cp), np.int32(band.shape[1]), d_out)
        opencl.from_device(h, d_out)
        out[:, p0:p1] = h[:, :p1 - p0]
    return out


# --------------------------------------------------------------------------- #
#  2-D convolution of cube planes                                              #
# --------------------------------------------------------------------------- #
def fft_good_size(n):
    """Smallest integer ≥ n whose prime factors are 2, 3 and 5."""
    n = max(1, int(n))
    best = 1 << (n - 1).bit_length()
    p5 = 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            m = p35
            while m < n:
                m *= 2
            best = min(best, m)
            p35 *= 3
        p5 *= 5
    return best


def fft_radix_plan(n):
    """Radices (4, 2, 3, 5) whose product is n (n must be 2^a 3^b 5^c)."""
    plan = []
    for r in (4, 2, 3, 5):
        while n % r == 0:
            plan.append(r)
            n //= r
    if n != 1:
        raise ValueError("FFT length must have only the prime factors 2, 3, 5")  # internal: n from fft_good_size
    return plan


#: FFT cost per padded pixel per pass, in units of one direct multiply-add (median fit
#: of benchmarks/convolution_speed.py on the 525 × 58 × 116 Lazuli cube, process CPU
#: time, 2-core EPYC VM): PoCL 20 (crossover: direct up to k = 15–17, FFT from k = 19),
#: SciPy 4.1 (crossover k = 7).  GPUs were not measured; they use the OpenCL value.
FFT_COST_PER_DIRECT_TAP = {"opencl": 20.0, "numpy": 4.1}


def choose_convolution_method(plane_shape, kernel_shape, backend="auto"):
    """"direct" or "fft" from a cost model: direct ∝ ny nx ky kx,
    FFT ∝ Ny Nx (n_passes + 2) with (Ny, Nx) the padded transform size; the ratio of
    the two unit costs is :data:`FFT_COST_PER_DIRECT_TAP` (measured crossover)."""
    (ny, nx), (ky, kx) = plane_shape, kernel_shape
    Ny, Nx = fft_good_size(ny + ky - 1), fft_good_size(nx + kx - 1)
    passes = len(fft_radix_plan(Ny)) + len(fft_radix_plan(Nx))
    direct = ny * nx * ky * kx
    fft = FFT_COST_PER_DIRECT_TAP[resolve_backend(backend)] * Ny * Nx * (passes + 2)
    return "direct" if direct <= fft else "fft"


def _check_conv_inputs(cube, kernels):
    cube = _finite_array(cube, "cube")
    kernels = _finite_array(kernels, "kernels")
    if cube.ndim != 3:
        raise ParameterError(f"cube must have shape (nλ, ny, nx), got {cube.shape}")
    if kernels.ndim not in (2, 3) or (kernels.ndim == 3 and kernels.shape[0] != cube.shape[0]):
        raise ParameterError(f"kernels must have shape (ky, kx) or ({cube.shape[0]}, ky, kx), got {kernels.shape}")
    ky, kx = kernels.shape[-2:]
    if ky % 2 == 0 or kx % 2 == 0:
        raise ParameterError(f"kernel sizes must be odd (centre at (ky//2, kx//2)), got {(ky, kx)}")
    return cube, kernels


def convolve_cube(cube, kernels, method="auto", backend="auto", *, max_bytes=DEFAULT_MAX_BYTES, precision="auto"):
    """Linear 2-D convolution of each λ-plane of ``cube`` with its PSF kernel.

    cube : (nλ, ny, nx) array (any units per cell).
    kernels : (nλ, ky, kx) per-plane kernels or one (ky, kx) kernel; odd sizes, centre
        at (ky//2, kx//2) (as scipy.ndimage.convolve and fftconvolve(mode="same")).
    method : "auto" (:func:`choose_convolution_method`), "direct" or "fft".
    precision : "auto", "double" or "single" kernels (:mod:`slicersim.backends.precision`; single:
        ≤ 1e-5 of each plane's peak against double); the result is float64 either way.
    Returns (nλ, ny, nx): out[l, y, x] = Σ_ab K[l, a, b] cube[l, y + ky//2 − a,
    x + kx//2 − b], zero outside the field (flux leaving the field is lost; a
    normalised kernel conserves the flux of sources far enough from the edges).
    """
    cube, kernels = _check_conv_inputs(cube, kernels)
    validation.choice("method", method, ("auto", "direct", "fft"))
    backend, precision = resolve_precision(precision, backend, "convolution")
    if method == "auto":
        method = choose_convolution_method(cube.shape[1:], kernels.shape[-2:], backend)
    if cube.size == 0:
        return cube.copy()
    if backend == "numpy":
        return (_direct_numpy if method == "direct" else _fft_numpy)(cube, kernels)
    if precision == "double":
        opencl.require_fp64()
    return (_direct_opencl if method == "direct" else _fft_opencl)(cube, kernels, max_bytes, precision=precision)


def _direct_numpy(cube, kernels):
    if kernels.ndim == 2:
        return scipy.ndimage.convolve(cube, kernels[None], mode="constant", cval=0.0)
    return np.stack([scipy.ndimage.convolve(p, k, mode="constant", cval=0.0)
                     for p, k in zip(cube, kernels)]) if len(cube) else cube.copy()


def _fft_numpy(cube, kernels):
    k = kernels if kernels.ndim == 3 else kernels[None]
    import scipy.signal            # here, not at import: scipy.signal (and scipy.stats) cost ~0.5 s per command
    return scipy.signal.fftconvolve(cube, k, mode="same", axes=(1, 2))


def _direct_opencl(cube, kernels, max_bytes, tiled=None, precision="double"):
    nl, ny, nx = cube.shape
    real = real_dtype(precision)
    size, opts = real.itemsize, opencl.precision_options(precision)
    ky, kx = kernels.shape[-2:]
    cy, cx = ky // 2, kx // 2
    kf = np.ascontiguousarray(kernels[..., ::-1, ::-1], real)
    kstride = ky * kx if kernels.ndim == 3 else 0
    dev = opencl.get_device()
    gpu = "GPU" in opencl.device_type(dev)
    TX = TY = 16
    fits = (TY + ky - 1) * (TX + kx - 1) * size <= int(dev.local_mem_size) - 1024
    tiled = (gpu if tiled is None else tiled) and fits   # local-memory tiles: GPUs only by default
    if tiled:
        VW = 1
        nyo, nxo = -(-ny // TY) * TY, -(-nx // TX) * TX
        kern = opencl.get_kernel("convolve.cl", "convolve_direct_tiled",
                                 (f"-DTX={TX}", f"-DTY={TY}", f"-DKY={ky}", f"-DKX={kx}") + opts)
    else:
        VW = 1 if gpu else opencl.preferred_vector_width(16 if size == 4 else 8, 8 // size)
        nyo, nxo = ny, -(-nx // VW) * VW
        kern = opencl.get_kernel("convolve.cl", "convolve_direct", (f"-DVW={VW}",) + opts)
    PY, PX = nyo + ky - 1, nxo + kx - 1
    per_plane = size * (2 * PY * PX + 2 * nyo * nxo + kstride)
    out = np.empty_like(cube)
    d_k = opencl.to_device(kf) if kstride == 0 else None
    for l0, l1 in chunk_ranges(nl, per_plane, max_bytes):
        b = l1 - l0
        P = np.zeros((b, PY, PX), real)
        # float32: each plane scaled to its peak first (fluxes of 1e-40 would underflow), undone below
        peak = np.ones(b) if size == 8 else _plane_peaks(cube[l0:l1])
        P[:, cy:cy + ny, cx:cx + nx] = cube[l0:l1] / peak[:, None, None]
        d_P = opencl.to_device(P)
        if kstride:
            d_k = opencl.to_device(np.ascontiguousarray(kf[l0:l1]))
        d_out = opencl.device_buffer(size * b * nyo * nxo)
        if tiled:
            opencl.launch(kern, (nxo, nyo, b), (TX, TY, 1), d_P, d_k, np.int32(PY), np.int32(PX),
                          np.int32(kstride), np.int32(nyo), np.int32(nxo), d_out)
        else:
            opencl.launch(kern, (nxo // VW, nyo, b), None, d_P, d_k, np.int32(ky), np.int32(kx),
                          np.int32(PY), np.int32(PX), np.int32(kstride), np.int32(nyo), np.int32(nxo), d_out)
        h = np.empty((b, nyo, nxo), real)
        opencl.from_device(h, d_out)
        out[l0:l1] = h[:, :ny, :nx] * peak[:, None, None] if size == 4 else h[:, :ny, :nx]
    return out


def _plane_peaks(planes):
    """max |plane| per plane (1 for an all-zero plane)."""
    peak = np.abs(planes).max(axis=(1, 2)) if planes.size else np.ones(len(planes))
    return np.where(peak > 0, peak, 1.0)


def _twiddles(n, precision="double"):
    """(cos 2πm/n, sin 2πm/n), m < n, computed in float64 and stored interleaved as real2
    (float64, or rounded once to float32 in single precision)."""
    twiddles = np.exp(2j * np.pi * np.arange(n) / n)
    return np.ascontiguousarray(twiddles.astype(np.complex64 if precision == "single" else np.complex128))


class _FFT2:
    """Batched 2-D complex FFT on device buffers (kernels/fft.cl): Stockham passes along
    the middle axis of (B, N, M) planes plus one transpose per 2-D transform.

    forward: (B, Ny, Nx) natural layout -> spectrum in transposed layout (B, Nx, Ny);
    inverse: transposed layout -> (B, Ny, Nx).  Both unnormalised."""

    def __init__(self, Ny, Nx, tiled_transpose=None, precision="double"):
        self.Ny, self.Nx = Ny, Nx
        self.sign = real_dtype(precision).type
        opts = opencl.precision_options(precision)
        self.plan_y, self.plan_x = fft_radix_plan(Ny), fft_radix_plan(Nx)
        self.tw_y, self.tw_x = (opencl.to_device(_twiddles(n, precision)) for n in (Ny, Nx))
        self.passes = {r: opencl.get_kernel("fft.cl", f"fft_pass_{r}", opts) for r in set(self.plan_y + self.plan_x)}
        if tiled_transpose is None:
            tiled_transpose = "GPU" in opencl.device_type()
        self.tiled = bool(tiled_transpose)
        self.tr = opencl.get_kernel("fft.cl", "transpose_tiled" if self.tiled else "transpose", opts)

    def _axis(self, src, dst, nplanes, N, M, plan, tw, s):
        p = 1
        for r in plan:
            opencl.launch(self.passes[r], (M, N // r, nplanes), None, src, dst, tw,
                          np.int32(N), np.int32(p), np.int32(N // (p * r)), s, np.int32(M))
            src, dst, p = dst, src, p * r
        return src, dst

    def _transpose(self, src, dst, nplanes, N, M):
        if self.tiled:
            opencl.launch(self.tr, (-(-M // 16) * 16, -(-N // 16) * 16, nplanes), (16, 16, 1),
                          src, dst, np.int32(N), np.int32(M))
        else:
            opencl.launch(self.tr, (M, N, nplanes), None, src, dst, np.int32(N), np.int32(M))
        return dst, src

    def forward(self, src, dst, nplanes):
        """Returns (buffer holding the spectrum, other buffer)."""
        s = self.sign(-1.0)
        src, dst = self._axis(src, dst, nplanes, self.Ny, self.Nx, self.plan_y, self.tw_y, s)
        src, dst = self._transpose(src, dst, nplanes, self.Ny, self.Nx)
        return self._axis(src, dst, nplanes, self.Nx, self.Ny, self.plan_x, self.tw_x, s)

    def inverse(self, src, dst, nplanes):
        s = self.sign(1.0)
        src, dst = self._axis(src, dst, nplanes, self.Nx, self.Ny, self.plan_x, self.tw_x, s)
        src, dst = self._transpose(src, dst, nplanes, self.Nx, self.Ny)
        return self._axis(src, dst, nplanes, self.Ny, self.Nx, self.plan_y, self.tw_y, s)


def _fft_opencl(cube, kernels, max_bytes, tiled_transpose=None, precision="double"):
    nl, ny, nx = cube.shape
    real = real_dtype(precision)
    size, opts = real.itemsize, opencl.precision_options(precision)
    ky, kx = kernels.shape[-2:]
    Ny, Nx = fft_good_size(ny + ky - 1), fft_good_size(nx + kx - 1)
    kstride = ky * kx if kernels.ndim == 3 else 0
    fft = _FFT2(Ny, Nx, tiled_transpose, precision)
    pack = opencl.get_kernel("convolve.cl", "pack_planes", opts)
    mult = opencl.get_kernel("convolve.cl", "multiply_pairs", opts)
    crop = opencl.get_kernel("convolve.cl", "crop_pairs", opts)
    per_plane = 2 * 2 * size * Ny * Nx + 2 * size * ny * nx + size * kstride
    if "GPU" not in opencl.device_type():
        max_bytes = min(max_bytes, CPU_FFT_CHUNK_BYTES)
    chunks = list(chunk_ranges(nl, per_plane, max_bytes, multiple=2))
    Bmax = max(l1 - l0 for l0, l1 in chunks)
    Bmax += Bmax % 2
    i32 = np.int32
    out = np.empty_like(cube)
    d_k = opencl.to_device(np.ascontiguousarray(kernels, real)) if kstride == 0 else None
    # device buffers allocated once for the largest chunk (first touch is costly on CPUs)
    cbytes = 2 * size * Bmax * Ny * Nx
    buf_a, buf_b = opencl.device_buffer(cbytes), opencl.device_buffer(cbytes)
    d_img, d_out = opencl.device_buffer(size * Bmax * ny * nx), opencl.device_buffer(size * Bmax * ny * nx)
    kmax = np.abs(kernels).max(axis=(-2, -1)) if kernels.size else np.zeros(1)
    for l0, l1 in chunks:
        nb = l1 - l0
        B = nb + (nb % 2)
        img = np.ascontiguousarray(cube[l0:l1])
        # per-plane normalisation of both halves of the packed transform (see convolve.cl)
        amax = np.abs(img).max(axis=(1, 2))
        km = kmax[l0:l1] if kstride else np.full(nb, kmax)
        zero = (amax == 0) | (km == 0)                    # exact zeros out, not rounding noise
        amax, km = np.where(amax > 0, amax, 1.0), np.where(km > 0, km, 1.0)
        opencl.to_device(np.ascontiguousarray(img / amax[:, None, None], real) if size == 4 else img, d_img)
        if kstride:
            d_k = opencl.to_device(np.ascontiguousarray(kernels[l0:l1], real))
        inv_img = np.ones_like(amax) if size == 4 else 1.0 / amax   # float32: the image was scaled already
        d_inv = opencl.to_device(np.ascontiguousarray(np.stack([inv_img, 1.0 / km], axis=1), real))
        # float32: the image's scale is applied on the host (a 1e-40 plane must not underflow)
        d_scale = opencl.to_device(np.where(zero, 0.0, (amax if size == 8 else 1.0) * km / (Ny * Nx)).astype(real))
        opencl.launch(pack, (Nx, Ny, B), None, d_img, d_k, d_inv, i32(nb), i32(ny), i32(nx), i32(ky), i32(kx),
                      i32(kstride), i32(Ny), i32(Nx), buf_a)
        a, b = fft.forward(buf_a, buf_b, B)                  # spectra in (B, Nx, Ny) layout
        opencl.launch(mult, (Ny, Nx, B // 2), None, a, i32(Nx), i32(Ny), b)
        a, b = fft.inverse(b, a, B // 2)
        opencl.launch(crop, (nx, ny, B // 2), None, a, i32(nb), i32(ny), i32(nx), i32(ky // 2), i32(kx // 2),
                      i32(Ny), i32(Nx), d_scale, d_out)
        if real == np.float64:
            opencl.from_device(out[l0:l1], d_out)
        else:
            h = np.empty((nb, ny, nx), real)
            opencl.from_device(h, d_out)
            out[l0:l1] = h * amax[:, None, None]
    return out
