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
from slicersim.sources.galaxies import GalaxyModel
from slicersim.targets import LazuliGalaxy
from slicersim.targets import LazuliSupernova
from slicersim.targets import LazuliTarget
from slicersim.errors import ParameterError

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


LBDA = np.arange(2000.0, 40000.0, 10.0)


@pytest.fixture(scope="module")
def sn_host():
    return LazuliSupernova(0.5, host="sersic")


def _state(target):
    params = None if target.host_model is None else dict(target.host_model.params)
    return target.redshift, params, target.host, target.host_centre(), target.get_readout_config()


@pytest.mark.parametrize("pair", [dict(host__mag=20, host__magabs=-20), dict(host__offset=(0.1, 0), host__position=(1, 1)),
                                  dict(host__r_kpc=2, host__r_eff=0.3), dict(host__ellip=0.2, host__axis_ratio=0.5),
                                  dict(host__n=1, host__sersic_index=3), dict(host__theta=5, host__position_angle=9)])
def test_update_refuses_conflicting_host_parameters(sn_host, pair):
    before = _state(sn_host)
    with pytest.raises(ParameterError, match="not both"):
        sn_host.update(redshift=0.6, **pair)
    after = _state(sn_host)
    assert after[0] == before[0] and after[1] == before[1] and after[2] is before[2] and after[3] == before[3]
    with pytest.raises(ParameterError, match="not both"):           # the constructor's rule, the same
        GalaxyModel("sersic", **{k[len("host__"):]: v for k, v in pair.items()})


def test_update_checks_the_aperture_in_the_combined_state():
    g = LazuliGalaxy(0.5)
    with pytest.raises(ParameterError, match="extends beyond the field"):
        g.update(aperture="5-arcsec", redshift=0.6)
    assert (g.aperture, g.redshift) == ("1-arcsec", 0.5)
    # a kpc aperture that fits at z = 0.5 (0.49″) but not at z = 0.1 (1.65″ > 1.16″)
    k = LazuliGalaxy(0.5, aperture="3-kpc")
    r_eff = k.host.profile.r_eff
    with pytest.raises(ParameterError, match="extends beyond the field"):
        k.update(redshift=0.1)
    assert k.redshift == 0.5 and k.host.profile.r_eff == r_eff and k.simulation.redshift == 0.5
    assert np.all(np.isfinite(k.get_spectrum()[1]))                 # still usable
    k.update(redshift=0.1, aperture="1-kpc")                         # a fitting combination is accepted
    assert (k.aperture, k.redshift) == ("1-kpc", 0.1)
    np.testing.assert_array_equal(k.get_spectrum()[1],                # and is the one extracted
                                  k.get_spectrum(aperture="1-kpc", method="aperture")[1])


class _CountingCube:
    """An array-like cube counting its reads."""

    def __init__(self, array):
        self.array, self.shape, self.reads = array, array.shape, 0

    def __getitem__(self, key):
        self.reads += 1
        return self.array[key]


def test_cubesource_host_is_resampled_once_per_grid_position_redshift():
    rng = np.random.default_rng(3)
    counting = _CountingCube(rng.random((24, 40, 40)) * 1e-20)
    source = CubeSource(counting, np.linspace(3000.0, 20000.0, 24), 0.02, redshift=0.5)
    t = LazuliSupernova(0.5, host=source)
    counting.reads = 0
    first = t.get_scene_cubes()["host"]
    reads = counting.reads
    assert reads > 0
    t.get_spectrum(of_host=True, method="aperture", aperture="0.5-arcsec")
    t.get_spectrum()
    again = t.get_scene_cubes()["host"]
    t.get_cube(max_bytes=2 * 10**7, progress=False)                # chunks: parts of the cached grid
    assert counting.reads == reads                                  # no new resampling
    np.testing.assert_array_equal(again, first)
    t.update(redshift=0.6)
    t.get_scene_cubes()
    assert counting.reads > reads                                   # another redshift: resampled
    reads = counting.reads
    t.update(redshift=0.5)
    np.testing.assert_array_equal(t.get_scene_cubes()["host"], first)
    assert counting.reads == reads                                  # back: served from the cache
    t.update(position=(5.0, 0.0))                                   # the host follows: another placement
    t.get_scene_cubes()
    assert counting.reads > reads


def test_user_models_and_hosts_are_never_changed():
    m = GalaxyModel("sersic", r_eff=0.5)
    params = dict(m.params)
    LazuliSupernova(0.2, host=m)
    assert m.params == params and "r_kpc" not in m.params
    assert LazuliSupernova(1.0, host=m).host.profile.r_eff == 0.5    # r_eff at the redshift it is used at
    host = Host(SersicProfile(1.0, 0.3, 0.8, 10.0, offset=(0.1, 0.0)), LBDA, np.full(LBDA.size, 3e-17))
    t = LazuliSupernova(0.5, host=host, position=(5.0, 2.0))
    t.update(position=(-3.0, 1.0), redshift=0.7)
    assert host.profile.offset == (0.1, 0.0) and host.profile.r_eff == 0.3
    cube = CubeSource(np.full((5, 8, 8), 1e-20), np.linspace(3000.0, 20000.0, 5), 0.05, centre=(0.2, 0.0))
    LazuliSupernova(0.5, host=cube, position=(4.0, 0.0))
    assert cube.centre == (0.2, 0.0)


def test_hosts_outside_the_field_negative_light_and_conflicts(sn_host):
    for host in ({"refmodel": "sersic", "offset": (100, 100)}, {"refmodel": "sersic", "position": (1e9, 0)}):
        with pytest.raises(ParameterError, match="light in the field"):
            LazuliSupernova(0.5, host=host)
    with pytest.raises(ParameterError, match="light in the field"):
        LazuliSupernova(0.5, host=CubeSource(np.ones((3, 4, 4)) * 1e-20, [3000.0, 9000.0, 20000.0], 0.05,
                                             centre=(30.0, 0.0)))
    before = _state(sn_host)
    with pytest.raises(ParameterError, match="light in the field"):
        sn_host.update(host__offset=(100.0, 0.0))
    assert _state(sn_host)[1:4] == before[1:4]
    # never negative: a compact Gaussian host (the exact integration cancels to −5e-17 far out)
    host = Host(SersicProfile(0.5, 0.1), LBDA, np.full(LBDA.size, 3e-17))
    assert host.flux_cube(LBDA[1000:1002], (58, 116), 0.04).min() >= 0
    assert SersicProfile(2.0, 0.8, offset=(100.0, 100.0)).cell_fractions((58, 116), 0.04).min() >= 0
    target = LazuliTarget(LBDA, np.full(LBDA.size, 1e-18), redshift=0.5, host=host)
    assert target.get_scene_cubes(unit="photon")["host"].min() >= 0
    # a dict's redshift must agree with the target's; a temperature given twice must agree
    with pytest.raises(ParameterError, match="redshift 3 but the target is at 0.5"):
        LazuliSupernova(0.5, host={"refmodel": "sersic", "redshift": 3.0})
    assert LazuliSupernova(0.5, host={"refmodel": "sersic", "redshift": 0.5}).host.redshift == 0.5
    with pytest.raises(ParameterError, match="6000 K black body but temperature=8000"):
        LazuliSupernova(0.5, host={"refmodel": "sersic:bb-6000", "temperature": 8000})
    assert GalaxyModel("sersic:bb-6000", temperature=6000).params["temperature"] == 6000
    assert GalaxyModel("sersic:bb-6000").updated(refmodel="sersic:bb-7000").params["temperature"] == 7000


def test_the_host_is_seen_in_both_fields():
    # 1.4.2's layout: the narrow field (2.32″ high) sits 0.06″ above the wide one (4.64″ high), so a
    # round host 3.54″ below the narrow field's centre is centred on the wide field
    dy = 4.64 / 2 + 0.06 + 2.32 / 2
    t = LazuliSupernova(0.5, host={"refmodel": "sersic", "offset": (0.0, -dy), "axis_ratio": 1.0, "r_kpc": 8.0})
    bare = LazuliSupernova(0.5)
    wide = t.get_field_rate_cubes()["wide"][0]
    wide_bare = bare.get_field_rate_cubes()["wide"][0]
    host = wide - wide_bare
    assert host.min() >= 0 and host.sum() > 0.01 * wide_bare.sum()      # the host lights the wide field
    np.testing.assert_allclose(host[:, ::-1, :], host, rtol=1e-9, atol=1e-12 * host.max())   # centred there
    np.testing.assert_allclose(host[:, :, ::-1], host, rtol=1e-9, atol=1e-12 * host.max())


def test_host_and_aperture_defaults_follow_1_4_2():
    """scenes_vs_142 finding: get_spectrum(of_host=True) used the PSF-weighted "core" fit (91.6–98.8 %
    low against 1.4.2's 1-arcsec sum), and method="aperture" summed the core radius, not 1"."""
    import numpy as np

    import slicersim as S
    sn = S.LazuliSupernova(0.5, host="sersic:bb-5000")
    host_default = sn.get_spectrum(of_host=True)[1]
    host_sum = sn.get_spectrum(of_host=True, aperture="1-arcsec", method="aperture")[1]
    np.testing.assert_array_equal(host_default, host_sum)
    assert not np.allclose(host_default, sn.get_spectrum(of_host=True, aperture="core")[1])
    np.testing.assert_array_equal(sn.get_spectrum(method="aperture")[1],
                                  sn.get_spectrum(method="aperture", aperture="1-arcsec")[1])
    np.testing.assert_array_equal(sn.get_spectrum()[1], sn.simulation.get_spectrum()[1])   # the ETC's
