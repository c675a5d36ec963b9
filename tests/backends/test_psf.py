"""Point-source PSF cubes (slicersim.backends.psf, kernels/psf.cl): kernels vs
NumPy twins, and physics (flux, analytic limits, symmetry, scaling).

Tolerances
----------
* Gaussian, OpenCL vs NumPy: 1e-12 of the peak.  Both evaluate the same cell
  fractions in float64 from identical arguments z: ½[erf(b) − erf(a)] where an
  edge is within |z| < ½, erfc differences in the tails (no cancellation).  A
  cell's error is then ≲ 2 ulp of ½ near the centre (erf ≤ 2 ulp on the GPU,
  scipy's measured ≤ 1.2e-16 on |z| < ½) and r·erfc(a) in the tails, with r the
  relative error of erfc: scipy's grows like z² ulp for inexact z (measured ≤ 12
  ulp below z = 4, 130 below 16, 515 below 27; NVIDIA documents 4 ulp).
  Summed over both axes relative to the peak this bounds the difference at
  ≤ 1.1e-14 for the four cases (seed 3, a source off the field, peak 9e-6),
  measured ≤ 7.5e-16 on PoCL: 1e-12 leaves ~100× margin.  The former plain erf
  difference had 2.3e-12 of the peak against the exact value for seed 3 (both
  backends; 5.5e-12 between an H200 and NumPy), through cancellation near ±1.
* Gaussian tails (exact dyadic z, erfcx reference): 1e-14 relative per cell —
  erfc to a few ulp at exact arguments and a difference amplified ≤ 1.09×
  (measured 6.4e-16 NumPy, 3.9e-16 PoCL); the plain erf difference was 100 % off.
* Airy, OpenCL vs NumPy: 1e-11 of the peak.  The NumPy twin uses scipy's J1,
  the kernel its own J1 (series below 12, Hankel expansion above), measured
  |ΔJ1| <= 2e-12 on [0, 500]; intensities are g² with g <= 1, so the
  difference is ~1e-12 of the peak at most (measured ~2e-14).
* Physics checks state their own tolerance (quadrature error of the chosen
  oversampling, measured values in comments).
"""

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.special import erf, erfcx, j1

from conftest import reference_target
from slicersim.backends.psf import bessel_j1, psf_cells, psf_cube
from slicersim.backends.psf_opencl import gaussian_opencl
from slicersim.errors import ParameterError
from slicersim.physics.psf import (airy_encircled_energy, airy_intensity, airy_rectangle_fraction,
                           airy_wavenumber, aperture_cells, blur_bin_taps, gaussian_psf_fractions,
                           gaussian_psf_sigmas)

BACKENDS = ["numpy", pytest.param("opencl", marks=pytest.mark.needs_opencl)]

NARROW = dict(spatial_scale=0.04, guiding_sigma=0.010, instrumental_sigma=np.sqrt(2.3**2 - 4))
SHARP = dict(spatial_scale=0.04, guiding_sigma=0.0, instrumental_sigma=0.0)   # no jitter, no blur
SIGMA_REF = 1.22 * 1e-6 / 3.0 / (np.pi / 648000) * 0.8 / 2.35                 # 0.028555″


def peak_err(a, b):
    return np.max(np.abs(a - b)) / np.max(np.abs(b))


# --------------------------------------------------------------------------- kernels vs twins
@pytest.mark.needs_opencl
def test_bessel_j1_kernel_matches_scipy():
    x = np.concatenate([[0.0, 1e-300, 11.999999, 12.0, 12.000001],
                        np.linspace(0, 40, 40001), np.geomspace(1e-8, 1e6, 40001)])
    err = np.abs(bessel_j1(x, backend="opencl") - j1(x))
    assert err.max() <= 5e-12                      # measured 1.6e-12 (at x = 12)


@pytest.mark.needs_opencl
@pytest.mark.parametrize("seed", range(4))
def test_gaussian_kernel_matches_numpy(seed):
    rng = np.random.default_rng(seed)
    ny, nx = [(7, 13), (1, 5), (29, 3), (58, 116)][seed]
    lbda = np.sort(rng.uniform(3000, 18000, rng.integers(1, 40)))
    pos = tuple(rng.uniform(-0.7, 0.7, 2) * (nx, ny))
    kw = dict(sigma_ref_arcsec=rng.uniform(0.005, 0.1), spatial_scale=rng.choice([0.04, 0.08]),
              guiding_sigma=rng.uniform(0, 0.03), instrumental_sigma=rng.uniform(0, 2))
    got = psf_cube(lbda, (ny, nx), pos, "gaussian", backend="opencl", **kw)
    want = psf_cube(lbda, (ny, nx), pos, "gaussian", backend="numpy", **kw)
    sig = gaussian_psf_sigmas(lbda, kw["sigma_ref_arcsec"], kw["spatial_scale"], kw["guiding_sigma"],
                              kw["instrumental_sigma"])
    assert np.array_equal(want, gaussian_psf_fractions(*sig, (ny, nx), pos))
    assert peak_err(got, want) <= 1e-12


@pytest.mark.parametrize("backend", BACKENDS)
def test_gaussian_tail_fractions_relative_accuracy(backend):
    """Cells from 16 σ below to 32 σ above the source: each fraction to 1e-14 of itself (the
    plain ½[erf(b) − erf(a)] gives 0 or rounding noise beyond |z| ≈ 6).  √2σ = 1 exactly and
    the edges sit at quarters, so z = e − x0 and z² are exact; reference
    ½ e^{−a²} [erfcx(a) − e^{−(b−a)(b+a)} erfcx(b)] (mirrored below), erf difference in the middle."""
    sig = np.array([0.7071067811865475])
    assert np.sqrt(2.0) * sig[0] == 1.0
    n, x0 = 48, -8.25
    z = np.arange(n + 1) - n / 2 - x0
    a, b = z[:-1], z[1:]
    def tail(a, b):
        return 0.5 * np.exp(-a * a) * (erfcx(a) - np.exp(-(b - a) * (b + a)) * erfcx(b))
    with np.errstate(over="ignore", invalid="ignore"):
        ref = np.where(a >= 0.5, tail(a, b), np.where(b <= -0.5, tail(-b, -a), 0.5 * (erf(b) - erf(a))))
    ref = ref * erf(0.5)                       # the y factor of a 1-cell row centred on the source
    if backend == "opencl":
        got = gaussian_opencl(sig, sig, (1, n), (x0, 0.0), 2**20)[0, 0]
    else:
        got = gaussian_psf_fractions(sig, sig, (1, n), (x0, 0.0))[0, 0]
    normal = ref > 1e-290                      # beyond z ≈ 26.5 erfc is subnormal, then 0
    assert normal.sum() == 42
    assert np.max(np.abs(got[normal] - ref[normal]) / ref[normal]) <= 1e-14
    assert np.all((got[~normal] >= 0) & (got[~normal] < 1e-290))


@pytest.mark.slow
@pytest.mark.needs_opencl
@pytest.mark.parametrize("case", range(6))
def test_airy_kernel_matches_numpy(case):
    rng = np.random.default_rng(100 + case)
    shape = [(7, 13), (13, 7), (1, 1), (9, 31), (6, 10), (11, 5)][case]
    grid = ["exact", "gauss"][case % 2]
    o = [1, (2, 3), 3, (4, 1), 5, "auto"][case]
    eps = [0.0, 0.3, 0.0, 0.45, 0.0, 0.2][case]
    guiding = [0.01, 0.0, 0.004, 0.02, 0.08, 0.01][case]    # 0.08″ = 2 cells: unfused row path
    lbda = np.sort(rng.uniform(3500, 17500, [5, 3, 1, 7, 2, 70][case]))
    pos = (rng.uniform(-1, 1) * shape[1], rng.uniform(-1, 1) * shape[0])
    kw = dict(spatial_scale=0.04, guiding_sigma=guiding, instrumental_sigma=rng.uniform(0, 1.5),
              obscuration=eps, oversampling=o, grid=grid, diameter=rng.uniform(2, 4))
    got = psf_cube(lbda, shape, pos, "airy", backend="opencl", max_bytes=2**16, **kw)
    want = psf_cube(lbda, shape, pos, "airy", backend="numpy", **kw)
    assert got.shape == want.shape == (lbda.size,) + shape
    assert peak_err(got, want) <= 1e-11


@pytest.mark.slow
@pytest.mark.needs_opencl
@pytest.mark.parametrize("case", range(5))
def test_airy_kernel_symmetric_sources_match_numpy(case):
    """The kernels evaluate equal |dx|, |dy| once (mirror blocks, shared rows, mirrored
    output blocks): sources on symmetry points of even/odd fields, both grids, ε ≥ 0."""
    shape = [(58, 116), (9, 31), (10, 17), (1, 8), (12, 12)][case]
    pos = [(0.0, 0.0), (0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (-2.0, 1.0)][case]
    kw = dict(spatial_scale=0.04, guiding_sigma=[0.01, 0.01, 0.004, 0.02, 0.01][case],
              instrumental_sigma=[1.1, 0.7, 0.0, 1.3, 0.4][case], obscuration=[0.0, 0.3, 0.0, 0.0, 0.2][case],
              oversampling=[(4, 3), 3, (2, 5), (3, 2), 4][case], grid=["exact", "gauss"][case % 2])
    lbda = np.linspace(3700.0, 17000.0, [9, 4, 3, 5, 2][case])
    got = psf_cube(lbda, shape, pos, "airy", backend="opencl", max_bytes=2**18, **kw)
    want = psf_cube(lbda, shape, pos, "airy", backend="numpy", **kw)
    assert peak_err(got, want) <= 1e-11                   # measured ~1e-14


def test_mirror_and_shared_offset_maps():
    from slicersim.backends.psf_opencl import mirror_blocks, output_mirror_blocks, shared_rows
    d = np.arange(-8.0, 8.0) + 0.5                        # symmetric about 0: 4 blocks of 4
    blocks = mirror_blocks(d, 4)
    assert blocks.tolist() == [[0, 3], [1, 2]]
    assert np.array_equal(np.abs(d[4 * 3:4 * 4]), np.abs(d[0:4])[::-1])
    assert mirror_blocks(d + 0.1, 4)[:, 1].tolist() == [-1] * 4       # nothing mirrors
    code = shared_rows(np.array([-1.5, -0.5, 0.5, 1.5, 2.5]))
    assert code.tolist() == [0, 2, 3, 1, -1]              # rows 2, 3 read slots 1, 0
    taps = np.array([0.1, 0.4, 0.4, 0.1])
    assert output_mirror_blocks(0, 16, 16, 0.0, taps, 4).tolist() == [[0, 3], [1, 2]]
    assert output_mirror_blocks(0, 16, 16, 0.0, taps + [0, 0, 0, 1e-3], 4)[:, 1].tolist() == [-1] * 4


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("profile", ["gaussian", "airy"])
def test_psf_cells_equal_cube(profile, backend):
    lbda = np.linspace(4000, 17000, 9)
    pos = (0.31, -0.62)
    kw = dict(NARROW, sigma_ref_arcsec=SIGMA_REF, backend=backend)
    cube = psf_cube(lbda, (58, 116), pos, profile, **kw)
    for cells in (aperture_cells((58, 116), pos, 7.14), ([0, 57, 30], [115, 0, 58])):
        got = psf_cells(lbda, (58, 116), pos, cells, profile, **kw)
        assert np.abs(got - cube[:, cells[0], cells[1]]).max() <= 1e-15


@pytest.mark.parametrize("backend", BACKENDS)
def test_chunking_does_not_change_the_cube(backend):
    """OpenCL: every cell is computed by the same operations whatever the chunk
    (bit-identical); NumPy: BLAS may block the GEMMs differently (1e-15 of peak)."""
    lbda = np.linspace(4000, 17000, 11)
    a = psf_cube(lbda, (9, 14), (0.2, 0.1), "airy", backend=backend, **NARROW)
    b = psf_cube(lbda, (9, 14), (0.2, 0.1), "airy", backend=backend, max_bytes=1, **NARROW)
    if backend == "opencl":
        assert np.array_equal(a, b)
    else:
        assert peak_err(b, a) <= 1e-15


# --------------------------------------------------------------------------- analytic Airy
@pytest.mark.needs_opencl
def test_device_resident_cube_equals_host_cube():
    """psf_cube_device leaves the Airy cube on the device: bit-identical to psf_cube's OpenCL
    result for one launch and for one wavelength per launch (planes placed at their offsets, odd
    sizes), reusing a buffer; holds the flux of a small field (< 1, most of it); other profiles
    and the reference grid fall back to psf_cube's host arrays."""
    from slicersim.backends.psf import DevicePSF, psf_cube_device
    lbda = np.linspace(4000, 17000, 11)
    host = psf_cube(lbda, (9, 15), (0.2, 0.1), "airy", backend="opencl", **NARROW)
    dev = psf_cube_device(lbda, (9, 15), (0.2, 0.1), "airy", backend="opencl", **NARROW)
    assert isinstance(dev, DevicePSF) and dev.shape == host.shape
    assert np.array_equal(dev.to_host(), host)
    again = psf_cube_device(lbda, (9, 15), (0.2, 0.1), "airy", backend="opencl", max_bytes=1,
                            out_buffer=dev.buffer, **NARROW)
    assert again.buffer is dev.buffer and np.array_equal(again.to_host(), host)
    total = host.sum(axis=(1, 2))
    assert np.all(total < 1.0) and np.all(total > 0.5)
    gauss = psf_cube_device(lbda, (9, 15), (0.2, 0.1), "gaussian", sigma_ref_arcsec=SIGMA_REF, **NARROW)
    assert isinstance(gauss, np.ndarray)
    assert np.array_equal(gauss, psf_cube(lbda, (9, 15), (0.2, 0.1), "gaussian", sigma_ref_arcsec=SIGMA_REF,
                                          **NARROW))
    ref = psf_cube_device(lbda, (9, 15), (0.2, 0.1), "airy", grid="reference", oversampling=3, **NARROW)
    assert isinstance(ref, np.ndarray)


def test_encircled_energy_analytic_and_numerical():
    lbda, D = np.array([4000.0, 10000.0]), 3.0
    r = 1.22 * lbda * 1e-10 / D / (np.pi / 648000)                  # first dark ring [arcsec]
    assert airy_encircled_energy(r, lbda, D) == pytest.approx(0.8378, abs=1e-4)
    radii = np.array([0.01, 0.1, 0.5, 2.0])
    ana = airy_encircled_energy(radii, 5000.0, D, 0.0)
    num = airy_encircled_energy(radii, 5000.0, D, 1e-12)           # radial-integral path
    assert np.abs(ana - num).max() <= 1e-12
    # ε > 0 against scipy.integrate.quad of the intensity (independent quadrature)
    k = airy_wavenumber(5000.0, D, 1.0)                             # rad per arcsec
    for eps in (0.3, 0.6):
        ee = airy_encircled_energy(0.2, 5000.0, D, eps)
        ref = quad(lambda t: 2 * np.pi * t * airy_intensity(t, k, eps), 0, 0.2, limit=400,
                   epsabs=1e-13)[0]
        assert ee == pytest.approx(ref, abs=1e-10)
        # far wings: 1 − E(V) → 2 / (π V (1 − ε)) (ring-averaged J1² ≈ 1/(π v))
        V = k * 100.0
        assert 1 - airy_encircled_energy(100.0, 5000.0, D, eps) == pytest.approx(2 / (np.pi * V * (1 - eps)),
                                                                                 rel=1e-2)


@pytest.mark.slow
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("eps", [0.0, 0.3])
def test_airy_flux_in_big_field(eps, backend):
    """Σ P over a 61×121 field vs the exact flux in that rectangle (radial/angular
    quadrature of the encircled energy) and vs the encircled energy itself."""
    lbda = np.array([4000.0, 10000.0, 17000.0])
    shape = (61, 121)
    flux = psf_cube(lbda, shape, (0.0, 0.0), "airy", obscuration=eps, backend=backend, **SHARP).sum(axis=(1, 2))
    k = airy_wavenumber(lbda, 3.0, 0.04)
    rect = np.array([airy_rectangle_fraction(shape[1] / 2, shape[0] / 2, kk, eps) for kk in k])
    assert np.abs(flux - rect).max() <= 5e-7       # measured 6e-8 ("auto": (8, 8), no blur: O(1/o²))
    half = np.array(shape) / 2 * 0.04                                # half sides [arcsec]
    ee_in = airy_encircled_energy(half.min(), lbda, 3.0, eps)        # inscribed circle
    ee_out = airy_encircled_energy(np.hypot(*half), lbda, 3.0, eps)  # circumscribed circle
    assert np.all(ee_in - 1e-6 <= flux) and np.all(flux <= ee_out + 1e-6)
    # a big square field vs the encircled energy of the circle of the same area
    square = psf_cube(lbda, (101, 101), (0.0, 0.0), "airy", obscuration=eps, backend=backend,
                      **SHARP).sum(axis=(1, 2))
    ee_eq = airy_encircled_energy(101 * 0.04 / np.sqrt(np.pi), lbda, 3.0, eps)
    assert np.abs(square - ee_eq).max() <= 1e-3                      # measured 1.2e-4 / 6e-4


@pytest.mark.parametrize("backend", BACKENDS)
def test_psf_much_larger_than_field(backend):
    lbda = np.array([4000.0, 10000.0, 17000.0])
    shape, pos = (9, 15), (0.0, 0.0)
    # Gaussian σ = 5–21 cells over 9×15 cells: erf product of the field half-sizes
    kw = dict(sigma_ref_arcsec=SIGMA_REF, spatial_scale=0.002, guiding_sigma=0.0, instrumental_sigma=0.0)
    sig = SIGMA_REF * lbda / 1e4 / 0.002
    want = erf(7.5 / (np.sqrt(2) * sig)) * erf(4.5 / (np.sqrt(2) * sig))
    got = psf_cube(lbda, shape, pos, "gaussian", backend=backend, **kw).sum(axis=(1, 2))
    assert np.abs(got - want).max() <= 1e-14
    # Airy with R_Airy = 17–71 cells: flux in the rectangle (sub-cell rules: GL is
    # spectrally accurate for this smooth unblurred integrand, midpoint is O(1/o²))
    k = airy_wavenumber(lbda, 3.0, 0.002)
    want = np.array([airy_rectangle_fraction(7.5, 4.5, kk) for kk in k])
    for grid, o, tol in (("gauss", 4, 1e-12), ("exact", 15, 1e-5)):
        got = psf_cube(lbda, shape, pos, "airy", backend=backend, oversampling=o, grid=grid,
                       **dict(kw, sigma_ref_arcsec=None)).sum(axis=(1, 2))
        assert np.abs(got / want - 1).max() <= tol


@pytest.mark.slow
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("profile", ["gaussian", "airy"])
def test_source_on_the_field_edge_and_far_outside(profile, backend):
    lbda = np.array([4000.0, 10000.0, 17000.0])
    shape = (58, 116)
    # On the right edge: half of the flux in a 2nx × ny rectangle centred on the source.
    # Airy: blur along x only (perpendicular to that edge; the PSF is symmetric about it,
    # so what the blur takes out the margin must bring back in) and no blur at all.
    if profile == "airy":
        k = airy_wavenumber(lbda, 3.0, 0.04)
        half = np.array([0.5 * airy_rectangle_fraction(116, 29, kk) for kk in k])
        blur_x = dict(SHARP, instrumental_sigma=NARROW["instrumental_sigma"])
        for kw in (SHARP, blur_x):
            on_edge = psf_cube(lbda, shape, (58.0, 0.0), profile, backend=backend, **kw).sum(axis=(1, 2))
            assert np.abs(on_edge - half).max() <= 1e-6                 # measured 1.6e-7
    else:
        sy, sx = gaussian_psf_sigmas(lbda, SIGMA_REF, 0.04, 0.01, NARROW["instrumental_sigma"])
        half = 0.5 * erf(116 / (np.sqrt(2) * sx)) * erf(29 / (np.sqrt(2) * sy))
        on_edge = psf_cube(lbda, shape, (58.0, 0.0), profile, sigma_ref_arcsec=SIGMA_REF, backend=backend,
                           **NARROW).sum(axis=(1, 2))
        assert np.abs(on_edge - half).max() <= 1e-14
    assert np.all(np.abs(on_edge - 0.5) < 0.01)
    # far outside: ~0, finite and non-negative
    for pos in ((1000.0, 0.0), (-1e5, 3.0), (0.0, 2e3)):
        p = psf_cube(lbda, shape, pos, profile, sigma_ref_arcsec=SIGMA_REF, backend=backend, **NARROW)
        assert np.all(np.isfinite(p)) and p.min() >= 0 and p.sum(axis=(1, 2)).max() < 1e-5


@pytest.mark.slow
@pytest.mark.parametrize("backend", BACKENDS)
def test_oversampling_convergence_undersampled_psf(backend):
    """Narrow field at 4000 Å: R_Airy = 0.84 cells.  With the jitter the midpoint rule
    converges spectrally (the Airy pattern is band-limited and the Gaussian kernel
    damps the aliases): max error / peak vs o = 31, measured at (0.37, -0.21):
    o = 1: 0.26 (1.3 at (0, 0): o = 1 is wrong), 2: 1.7e-2, 3: 1.9e-4, 4: 3.6e-7,
    5: 8e-11, 6: 2e-15."""
    lbda = np.array([4000.0])
    for pos in ((0.0, 0.0), (0.37, -0.21)):
        oracle = psf_cube(lbda, (15, 17), pos, "airy", oversampling=31, backend=backend, **NARROW)
        err = [peak_err(psf_cube(lbda, (15, 17), pos, "airy", oversampling=o, backend=backend, **NARROW),
                        oracle) for o in range(1, 7)]
        assert err[0] > 0.1
        assert all(b < a for a, b in zip(err[:5], err[1:5]))
        assert err[2] < 1e-3 and err[3] < 1e-6 and err[5] < 1e-12


@pytest.mark.slow
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("field, scale, expected", [("narrow", 0.04, (4, 3)), ("wide", 0.08, (8, 4))])
def test_auto_oversampling(field, scale, expected, backend):
    """"auto" picks (o_y, o_x) per axis from the aliasing bound (< 1e-4 of the peak):
    few sub-samples along the strongly blurred x axis, more along y (jitter only)."""
    from slicersim.backends.psf import auto_oversampling
    kw = dict(NARROW, spatial_scale=scale)
    lbda = np.array([4000.0, 7000.0])
    assert auto_oversampling(lbda, **kw) == expected
    assert np.all(np.less(auto_oversampling([17000.0], **kw), expected))  # longer λ: fewer samples
    kw["backend"] = backend
    oracle = psf_cube(lbda, (15, 17), (0.37, -0.21), "airy", oversampling=31, **kw)
    auto = psf_cube(lbda, (15, 17), (0.37, -0.21), "airy", **kw)
    assert np.array_equal(auto, psf_cube(lbda, (15, 17), (0.37, -0.21), "airy", oversampling=expected, **kw))
    assert peak_err(auto, oracle) < 1e-5                               # measured 3e-7 / 7e-8


@pytest.mark.parametrize("backend", BACKENDS)
def test_blur_conserves_flux(backend):
    # the discrete blur-and-bin operator: every sub-sample's light is shared out completely
    for o, grid, sigma in ((1, "exact", 0.0), (3, "exact", 0.25), (4, "gauss", 1.16), (5, "exact", 3.3)):
        taps = blur_bin_taps(o, grid, sigma)
        assert taps.sum() == pytest.approx(1.0, abs=1e-15)
        assert taps.min() >= 0
    # a source in the centre of a 61×121 field at 4000 Å: jitter + blur move < 1e-6 of the flux
    # across the field edges (measured 1.8e-7)
    lbda = np.array([4000.0])
    sharp = psf_cube(lbda, (61, 121), (0.0, 0.0), "airy", oversampling=5, backend=backend, **SHARP).sum()
    blurred = psf_cube(lbda, (61, 121), (0.0, 0.0), "airy", oversampling=5, backend=backend, **NARROW).sum()
    assert abs(blurred / sharp - 1) <= 1e-6


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("profile", ["gaussian", "airy"])
def test_symmetry_of_a_centred_source(profile, backend):
    lbda = np.array([4000.0, 9000.0])
    p = psf_cube(lbda, (10, 14), (0.0, 0.0), profile, sigma_ref_arcsec=SIGMA_REF, backend=backend,
                 obscuration=0.2, **NARROW)
    scale = p.max()
    assert np.abs(p - p[:, ::-1, :]).max() <= 1e-14 * scale
    assert np.abs(p - p[:, :, ::-1]).max() <= 1e-14 * scale
    # with equal blur on both axes the square-field PSF is also symmetric under x <-> y
    q = psf_cube(lbda, (12, 12), (0.0, 0.0), profile, sigma_ref_arcsec=SIGMA_REF, backend=backend,
                 spatial_scale=0.04, guiding_sigma=0.01, instrumental_sigma=0.0)
    assert np.abs(q - q.transpose(0, 2, 1)).max() <= 1e-14 * q.max()


@pytest.mark.slow
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("profile", ["gaussian", "airy"])
def test_psf_width_scales_with_wavelength(profile, backend):
    """Without jitter or blur, the flux in a box of half-side a at λ equals that
    in a box of 2a at 2λ (cells of the same size)."""
    kw = dict(SHARP, spatial_scale=0.01, sigma_ref_arcsec=SIGMA_REF, backend=backend, grid="gauss",
              oversampling=8)
    for lbda, a in ((4500.0, 3), (6000.0, 4)):
        small = psf_cube([lbda], (2 * a, 2 * a), (0.0, 0.0), profile, **kw).sum()
        large = psf_cube([2 * lbda], (4 * a, 4 * a), (0.0, 0.0), profile, **kw).sum()
        assert small == pytest.approx(large, abs=1e-12)                # measured 1e-16
        assert 0.5 < small < 0.99


def test_bad_input():
    kw = dict(NARROW, sigma_ref_arcsec=SIGMA_REF)
    cases = [("moffat", {}, r"unknown profile 'moffat'"), ("airy", {"grid": "nearest"}, r"unknown grid 'nearest'"),
             ("airy", {"grid": "reference", "obscuration": 0.3}, "obscuration"),
             ("airy", {"grid": "reference", "backend": "opencl"}, "NumPy only"),
             ("airy", {"oversampling": 0}, "oversampling"), ("airy", {"obscuration": 1.0}, "obscuration"),
             ("airy", {"diameter": -3.0}, "diameter"), ("airy", {"spatial_scale": 0.0}, "spatial_scale"),
             ("airy", {"guiding_sigma": -0.1}, "guiding_sigma"), ("airy", {"oversampling": "many"}, "oversampling"),
             ("airy", {"diamter": 3.0}, "unknown PSF keyword.*'diamter'")]
    for profile, extra, message in cases:
        with pytest.raises(ParameterError, match=message):
            psf_cube([5000.0], (4, 4), (0, 0), profile, **{**kw, **extra})
    with pytest.raises(ParameterError, match="lbda"):
        psf_cube([-5000.0], (4, 4), (0, 0), "airy", **kw)
    with pytest.raises(ParameterError, match="shape"):
        psf_cube([5000.0], (4, 0), (0, 0), "airy", **kw)
    with pytest.raises(ParameterError, match="position"):
        psf_cube([5000.0], (4, 4), (0, float("nan")), "airy", **kw)
    with pytest.raises(ParameterError, match="sigma_ref_arcsec"):
        psf_cube([5000.0], (4, 4), (0, 0), "gaussian", **NARROW)        # no sigma_ref
    with pytest.raises(ParameterError, match="needs spatial_scale"):
        psf_cube([5000.0], (4, 4), (0, 0), "airy", guiding_sigma=0.0, instrumental_sigma=0.0)
    with pytest.raises(ParameterError, match="cells must lie within"):
        psf_cells([5000.0], (4, 4), (0, 0), ([0, 4], [0, 0]), "airy", **kw)
    with pytest.raises(ParameterError, match="cells="):
        psf_cells([5000.0], (4, 4), (0, 0), None, "airy", **kw)


def test_optics_object_equals_keywords():
    """psf_cube(optics=PSFOptics(...)) is the keyword form; both forms at once are refused."""
    from slicersim.backends.psf import PSFOptics
    kw = dict(NARROW, sigma_ref_arcsec=SIGMA_REF)
    optics = PSFOptics(**kw)
    for profile in ("gaussian", "airy"):
        np.testing.assert_array_equal(psf_cube([5000.0, 9000.0], (6, 5), (0.3, -0.2), profile, optics=optics,
                                               backend="numpy"),
                                      psf_cube([5000.0, 9000.0], (6, 5), (0.3, -0.2), profile, backend="numpy", **kw))
    with pytest.raises(ParameterError, match="not both"):
        psf_cube([5000.0], (4, 4), (0, 0), "airy", optics=optics, diameter=2.0)


# --------------------------------------------------------------------------- slicersim 1.0 grid
REF_CASES = ["sn_z1.00_cbe_narrow_snr20", "sn_z1.00_cbe_wide_snr20", "sn_z1.00_eol_narrow_snr20"]


@pytest.mark.reference
@pytest.mark.parametrize("case", REF_CASES)
def test_reference_airy_cube(case, refdir, reference_case):
    """grid="reference" reproduces the reference's Airy cube slices and sums (cube =
    LSF[F f2p P + uniform] QE t_int g r) at its three slice wavelengths; only the
    ±5 bins the LSF mixes are computed.  Measured agreement 2.2e-8 of the peak
    (the reference's rounded h c, as for the Gaussian path)."""
    from slicersim.instrument.detector import readout_times
    meta, arr = reference_case(case)
    sim = reference_target(refdir, meta, arr, position=False).simulation
    tel, spec = sim.telescope, sim.spectrograph
    idx = np.array(meta["cube"]["slice_indices"])
    near = np.unique((idx[:, None] + np.arange(-6, 7)).ravel())
    psf = np.zeros((sim.lbda.size,) + spec.shape)
    psf[near] = psf_cube(sim.lbda[near], spec.shape, (0.0, 0.0), "airy", grid="reference", oversampling=3,
                         spatial_scale=spec.spatial_scale, guiding_sigma=tel.guiding_sigma,
                         instrumental_sigma=sim.instrumental_sigma, diameter=tel.diameter_ext)
    nmd, nramps = tuple(meta["cube"]["readout"]["nmd"]), meta["cube"]["readout"]["nramps"]
    tint = readout_times(nmd, sim.detector.tframe)["integration_time_per_ramp"]
    point = (sim.pointsource_flambda * sim.flambda_to_photon)[:, None, None] * psf
    uniform = (sim.background_photons + sim.thermal_photons)[:, None, None]
    cube = spec.apply_lsf(point + uniform, axis=0)[idx] * (sim.qe * tint * sim.detector.gain * nramps)[idx, None, None]
    ref_slices = arr["cube_airy_signal_slices_adu"]
    assert peak_err(cube, ref_slices) <= 1e-6
    ref_sum = arr["cube_airy_signal_sum_adu"]
    assert np.abs(cube.sum(axis=(1, 2)) - ref_sum[idx]).max() <= 1e-6 * ref_sum.max()
    # the reference Airy PSF holds more than 100 % of the flux (its sub-sample grid)
    assert np.all(psf[idx].sum(axis=(1, 2)) > 1.002)


def test_quadrature_thermal_and_lsf_arguments_are_parameter_errors():
    from slicersim.errors import ParameterError
    from slicersim.physics.lsf import check_sigma
    from slicersim.physics.psf import cell_quadrature
    from slicersim.physics.thermal import solid_angle_from_fratio
    with pytest.raises(ParameterError, match=r"unknown grid 'gaus' \(did you mean 'gauss'\?\); valid: 'exact', 'gauss'"):
        cell_quadrature(3, "gaus")
    with pytest.raises(ParameterError, match="oversampling must be an integer"):
        cell_quadrature(2.5)
    with pytest.raises(ParameterError, match=r"unknown optics geometry 'round'; valid: 'square', 'circular'"):
        solid_angle_from_fratio(3.0, "round")
    with pytest.raises(ParameterError, match="fratio"):
        solid_angle_from_fratio((0.0, 3.0))
    with pytest.raises(ParameterError, match="truncate must be"):
        check_sigma(1.0, 4, -1.0)
    with pytest.raises(ParameterError, match=r"sigma_bins \[bins\] must be ≥ 0"):
        check_sigma([1.0, -1.0], 2, 4.0)
    with pytest.raises(ParameterError, match="sigma_bins .*must be an array of real numbers"):
        check_sigma("wide", 2, 4.0)
