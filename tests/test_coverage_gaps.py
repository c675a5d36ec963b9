"""Features without a test elsewhere: batch reference search, Kubik16 in the batch ETC,
MLASpectrograph, grids from a resolving power, Target detector products and change_* methods,
lazuli_etc / lazuli_sn_etc, and ramp statistics (Gaussian-path moments, Kubik16 for few groups).

Every expectation is physics or an independent value (hand formulas, a second code path),
never the implementation's own output copied into the test.
"""
import math

import h5py
import numpy as np
import pytest

from slicersim.errors import ConfigError, ReadoutError
from slicersim.etc.solve import solve_many
from slicersim.physics.readout import readout_times, variance_kubik16, variance_rauscher07
from slicersim.instrument.spectrograph import (MLASpectrograph, SlicerSpectrograph, Spectrograph,
                                               wavelength_grid_from_resolving_power)
from slicersim.simulation import Simulation
from slicersim.targets import LazuliTarget, lazuli_etc, lazuli_sn_etc

BACKENDS = ["numpy", pytest.param("opencl", marks=pytest.mark.needs_opencl)]

LBDA = np.arange(3000.0, 20000.0, 10.0)
TFRAME = 2.83                                        # Lazuli frame time [s] (built-in TOML)


def flat(level=1e-17):
    return np.full(LBDA.size, level)


def sloped(level=1e-17):
    return level * (LBDA / 1e4) ** -1.5


@pytest.fixture(scope="module")
def short_range_toml(tmp_path_factory):
    """Overlay TOML: the built-in CBE instrument on 9000–10000 Å only (fast detector products)."""
    path = tmp_path_factory.mktemp("cfg") / "short_range.toml"
    path.write_text("[spectrograph]\nspectral_range = [9000, 10000]\n", encoding="utf-8")
    return str(path)


@pytest.fixture(scope="module")
def kubik_toml(tmp_path_factory):
    path = tmp_path_factory.mktemp("cfg") / "kubik.toml"
    path.write_text('[detector]\nvariance_model = "Kubik16"\n', encoding="utf-8")
    return str(path)


# --------------------------------------------------------------------------- batch ETC
BATCH = [(flat(1e-17), (8000.0, 11000.0)), (flat(3e-18), (8000.0, 11000.0)),
         (sloped(5e-17), (5000.0, 7000.0)), (sloped(2e-18), (12000.0, 15000.0))]


def test_solve_many_reference_search_equals_single_target_reference_search():
    fluxes = np.array([f for f, _ in BATCH])
    ranges = np.array([r for _, r in BATCH])
    table = solve_many(LBDA, fluxes, 20.0, ranges, search="reference")
    assert table.meta["search"] == "reference" and len(table) == len(BATCH)
    for i, (flux, band) in enumerate(BATCH):
        target = LazuliTarget(LBDA, flux)
        res = target.setup_to_snr(20.0, lbda_range=band, search="reference")
        assert (table["n"][i], table["m"][i], table["d"][i]) == tuple(res["nmd"]), i
        assert table["nramps"][i] == res["nramps"], i
        assert table["exposure_time"][i] == pytest.approx(res["exposure_time"], rel=1e-12)
        assert table["snr_per_bin"][i] == pytest.approx(res["snr"], rel=1e-9)
        # the SNR reached, re-evaluated independently at the chosen readout
        nmd = (int(table["n"][i]), int(table["m"][i]), int(table["d"][i]))
        again = target.simulation.get_band_snr(band, nmd=nmd, nramps=int(table["nramps"][i]))
        assert again == pytest.approx(table["snr_per_bin"][i], rel=1e-9)


def test_solve_many_kubik16_equals_single_target_exact_search(kubik_toml):
    cfg = ["cbe", kubik_toml]
    fluxes = np.array([f for f, _ in BATCH])
    ranges = np.array([r for _, r in BATCH])
    table = solve_many(LBDA, fluxes, 20.0, ranges, config=cfg, search="exact")
    rauscher = solve_many(LBDA, fluxes, 20.0, ranges, search="exact")
    tau = 20.0 / math.sqrt(2.3)
    differs = False
    for i, (flux, band) in enumerate(BATCH):
        target = LazuliTarget(LBDA, flux, config=cfg)
        sim = target.simulation
        assert sim.detector.variance_model == "Kubik16"
        res = target.setup_to_snr(20.0, lbda_range=band, search="exact")
        nmd = (int(table["n"][i]), int(table["m"][i]), int(table["d"][i]))
        r = int(table["nramps"][i])
        assert nmd == tuple(res["nmd"]) and r == res["nramps"], i
        assert table["exposure_time"][i] == pytest.approx(res["exposure_time"], rel=1e-12)
        # minimal: reaches the target, one group less / one ramp less does not
        reached = sim.get_band_snr(band, nmd=nmd, nramps=r)
        assert reached >= tau * (1 - 1e-12) and reached == pytest.approx(table["snr_per_bin"][i], rel=1e-9)
        if nmd[0] > sim.detector.min_group:
            assert sim.get_band_snr(band, nmd=(nmd[0] - 1, nmd[1], nmd[2]), nramps=r) < tau
        if r > 1:
            assert sim.get_band_snr(band, nmd=nmd, nramps=r - 1) < tau
        differs |= (table["snr_per_bin"][i] != rauscher["snr_per_bin"][i])
    assert differs                                # the variance model reached the batch ETC


# --------------------------------------------------------------------------- spectrographs
@pytest.mark.parametrize("xss, xs, width, expected", [(0.9, 0.3, 10, 19),    # ⌈20·0.9487⌉
                                                      (0.3, 0.4, 5, 5),      # ⌈10·0.5⌉
                                                      (0.5, 0.0, 3, 3),      # ⌈6·0.5⌉
                                                      (0.0, 0.01, 1, 1)])    # at least one pixel
def test_mla_pixels_per_cell_and_anamorphosis(xss, xs, width, expected):
    kw = dict(resolving_power=100.0, spectral_range=(9000.0, 11000.0), spatial_shape=(20, 30))
    mla = MLASpectrograph(xdisp_sigma_spectral=xss, xdisp_sigma=xs, xdisp_width_insigma=width, **kw)
    assert mla.pixels_per_cell == expected
    assert mla.shape == (20, 30)                                  # square cells: no anamorphosis
    assert mla.xdisp_sigma_at(2e4) == pytest.approx(math.hypot(2 * xss, xs), rel=1e-14)
    slicer = SlicerSpectrograph(**kw)
    assert slicer.shape == (20, 60) and slicer.pixels_per_cell == 2


@pytest.fixture(scope="module")
def generic_and_mla():
    base = LazuliTarget(LBDA, flat(1e-17)).simulation
    kw = dict(resolving_power=100.0, spectral_range=(8000.0, 11000.0), dispersion_resolution=2.3,
              throughput=0.5, spatial_scale=0.04, spatial_shape=(30, 30))
    sims = {}
    for name, spec in (("generic", Spectrograph(**kw)), ("mla", MLASpectrograph(**kw))):
        sims[name] = Simulation(base.scene, base.telescope, spec, base.detector)
    return sims["generic"], sims["mla"]


def test_mla_simulation_spreads_cells_over_pixels(generic_and_mla):
    """Same optics, p pixels per cell instead of 1: the signal is unchanged; every cell pays p
    pixels of read noise and dark (Rauscher07 is linear in the rate:
    V_p(R) − V_1(R) = (p − 1) V_1(0)), and saturates p times later."""
    gen, mla = generic_and_mla
    p = mla.spectrograph.pixels_per_cell
    assert p == 19 and gen.spectrograph.pixels_per_cell == 1
    nmd = (16, 8, 0)
    rate = np.array([0.0, 0.5, 30.0])
    v1, _ = gen.cell_variance(rate, nmd)
    vp, _ = mla.cell_variance(rate, nmd)
    np.testing.assert_allclose(vp - v1, (p - 1) * v1[0], rtol=1e-10)
    tint = readout_times(nmd, gen.detector.tframe)["integration_time_per_ramp"]
    bright = np.array([3.0 * gen.detector.saturation / tint])       # 3× a pixel's full scale
    assert gen.cell_variance(bright, nmd)[1].all() and not mla.cell_variance(bright, nmd)[1].any()
    _, s1, var1 = gen.get_spectrum(nmd=nmd, nramps=1)
    _, sp, varp = mla.get_spectrum(nmd=nmd, nramps=1)
    np.testing.assert_allclose(sp, s1, rtol=1e-12)
    assert np.all(varp > var1)
    assert mla.get_band_snr((8500.0, 10500.0), nmd=nmd) < gen.get_band_snr((8500.0, 10500.0), nmd=nmd)


@pytest.mark.parametrize("dr", [2.0, 2.3])
def test_wavelength_grid_from_constant_resolving_power(dr):
    """Constant R: geometric bins, λ/Δλ = R·dr (exact: 1/(2 sinh(h/2)), h = 1/(R dr)),
    N = round(R dr ln(λmax/λmin)) + 1 bins."""
    R, lo, hi = 150.0, 4000.0, 17000.0
    lbda, edges = wavelength_grid_from_resolving_power(R, (lo, hi), dr)
    assert lbda.size == round(R * dr * math.log(hi / lo)) + 1 and edges.size == lbda.size + 1
    assert lbda[0] == pytest.approx(lo, rel=1e-6)
    recovered = lbda / np.diff(edges) / dr
    h = 1.0 / (R * dr)
    np.testing.assert_allclose(recovered, 1.0 / (2 * math.sinh(h / 2)) / dr, rtol=1e-5)
    np.testing.assert_allclose(recovered, R, rtol=1e-4)
    spec = Spectrograph(resolving_power=R, spectral_range=(lo, hi), dispersion_resolution=dr)
    np.testing.assert_allclose(spec.resolving_power, R, rtol=1e-4)


def test_wavelength_grid_from_varying_resolving_power():
    """R(λ) = 60 + λ/100 Å (100 → 230): λ/Δλ/dr recovers R(λ) to 0.1 % (R changes by < 1 % per bin)."""
    def R(lam):
        return 60.0 + np.asarray(lam) / 100.0
    lbda, edges = wavelength_grid_from_resolving_power(R, (4000.0, 17000.0), 2.3)
    recovered = lbda / np.diff(edges) / 2.3
    np.testing.assert_allclose(recovered, R(lbda), rtol=1e-3)
    # N − 1 = ∫ R dr dλ/λ = dr [60 ln(λ1/λ0) + (λ1 − λ0)/100]
    expected = 2.3 * (60 * math.log(17000 / 4000) + 130.0)
    assert abs((lbda.size - 1) - expected) <= 0.5 + 1e-9
    with pytest.raises(ValueError):
        wavelength_grid_from_resolving_power(lambda lam: 0 * lam, (4000.0, 17000.0))


# --------------------------------------------------------------------------- Target detector products
@pytest.fixture(scope="module")
def short_target(short_range_toml):
    return LazuliTarget(LBDA, sloped(2e-17), config=["cbe", short_range_toml])


@pytest.mark.parametrize("backend", BACKENDS)
def test_detector_image_conserves_the_field_rate_cubes(short_target, backend):
    image = short_target.get_detector_image(backend=backend)
    cubes = short_target.get_field_rate_cubes()
    assert image.shape == (4096, 4096) and np.all(image >= 0)
    narrow, wide = cubes["narrow"][0].sum(), cubes["wide"][0].sum()
    assert image.sum() == pytest.approx(narrow + wide, rel=1e-9)
    assert image[:2048].sum() == pytest.approx(wide, rel=1e-9)          # the fields' detector halves
    assert image[2048:].sum() == pytest.approx(narrow, rel=1e-9)
    # the point source sits in the narrow field only: its photons add to the narrow half
    dark_sky = LazuliTarget(LBDA, np.zeros(LBDA.size), config=short_target.config)
    blank = dark_sky.get_detector_image(backend=backend)
    assert blank[:2048].sum() == pytest.approx(wide, rel=1e-9)
    sim = short_target.simulation
    point = (sim.spectrograph.apply_lsf(sim.pointsource_flambda * sim.flambda_to_photon) * sim.qe).sum()
    assert image.sum() - blank.sum() == pytest.approx(point, rel=2e-2)  # LSF/PSF edge losses only


@pytest.mark.needs_opencl      # the NumPy ramp sampler needs ~2 min for 4096² pixels
def test_get_ramps_file_shapes_and_attributes(short_target, tmp_path):
    det = short_target.simulation.detector
    image = short_target.get_detector_image(backend="opencl")
    path = short_target.get_ramps(out=str(tmp_path / "ramps.h5"), nmd=(3, 1, 0), nramps=1, seed=3,
                                  backend="opencl")
    with h5py.File(path, "r") as f:
        assert f["SCI"].shape == f["GROUPDQ"].shape == (1, 3, 4096, 4096)
        assert f["SCI"].dtype == np.uint16 and f["PIXELDQ"].shape == (4096, 4096)
        a = f.attrs
        assert (a["NGROUPS"], a["NFRAMES"], a["GROUPGAP"], a["NINTS"]) == (3, 1, 0, 1)
        assert a["READPATT"] == "MACC(3,1,0)" and a["SEED"] == 3 and bool(a["COMPLETE"])
        assert a["TFRAME"] == det.tframe and a["READNOISE"] == det.ron and a["GAIN"] == det.gain
        assert a["DARK"] == det.dark and a["ROIC_GLOW"] == det.roic_glow
        assert a["THERMAL_DARK"] == pytest.approx(short_target.simulation.thermal_dark, rel=1e-12)
        truth = f["truth/rate"][...]
        # the truth image is the detector image, stored at the file's precision (float32: 6e-8)
        np.testing.assert_allclose(truth, image,
                                   rtol=np.finfo(truth.dtype).eps, atol=0)
        sci = f["SCI"][0].astype(float)
    # mean charge accumulated between group 0 and 2 (two frames) over all pixels:
    # (rate + dark + thermal dark + glow / t_f) · 2 t_f · gain, known to ±4 standard errors
    diff = (sci[2] - sci[0]).ravel()
    rate = image.mean()
    d_eff = det.dark + short_target.simulation.thermal_dark + det.roic_glow / det.tframe
    expected = (rate + d_eff) * 2 * det.tframe * det.gain
    assert abs(diff.mean() - expected) < 4 * diff.std() / math.sqrt(diff.size)


# --------------------------------------------------------------------------- Target.change_*
BAND = (8000.0, 11000.0)


def fresh_target():
    target = LazuliTarget(LBDA, sloped(1e-17))
    target.change_detector(nmd=(16, 8, 0), nramps=1)
    return target


def test_change_configuration_eol_lowers_snr_and_keeps_readout():
    target = fresh_target()
    cbe = target.get_band_snr(BAND)
    target.change_configuration("eol")
    assert target.get_readout_config() == {"nmd": (16, 8, 0), "nramps": 1}
    det = target.simulation.detector
    assert (det.ron, det.dark) == (20.0, 1e-2)                    # the eol overlay's values
    assert target.get_band_snr(BAND) < cbe                       # more noise, lower throughput
    target.change_configuration("cbe")
    assert target.get_band_snr(BAND) == pytest.approx(cbe, rel=1e-12)


def test_change_field_wide_doubles_the_cell_and_quadruples_the_sky_per_cell():
    target = fresh_target()
    narrow = target.simulation
    target.change_field("wide")
    wide = target.simulation
    assert target.get_readout_config() == {"nmd": (16, 8, 0), "nramps": 1}
    assert wide.spectrograph.spatial_scale == pytest.approx(2 * narrow.spectrograph.spatial_scale)
    assert wide.spectrograph.shape == narrow.spectrograph.shape
    # zodiacal light per cell ∝ cell solid angle × throughput: ×4 × T_wide / T_narrow
    ratio = wide.background_photons / narrow.background_photons
    thr = wide.spectrograph.throughput / narrow.spectrograph.throughput
    ok = narrow.background_photons > 0
    np.testing.assert_allclose(ratio[ok], 4 * thr[ok], rtol=1e-9)
    # the same PSF in arcsec covers half as many cells: more of the flux in the brightest cell
    assert wide.get_psf().max(axis=(1, 2)).mean() > narrow.get_psf().max(axis=(1, 2)).mean()
    with pytest.raises(ConfigError, match=r"unknown field 'medium'; valid: 'narrow', 'wide'"):
        target.change_field("medium")


def test_change_spectrograph_dispersion_resolution_rescales_the_grid():
    """Bins are 1/dr of a resolution element: the bin count scales with dr, R(λ) does not."""
    target = fresh_target()
    before = target.simulation.spectrograph
    n0, r0 = before.nlbda, before.resolving_power.copy()
    lbda0 = before.lbda.copy()
    target.change_spectrograph(dispersion_resolution=4.6)
    spec = target.simulation.spectrograph
    assert spec.dispersion_resolution == 4.6 and spec.lsf_sigma == pytest.approx(2.3)
    assert (spec.nlbda - 1) == pytest.approx(2 * (n0 - 1), abs=1)
    np.testing.assert_allclose(np.interp(lbda0[5:-5], spec.lbda, spec.resolving_power), r0[5:-5], rtol=2e-2)


def test_change_detector_readout_and_noise():
    target = fresh_target()
    snr1 = target.get_band_snr(BAND)
    target.change_detector(nramps=4)
    assert target.get_band_snr(BAND) == pytest.approx(2 * snr1, rel=1e-12)      # √4 independent ramps
    assert target.get_exposure_time() == pytest.approx(4 * 16 * 8 * TFRAME, rel=1e-12)
    target.change_detector(nmd=(32, 8, 0), nramps=1)
    assert target.get_exposure_time() == pytest.approx(32 * 8 * TFRAME, rel=1e-12)
    assert target.get_band_snr(BAND) > snr1                                        # longer ramp
    target.change_detector(nmd=(16, 8, 0))
    assert target.get_band_snr(BAND) == pytest.approx(snr1, rel=1e-12)
    target.change_detector(ron=0.0)
    assert target.get_band_snr(BAND) > snr1                                        # no read noise
    with pytest.raises(ReadoutError, match=r"nmd = \(65, 8, 0\): n = 65 exceeds max_group = 64"):
        target.change_detector(nmd=(65, 8, 0))                                     # > max_group 64


# --------------------------------------------------------------------------- one-call ETCs
KEYS = {"nmd", "nramps", "exposure_time", "snr", "snr_per_bin", "snr_target_per_bin", "lbda_range_obs",
        "data_volume", "config", "field", "target"}


def _check_etc_result(res, snr, band_obs, dr=2.3):
    assert KEYS <= set(res)
    n, m, d = res["nmd"]
    r = res["nramps"]
    assert res["exposure_time"] == pytest.approx(r * (n * (m + d) - d) * TFRAME, rel=1e-12)
    assert res["data_volume"] == pytest.approx(r * n * 4096**2 * 16 / 8e9, rel=1e-12)
    assert res["snr_target_per_bin"] == pytest.approx(snr / math.sqrt(dr), rel=1e-12)
    assert res["snr"] == pytest.approx(res["snr_per_bin"] * math.sqrt(dr), rel=1e-12)
    assert res["snr"] >= snr * (1 - 1e-12)                      # the exact search reaches the target
    assert tuple(res["lbda_range_obs"]) == pytest.approx(band_obs, rel=1e-12)
    target = res["target"]
    assert target.get_readout_config() == {"nmd": tuple(res["nmd"]), "nramps": r}
    assert target.get_exposure_time() == pytest.approx(res["exposure_time"], rel=1e-12)
    assert target.get_band_snr(band_obs, frame="obs") == pytest.approx(res["snr_per_bin"], rel=1e-9)


def test_lazuli_etc_keys_and_self_consistency():
    res = lazuli_etc(LBDA, sloped(1e-17), snr=15, lbda_range=(9000, 12000))
    _check_etc_result(res, 15, (9000.0, 12000.0))
    assert (res["config"], res["field"]) == ("cbe", "narrow")
    # a source 4× fainter needs more time
    faint = lazuli_etc(LBDA, sloped(2.5e-18), snr=15, lbda_range=(9000, 12000))
    assert faint["exposure_time"] > res["exposure_time"]


def test_lazuli_sn_etc_keys_and_self_consistency():
    z = 0.5
    res = lazuli_sn_etc(z, snr=10, config="eol", field="wide")
    _check_etc_result(res, 10, (4000 * (1 + z), 6800 * (1 + z)), dr=2.5)
    assert (res["config"], res["field"]) == ("eol", "wide")
    assert res["target"].redshift == z


# --------------------------------------------------------------------------- ramp statistics
@pytest.mark.parametrize("backend", BACKENDS)
def test_ramp_gaussian_path_moments(backend):
    """Rounded-Gaussian frame increments (μ = 113 e-/frame > gauss_min_mean), no read noise, m = 2:
    group-mean difference g1 − g0 = (x1 + 2 x2 + x3)/2 → mean 2μ, variance (1+4+1)/4 μ = 1.5 μ
    (+ rounding ~1/6 ADU²); last − first = x1/2 + x2…x10 + x11/2 → mean 10 μ, variance 9.5 μ."""
    from slicersim.backends.ramp import simulate_block_numpy, simulate_block_opencl
    from slicersim.products.ramps import RampParameters, frame_mean_charge
    p = RampParameters(nmd=(6, 2, 0), gauss_min_mean=50.0, ron=0.0, roic_glow=0.0, bias=0.0, full_well=1e9)
    npix = 20001
    mu_frame = frame_mean_charge(np.full(npix, 40.0), 0.0, 0.0, 0.0, p.tframe)
    mu = 40.0 * p.tframe
    assert mu_frame[0] == pytest.approx(mu, rel=1e-12) and mu > 50.0
    run = simulate_block_numpy if backend == "numpy" else simulate_block_opencl
    sci = run(mu_frame, np.zeros(npix, bool), 0, 0, 9, p)[0].astype(float)
    for diff, k_mean, k_var in ((sci[1] - sci[0], 2.0, 1.5), (sci[5] - sci[0], 10.0, 9.5)):
        mean_exp, var_exp = k_mean * mu, k_var * mu
        var = diff.var(ddof=1)
        assert abs(diff.mean() - mean_exp) < 4 * math.sqrt(var_exp / npix)
        assert abs(var - var_exp) < 4 * var_exp * math.sqrt(2.0 / (npix - 1)) + 0.5    # + rounding


@pytest.mark.parametrize("nmd", [(2, 8, 0), (3, 4, 1)])
def test_ramp_slope_variance_matches_kubik16_for_few_groups(nmd):
    """For n ≤ 3 groups least squares is the maximum-likelihood slope: the empirical variance of
    simulated slopes × t_int equals Kubik16 (and Rauscher07) within 4 σ of its Monte Carlo error.
    Group means are rounded to ADU: σ_eff² = σ² + m/12 (gain 1)."""
    from slicersim.products.ramps import fit_slopes, simulate
    npix, rate, ron, tf = 40000, 2.0, 12.0, TFRAME
    sci = simulate(np.full((200, 200), rate), nmd, seed=17, ron=ron, dark=0.0, roic_glow=0.0,
                   backend="numpy")[0]
    n, m, d = nmd
    tint = (n - 1) * (m + d) * tf
    est = fit_slopes(sci.reshape(n, -1), nmd, tf) * tint
    var = est.var(ddof=1)
    ron_eff = math.sqrt(ron**2 + m / 12.0)
    kubik = float(variance_kubik16(rate, nmd, tf, ron_eff, 0.0))
    mc_err = kubik * math.sqrt(2.0 / (npix - 1))
    assert abs(var - kubik) < 4 * mc_err, (var, kubik, mc_err)
    assert kubik == pytest.approx(float(variance_rauscher07(rate, nmd, tf, ron_eff, 0.0)), rel=1e-3)
