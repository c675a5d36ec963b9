"""LSF along λ and 2-D convolution of cube planes: OpenCL kernels vs NumPy/SciPy twins,
plus physics (flux conservation, moments, edge losses).

Tolerances
----------
* LSF, constant σ, vs ``scipy.ndimage.gaussian_filter1d``: 1e-12 of the peak (the
  requirement).  Same weights; the folded matrix merges reflected taps before the
  sum, so only the summation order differs (a few ulp × ≤ 2r+1 terms).
* LSF flux: Σ_λ conserved to 1e-12 relative (columns of the LSF matrix sum to 1 to
  ~1 ulp; sums of ≤ 525 positive terms).
* Convolution vs the float64 oracle ``scipy.ndimage.convolve`` (direct sum): 1e-12 of
  the peak.  Direct kernels only reorder/contract (FMA) ≤ 61² products; the FFT path
  (own mixed-radix FFT, float64) has errors ~ε log N relative to the plane's largest
  values, measured ≤ 3e-15 here.
* Flux conservation / moments of a convolution: 1e-12 (sums of positive terms).
"""
import numpy as np
import pytest
import scipy.ndimage

from slicersim.backends import convolution as cc
from slicersim.physics import lsf

BACKENDS = ["numpy", pytest.param("opencl", marks=pytest.mark.needs_opencl)]


def peak_error(a, b):
    return np.abs(a - b).max() / np.abs(b).max()


# --------------------------------------------------------------------------- #
#  LSF                                                                         #
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("n, sigma, pix", [(525, 1.15, (3, 5)), (51, 2.7, (7,)), (50, 1000.0, (2, 3)),
                                           (1, 1.5, (4,)), (9, 0.3, (1, 1)), (13, 6.0, ())])
def test_lsf_constant_sigma_equals_gaussian_filter1d(backend, n, sigma, pix):
    x = np.random.default_rng(n).random((n,) + pix)
    ref = scipy.ndimage.gaussian_filter1d(x, sigma, axis=0, mode="reflect", truncate=4.0)
    out = cc.apply_lsf(x, sigma, backend=backend)
    assert peak_error(out, ref) <= 1e-12
    assert np.allclose(out.sum(axis=0), x.sum(axis=0), rtol=1e-12, atol=0)   # reflect conserves flux


@pytest.mark.parametrize("backend", BACKENDS)
def test_lsf_axis_argument(backend):
    x = np.random.default_rng(3).random((6, 37))
    ref = scipy.ndimage.gaussian_filter1d(x, 1.7, axis=-1, mode="reflect")
    assert peak_error(cc.apply_lsf(x, 1.7, axis=-1, backend=backend), ref) <= 1e-12


def scatter_reference(x, sigma, truncate=4.0):
    """Literal flux-conserving scatter with reflect folding (plain Python)."""
    n = len(x)
    out = np.zeros_like(x)
    for j in range(n):
        r = int(truncate * sigma[j] + 0.5)
        ms = range(-r, r + 1)
        w = [1.0 if m == 0 else np.exp(-0.5 * (m / sigma[j]) ** 2) for m in ms]
        tot = sum(w)
        for m, wm in zip(ms, w):
            t = (j + m) % (2 * n)
            k = t if t < n else 2 * n - 1 - t
            out[k] += x[j] * wm / tot
    return out


@pytest.mark.parametrize("backend", BACKENDS)
def test_lsf_varying_sigma_conserves_flux_and_matches_definition(backend):
    rng = np.random.default_rng(7)
    n = 61
    sigma = np.concatenate([np.zeros(5), rng.uniform(0.2, 3.0, n - 15), np.full(10, 40.0)])
    x = rng.random((n, 3, 4))
    out = cc.apply_lsf(x, sigma, backend=backend)
    ref = np.apply_along_axis(scatter_reference, 0, x, sigma)
    assert peak_error(out, ref) <= 1e-12
    assert np.allclose(out.sum(axis=0), x.sum(axis=0), rtol=1e-12, atol=0)
    cols = np.asarray(lsf.lsf_matrix(sigma, n).sum(axis=0)).ravel()
    assert np.abs(cols - 1).max() <= 1e-13


def test_lsf_constant_sigma_scatter_equals_gather_everywhere():
    """For constant σ the flux-conserving matrix is symmetric: the two forms coincide,
    edges included."""
    M = lsf.lsf_matrix(np.full(40, 2.3), 40).toarray()
    assert np.abs(M - M.T).max() <= 1e-16
    x = np.random.default_rng(1).random((40, 2))
    ref = scipy.ndimage.gaussian_filter1d(x, 2.3, axis=0, mode="reflect")
    assert peak_error(M @ x, ref) <= 1e-12


@pytest.mark.parametrize("backend", BACKENDS)
def test_lsf_line_width_and_limits(backend):
    n = 201
    x = np.zeros(n)
    x[100] = 1.0
    for sigma in (1.15, 3.0):
        out = cc.apply_lsf(x, sigma, backend=backend)
        k = np.arange(n) - 100.0
        assert abs(out.sum() - 1) < 1e-14 and abs((k * out).sum()) < 1e-13
        r = int(4 * sigma + 0.5)                                  # truncated discrete Gaussian
        m = np.arange(-r, r + 1)
        w = np.exp(-0.5 * (m / sigma) ** 2)
        assert abs((k**2 * out).sum() - (m**2 * w).sum() / w.sum()) < 1e-12
        assert abs((k**2 * out).sum() / sigma**2 - 1) < 1e-3      # ≈ σ² (tails beyond 4σ: 5e-4)
    # σ → 0: identity, no NaN
    y = np.random.default_rng(2).random((n, 2))
    for s0 in (0.0, 1e-300, 0.05):
        assert np.array_equal(cc.apply_lsf(y, s0, backend=backend), y)
    assert np.array_equal(cc.apply_lsf(y, np.zeros(n), backend=backend), y)
    # σ ≫ spectrum: repeated folding tends to a flat spectrum, flux conserved
    z = np.random.default_rng(4).random(50)
    flat = cc.apply_lsf(z, 1000.0, backend=backend)
    assert abs(flat.sum() / z.sum() - 1) < 1e-12 and np.ptp(flat) / flat.mean() < 1e-4
    flat_v = cc.apply_lsf(z, np.full(50, 1000.0), backend=backend)
    assert abs(flat_v.sum() / z.sum() - 1) < 1e-12


def test_lsf_rejects_bad_input():
    x = np.ones((5, 2))
    with pytest.raises(ValueError, match="NaN"):
        cc.apply_lsf(np.array([1.0, np.nan, 2.0]), 1.0)
    with pytest.raises(ValueError, match="sigma"):
        cc.apply_lsf(x, -1.0)
    with pytest.raises(ValueError, match="sigma"):
        cc.apply_lsf(x, np.ones(4))
    with pytest.raises(ValueError, match="sigma"):
        cc.apply_lsf(x, np.array([1, 1, np.nan, 1, 1.0]))


# --------------------------------------------------------------------------- #
#  2-D convolution                                                             #
# --------------------------------------------------------------------------- #
def oracle(cube, kernels):
    k = kernels if kernels.ndim == 3 else np.broadcast_to(kernels, (len(cube),) + kernels.shape)
    return np.stack([scipy.ndimage.convolve(p, kk, mode="constant", cval=0.0) for p, kk in zip(cube, k)])


CASES = [((3, 7, 9), (3, 5), False), ((4, 13, 11), (7, 3), True), ((5, 29, 58), (21, 21), False),
         ((1, 1, 1), (1, 1), False), ((2, 5, 3), (9, 11), False), ((7, 30, 25), (61, 5), False),
         ((2, 29, 47), (61, 59), True), ((5, 17, 19), (5, 5), False)]


@pytest.mark.slow
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("method", ["direct", "fft"])
@pytest.mark.parametrize("shape, kshape, shared", CASES)
def test_convolution_matches_oracle(backend, method, shape, kshape, shared):
    rng = np.random.default_rng(sum(shape) + sum(kshape))
    cube = rng.random(shape)
    k = rng.random(kshape) if shared else rng.random((shape[0],) + kshape)
    out = cc.convolve_cube(cube, k, method=method, backend=backend)
    assert out.shape == cube.shape
    assert peak_error(out, oracle(cube, k)) <= 1e-12


@pytest.mark.slow
@pytest.mark.needs_opencl
def test_convolution_chunks_and_local_memory_tiles():
    rng = np.random.default_rng(5)
    cube, k = rng.random((9, 23, 37)), rng.random((9, 7, 9))
    ref = oracle(cube, k)
    for method in ("direct", "fft"):   # chunks of one or two planes
        assert peak_error(cc.convolve_cube(cube, k, method=method, backend="opencl", max_bytes=1), ref) <= 1e-12
    # the GPU local-memory kernels (direct tiles, tiled transpose), run on whatever device is present
    assert peak_error(cc._direct_opencl(cube, k, cc.DEFAULT_MAX_BYTES, tiled=True), ref) <= 1e-12
    assert peak_error(cc._fft_opencl(cube, k, cc.DEFAULT_MAX_BYTES, tiled_transpose=True), ref) <= 1e-12


@pytest.mark.parametrize("backend", BACKENDS)
def test_fft_keeps_precision_for_tiny_and_disparate_planes(backend):
    """Physical cubes are ~1e-20 erg/s/cm²/Å per cell while kernels are ~0.1, and
    neighbouring planes can differ by many orders of magnitude: the packed two-for-one
    transforms must still give errors relative to each plane's own peak."""
    rng = np.random.default_rng(11)
    cube = rng.random((5, 21, 34)) * np.array([1e-20, 1.0, 1e-30, 1e5, 0.0])[:, None, None]
    k = rng.random((5, 9, 7)) * np.array([0.1, 1e-8, 3.0, 1.0, 1.0])[:, None, None]
    out = cc.convolve_cube(cube, k, method="fft", backend=backend)
    ref = oracle(cube, k)
    for p in range(4):
        assert peak_error(out[p], ref[p]) <= 1e-12
    assert np.all(out[4] == 0)


def gaussian_kernel(sig_y, sig_x, size):
    a = np.arange(size) - size // 2
    k = np.exp(-0.5 * (a[:, None] / sig_y) ** 2 - 0.5 * (a[None, :] / sig_x) ** 2)
    return k / k.sum()


def moments(img):
    y, x = np.indices(img.shape)
    f = img.sum()
    my, mx = (img * y).sum() / f, (img * x).sum() / f
    return f, my, mx, (img * (y - my) ** 2).sum() / f, (img * (x - mx) ** 2).sum() / f


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("method", ["direct", "fft"])
def test_convolution_conserves_flux_and_adds_variances(backend, method):
    """Normalised PSF, source well inside: flux conserved, centroid kept, variances add."""
    ny, nx = 58, 116
    src = np.zeros((2, ny, nx))
    src[0, 29, 40] = 3.0                                   # point source
    src[1, 20:35, 60:75] = gaussian_kernel(1.3, 2.1, 15)   # extended source
    ker = np.stack([gaussian_kernel(2.0, 1.5, 21), np.pad(gaussian_kernel(1.1, 2.4, 17), 2)])
    out = cc.convolve_cube(src, ker, method=method, backend=backend)
    for p in range(2):
        f0, my0, mx0, vy0, vx0 = moments(src[p])
        f1, my1, mx1, vy1, vx1 = moments(out[p])
        _, _, _, ky, kx = moments(ker[p])
        assert abs(f1 / f0 - 1) < 1e-12
        assert abs(my1 - my0) < 1e-10 and abs(mx1 - mx0) < 1e-10
        assert abs(vy1 - (vy0 + ky)) < 1e-9 and abs(vx1 - (vx0 + kx)) < 1e-9


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("method", ["direct", "fft"])
def test_convolution_loses_exactly_the_flux_leaving_the_field(backend, method):
    ny, nx, ky, kx = 20, 31, 9, 13
    k = np.random.default_rng(9).random((ky, kx))
    k /= k.sum()
    src = np.zeros((1, ny, nx))
    src[0, 0, 2] = 1.0                      # corner row, 2 cells from the left edge
    out = cc.convolve_cube(src, k, method=method, backend=backend)
    # delta at (0, 2): out[y, x] = K[y + ky//2, x − 2 + kx//2]; inside ⇔ a ≥ ky//2, b ≥ kx//2 − 2
    expected = k[ky // 2:, kx // 2 - 2:].sum()
    assert abs(out.sum() - expected) < 1e-14
    assert np.abs(out).sum() > 0 and expected < 0.7


def test_auto_method_crossover():
    shape = (58, 116)
    assert cc.choose_convolution_method(shape, (5, 5), "opencl") == "direct"
    assert cc.choose_convolution_method(shape, (61, 61), "opencl") == "fft"
    assert cc.choose_convolution_method(shape, (61, 61), "numpy") == "fft"
    assert cc.fft_good_size(118) == 120 and cc.fft_good_size(176) == 180 and cc.fft_good_size(1) == 1
    for n in (1, 2, 7, 97, 118, 1000):
        g = cc.fft_good_size(n)
        assert g >= n and int(np.prod(cc.fft_radix_plan(g))) == g
        assert all(cc.fft_good_size(m) != m for m in range(n, g))   # smallest such size


def test_convolution_rejects_bad_input():
    cube = np.ones((2, 5, 5))
    with pytest.raises(ValueError, match="odd"):
        cc.convolve_cube(cube, np.ones((4, 3)))
    with pytest.raises(ValueError, match="NaN"):
        cc.convolve_cube(np.where(cube > 0, np.nan, 0), np.ones((3, 3)))
    with pytest.raises(ValueError, match="kernels"):
        cc.convolve_cube(cube, np.ones((3, 3, 3)))
    with pytest.raises(ValueError, match="method"):
        cc.convolve_cube(cube, np.ones((3, 3)), method="spline")


def test_convolution_arguments_are_parameter_errors_naming_them():
    from slicersim.backends.convolution import apply_lsf as lsf_backend, convolve_cube
    from slicersim.errors import ParameterError
    cube = np.ones((2, 5, 5))
    with pytest.raises(ParameterError, match=r"unknown method 'fftw' \(did you mean 'fft'\?\); valid: 'auto', 'direct', 'fft'"):
        convolve_cube(cube, np.ones((3, 3)), method="fftw", backend="numpy")
    with pytest.raises(ParameterError, match="kernel sizes must be odd"):
        convolve_cube(cube, np.ones((2, 2)), backend="numpy")
    with pytest.raises(ParameterError, match="cube contains 1 NaN/inf"):
        convolve_cube(np.where(np.arange(50).reshape(2, 5, 5) == 7, np.nan, 1.0), np.ones((3, 3)), backend="numpy")
    with pytest.raises(ParameterError, match="axis must be an integer"):
        lsf_backend(np.ones(8), 1.0, axis=0.5, backend="numpy")
