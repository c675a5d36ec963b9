"""More sources: power law, any sncosmo source by name, kilonova (POSSIS files), CALSPEC files.

Physics checks: the power law has the requested magnitude (sncosmo on its own table, and an
independent trapezoid AB integral) and slicersim 1.4.2's F_λ ∝ (λ/5500 Å)^α values (its
log, /work/notes/issue10_examples142.log: α = −2, bessellr 20, dense-grid normalisation);
sncosmo sources equal ``sncosmo.Model`` directly; the kilonova model is built log-linear in
(t, λ, cos θ), so the interpolated spectra have a closed form.
"""
import urllib.error

import numpy as np
import pytest
import sncosmo
from astropy.cosmology import Planck18
from astropy.io import fits

from slicersim.errors import ParameterError, SpectrumError
from slicersim.sources.kilonova import AngularTimeSeriesSource, kilonova_source
from slicersim.sources.spectra import CALSPEC_URL, snia_spectrum
from slicersim.targets import LazuliSupernova
from slicersim.targets.sources import (LazuliCalSpec, LazuliKilonova, LazuliPowerLaw, LazuliSncosmoTarget,
                                       PowerLaw, SncosmoTarget)

C_AA = 2.99792458e18          # speed of light [Å/s]
WAVES = np.array([5000.0, 6000.0, 8000.0, 10000.0, 15000.0])
#: slicersim 1.4.2, LazuliPowerLaw(alpha=-2, mag=20, band="bessellr"), normalised on a dense 2 Å grid
FLUX_142 = np.array([4.35419e-17, 3.02374e-17, 1.70085e-17, 1.08855e-17, 4.83798e-18])


def _table(target):
    ps = target.pointsource
    return ps.lbda_in, ps.flux_in * ps.flux_ratio


def _ab_mag_trapezoid(lbda, flux, band):
    """m_AB = −2.5 log10(∫ F λ T dλ / ∫ f_AB c/λ² λ T dλ), f_AB = 3631 Jy, on the band's grid."""
    bp = sncosmo.get_bandpass(band)
    x = np.linspace(bp.minwave(), bp.maxwave(), 20001)
    trans = bp(x)
    num = np.trapezoid(np.interp(x, lbda, flux) * x * trans, x)
    den = np.trapezoid(3631e-23 * C_AA / x**2 * x * trans, x)
    return -2.5 * np.log10(num / den)


# --------------------------------------------------------------------------- power law
@pytest.mark.parametrize("alpha", [-2.0, 0.0, 1.5])
def test_powerlaw_magnitude_and_index(alpha):
    target = LazuliPowerLaw(alpha, 20.0, band="bessellr")
    lbda, flux = _table(target)
    assert sncosmo.Spectrum(lbda, flux).bandmag("bessellr", "ab") == pytest.approx(20.0, abs=1e-10)
    assert _ab_mag_trapezoid(lbda, flux, "bessellr") == pytest.approx(20.0, abs=1e-4)
    f = target.pointsource.flambda(WAVES)
    np.testing.assert_allclose(f / f[0], (WAVES / WAVES[0]) ** alpha, rtol=1e-5)       # F_λ ∝ λ^α
    sim = target.simulation                                 # what the instrument sees on its grid
    np.testing.assert_allclose(sim.pointsource_flambda, f[0] * (sim.lbda / WAVES[0]) ** alpha, rtol=1e-5)


def test_powerlaw_matches_slicersim_142_values():
    target = PowerLaw(-2, 20, band="bessellr")
    np.testing.assert_allclose(target.pointsource.flambda(WAVES), FLUX_142, rtol=5e-6)   # 6 printed digits
    assert target.pointsource.flambda(10000.0) / target.pointsource.flambda(5000.0) == pytest.approx(0.25, rel=1e-6)


def test_powerlaw_bad_input():
    with pytest.raises(SpectrumError, match="alpha"):
        PowerLaw(float("nan"), 20)
    with pytest.raises(SpectrumError, match="alpha"):
        PowerLaw("steep", 20)
    with pytest.raises(ParameterError, match="mag"):
        PowerLaw(-2, None)
    with pytest.raises(SpectrumError, match="bessellr"):                 # grid does not cover the band
        PowerLaw(-2, 20, band="bessellr", lbda=np.arange(3000.0, 5000.0, 5.0))
    with pytest.raises(SpectrumError, match="nosuchband"):
        PowerLaw(-2, 20, band="nosuchband")


# --------------------------------------------------------------------------- sncosmo by name
def _sncosmo_direct(source, z, phase, peak_absmag, lbda):
    """sncosmo itself at a rest-frame ``phase``: observer time t = phase (1 + z) from t0 = 0."""
    model = sncosmo.Model(source)
    model.set(z=z, t0=0.0)
    model.set_source_peakabsmag(peak_absmag, "bessellb", "ab", cosmo=Planck18)
    return model.flux(phase * (1 + z), lbda)


def test_sncosmo_source_by_name_equals_sncosmo():
    target = LazuliSncosmoTarget("hsiao-subsampled", 0.5, phase=3.0, peak_absmag=-19.1)
    lbda, flux = _table(target)
    assert lbda[0] == 3000.0 and lbda[-1] == 19990.0
    np.testing.assert_array_equal(flux, _sncosmo_direct("hsiao-subsampled", 0.5, 3.0, -19.1, lbda))
    # (name, version) and the SN Ia shortcut are the same code
    versioned = SncosmoTarget(("hsiao-subsampled", "3.0"), 0.5, phase=3.0, peak_absmag=-19.1)
    np.testing.assert_array_equal(_table(versioned)[1], flux)
    np.testing.assert_array_equal(snia_spectrum(0.5, 3.0, peak_absmag=-19.1)[1], flux)
    sn = LazuliSupernova(0.5, phase=3.0, peak_absmag=-19.1)
    assert sn.get_band_snr() == pytest.approx(target.get_band_snr((4000, 6800), frame="rest"), rel=1e-12)
    # a new redshift recomputes the spectrum (and the band SNR falls with distance)
    snr = target.get_band_snr((4000, 6800), frame="rest")
    target.update(redshift=0.7)
    np.testing.assert_array_equal(_table(target)[1], _sncosmo_direct("hsiao-subsampled", 0.7, 3.0, -19.1,
                                                                      _table(target)[0]))
    assert target.get_band_snr((4000, 6800), frame="rest") < snr


def test_sncosmo_observed_mag_and_own_source():
    target = SncosmoTarget("hsiao-subsampled", 0.3, phase=-5.0, mag=22.0, band="bessellr")
    assert sncosmo.Spectrum(*_table(target)).bandmag("bessellr", "ab") == pytest.approx(22.0, abs=1e-10)
    # a user-built sncosmo.Source (the "own files" route) goes through unchanged
    phase, wave = np.linspace(-20, 50, 71), np.arange(2000.0, 12000.0, 20.0)
    flux = np.exp(-0.5 * (phase[:, None] / 15.0) ** 2) * (wave[None, :] / 5000.0) ** -1.5
    own = sncosmo.TimeSeriesSource(phase, wave, flux, name="my-model")
    target = SncosmoTarget(own, 0.2, phase=4.0, peak_absmag=-18.0)
    lbda, got = _table(target)
    np.testing.assert_array_equal(got, _sncosmo_direct(own, 0.2, 4.0, -18.0, lbda))
    assert lbda[0] >= 2000.0 * 1.2 and lbda[-1] <= 12000.0 * 1.2


def test_unavailable_sncosmo_source_says_how_to_provide_it(monkeypatch):
    from sncosmo.builtins import DATADIR

    def offline(*args, **kwargs):
        raise urllib.error.URLError("no network (test)")
    monkeypatch.setattr(DATADIR, "abspath", offline)            # files absent, download impossible
    with pytest.raises(SpectrumError) as err:
        LazuliSncosmoTarget("nugent-sn2p", 0.1, peak_absmag=-17.0)
    msg = str(err.value)
    assert "\n" not in msg and 'sncosmo source "nugent-sn2p"' in msg
    assert "models/nugent/" in msg and "SNCOSMO_DATA_DIR" in msg and "sncosmo.Source" in msg
    with pytest.raises(SpectrumError, match='sncosmo source "no-such-model" is not a name sncosmo knows'):
        SncosmoTarget("no-such-model", 0.1, peak_absmag=-17.0)


def test_sncosmo_bad_input():
    with pytest.raises(ParameterError, match="exactly one normalisation"):
        SncosmoTarget("hsiao-subsampled", 0.5)
    with pytest.raises(ParameterError, match="exactly one normalisation"):
        SncosmoTarget("hsiao-subsampled", 0.5, peak_absmag=-19, mag=22)
    with pytest.raises(ParameterError, match="its parameters are amplitude"):
        SncosmoTarget("hsiao-subsampled", 0.5, peak_absmag=-19, params={"x1": 1.0})
    with pytest.raises(ParameterError, match="redshift"):
        SncosmoTarget("hsiao-subsampled", -0.5, peak_absmag=-19)
    with pytest.raises(SpectrumError, match="name, a \\(name, version\\) pair"):
        SncosmoTarget(42, 0.5, peak_absmag=-19)


# --------------------------------------------------------------------------- kilonova
KN_PHASE = np.linspace(0.5, 10.0, 20)
KN_WAVE = np.arange(1000.0, 30001.0, 100.0)
KN_COS = np.linspace(0.0, 1.0, 11)
KN_A, KN_B, KN_K = -0.3, -1.2e-4, 1.5                  # log M = a t + b λ + k cos θ (exact under log-linear interp)


def _kn_flux():
    t, lam, c = np.meshgrid(KN_PHASE, KN_WAVE, KN_COS, indexing="ij")
    return np.exp(KN_A * t + KN_B * lam + KN_K * c)           # (phase, wave, cos θ)


@pytest.fixture(scope="module")
def kn_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("kilonova")
    flux = _kn_flux()
    hdus = fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(np.moveaxis(flux, -1, 0), name="MODEL"),
                         fits.ImageHDU(KN_PHASE, name="PHASE"), fits.ImageHDU(KN_WAVE, name="LBDA"),
                         fits.ImageHDU(KN_COS, name="COSTHETA")])
    hdus.writeto(folder / "model.fits")
    with open(folder / "model.txt", "w") as fh:                   # POSSIS text layout
        fh.write(f"{KN_COS.size}\n{KN_WAVE.size}\n{KN_PHASE.size} {KN_PHASE[0]} {KN_PHASE[-1]}\n")
        for i in range(KN_COS.size):
            np.savetxt(fh, np.column_stack([KN_WAVE, flux[:, :, i].T]), fmt="%.17g")
    return folder


def test_kilonova_spectrum_closed_form(kn_files):
    z, phase, theta = 0.05, 3.3, 37.0
    target = LazuliKilonova(str(kn_files / "model.fits"), redshift=z, phase=phase, theta=theta)
    lbda, flux = _table(target)
    # observer frame: F(λ) ∝ exp(b λ / (1+z)); ``phase`` is rest-frame days: observer time phase (1+z)
    np.testing.assert_allclose(flux / flux[0], np.exp(KN_B * (lbda - lbda[0]) / (1 + z)), rtol=1e-9)
    model = sncosmo.Model(target.source)                             # the same as sncosmo directly
    model.set(z=z, t0=0.0, theta=theta)
    model.set_source_peakabsmag(-15.8, "bessellr", "ab", cosmo=Planck18)
    np.testing.assert_allclose(flux, model.flux(phase * (1 + z), lbda), rtol=1e-12)
    # slicersim 1.0 read the phase in the observer frame
    old = LazuliKilonova(str(kn_files / "model.fits"), redshift=z, phase=phase, theta=theta,
                         conventions="slicersim-1.0")
    np.testing.assert_allclose(_table(old)[1], model.flux(phase, lbda), rtol=1e-12)
    # normalisation: at the rest-frame peak (t = 0.5 d, the model fades) the rest-frame spectrum
    # (1+z) F(λ (1+z)) has m = M + μ(z) in bessellr (independent trapezoid integral)
    peak = LazuliKilonova(str(kn_files / "model.fits"), redshift=z, phase=0.5, theta=theta)
    lbda_obs, flux_obs = _table(peak)
    m_rest = _ab_mag_trapezoid(lbda_obs / (1 + z), flux_obs * (1 + z), "bessellr")
    assert m_rest == pytest.approx(-15.8 + Planck18.distmod(z).value, abs=2e-4)
    # the text layout is the same model
    text = LazuliKilonova(str(kn_files / "model.txt"), redshift=z, phase=phase, theta=theta)
    np.testing.assert_allclose(_table(text)[1], flux, rtol=1e-12)
    # an observed magnitude instead
    bright = LazuliKilonova(str(kn_files / "model.fits"), redshift=z, phase=phase, mag=21.0)
    assert sncosmo.Spectrum(*_table(bright)).bandmag("bessellr", "ab") == pytest.approx(21.0, abs=1e-10)


def test_kilonova_viewing_angle_and_phase(kn_files):
    source = kilonova_source(kn_files / "model.fits")
    assert isinstance(source, AngularTimeSeriesSource)
    lam = np.array([4000.0, 9000.0])
    source.set(theta=0.0)
    pole = source.flux(2.2, lam)
    source.set(theta=60.0)
    np.testing.assert_allclose(source.flux(2.2, lam) / pole, np.exp(KN_K * (0.5 - 1.0)), rtol=1e-12)
    source.set(theta=120.0)                                          # symmetric about the equator
    np.testing.assert_allclose(source.flux(2.2, lam) / pole, np.exp(KN_K * (0.5 - 1.0)), rtol=1e-12)
    source.set(theta=0.0)
    np.testing.assert_allclose(source.flux(4.7, lam) / source.flux(2.2, lam), np.exp(KN_A * 2.5), rtol=1e-12)


def test_kilonova_missing_or_bad_file(kn_files, tmp_path):
    for model in ("bulla23", str(tmp_path / "absent.fits")):
        with pytest.raises(SpectrumError) as err:
            LazuliKilonova(model, redshift=0.05)
        msg = str(err.value)
        assert "\n" not in msg and repr(model) in msg and "github.com/mbulla/kilonova_models" in msg
    bad = tmp_path / "bad.txt"
    bad.write_text("3\n10\n5 0.5 10\n1 2 3\n")
    with pytest.raises(SpectrumError, match="POSSIS"):
        LazuliKilonova(str(bad), redshift=0.05)
    with pytest.raises(ParameterError, match="theta"):
        LazuliKilonova(str(kn_files / "model.fits"), redshift=0.05, theta=200.0)


def test_model_and_star_files_that_are_not_regular_files_are_named_so(tmp_path, monkeypatch):
    """A FIFO or a device exists: 'not a regular file', not 'not found' (and never opened)."""
    import os
    monkeypatch.delenv("SLICERSIM_CALSPEC_DIR", raising=False)
    fifo = tmp_path / "model.fits"
    os.mkfifo(fifo)
    for path in (str(fifo), "/dev/zero"):
        with pytest.raises(SpectrumError, match=rf"^kilonova model file: {path} is not a regular file$"):
            LazuliKilonova(path, redshift=0.05)
        with pytest.raises(SpectrumError, match=rf"^CALSPEC file: {path} is not a regular file$"):
            LazuliCalSpec(path)


# --------------------------------------------------------------------------- CALSPEC
def _write_calspec(path, scale, wave_unit="ANGSTROMS"):
    lbda = np.arange(1150.0, 25000.0, 5.0)
    flux = scale * 1e-14 * (lbda / 5000.0) ** -3
    cols = [fits.Column("WAVELENGTH", "D", unit=wave_unit, array=lbda),
            fits.Column("FLUX", "E", unit="FLAM", array=flux),
            fits.Column("STATERROR", "E", unit="FLAM", array=0.01 * flux)]
    fits.HDUList([fits.PrimaryHDU(), fits.BinTableHDU.from_columns(cols)]).writeto(path)
    return lbda, flux.astype(np.float32).astype(float)


def test_calspec_from_user_files(tmp_path, monkeypatch):
    _write_calspec(tmp_path / "bd_17d4708_stisnic_006.fits", 1.0)
    lbda, flux = _write_calspec(tmp_path / "bd_17d4708_stisnic_007.fits", 2.0)
    star = LazuliCalSpec("bd_17d4708", calspec_dir=tmp_path)
    assert star.path.name == "bd_17d4708_stisnic_007.fits"                    # latest version wins
    np.testing.assert_array_equal(_table(star)[0], lbda)
    np.testing.assert_array_equal(_table(star)[1], flux)                     # absolute flux, untouched
    monkeypatch.setenv("SLICERSIM_CALSPEC_DIR", str(tmp_path))
    np.testing.assert_array_equal(_table(LazuliCalSpec("BD_17D4708"))[1], flux)
    direct = LazuliCalSpec(str(tmp_path / "bd_17d4708_stisnic_006.fits"), mag=15.0, band="bessellr")
    assert sncosmo.Spectrum(*_table(direct)).bandmag("bessellr", "ab") == pytest.approx(15.0, abs=1e-10)


def test_calspec_missing_or_bad_file(tmp_path, monkeypatch):
    monkeypatch.delenv("SLICERSIM_CALSPEC_DIR", raising=False)
    for kwargs in ({}, {"calspec_dir": tmp_path}, {"calspec_dir": tmp_path / "nowhere"}):
        with pytest.raises(SpectrumError) as err:
            LazuliCalSpec("gd71", **kwargs)
        msg = str(err.value)
        assert "\n" not in msg and "'gd71'" in msg and CALSPEC_URL in msg and "calspec_dir" in msg
    _write_calspec(tmp_path / "gd71_nm.fits", 1.0, wave_unit="nm")
    with pytest.raises(SpectrumError, match="Angstroms"):
        LazuliCalSpec("gd71", calspec_dir=tmp_path)


def test_spectrum_arguments_name_the_parameter():
    """Strings or a bad temperature are SpectrumErrors naming the argument (were NumPy's ValueError
    or a TypeError from the comparison)."""
    from slicersim.sources.cosmology import redshift_scalings
    from slicersim.sources.spectra import PointSource, blackbody_flambda, validate_spectrum
    with pytest.raises(SpectrumError, match="spectrum: wavelengths must be an array of real numbers"):
        validate_spectrum(["a", "b"], [1.0, 2.0])
    with pytest.raises(SpectrumError, match=r"blackbody temperature \[K\] must be a number"):
        blackbody_flambda([5000.0], "hot")
    with pytest.raises(SpectrumError, match=r"blackbody temperature \[K\] must be > 0"):
        blackbody_flambda([5000.0], -5.0)
    with pytest.raises(SpectrumError, match=r"mag \[AB\] must be finite"):
        PointSource([4000.0, 5000.0], [1.0, 1.0], mag=float("nan"))
    src = PointSource([4000.0, 5000.0], [1.0, 1.0])
    with pytest.raises(SpectrumError, match="flux_ratio must be"):
        src.set_spectrum([4000.0, 6000.0], [1.0, 1.0], flux_ratio=-1.0)
    assert src.lbda_in[-1] == 5000.0                       # a failed change changes nothing
    with pytest.raises(ParameterError, match="from_redshift must be a number"):
        redshift_scalings("0.5", 1.0)


@pytest.mark.parametrize("phase", [1e300, 85.5, -1e300])
def test_a_phase_outside_the_sncosmo_model_is_refused(phase):
    """LazuliSupernova(phase=1e300) was the model's last epoch (sncosmo repeats it) without a word."""
    with pytest.raises(SpectrumError, match=r"phase .* days is outside the range -20 to 85 days \(rest frame\) "
                                            r"of the sncosmo model 'hsiao-subsampled'"):
        LazuliSupernova(1.0, phase=phase)
    assert LazuliSupernova(1.0, phase=85.0).redshift == 1.0
    # slicersim 1.0 counted the phase in the observer frame: hsiao's 85 rest-frame days are 170 at z = 1
    with pytest.raises(SpectrumError, match=r"outside the range -40 to 170 days \(observer frame at redshift 1\)"):
        LazuliSupernova(1.0, phase=phase * 2 if abs(phase) < 1e3 else phase, conventions="slicersim-1.0")
    assert LazuliSupernova(1.0, phase=170.0, conventions="slicersim-1.0").redshift == 1.0
