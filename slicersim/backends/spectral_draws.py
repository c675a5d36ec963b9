"""Random Fourier coefficients of Gaussian noise streams with a given PSD, for the correlated read
noise (:mod:`slicersim.backends.correlated_noise`): spectral amplitudes, FFT lengths and the
Philox/Box–Muller draws (``kernels/correlated_noise.cl`` ``spectral_coefficients`` and its NumPy twin).

Bin k of a length-L stream at cadence Δt gets X_k = a_k (z₀ + i z₁), a_k = √(L S(f_k) / (4Δt)),
f_k = k/(LΔt) (E|X_k|² = L S_k/(2Δt), so Var x = Σ S_k Δf), then ``scipy.fft.irfft``.
"""
from __future__ import annotations

import functools

import numpy as np

from slicersim import rng
from slicersim.backends import opencl

__all__ = ["stream_amplitudes", "fft_length", "spectral_coefficients_numpy", "spectral_coefficients_opencl"]

_VW = 16                    # Philox blocks per work item on CPUs (AVX-512 lanes of floats)


def stream_amplitudes(psd, length, dt, edge_bins=64, sub=32):
    """a_k = √(L S̄_k/(4Δt)) for the L//2 + 1 bins of a length-L stream at cadence Δt, with DC
    and (even L) Nyquist bins set to 0; ``psd``: callable f [Hz] → S [e-²/Hz].

    S̄_k is S averaged over the bin [f_k − Δf/2, f_k + Δf/2] (``sub`` midpoints) for the
    ``edge_bins`` bins next to 0 Hz and to Nyquist, where 1/f spectra (and ACN's mirrored one)
    change fast across a bin, so Σ S̄_k Δf is the model's integral (point samples lose up to
    ~0.4 e-fold of a pink spectrum's power there); S(f_k) elsewhere."""
    nb = length // 2 + 1
    df = 1.0 / (length * dt)
    f = np.arange(nb) * df
    s = np.asarray(psd(f), dtype=float)
    edge = np.unique(np.concatenate([np.arange(1, min(edge_bins, nb)), np.arange(max(1, nb - edge_bins), nb)]))
    offsets = (np.arange(sub) + 0.5) / sub - 0.5
    s[edge] = np.asarray(psd((edge[:, None] + offsets[None, :]) * df), dtype=float).mean(axis=1)
    amp = np.sqrt(np.maximum(s, 0.0) * length / (4.0 * dt))
    amp[0] = 0.0
    if length % 2 == 0:
        amp[-1] = 0.0
    return amp.astype(np.float32)


@functools.lru_cache(maxsize=64)
def fft_length(n):
    """Smallest 2ᵃ3ᵇ5ᶜ ≥ n: pocketfft runs these ≈ 1.5× faster than lengths with factors 7 or 11."""
    best, p5 = None, 1
    while p5 < 2 * n:
        p35 = p5
        while p35 < 2 * n:
            p = p35
            while p < n:
                p *= 2
            best = p if best is None else min(best, p)
            p35 *= 3
        p5 *= 5
    return best


def _padded(nbins, vw):
    return -(-nbins // vw) * vw


def spectral_coefficients_numpy(amp, kind, hi, stream, draw, seed):
    """complex64 (rows, nbins): X[r, k] = amp[kind[r], k]·√(−2 ln u)·e^{2πi v} (twin of the kernel).

    Bins 2b and 2b + 1 of row r use the Philox block (index = hi[r]·2³² + b, stream[r], draw[r]):
    u = (2(w ≫ 9) + 1)·2⁻²⁴ from words 0 and 2 (radii), words 1 and 3 (phases).  Float32
    arithmetic; the phase is evaluated in double and rounded (the kernel's cospi/sinpi are
    within 4 ulp of it).  amp: float32 (kinds, nbins); kind, hi, stream, draw: one uint per row."""
    amp = np.asarray(amp, np.float32)
    nbins = amp.shape[1]
    nblocks = -(-nbins // 2)
    out = np.empty((len(kind), 2 * nblocks), np.complex64)
    b = np.arange(nblocks, dtype=np.uint64)
    for r in range(len(kind)):
        w = rng.random_words(seed, (np.uint64(hi[r]) << np.uint64(32)) | b, int(stream[r]), int(draw[r]))
        u = ((w >> np.uint32(9)) * np.uint32(2) + np.uint32(1)).astype(np.float32) * np.float32(2.0**-24)
        rad = np.sqrt(np.float32(-2.0) * np.log(u[:, 0::2]))                   # (blocks, 2)
        phase = 2.0 * np.pi * u[:, 1::2].astype(np.float64)
        re = rad * np.cos(phase).astype(np.float32)
        im = rad * np.sin(phase).astype(np.float32)
        a = np.zeros(2 * nblocks, np.float32)
        a[:nbins] = amp[kind[r]]
        out[r].real = a * re.ravel()
        out[r].imag = a * im.ravel()
    return out[:, :nbins]


def spectral_coefficients_opencl(amp, kind, hi, stream, draw, seed, vector_width=None):
    """OpenCL twin of :func:`spectral_coefficients_numpy` (within a few float ulps); returns
    complex64 (rows, padded bins): bins past nbins are padding (``irfft(n=L)`` crops them)."""
    dev_gpu = "GPU" in opencl.device_type(opencl.get_device())
    vw = 1 if dev_gpu else (_VW if vector_width is None else int(vector_width))
    amp = np.asarray(amp, np.float32)
    nb = _padded(amp.shape[1], 2 * vw)
    amp_p = np.zeros((amp.shape[0], nb), np.float32)
    amp_p[:, :amp.shape[1]] = amp
    rows = len(kind)
    out = np.empty((rows, nb), np.complex64)
    key = rng.seed_to_key(seed)
    kern = opencl.cached_kernel("correlated_noise.cl", "spectral_coefficients", (f"-DFVW={vw}",))
    bufs = [opencl.to_device(np.ascontiguousarray(a, np.uint32)) for a in (kind, hi, stream, draw)]
    d_amp = opencl.to_device(amp_p)
    zero_copy = not dev_gpu                     # CPU devices write the host array in place
    d_out = opencl.host_buffer(out) if zero_copy else opencl.scratch_buffer("cn_coeff", out.nbytes)
    opencl.launch(kern, (nb // (2 * vw), rows), None, d_amp, *bufs, np.uint32(nb), np.uint32(key[0]),
                  np.uint32(key[1]), d_out)
    if zero_copy:
        opencl.sync_to_host(d_out, out)
    else:
        opencl.from_device(out, d_out)
    return out
