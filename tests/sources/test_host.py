"""Extended sources: Sersic profiles integrated over cells, host spectra, user cubes.

Tolerances
----------
* Cell fractions of the Sersic profile (exact polar integration): 1e-12 per cell
  against the analytic n = 0.5 Gaussian (erf products); measured ≤ 3e-16.
* Totals: 1e-10 for the analytic normalisation (quad, relative tolerance 1e-11),
  analytic enclosed-flux bounds P(2n, x) for finite fields (strict inequalities).
* CubeSource: flux conserved to 1e-12 relative (sums of overlap fractions that add
  up to 1 per pixel); edge losses and λ interpolation exact to 1e-12.
"""
import math

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.special import erf, gammainc, gammaincinv

from slicersim.sources.extended import CubeSource, Host, SersicProfile, integrate_radial_cells, sersic_bn

NARROW = ((58, 116), 0.04)


def erf_fractions(edges, centre, sigma):
    return 0.5 * np.diff(erf((edges - centre) / (math.sqrt(2) * sigma)))


def edges(n, s):
    return (np.arange(n + 1) - n / 2) * s


def test_bn_definition():
    for n in (0.5, 1, 2.5, 4, 10):
        assert abs(gammainc(2 * n, sersic_bn(n)) - 0.5) < 1e-14
    assert abs(sersic_bn(1) - 1.678346990016661) < 1e-12
    assert abs(sersic_bn(4) - 7.669249442500804) < 1e-9
    assert abs(sersic_bn(0.5) - math.log(2)) < 1e-14


@pytest.mark.parametrize("n", [0.5, 1, 4])
def test_sersic_total_flux_is_one(n):
    p = SersicProfile(n, 0.3, axis_ratio=0.5, position_angle=30)
    total = quad(lambda r: p.radial_profile(r) * 2 * math.pi * p.axis_ratio * r, 0, np.inf,
                 limit=400, epsabs=0, epsrel=1e-11)[0]
    assert abs(total - 1) < 1e-10
    half = quad(lambda r: p.radial_profile(r) * 2 * math.pi * p.axis_ratio * r, 0, p.r_eff,
                epsabs=0, epsrel=1e-12)[0]
    assert abs(half - 0.5) < 1e-10                      # r_eff encloses half the light


@pytest.mark.parametrize("n", [0.5, 1, 4])
def test_cell_sums_within_analytic_ellipse_bounds(n):
    """Σ cells lies between the flux of the largest ellipse inside the field and of the
    smallest one containing it (both analytic: P(2n, b_n (a/r_e)^(1/n)))."""
    (ny, nx), s = NARROW
    p = SersicProfile(n, 1.0, axis_ratio=0.5, position_angle=30)
    total = p.cell_fractions((ny, nx), s).sum()
    th = math.radians(30)
    ex = math.sqrt(math.cos(th) ** 2 + (0.5 * math.sin(th)) ** 2)   # half-extents per unit a
    ey = math.sqrt(math.sin(th) ** 2 + (0.5 * math.cos(th)) ** 2)
    a_in = min(nx * s / 2 / ex, ny * s / 2 / ey)
    a_out = float(p.elliptical_radius(np.array([1, 1, -1, -1]) * nx * s / 2,
                                      np.array([1, -1, 1, -1]) * ny * s / 2).max())
    lo, hi = p.enclosed_fraction(a_in), p.enclosed_fraction(a_out)
    assert lo < total < hi
    assert hi - lo > 1e-4                                    # the bounds are informative


@pytest.mark.parametrize("n, tol", [(0.5, 1e-13), (1, 1e-13), (4, 1e-6)])
def test_cell_sum_tends_to_one_on_a_large_field(n, tol):
    """25″ × 25″ field (0.25″ cells) around r_eff = 0.05″: Σ → 1 (n = 4 keeps 6e-8 in its wings)."""
    p = SersicProfile(n, 0.05, axis_ratio=0.5, position_angle=30, offset=(0.013, -0.021))
    total = p.cell_fractions((101, 101), 0.25).sum()
    assert abs(total - 1) < tol
    # what is missing is at most the flux outside the inscribed ellipse
    assert 1 - total <= 1 - p.enclosed_fraction(50.4 * 0.25 * 0.5) + 1e-13


@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.013, 0.007), (0.02, 0.0), (2.3, -1.0)])
@pytest.mark.parametrize("r_eff", [0.004, 0.03, 1.0])
def test_n_half_is_the_analytic_gaussian(offset, r_eff):
    """n = 0.5: I ∝ exp(−ln2 (r/r_e)²), σ_major = r_e/√(2 ln 2), σ_minor = q σ_major."""
    (ny, nx), s = NARROW
    sig = r_eff / math.sqrt(2 * math.log(2))
    for pa, (sx, sy) in ((0.0, (sig, 0.4 * sig)), (90.0, (0.4 * sig, sig))):
        p = SersicProfile(0.5, r_eff, axis_ratio=0.4, position_angle=pa, offset=offset)
        ref = np.outer(erf_fractions(edges(ny, s), offset[1], sy), erf_fractions(edges(nx, s), offset[0], sx))
        assert np.abs(p.cell_fractions((ny, nx), s) - ref).max() < 1e-12


def test_position_angle_convention_and_symmetry():
    p0 = SersicProfile(4, 0.2, axis_ratio=0.3, position_angle=0)
    p90 = SersicProfile(4, 0.2, axis_ratio=0.3, position_angle=90)
    p180 = SersicProfile(4, 0.2, axis_ratio=0.3, position_angle=180)
    f0, f90 = p0.cell_fractions((40, 40), 0.04), p90.cell_fractions((40, 40), 0.04)
    assert np.abs(f90 - f0.T).max() < 1e-14               # 90° turns the image
    assert np.abs(p180.cell_fractions((40, 40), 0.04) - f0).max() < 1e-14
    y, x = np.indices(f0.shape) - 19.5
    assert (f0 * x**2).sum() > 3 * (f0 * y**2).sum()       # PA = 0: major axis along +x
    f = p0.cell_fractions((40, 40), 0.04)
    assert np.abs(f - f[::-1, ::-1]).max() < 1e-14         # centred source: point symmetry


def test_exact_integration_agrees_with_midpoint_sampling():
    """Independent check: plain midpoint sampling converges to the exact cell integrals."""
    shape, s = (24, 30), 0.04
    smooth = SersicProfile(1, 0.3, axis_ratio=0.6, position_angle=20, offset=(0.05, 0.011))
    exact = smooth.cell_fractions(shape, s)
    err16, err64 = (np.abs(smooth.cell_fractions(shape, s, oversampling=o) - exact).max() for o in (16, 64))
    assert err64 < 2e-7 and err16 / err64 > 10             # midpoint rule: O(h²)
    # n = 4 with r_eff = 0.2 cell: the cusp makes sampling converge slowly, but it converges
    cusp = SersicProfile(4, 0.008, axis_ratio=0.7, position_angle=20, offset=(0.0123, 0.0071))
    exact = cusp.cell_fractions(shape, s)
    errors = [np.abs(cusp.cell_fractions(shape, s, oversampling=o) - exact).max() for o in (8, 32, 128)]
    assert errors[0] > errors[1] > errors[2] and errors[2] < 0.25 * errors[0]
    assert abs(exact.sum() - cusp.enclosed_fraction(0.48 / 0.7)) < 0.01   # most flux in the field


def test_integrate_radial_cells_components():
    p = SersicProfile(1, 0.2)
    two = integrate_radial_cells(p.geometry, [p.radial_profile, lambda r: 2 * p.radial_profile(r)], *NARROW)
    assert np.abs(two[1] - 2 * two[0]).max() < 1e-15


def test_host_uniform_spectrum_flux_cube():
    lbda = np.linspace(3000.0, 18000.0, 151)
    flux = 1e-17 * (1 + (lbda - 3000) / 15000)              # linear: interpolation exact
    p = SersicProfile(1, 0.1, axis_ratio=0.7, position_angle=10)
    host = Host(p, lbda, flux)
    grid = np.linspace(4000.0, 17000.0, 17) + 3.3
    cube = host.flux_cube(grid, (101, 101), 0.2)             # 20″ field: all the flux
    assert cube.shape == (17, 101, 101)
    expected = 1e-17 * (1 + (grid - 3000) / 15000)
    assert np.allclose(cube.sum(axis=(1, 2)), expected, rtol=1e-10, atol=0)
    frac = p.cell_fractions((101, 101), 0.2)
    assert np.allclose(cube, expected[:, None, None] * frac, rtol=1e-14, atol=0)
    with pytest.raises(ValueError, match="beyond"):
        host.flux_cube([2000.0, 5000.0], (5, 5), 0.04)


def test_host_radially_varying_spectrum():
    lbda = np.array([3000.0, 20000.0])
    core, outs = np.array([2.0, 2.0]), np.array([1.0, 1.0])
    p = SersicProfile(2, 0.15, axis_ratio=0.8, position_angle=45, offset=(0.02, 0.0))
    host = Host(p, lbda, core, flux_outskirts=outs, blend_radius=0.1)
    W = host.core_weight()
    # independent W: Sersic n = 2 written out here (b_n from gammaincinv, not sersic_bn), the
    # elliptical area element cancels in the ratio; W = ∫ I e^{−r/r_b} r dr / ∫ I r dr
    b2 = gammaincinv(4.0, 0.5)
    prof = lambda r: math.exp(-b2 * (math.sqrt(r / 0.15) - 1.0)) * r          # noqa: E731
    top = quad(lambda r: prof(r) * math.exp(-r / 0.1), 0, np.inf, limit=400, epsabs=0, epsrel=1e-12)[0]
    bottom = quad(prof, 0, np.inf, limit=400, epsabs=0, epsrel=1e-12)[0]
    assert W == pytest.approx(top / bottom, rel=1e-8)
    assert 0.1 < W < 0.9
    big = host.flux_cube([5000.0, 9000.0], (101, 101), 0.5)  # 50″ field: nothing lost
    assert np.allclose(big.sum(axis=(1, 2)), 2 * W + 1 * (1 - W), rtol=1e-10, atol=0)
    cube = host.flux_cube([5000.0], (61, 61), 0.04)
    frac = p.cell_fractions((61, 61), 0.04)
    ratio = cube[0] / frac                                   # local spectrum in units of F_out
    assert 1.5 < ratio[30, 30] < 2.0                          # core-dominated centre
    assert ratio[30, 60] < 1.05                               # outskirts spectrum 1.2″ out
    assert np.all(np.diff(ratio[30, 31:]) < 0)                # monotonic blend along x


def test_sersic_rejects_bad_parameters():
    for kw in ({"sersic_index": 0.0, "r_eff": 1}, {"sersic_index": 1, "r_eff": -1},
               {"sersic_index": 1, "r_eff": 1, "axis_ratio": 1.5}):
        with pytest.raises(ValueError):
            SersicProfile(**kw)


# --------------------------------------------------------------------------- #
#  user cubes                                                                  #
# --------------------------------------------------------------------------- #
def random_cube(seed=1, shape=(12, 17, 23)):
    rng = np.random.default_rng(seed)
    return rng.random(shape), np.linspace(4000.0, 9000.0, shape[0])


@pytest.mark.parametrize("rotation", [0.0, 33.0, 90.0, 217.0])
def test_cube_fully_inside_conserves_flux(rotation):
    cube, lb = random_cube()
    src = CubeSource(cube, lb, 0.05, centre=(0.1, -0.2), rotation=rotation)
    out = src.flux_cube(lb, *NARROW)                          # same λ grid: no interpolation
    assert out.shape == (12, 58, 116)
    assert np.allclose(out.sum(axis=(1, 2)), cube.sum(axis=(1, 2)), rtol=1e-12, atol=0)
    assert out.min() >= 0


def test_cube_straddling_the_edge_loses_exactly_the_outside_part():
    """Input pixels 0.05″, field edge x = −2.32″ cuts column 3 of the cube at 1/4 of its width."""
    cube, lb = random_cube(2)
    nxi = cube.shape[2]
    p = 0.05
    left = -2.32 - 3.25 * p                                  # left edge of input column 0
    cx = left + nxi * p / 2
    for rotation in (0.0, 1e-12):                             # separable and polygon paths
        out = CubeSource(cube, lb, p, centre=(cx, 0.0), rotation=rotation).flux_cube(lb, *NARROW)
        expected = cube[:, :, 4:].sum(axis=(1, 2)) + 0.75 * cube[:, :, 3].sum(axis=1)
        assert np.allclose(out.sum(axis=(1, 2)), expected, rtol=1e-12, atol=0)


def test_cube_rotation_by_90_degrees_is_exact_and_counter_clockwise():
    cube, lb = random_cube(3)
    a = CubeSource(np.rot90(cube, -1, axes=(1, 2)), lb, 0.05, centre=(0.1, -0.2)).flux_cube(lb, *NARROW)
    b = CubeSource(cube, lb, 0.05, centre=(0.1, -0.2), rotation=90).flux_cube(lb, *NARROW)
    assert np.abs(a - b).max() < 1e-13 * a.max()


def test_rotated_pixel_overlaps_are_exact_areas():
    """One pixel of side 0.04″ rotated by 45° around a cell corner: a diamond shared
    equally by four cells; centred on a cell it overlaps the four edge neighbours by
    triangles of area (0.04√2/2 − 0.02)²."""
    one = np.ones((2, 1, 1))
    lb = np.array([5000.0, 6000.0])
    out = CubeSource(one, lb, 0.04, centre=(0.0, 0.0), rotation=45).flux_cube([5500.0], (4, 4), 0.04)[0]
    assert np.abs(out[1:3, 1:3] - 0.25).max() < 1e-14 and abs(out.sum() - 1) < 1e-14
    out = CubeSource(one, lb, 0.04, centre=(0.02, 0.02), rotation=45).flux_cube([5500.0], (4, 4), 0.04)[0]
    tri = (0.04 * math.sqrt(2) / 2 - 0.02) ** 2 / 0.04**2
    assert abs(out[2, 2] - (1 - 4 * tri)) < 1e-14
    for j, k in ((1, 2), (3, 2), (2, 1), (2, 3)):
        assert abs(out[j, k] - tri) < 1e-14


def test_cube_wavelength_interpolation():
    nl = 9
    lb = np.linspace(5000.0, 7000.0, nl)
    cube = (lb[:, None, None] - 4000.0) * np.ones((nl, 3, 4))  # linear in λ
    grid = np.array([5000.0, 5123.4, 6999.0, 7000.0])
    out = CubeSource(cube, lb, 0.02).flux_cube(grid, (10, 10), 0.04)
    assert np.allclose(out.sum(axis=(1, 2)), 12 * (grid - 4000.0), rtol=1e-13, atol=0)
    with pytest.raises(ValueError, match="beyond"):
        CubeSource(cube, lb, 0.02).flux_cube([4999.0], (10, 10), 0.04)
    with pytest.raises(ValueError):
        CubeSource(np.full((2, 2, 2), np.nan), [1.0, 2.0], 0.04)
