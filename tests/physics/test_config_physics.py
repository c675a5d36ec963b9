"""Built-in configurations and the physics building blocks: LSF, PSF, thermal emission,
Simulation.update consistency and multi-ramp scaling."""
import math
import os

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter1d
from scipy.special import erf, lambertw

from slicersim.io.config import builtin_config_dir
from slicersim.constants import C_LIGHT, H_PLANCK, K_BOLTZMANN
from slicersim.physics.psf import cell_centres, gaussian_psf_fractions
from slicersim.physics.lsf import apply_lsf, lsf_weights
from slicersim.targets import LazuliTarget, build_simulation
from slicersim.physics.thermal import photon_radiance

BAND = (8000.0, 13600.0)
LBDA = np.linspace(3000.0, 20000.0, 600)
FLUX = 2e-17 * (LBDA / 1e4) ** -1.0      # erg/s/cm²/Å, smooth and positive


# --------------------------------------------------------------------------- #
#  built-in configurations                                                     #
# --------------------------------------------------------------------------- #
@pytest.fixture(scope="module")
def builtin_sims():
    return {("cbe", "narrow"): build_simulation("cbe", "narrow"),
            ("eol", "wide"): build_simulation("eol", "wide")}


def test_builtin_configs_load(builtin_sims):
    cbe, eol = builtin_sims[("cbe", "narrow")], builtin_sims[("eol", "wide")]
    assert cbe.spectrograph.spatial_scale == 0.04 and eol.spectrograph.spatial_scale == 0.08
    assert cbe.spectrograph.dispersion_resolution == 2.3 and eol.spectrograph.dispersion_resolution == 2.5
    assert cbe.detector.ron == 10.0 and eol.detector.ron == 20.0
    assert cbe.spectrograph.shape == (58, 116)                    # 1×2 anamorphosis of 58×58
    assert os.path.isfile(os.path.join(builtin_config_dir(), "lazuli_cbe.toml"))


def test_builtin_cbe_resolving_power(builtin_sims):
    spec = builtin_sims[("cbe", "narrow")].spectrograph
    # dispersion_scale 1.3 is chosen for R_min = 100
    assert spec.resolving_power.min() == pytest.approx(100.0, rel=0.05)
    assert np.all(spec.resolving_power < 1000)


@pytest.mark.parametrize("key", [("cbe", "narrow"), ("eol", "wide")])
def test_builtin_grids_and_curves(builtin_sims, key):
    sim = builtin_sims[key]
    lbda = sim.lbda
    assert np.all(np.diff(lbda) > 0)
    assert np.all(np.diff(sim.spectrograph.lbda_edges) > 0)
    # bin centres lie between their edges
    edges = sim.spectrograph.lbda_edges
    assert np.all((edges[:-1] < lbda) & (lbda < edges[1:]))
    assert lbda[0] == pytest.approx(4000.0, abs=1.0) and lbda[-1] < 17000.0 + 50
    thr = sim.spectrograph.throughput
    assert np.all(np.isfinite(thr)) and np.all((thr >= 0) & (thr <= 1)) and thr.max() > 0.1
    qe = sim.detector.get_qe(np.linspace(2000.0, 25000.0, 2001))
    assert np.all((qe >= 0) & (qe <= 1)) and qe.max() > 0.5
    assert np.all((sim.qe >= 0) & (sim.qe <= 1))
    # H4RG 1.7 µm cut-off: no response at 1.8 µm
    assert sim.detector.get_qe(np.array([18000.0]))[0] == pytest.approx(0.0, abs=1e-3)


# --------------------------------------------------------------------------- #
#  line-spread function                                                        #
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("sigma", [1.15, 1.25, 3.3])
def test_lsf_conserves_flux(sigma):
    rng = np.random.default_rng(3)
    x = np.zeros(300)
    x[40:260] = rng.random(220) * 5.0          # zero within 4σ of both ends
    out = apply_lsf(x, sigma)
    assert out.sum() == pytest.approx(x.sum(), rel=1e-12)
    assert not np.allclose(out, x)             # it did smooth


@pytest.mark.parametrize("sigma", [1.15, 1.25, 0.7])
def test_lsf_delta_gives_weights(sigma):
    offsets, w = lsf_weights(sigma)
    half = int(4.0 * sigma + 0.5)
    np.testing.assert_array_equal(offsets, np.arange(-half, half + 1))
    expected = np.exp(-0.5 * (offsets / sigma) ** 2)
    np.testing.assert_allclose(w, expected / expected.sum(), rtol=1e-14)
    x = np.zeros(101)
    x[50] = 1.0
    out = apply_lsf(x, sigma)
    np.testing.assert_allclose(out[50 + offsets], w, rtol=1e-14, atol=0)
    mask = np.ones(101, bool)
    mask[50 + offsets] = False
    assert np.all(out[mask] == 0)


@pytest.mark.parametrize("sigma", [1.15, 1.25, 0.7, 3.3])
def test_lsf_matches_scipy_gaussian_filter(sigma):
    rng = np.random.default_rng(7)
    x = rng.random((400, 3))
    out = apply_lsf(x, sigma, axis=0)
    ref = gaussian_filter1d(x, sigma, axis=0, mode="reflect", truncate=4.0)
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-14)
    # reflect boundary: a constant stays constant up to the ends
    np.testing.assert_allclose(apply_lsf(np.full(50, 2.0), sigma), 2.0, rtol=1e-14)


def test_lsf_zero_sigma_is_identity():
    x = np.arange(10.0)
    np.testing.assert_array_equal(apply_lsf(x, 0.0), x)


# --------------------------------------------------------------------------- #
#  Gaussian PSF                                                                #
# --------------------------------------------------------------------------- #
SHAPE = (58, 116)


def test_psf_small_sigma_sums_to_one():
    sig = np.array([0.3, 1.0, 2.0, 3.5])          # ≥ 8σ from the field edges
    psf = gaussian_psf_fractions(sig, 1.5 * sig, SHAPE, (0.0, 0.0))
    assert psf.shape == (4,) + SHAPE
    assert np.all(psf >= 0)
    np.testing.assert_allclose(psf.sum(axis=(1, 2)), 1.0, rtol=0, atol=1e-12)


def test_psf_large_sigma_loses_flux_outside():
    sig_y, sig_x = np.array([10.0, 20.0, 40.0]), np.array([25.0, 30.0, 80.0])
    psf = gaussian_psf_fractions(sig_y, sig_x, SHAPE, (0.0, 0.0))
    # fraction inside a 58 × 116 field centred on the source
    expected = erf(29.0 / (math.sqrt(2) * sig_y)) * erf(58.0 / (math.sqrt(2) * sig_x))
    np.testing.assert_allclose(psf.sum(axis=(1, 2)), expected, rtol=1e-12)
    assert np.all(expected < 0.99)


def test_psf_symmetric_at_centre():
    sig_y, sig_x = np.array([0.8, 4.0, 15.0]), np.array([1.1, 6.0, 20.0])
    psf = gaussian_psf_fractions(sig_y, sig_x, SHAPE, (0.0, 0.0))
    np.testing.assert_allclose(psf, psf[:, ::-1, :], rtol=1e-13, atol=1e-300)
    np.testing.assert_allclose(psf, psf[:, :, ::-1], rtol=1e-13, atol=1e-300)
    # source on the corner of the four central cells: they share the peak
    c = psf[0, 28:30, 57:59]
    np.testing.assert_allclose(c, c[0, 0], rtol=1e-13)
    assert c[0, 0] == pytest.approx(psf[0].max())


def test_psf_position_is_x_then_y():
    # position = (x0, y0): x runs along the 116-cell axis (last axis)
    sig = np.array([1.5])
    psf = gaussian_psf_fractions(sig, sig, SHAPE, (3.0, -2.0))[0]
    yc, xc = cell_centres(SHAPE)
    total = psf.sum()
    assert (psf * xc).sum() / total == pytest.approx(3.0, abs=1e-6)
    assert (psf * yc).sum() / total == pytest.approx(-2.0, abs=1e-6)


# --------------------------------------------------------------------------- #
#  thermal emission                                                            #
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("temperature", [50.0, 228.0, 293.0, 5800.0])
def test_photon_radiance_matches_astropy(temperature):
    import astropy.constants as const
    import astropy.units as u
    from astropy.modeling.models import BlackBody

    lbda = np.array([5000.0, 10000.0, 17000.0, 25000.0, 1e5])          # Å
    bb = BlackBody(temperature=temperature * u.K, scale=1.0 * u.W / (u.m**2 * u.AA * u.sr))
    energy = bb(lbda * u.AA).to(u.W / (u.m**2 * u.AA * u.sr))
    photon_energy = (const.h * const.c / (lbda * u.AA)).to(u.J)
    expected = (energy / photon_energy).to(1 / (u.s * u.m**2 * u.AA * u.sr)).value
    got = photon_radiance(lbda, temperature)
    keep = expected > 1e-290            # astropy and slicersim both underflow far in the Wien tail
    assert keep.sum() >= 3
    np.testing.assert_allclose(got[keep], expected[keep], rtol=1e-10)


def test_photon_radiance_limits():
    hc_k = H_PLANCK * C_LIGHT / K_BOLTZMANN                               # m K
    # Wien limit (x = hc/λkT ≫ 1): B_ph = 2c/λ⁴ e^{−x} [per m] · 1e-10 [per Å]
    lam_m, temp = 1e-6, 230.0
    x = hc_k / (lam_m * temp)
    assert photon_radiance(1e4, temp) == pytest.approx(2 * C_LIGHT / lam_m**4 * math.exp(-x) * 1e-10, rel=1e-12)
    # Rayleigh-Jeans limit (x ≪ 1): B_ph = 2 k T / (h λ³) · 1e-10, relative error ≈ x/2
    lam_m, temp = 1.0, 300.0
    x = hc_k / (lam_m * temp)
    rj = 2 * K_BOLTZMANN * temp / (H_PLANCK * lam_m**3) * 1e-10
    assert photon_radiance(1e10, temp) == pytest.approx(rj, rel=x)
    # no emission at 0 K
    np.testing.assert_array_equal(photon_radiance(np.array([1e4, 2e4]), 0.0), 0.0)


def test_photon_radiance_peak_scaling():
    from scipy.optimize import minimize_scalar
    # photon radiance per unit λ peaks at x_p = 4 + W₀(−4 e^{−4}) = 3.920690395
    x_peak = 4.0 + lambertw(-4.0 * math.exp(-4.0)).real
    assert x_peak == pytest.approx(3.920690395, rel=1e-9)
    hc_k = H_PLANCK * C_LIGHT / K_BOLTZMANN
    peaks = []
    for temp in (230.0, 460.0, 2900.0):
        guess = hc_k / (x_peak * temp) * 1e10                              # Å
        res = minimize_scalar(lambda lam: -photon_radiance(lam, temp) / photon_radiance(guess, temp),
                              bounds=(0.5 * guess, 2 * guess), method="bounded", options={"xatol": 1e-6 * guess})
        peaks.append(res.x)
        assert res.x == pytest.approx(guess, rel=1e-5)
    # Wien displacement: λ_peak ∝ 1/T
    assert peaks[0] * 230.0 == pytest.approx(peaks[1] * 460.0, rel=1e-5)
    assert peaks[0] * 230.0 == pytest.approx(peaks[2] * 2900.0, rel=1e-5)
    # and the peak value grows as T⁴ (B_ph(λ_p) ∝ T⁴ since λ_p ∝ 1/T)
    ratio = photon_radiance(peaks[1], 460.0) / photon_radiance(peaks[0], 230.0)
    assert ratio == pytest.approx(2.0**4, rel=1e-8)


# --------------------------------------------------------------------------- #
#  Simulation.update consistency                                               #
# --------------------------------------------------------------------------- #
def _sim():
    return LazuliTarget(LBDA, FLUX).simulation


def test_update_dispersion_resolution():
    sim = _sim()
    nbins = sim.lbda.size
    _, s0, _ = sim.get_spectrum()
    assert s0.size == nbins and sim.qe.size == nbins          # fill the caches
    sim.update(dispersion_resolution=2.5)
    assert sim.spectrograph.dispersion_resolution == 2.5
    assert sim.spectrograph.lsf_sigma == 1.25
    # the law is scaled by dr/2: ≈ 2.5/2.3 times more bins over the same range
    assert sim.lbda.size != nbins
    assert sim.lbda.size == pytest.approx(nbins * 2.5 / 2.3, rel=0.01)
    lbda, signal, variance = sim.get_spectrum()
    assert lbda.size == signal.size == variance.size == sim.lbda.size
    np.testing.assert_array_equal(lbda, sim.lbda)
    # every derived per-bin quantity follows (no stale cache)
    assert sim.qe.size == sim.flambda_to_photon.size == sim.background_photons.size == sim.lbda.size
    assert sim.spectrograph.throughput.size == sim.lbda.size
    # R = λ/Δλ/dr is unchanged by the resampling
    assert sim.spectrograph.resolving_power.min() == pytest.approx(100.0, rel=0.05)
    # and the updated simulation equals one built with dispersion_resolution = 2.5
    fresh = LazuliTarget(LBDA, FLUX).simulation
    fresh.spectrograph.update(dispersion_resolution=2.5)
    fresh._cache.clear()
    np.testing.assert_array_equal(fresh.lbda, sim.lbda)
    np.testing.assert_allclose(fresh.get_spectrum()[1], signal, rtol=1e-13)
    np.testing.assert_allclose(fresh.get_spectrum()[2], variance, rtol=1e-13)
    assert sim.get_band_snr(BAND) == pytest.approx(fresh.get_band_snr(BAND), rel=1e-13)


def test_update_readout():
    sim = _sim()
    sim.update(nmd=(10, 4, 0), nramps=3)
    times = sim.get_times()
    assert times["nmd"] == (10, 4, 0) and times["nramps"] == 3
    assert times["exposure_time"] == pytest.approx(3 * (10 * 4) * 2.83, rel=1e-14)
    assert times["integration_time"] == pytest.approx(3 * 9 * 4 * 2.83, rel=1e-14)
    assert sim.get_data_volume() == pytest.approx(3 * 10 * 4096**2 * 16 / 8e9, rel=1e-14)
    _, s3, v3 = sim.get_spectrum()
    _, s1, v1 = sim.get_spectrum(nramps=1)
    ok = np.isfinite(v1) & (s1 > 0)
    assert ok.sum() > 100
    np.testing.assert_allclose(s3[ok], 3 * s1[ok], rtol=1e-14)
    np.testing.assert_allclose(v3[ok], 3 * v1[ok], rtol=1e-14)
    # a different readout with the same ramp count gives a different spectrum
    _, s_other, _ = sim.get_spectrum(nmd=(20, 4, 0), nramps=3)
    assert not np.allclose(s_other[ok], s3[ok])
    # the integrated signal follows t_int: 19·4 vs 9·4 frames
    np.testing.assert_allclose(s_other[ok], s3[ok] * 19 / 9, rtol=1e-13)


def test_band_snr_scales_as_sqrt_ramps():
    sim = _sim()
    one = sim.get_band_snr(BAND, nmd=(64, 8, 0), nramps=1)
    four = sim.get_band_snr(BAND, nmd=(64, 8, 0), nramps=4)
    nine = sim.get_band_snr(BAND, nmd=(64, 8, 0), nramps=9)
    assert np.isfinite(one) and one > 0
    assert four == pytest.approx(2 * one, rel=1e-12)
    assert nine == pytest.approx(3 * one, rel=1e-12)
    # per resolution element: × √dispersion_resolution
    per_res = sim.get_band_snr(BAND, nmd=(64, 8, 0), nramps=4, per_resolution=True)
    assert per_res == pytest.approx(four * math.sqrt(2.3), rel=1e-12)


def test_config_file_and_values_that_are_not_what_they_say(tmp_path):
    """A binary file given as --config, a non-numeric bias and a fractional readout n are
    ConfigErrors naming the key (not a UnicodeDecodeError, a ValueError or n truncated)."""
    from slicersim.errors import ConfigError
    from slicersim.io.config import load_config
    binary = tmp_path / "binary.toml"
    binary.write_bytes(bytes(range(128, 256)))
    with pytest.raises(ConfigError, match="cannot parse TOML .*binary.toml"):
        load_config(str(binary))
    with pytest.raises(ConfigError, match=r"\[detector\] bias = 'high': must be a number"):
        load_config({"detector": {"bias": "high"}})
    for text, key in (("[detector]\nreadout_mode = [2.7, 1, 0]\n", r"\[detector\] readout_mode = .*must be \(n, m, d\)"),
                      ("[detector]\nQE = " + str([1.5] * 500) + "\n", r"\[detector\] QE = \[1.5, 1.5[^\]]*…: QE must lie in")):
        bad = tmp_path / "bad.toml"
        bad.write_text(text)
        with pytest.raises(ConfigError, match=key):
            load_config(["cbe", str(bad)])


def test_unknown_config_key_or_table_suggests_the_near_one(tmp_path):
    from slicersim.errors import ConfigError
    from slicersim.io.config import load_config
    bad = tmp_path / "typo.toml"
    bad.write_text("[detector]\ngian = 2.0\n")
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['gian'\] in \[detector\] \(did you mean 'gain'\?\); allowed:"):
        load_config(["cbe", str(bad)])
    bad.write_text("[detecter]\ngain = 2.0\n")
    with pytest.raises(ConfigError, match=r"unknown configuration table \[detecter\] \(did you mean 'detector'\?\)"):
        load_config(["cbe", str(bad)])


@pytest.mark.parametrize("text, message", [
    ('[spectrograph.optics]\ndispersed = ["no", true, false, false, false]\n',
     r"\[spectrograph.optics\] dispersed = .*must be booleans \(true / false\), got 'no'"),
    ("[spectrograph.optics]\ndispersed = [1, 1, 0, 0, 0]\n", r"dispersed = .*must be booleans.*got 1"),
    ("[spectrograph.psf.detector]\nxdisp_sigma = -5\n", r"\[spectrograph.psf.detector\] xdisp_sigma = -5: must be ≥ 0"),
    ("[extraction]\nxdisp_width_insigma = -1\n", r"\[extraction\] xdisp_width_insigma = -1: must be > 0"),
    ("[spectrograph.psf.detector]\nxdisp_sigma = 0.6\n",
     r"xdisp_sigma = 0.6 is used only by the micro-lens-array spectrograph .*remove the key"),
    ("[extraction]\nxdisp_width_insigma = 4\n", r"\[extraction\] xdisp_width_insigma = 4 is used only by the micro-lens"),
])
def test_configuration_booleans_are_booleans_and_every_key_is_used_or_refused(tmp_path, text, message):
    """``dispersed = ["no", …]`` was read as true; ``xdisp_sigma = -5`` and ``xdisp_width_insigma = -1`` were
    accepted and ignored by the slicer (the docs say every key is used or refused)."""
    from slicersim.errors import ConfigError
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    with pytest.raises(ConfigError, match=message):
        build_simulation(["cbe", str(bad)])
    # programmatic optics too: a string is not a truth value
    from slicersim.errors import ParameterError
    from slicersim.instrument.spectrograph import Spectrograph
    with pytest.raises(ParameterError, match=r"optics dispersed\[0\] must be True or False, got 'no'"):
        Spectrograph._make_optics({"temperature": [200.0], "dispersed": ["no"]})


def test_a_toml_nested_too_deeply_is_one_config_error(tmp_path):
    """A 100 000-deep TOML array was a RecursionError (exit 3, 'this is a bug')."""
    from slicersim.errors import ConfigError
    deep = tmp_path / "deep.toml"
    deep.write_text("[detector]\nshape = " + "[" * 100_000 + "]" * 100_000 + "\n")
    with pytest.raises(ConfigError, match=r"configuration file .*deep.toml is not valid TOML for slicersim: .*nested too deeply"):
        build_simulation(str(deep))
    from slicersim.campaign.spec import load_spec
    spec = tmp_path / "spec.toml"
    spec.write_text("seed = " + "[" * 100_000 + "]" * 100_000 + "\n")
    with pytest.raises(ConfigError, match=r"campaign spec .*spec.toml is not valid TOML for slicersim"):
        load_spec(str(spec))
