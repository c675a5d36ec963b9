"""Galaxy targets and spectral extraction (issue 10).

Physics checked (noiseless cubes built by ``Simulation.get_cube``)
-------------------------------------------------------------------
* isolated point source: the aperture sum equals the point-source light in the cube × the
  enclosed-energy fraction EE = Σ_aperture P (3e-5 in the grid interior, 1e-3 at its edges,
  where the LSF mixes the PSFs of neighbouring bins; measured 7.7e-6 / 7.5e-4); optimal extraction is unbiased: exact
  (1e-12) with the cube's own profile as weights, and with the nominal PSF weights within
  5e-5 in the grid interior (the LSF mixes PSFs of neighbouring bins; 1e-3 at the grid edges);
* the model-level extraction (no cube) equals the same formulas applied to the cube (1e-9);
* units: ADU = flambda · f2p · QE · g · t_int · r, rate = ADU / exposure time;
* the galaxy ETC reaches its target and no cheaper readout would;
* bad input: one clear error each (unknown galaxy names list the known ones, negative Sersic
  index or radius, apertures beyond the field, a missing data package); a user cube larger than
  the memory budget is processed in blocks and gives the unchunked result.
"""
import sys
import tracemalloc

import numpy as np
import pytest

from slicersim.errors import ETCError, ParameterError
from slicersim.physics.psf import aperture_cells, gaussian_psf_cells
from slicersim.products.extraction import extract_aperture, extract_optimal, parse_aperture, unit_factors
from slicersim.sources.extended import CubeSource, ImageProfile, SersicProfile
from slicersim.sources.galaxies import GalaxyDataUnavailable, GalaxyModel
from slicersim.targets.base import LazuliTarget
from slicersim.targets.galaxy import LazuliGalaxy

LBDA = np.arange(3000.0, 20000.0, 10.0)


def has_galaxy_data():
    try:
        import lazuli_astrosim_data  # noqa: F401
        return True
    except ImportError:
        return False


def _scene_cube(sim, drop):
    """Noiseless signal and variance cubes, and the signal with component ``drop`` removed."""
    signal, variance = sim.get_cube(backend="numpy")[:2]
    saved = getattr(sim.scene, drop)
    setattr(sim.scene, drop, None)
    try:
        rest = sim.get_cube(backend="numpy")[0]
    finally:
        setattr(sim.scene, drop, saved)
    return signal - rest, variance


@pytest.fixture(scope="module")
def point():
    t = LazuliTarget(LBDA, 1e-17 * (LBDA / 6000.0) ** -1.0, position=(1.3, -0.6))
    t.change_detector(nmd=(16, 8, 0))
    cube, variance = _scene_cube(t.simulation, "pointsource")
    return t, cube, variance


def test_point_source_aperture_sum_is_the_enclosed_energy(point):
    t, cube, variance = point
    sim = t.simulation
    light = cube.sum(axis=(1, 2))                       # all the point-source light in the cube [ADU]
    for aperture, radius in (("core", sim.aperture_radius), ("0.1-arcsec", 0.1 / 0.04)):
        cells = aperture_cells(sim.spectrograph.shape, sim.position, radius)
        ee = gaussian_psf_cells(*sim.psf_sigmas, sim.spectrograph.shape, sim.position, cells).sum(axis=1)
        s, v = extract_aperture(cube, variance, cells)
        err = np.abs(s / (ee * light) - 1)                 # the LSF mixes PSFs of neighbouring bins
        assert err[10:-10].max() < 3e-5 and err.max() < 1e-3
        assert np.all(s <= light * (1 + 1e-12))
        _, s_model, v_model = t.get_spectrum(method="aperture", aperture=aperture)
        np.testing.assert_allclose(s_model, s, rtol=1e-9)
        np.testing.assert_allclose(v_model, v, rtol=1e-9)
    assert 0.5 < ee.min() < 0.9 and ee.max() <= 1               # 0.1″ loses a measurable part


def test_point_source_optimal_extraction_is_unbiased(point):
    t, cube, variance = point
    sim = t.simulation
    light = cube.sum(axis=(1, 2))
    cells = sim.aperture
    own = cube[:, cells[0], cells[1]] / light[:, None]           # the cube's own profile
    s_exact, _ = extract_optimal(cube, variance, own, cells)
    np.testing.assert_allclose(s_exact, light, rtol=1e-12)
    weights = gaussian_psf_cells(*sim.psf_sigmas, sim.spectrograph.shape, sim.position, cells)
    s, v = extract_optimal(cube, variance, weights, cells)
    bias = s / light - 1
    assert np.max(np.abs(bias[10:-10])) < 5e-5 and np.max(np.abs(bias)) < 1e-3
    _, s_sim, v_sim = t.get_spectrum()                            # Simulation.get_spectrum
    np.testing.assert_allclose(v_sim, v, rtol=1e-12)


def test_units_convert_adu_consistently(point):
    t = point[0]
    sim = t.simulation
    times = sim.get_times()
    _, adu, var = t.get_spectrum()
    _, flam, var_f = t.get_spectrum(unit="flambda")
    np.testing.assert_allclose(flam * sim.flambda_to_photon * sim.qe * sim.detector.gain * times["integration_time"],
                               adu, rtol=1e-12)
    np.testing.assert_allclose(var_f, var * unit_factors(sim, "flambda") ** 2, rtol=1e-12)
    _, rate, _ = t.get_spectrum(unit="adu/s")
    # ADU/s per second of integration time: the slope a ramp fit measures, as the reduced spectra
    # (per second of exposure time it was 6.7 % lower at (16, 8, 0) than the reduction's rates)
    np.testing.assert_allclose(rate * times["integration_time"], adu, rtol=1e-12)
    _, fph, _ = t.get_spectrum(unit="fphoton")
    np.testing.assert_allclose(fph, flam * sim.flambda_to_photon, rtol=1e-12)
    # the optimal flambda is the input spectrum (through the LSF) in the grid interior
    inside = slice(30, -30)
    np.testing.assert_allclose(flam[inside], sim.pointsource_flambda[inside], rtol=2e-3)
    with pytest.raises(ParameterError, match="unknown unit"):
        t.get_spectrum(unit="jansky")


@pytest.fixture(scope="module")
def galaxy():
    g = LazuliGalaxy(0.5, model="sersic:bb-5000", aperture="1-arcsec", band="bessellr", position=(2.0, -1.0))
    g.change_detector(nmd=(16, 8, 0))
    return g


def test_galaxy_extraction_equals_the_cube_formulas(galaxy):
    sim = galaxy.simulation
    assert sim.scene.pointsource is None and galaxy.method == "aperture"
    cube, variance = _scene_cube(sim, "host")
    centre = galaxy.host_centre()
    assert centre == pytest.approx((2.0, -1.0))
    cells = aperture_cells(sim.spectrograph.shape, centre, 1 / 0.04)
    s, v = extract_aperture(cube, variance, cells)
    _, s_model, v_model = galaxy.get_spectrum()
    np.testing.assert_allclose(s_model, s, rtol=1e-9)
    np.testing.assert_allclose(v_model, v, rtol=1e-9)
    weights = gaussian_psf_cells(*sim.psf_sigmas, sim.spectrograph.shape, centre, cells)
    s_opt, v_opt = extract_optimal(cube, variance, weights, cells)
    _, s_model, v_model = galaxy.get_spectrum(method="optimal")
    np.testing.assert_allclose(s_model, s_opt, rtol=1e-9)
    np.testing.assert_allclose(v_model, v_opt, rtol=1e-9)
    # the 1″ aperture holds most, not all, of the galaxy (r_eff = 0.79″ at z = 0.5)
    _, flam, _ = galaxy.get_spectrum(unit="flambda")
    frac = flam[100:400] / galaxy.host.total_flux(sim.lbda[100:400])
    assert np.all((0.5 < frac) & (frac < 0.75))


def test_galaxy_apertures_and_kpc_scale(galaxy):
    assert parse_aperture("2-kpc") == ("kpc", 2.0) and parse_aperture(" 0.5-arcsec") == ("arcsec", 0.5)
    _, s1, _ = galaxy.get_spectrum()
    _, s2, _ = galaxy.get_spectrum(aperture="2-kpc")
    _, core, _ = galaxy.get_spectrum(aperture="core")
    assert np.all(s2[50:-50] < s1[50:-50]) and np.all(core[50:-50] < s2[50:-50])
    # 2 kpc = 0.318″ at z = 0.5: a 0.318-arcsec aperture is the same cells
    from slicersim.sources.cosmology import arcsec_per_kpc
    _, s3, _ = galaxy.get_spectrum(aperture=f"{2 * arcsec_per_kpc(0.5):.12f}-arcsec")
    np.testing.assert_allclose(s2, s3, rtol=1e-12)
    with pytest.raises(ParameterError, match="no point source"):
        galaxy.get_spectrum(of_host=False)


def test_galaxy_etc_reaches_the_target_with_the_cheapest_readout():
    g = LazuliGalaxy(0.5, aperture="2-kpc")
    res = g.setup_to_snr(5)
    assert res["snr_per_resolution"] >= 5 and g.get_readout_config()["nmd"] == res["nmd"]
    assert g.get_band_snr(per_resolution=True) == pytest.approx(res["snr_per_resolution"], rel=1e-12)
    n, m, d = res["nmd"]
    if n > 2:                                   # one group fewer does not reach it
        g.change_detector(nmd=(n - 1, m, d), nramps=res["nramps"])
        assert g.get_band_snr(per_resolution=True) < 5
    budget = g.get_band_variance_contribution()
    assert budget["pointsource"] == 0 and budget["host"] > 0
    assert sum(budget[k] for k in ("dark", "roic_glow", "ron", "background", "host")) <= budget["variance"] * 1.01
    with pytest.raises(ETCError, match="exact"):
        g.setup_to_snr(5, search="reference")


def test_galaxy_update_redshift_and_aperture():
    g = LazuliGalaxy(0.5, aperture="2-kpc")
    r05 = g.host.profile.r_eff
    _, s05, _ = g.get_spectrum()
    g.update(redshift=1.0)
    assert g.host.redshift == 1.0 and g.host.profile.r_eff < r05
    _, s10, _ = g.get_spectrum()
    assert np.nanmax(s10) < np.nanmax(s05)
    g.update(aperture="core", method="default")
    assert g.method == "optimal"
    with pytest.raises(ParameterError, match="beyond the field"):
        g.update(aperture="1.5-arcsec")
    assert g.aperture == "core"


# --------------------------------------------------------------------------- bad input
def test_bad_input_one_clear_error_each():
    with pytest.raises(ParameterError, match="Sersic index must be > 0"):
        GalaxyModel("sersic", n=-1)
    with pytest.raises(ParameterError, match="half-light radius r_kpc must be > 0"):
        GalaxyModel("sersic", r_kpc=-3)
    with pytest.raises(ParameterError, match="Sersic index must be in"):
        SersicProfile(-1.0, 1.0)
    with pytest.raises(ParameterError, match="radius must be > 0"):
        SersicProfile(1.0, -0.5)
    with pytest.raises(ParameterError, match="beyond the field.*at most"):
        LazuliGalaxy(0.5, aperture="3-arcsec")
    with pytest.raises(ParameterError, match="'core', '<x>-arcsec' or '<x>-kpc'"):
        LazuliGalaxy(0.5, aperture="1-parsec")
    with pytest.raises(ParameterError, match="-arcsec"):
        parse_aperture("-1-arcsec")
    with pytest.raises(ParameterError, match="needs a redshift"):
        LazuliGalaxy(None)


@pytest.mark.skipif(not has_galaxy_data(), reason="lazuli-astrosim-data not installed")
def test_unknown_galaxy_names_list_the_known_ones():
    with pytest.raises(ParameterError, match=r"unknown galaxy 'ngc9999'; known: ngc0337, .*ngc0628"):
        GalaxyModel("sersic:ngc9999")
    with pytest.raises(ParameterError, match=r"spectrum only.*'sersic:ngc2403'.*known: ngc0337"):
        LazuliGalaxy(0.5, model="ngc2403")
    g = LazuliGalaxy(0.5, model="ngc4321", aperture="1-arcsec")
    _, s, _ = g.get_spectrum()
    assert np.all(s[50:-50] > 0)


def test_missing_data_package_is_named(monkeypatch):
    import slicersim.sources.galaxies as galaxies
    monkeypatch.setitem(sys.modules, "lazuli_astrosim_data", None)
    monkeypatch.setitem(sys.modules, "lazuli_astrosim_data.io", None)
    galaxies.known_galaxies.cache_clear()
    try:
        with pytest.raises(GalaxyDataUnavailable, match="lazuli-astrosim-data.*slicersim\\[galaxies\\]"):
            GalaxyModel("ngc0628")
        assert GalaxyModel("sersic:bb-4000").name == "sersic:bb-4000"     # the core needs nothing
    finally:
        galaxies.known_galaxies.cache_clear()


def test_host_larger_than_the_memory_budget_is_chunked(tmp_path):
    """A 48 MB memory-mapped user cube, 1 MB budget: same cube as in memory, small peak."""
    rng = np.random.default_rng(5)
    shape = (24, 500, 500)
    mm = np.lib.format.open_memmap(tmp_path / "cube.npy", mode="w+", dtype=np.float64, shape=shape)
    for k in range(shape[0]):
        mm[k] = rng.random(shape[1:]) * 1e-20
    mm.flush()
    lb = np.linspace(3000.0, 20000.0, shape[0])
    grid = LBDA[::40]
    whole = np.asarray(mm)
    for rotation in (0.0, 25.0):
        lazy = CubeSource(np.load(tmp_path / "cube.npy", mmap_mode="r"), lb, 0.02, centre=(0.3, -0.1),
                          rotation=rotation, max_bytes=2**20)
        tracemalloc.start()
        out = lazy.flux_cube(grid, (58, 116), 0.04)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        ref = CubeSource(whole, lb, 0.02, centre=(0.3, -0.1), rotation=rotation,
                         max_bytes=2**31).flux_cube(grid, (58, 116), 0.04)
        assert np.max(np.abs(out - ref)) < 1e-12 * ref.max()
        assert peak < 12 * 2**20                                      # not the 48 MB cube
    img = np.random.default_rng(1).random((300, 200))
    a = ImageProfile(img, 0.006, offset=(0.2, 0.0), rotation=30.0, max_bytes=2**16).cell_fractions((58, 116), 0.04)
    b = ImageProfile(img, 0.006, offset=(0.2, 0.0), rotation=30.0).cell_fractions((58, 116), 0.04)
    assert np.max(np.abs(a - b)) < 1e-15 and abs(a.sum() - 1) < 1e-12
    # a galaxy far larger than the field is accepted (its light outside the field is lost)
    huge = GalaxyModel("sersic", r_kpc=500.0).host(0.1)
    assert huge.flux_cube(LBDA[:3], (58, 116), 0.04).sum(axis=(1, 2))[0] < 1e-3 * huge.total_flux(LBDA[:1])[0]
