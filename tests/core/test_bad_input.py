"""Bad input raises one clear error that names the problem; reference-format TOML layering.

Every ``pytest.raises`` pins both the exception class (the most specific one the
library defines) and a regex on the message, so a generic crash deep inside
NumPy (IndexError, ZeroDivision, a NaN result) would fail these tests.
"""
import os
import shutil

import numpy as np
import pytest

from slicersim.io.config import builtin_config_dir, load_config
from slicersim.etc.solve import solve_many
from slicersim.errors import ConfigError, ETCError, ParameterError, ReadoutError, SpectrumError
from slicersim.targets import LazuliTarget, build_simulation
from slicersim.targets import Lazuli3DFlat
from slicersim.targets.sources import LazuliCalSpec
from slicersim.targets import LazuliGalaxy
from slicersim.targets.sources import LazuliPowerLaw
from slicersim.targets import LazuliSupernova
from astropy.io import fits
import warnings
import math
from model_state import (STATE_BAND as BAND_9_12, STATE_FLUX as FLUX_500,  # noqa: F401
                         STATE_LBDA as LBDA_500, assert_rejected_unchanged, flat_target, model_state as state)

BAND = (8000.0, 13600.0)
LBDA = np.linspace(3000.0, 20000.0, 400)
FLUX = np.full(LBDA.size, 1e-17)          # erg/s/cm²/Å, flat and faint


@pytest.fixture(scope="module")
def target():
    return LazuliTarget(LBDA, FLUX)


def test_error_classes_are_value_errors():
    for cls in (SpectrumError, ReadoutError, ConfigError, ETCError):
        assert issubclass(cls, ValueError)


# --------------------------------------------------------------------------- #
#  input spectrum (single target)                                             #
# --------------------------------------------------------------------------- #
def _with(index, value):
    flux = FLUX.copy()
    flux[index] = value
    return flux


@pytest.mark.parametrize("lbda, flux, match", [
    (LBDA, _with(10, np.nan), r"flux contains 1 NaN/inf"),
    (LBDA, _with([3, 7], np.inf), r"flux contains 2 NaN/inf"),
    (LBDA, _with(5, -1e-18), r"flux contains 1 negative"),
    ([], [], r"wavelengths must be a non-empty 1-D array, got shape \(0,\)"),
    (np.stack([LBDA, LBDA]), np.stack([FLUX, FLUX]),
     r"wavelengths must be a non-empty 1-D array, got shape \(2, 400\)"),
    (LBDA, FLUX[:-1], r"flux shape \(399,\) differs from wavelength shape \(400,\)"),
    (LBDA[::-1], FLUX, r"strictly increasing"),
    (np.r_[LBDA[:5], LBDA[4], LBDA[6:]], FLUX, r"strictly increasing"),   # repeated λ
    (np.r_[np.nan, LBDA[1:]], FLUX, r"finite and strictly increasing"),
], ids=["nan", "inf", "negative", "empty", "2-D", "shape", "decreasing", "repeated", "nan-lbda"])
def test_bad_spectrum(lbda, flux, match):
    with pytest.raises(SpectrumError, match=match):
        LazuliTarget(lbda, flux)


def test_single_sample_spectrum():
    with pytest.raises(SpectrumError, match=r"at least 2 samples"):
        LazuliTarget([5000.0], [1e-17])


def test_spectrum_outside_instrument_range():
    lbda = np.linspace(20000.0, 30000.0, 50)
    with pytest.raises(ValueError, match=r"does not overlap the instrument range"):
        LazuliTarget(lbda, np.full(lbda.size, 1e-17))


# --------------------------------------------------------------------------- #
#  readout                                                                     #
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("kwargs, match", [
    (dict(nmd=(1, 8, 0)), r"nmd\[0\] \(n, groups per ramp\) must be an integer in \[2, \d+\], got 1$"),
    (dict(nmd=(0, 8, 0)), r"nmd\[0\] \(n, groups per ramp\) must be an integer in \[2, \d+\], got 0$"),
    (dict(nmd=(16, 0, 0)), r"nmd\[1\] \(m, frames per group\) must be an integer in \[1, \d+\], got 0$"),
    (dict(nmd=(16, 8, -1)), r"nmd\[2\] \(d, dropped frames between groups\) must be an integer in \[0, \d+\], got -1$"),
    (dict(nmd=(16.5, 8, 0)), r"nmd\[0\] \(n, groups per ramp\) must be an integer.*got 16.5$"),
    (dict(nmd=(16, 8)), r"triple \(n, m, d\)"),
    (dict(nmd=(70, 8, 0), max_group=64), r"n = 70 exceeds max_group = 64"),
    (dict(nramps=0), r"nramps must be an integer.*, got 0"),
    (dict(nramps=-2), r"nramps must be an integer.*, got -2"),
    (dict(nramps=1.5), r"nramps must be an integer.*, got 1.5"),
    (dict(nmd=(16, 8, 0), nramps=2.5), r"nramps must be an integer.*, got 2.5"),
], ids=["n=1", "n=0", "m=0", "d<0", "n-float", "pair", "max_group", "r=0", "r<0", "r=1.5", "nmd+r=2.5"])
def test_bad_readout(kwargs, match):
    target = LazuliTarget(LBDA, FLUX)
    before = target.get_readout_config()
    with pytest.raises(ReadoutError, match=match):
        target.change_detector(**kwargs)
    # a refused change leaves the readout untouched
    assert target.get_readout_config() == before


def test_bad_readout_on_simulation_queries(target):
    sim = target.simulation
    with pytest.raises(ReadoutError, match=r"nmd\[1\] \(m, frames per group\)"):
        sim.get_band_snr(BAND, nmd=(16, 0, 0))
    with pytest.raises(ReadoutError, match=r"nramps"):
        sim.get_spectrum(nmd=(16, 8, 0), nramps=0)
    with pytest.raises(ReadoutError, match=r"nmd\[0\] \(n, groups per ramp\)"):
        sim.get_times(nmd=(1, 1, 0))


# --------------------------------------------------------------------------- #
#  configuration                                                               #
# --------------------------------------------------------------------------- #
CBE = os.path.join(builtin_config_dir(), "lazuli_cbe.toml")
EOL = os.path.join(builtin_config_dir(), "lazuli_eol.toml")


@pytest.fixture
def cfgdir(tmp_path):
    """Copy of the built-in configuration directory (curve files resolve next to the TOML)."""
    dst = tmp_path / "lazuli"
    shutil.copytree(builtin_config_dir(), dst)
    return dst


def _cbe_text():
    with open(CBE, encoding="utf-8") as fh:
        return fh.read()


def test_copied_builtin_config_loads(cfgdir):
    # sanity check of the fixture: the unmodified copy must load, so that the
    # failures below come from the single modification
    sim = build_simulation(str(cfgdir / "lazuli_cbe.toml"), "narrow")
    assert sim.detector.ron == 10.0


def test_unknown_key(cfgdir):
    text = _cbe_text().replace("[detector]\n", "[detector]\nbogus_key = 3\n", 1)
    path = cfgdir / "bogus_key.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['bogus_key'\] in \[detector\]"):
        load_config(str(path))
    with pytest.raises(ConfigError, match=r"bogus_key"):
        build_simulation(str(path), "narrow")


def test_unknown_table(cfgdir):
    path = cfgdir / "bogus_table.toml"
    path.write_text(_cbe_text() + "\n[detecter]\nron = 5\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"unknown configuration table \[detecter\]"):
        load_config(str(path))


def test_top_level_key(cfgdir):
    path = cfgdir / "toplevel.toml"
    path.write_text("ron = 5\n" + _cbe_text(), encoding="utf-8")
    with pytest.raises(ConfigError, match=r"top-level key 'ron'"):
        load_config(str(path))


def test_missing_curve_file(cfgdir):
    text = _cbe_text().replace('QE = "qe_h4rg_1p7.ecsv"', 'QE = "does_not_exist.ecsv"')
    assert "does_not_exist.ecsv" in text
    path = cfgdir / "missing_curve.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError, match=r"\[detector\] QE = 'does_not_exist.ecsv': curve file not found"):
        load_config(str(path))


@pytest.mark.parametrize("kind", ["fifo", "zero"])
def test_a_curve_file_that_is_not_a_regular_file_is_named_so_not_missing(tmp_path, kind):
    """A QE or throughput curve path that is a FIFO or a device exists: 'not a regular file', not 'not found'
    (in a TOML file, and in a configuration given as a dict)."""
    path = tmp_path / "qe.ecsv" if kind == "fifo" else "/dev/zero"
    if kind == "fifo":
        os.mkfifo(path)
    toml = tmp_path / "qe.toml"
    toml.write_text(f'[detector]\nQE = "{path}"\n', encoding="utf-8")
    with pytest.raises(ConfigError, match=rf"\[detector\] QE = '{path}': curve file: {path} is not a regular file"):
        load_config(str(toml))
    with pytest.raises(ConfigError, match=rf"\[spectrograph.throughput\] throughput = '{path}': curve file: "
                                          rf"{path} is not a regular file"):
        load_config({"spectrograph.throughput": {"throughput": str(path)}})


@pytest.mark.parametrize("text, match", [
    ("[telescope]\ngain = 2.0\n", r"\[telescope\] has no key\(s\) 'gain': 'gain' belongs in \[detector\]; "),
    ("[spectrograph]\nnoptics = 3\n", r"'noptics' belongs in \[spectrograph.throughput\]; "),
    ("[telescope]\ngain = 2.0\nfoo = 1\n", r"'foo' is unknown; 'gain' belongs in \[detector\]; "),
    ("QE = 0.8\n", r"top-level key 'QE' must live in its table: 'QE' belongs in \[detector\]; "),
    ("[telescope]\ngaine = 2.0\n", r"unknown key\(s\) \['gaine'\] in \[telescope\] \(did you mean 'gain' of "
                                    r"\[detector\]\?\)"),
])
def test_a_key_in_the_wrong_table_names_its_table_and_the_complete_default(tmp_path, text, match):
    path = tmp_path / "mine.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError, match=match) as info:
        load_config(str(path))
    message = str(info.value)
    assert message.startswith(f"{path}: ") and "\n" not in message
    if "belongs" in message:
        assert f"{builtin_config_dir()}/lazuli_cbe.toml" in message and "--config cbe --config FILE" in message


def test_a_partial_configuration_names_the_missing_key_and_the_complete_default(tmp_path):
    """A configuration file replaces the built-in one: a file with a few keys lacks the dispersion; layered on
    'cbe' it is the CBE with those keys changed."""
    path = tmp_path / "partial.toml"
    path.write_text("[detector]\ngain = 2.0\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"the configuration \(partial.toml\) sets neither \[spectrograph\] "
                                          r"dispersion_law nor resolving_power.*does not amend it.*lazuli_cbe.toml.*"
                                          r"config=\['cbe', FILE\]"):
        build_simulation(str(path), "narrow")
    assert build_simulation(["cbe", str(path)], "narrow").detector.gain == 2.0


def test_missing_toml_file(tmp_path):
    with pytest.raises(ConfigError, match=r"configuration file not found"):
        load_config(str(tmp_path / "nope.toml"))


def test_unparsable_toml(tmp_path):
    path = tmp_path / "broken.toml"
    path.write_text("[detector\nron = 3\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"configuration file .*broken.toml is not valid TOML: Expected"):
        load_config(str(path))


def test_unknown_config_name():
    with pytest.raises(ConfigError, match=r"unknown configuration 'foo'"):
        build_simulation("foo", "narrow")
    with pytest.raises(ConfigError, match=r"unknown configuration 'foo'"):
        LazuliTarget(LBDA, FLUX, config="foo")


def test_empty_config_list():
    with pytest.raises(ConfigError, match=r"empty configuration list"):
        load_config([])


def test_unknown_field():
    with pytest.raises(ConfigError, match=r"unknown field 'medium'"):
        build_simulation("cbe", "medium")
    with pytest.raises(ConfigError, match=r"unknown field 'medium'"):
        LazuliTarget(LBDA, FLUX, field="medium")


# reference-format layering ----------------------------------------------------
def test_reference_toml_list_applies_eol_overrides():
    sim = build_simulation(config=[CBE, EOL], field="narrow")
    assert sim.spectrograph.dispersion_resolution == 2.5
    assert sim.detector.ron == 20.0
    assert sim.detector.dark == 1e-2
    # keys the EOL file does not touch keep their CBE value
    assert sim.detector.tframe == 2.83
    # and the list is the same instrument as the built-in "eol" name
    eol = build_simulation("eol", "narrow")
    np.testing.assert_array_equal(sim.lbda, eol.lbda)
    np.testing.assert_array_equal(sim.spectrograph.throughput, eol.spectrograph.throughput)
    # the plain CBE differs (so the comparison above is not vacuous)
    cbe = build_simulation(config=[CBE], field="narrow")
    assert cbe.spectrograph.dispersion_resolution == 2.3 and cbe.detector.ron == 10.0


def test_later_file_overrides_earlier(tmp_path):
    over = tmp_path / "dark.toml"
    over.write_text("[detector]\ndark = 0.5\n", encoding="utf-8")
    cfg = load_config([CBE, str(over)])
    assert cfg["detector"]["dark"] == 0.5
    assert cfg["detector"]["ron"] == 10.0                  # untouched key kept
    assert cfg["_sources"] == [os.path.abspath(CBE), os.path.abspath(str(over))]
    assert build_simulation([CBE, str(over)], "narrow").detector.dark == 0.5
    # reversed order: the CBE comes last and wins
    assert load_config([str(over), CBE])["detector"]["dark"] == 2.8e-3
    assert build_simulation([str(over), CBE], "narrow").detector.dark == 2.8e-3


def test_readout_noise_alias(tmp_path):
    over = tmp_path / "alias.toml"
    over.write_text("[detector]\nreadout_noise = 7.5\n", encoding="utf-8")
    cfg = load_config([CBE, str(over)])
    assert cfg["detector"]["ron"] == 7.5
    assert "readout_noise" not in cfg["detector"]
    assert build_simulation([CBE, str(over)], "narrow").detector.ron == 7.5


# --------------------------------------------------------------------------- #
#  ETC requests (single target)                                                #
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("kwargs, match", [
    (dict(snr=0), r"target SNR must be a finite number > 0, got 0"),
    (dict(snr=-5), r"target SNR must be a finite number > 0, got -5"),
    (dict(snr=float("nan")), r"target SNR must be a finite number > 0, got nan"),
    (dict(snr=float("inf")), r"target SNR must be a finite number > 0, got inf"),
    (dict(snr=10, lbda_range=(9000, 8000)), r"lo < hi, got \(9000, 8000\)"),
    (dict(snr=10, lbda_range=(9000, 9000)), r"lo < hi"),
    (dict(snr=10, lbda_range=BAND, frame="rest"), r"frame='rest' needs a target redshift"),
    (dict(snr=10, lbda_range=BAND, search="bisect"), r"unknown search 'bisect'"),
], ids=["snr=0", "snr<0", "snr=nan", "snr=inf", "lo>hi", "lo=hi", "rest-no-z", "bad-search"])
def test_bad_etc_request(target, kwargs, match):
    before = target.get_readout_config()
    with pytest.raises(ETCError, match=match):
        target.setup_to_snr(**kwargs)
    assert target.get_readout_config() == before


def test_bad_frame_lists_the_valid_ones(target):
    """frame: "rest", "obs" or None only; a typo is a ParameterError with a did-you-mean and the list."""
    before = target.get_readout_config()
    with pytest.raises(ParameterError, match=r"unknown frame 'restframe' \(did you mean 'rest'\?\); "
                                             r"valid: 'rest', 'obs', None"):
        target.setup_to_snr(10, BAND, frame="restframe")
    with pytest.raises(ParameterError, match=r"unknown frame 'galactic'"):
        target.simulation.get_band_snr(BAND, frame="galactic")
    assert target.get_readout_config() == before


def test_band_without_bins(target):
    with pytest.raises(ValueError, match=r"band \(30000.0, 40000.0\) Å contains no bin"):
        target.setup_to_snr(10, lbda_range=(30000, 40000))
    with pytest.raises(ValueError, match=r"contains no bin"):
        target.get_band_snr((30000, 40000))


def test_rest_frame_with_redshift_is_accepted():
    # the same request with a redshift works: the error above is about the redshift only
    tgt = LazuliTarget(LBDA, FLUX, redshift=0.5)
    res = tgt.setup_to_snr(5, lbda_range=(6000, 8000), frame="rest")
    assert res["lbda_range_obs"] == pytest.approx((9000.0, 12000.0))


# --------------------------------------------------------------------------- #
#  batch ETC                                                                   #
# --------------------------------------------------------------------------- #
LB_BATCH = np.linspace(3000.0, 20000.0, 300)
FL_BATCH = np.full((3, LB_BATCH.size), 1e-17)


def _solve(**kwargs):
    args = dict(lbda=LB_BATCH, fluxes=FL_BATCH, snr=10, lbda_ranges=BAND)
    args.update(kwargs)
    return solve_many(**args)


def _fluxes(target_index, sample, value):
    fl = FL_BATCH.copy()
    fl[target_index, sample] = value
    return fl


def test_batch_good_input_solves():
    table = _solve()
    assert len(table) == 3 and np.all(table["nramps"] >= 1) and np.all(table["n"] >= 2)


@pytest.mark.parametrize("kwargs, cls, match", [
    (dict(fluxes=_fluxes(1, 5, np.nan)), SpectrumError, r"target\(s\) \[1\] contain NaN/inf"),
    (dict(fluxes=_fluxes(0, 9, np.inf)), SpectrumError, r"target\(s\) \[0\] contain NaN/inf"),
    (dict(fluxes=_fluxes(2, 5, -1e-20)), SpectrumError, r"target\(s\) \[2\] contain negative"),
    (dict(fluxes=FL_BATCH[:, :-1]), SpectrumError, r"fluxes must have shape \(N, 300\), got \(3, 299\)"),
    (dict(fluxes=np.zeros((0, 300))), SpectrumError, r"fluxes must have shape \(N, 300\), got \(0, 300\)"),
    (dict(lbda=LB_BATCH[::-1]), SpectrumError, r"lbda must be finite and strictly increasing"),
    (dict(lbda=LB_BATCH[:1], fluxes=FL_BATCH[:, :1]), SpectrumError, r"at least 2 wavelengths"),
    (dict(lbda_ranges=np.array([[8000, 9000]] * 2)), ETCError, r"lbda_ranges must have shape \(N, 2\)"),
    (dict(lbda_ranges=[[8000, 9000], [9000, 8000], [8000, 9000]]), ETCError, r"lo < hi"),
    (dict(snr=0), ETCError, r"target SNR must be a finite number > 0"),
    (dict(snr=-3.0), ETCError, r"target SNR must be a finite number > 0"),
    (dict(snr=[10, 0, 10]), ETCError, r"target SNR must be a finite number > 0"),
    (dict(snr=np.nan), ETCError, r"target SNR must be a finite number > 0"),
    (dict(lbda_ranges=(30000, 40000)), ETCError, r"target\(s\) \[0, 1, 2\] contains no instrument bin"),
    (dict(lbda_ranges=[[8000, 9000], [30000, 40000], [8000, 9000]]), ETCError,
     r"band of target\(s\) \[1\] contains no instrument bin"),
    (dict(frame="rest"), ETCError, r"frame='rest' needs the redshifts"),
    (dict(frame="galactic"), ParameterError, r"unknown frame 'galactic'; valid: 'rest', 'obs', None"),
    (dict(search="bisect"), ETCError, r"unknown search 'bisect'"),
    (dict(lbda=np.linspace(20000.0, 30000.0, 300)), SpectrumError, r"do not overlap the instrument range"),
    (dict(config="foo"), ConfigError, r"unknown configuration 'foo'"),
    (dict(field="medium"), ConfigError, r"unknown field 'medium'"),
], ids=["nan", "inf", "negative", "shape", "no-target", "unsorted", "one-sample", "ranges-shape",
        "range-lo>hi", "snr=0", "snr<0", "snr-one-0", "snr-nan", "empty-band-all", "empty-band-one",
        "rest-no-z", "bad-frame", "bad-search", "no-overlap", "bad-config", "bad-field"])
def test_batch_bad_input(kwargs, cls, match):
    with pytest.raises(cls, match=match):
        _solve(**kwargs)


@pytest.fixture(scope="module")
def sn_host():
    return LazuliSupernova(0.5, host="sersic")


@pytest.fixture(scope="module")
def qth():
    return Lazuli3DFlat.from_qth()


def test_types_and_error_messages(sn_host, qth, tmp_path):
    for flag in ("no", 1, None):
        with pytest.raises(ParameterError, match="of_host must be True or False"):
            sn_host.get_spectrum(of_host=flag)
    with pytest.raises(ParameterError, match="band and magsys must be sncosmo names"):
        LazuliPowerLaw(-2, 20, band=["bessellr"])
    galaxy = LazuliGalaxy(0.5)
    with pytest.raises(ParameterError, match="target SNR must be a finite number"):
        galaxy.setup_to_snr("10")
    # CALSPEC stars take a host like every target
    lbda = np.arange(2000.0, 25000.0, 5.0)
    cols = [fits.Column("WAVELENGTH", "D", unit="ANGSTROMS", array=lbda),
            fits.Column("FLUX", "E", unit="FLAM", array=1e-15 * (lbda / 5000.0) ** -2)]
    fits.HDUList([fits.PrimaryHDU(), fits.BinTableHDU.from_columns(cols)]).writeto(tmp_path / "star_stis_001.fits")
    star = LazuliCalSpec("star", calspec_dir=tmp_path, redshift=0.1, host="sersic")
    assert star.host is not None and star.host.redshift == 0.1
    with pytest.raises(ParameterError, match="takes no host"):
        qth.set_host("sersic")
    with pytest.raises(ParameterError, match="use a larger aperture") as err:
        sn_host.get_spectrum(method="aperture", aperture="1e-9-arcsec")
    assert "aperture_radius_insigma" not in str(err.value)


@pytest.mark.parametrize("make", [lambda: LazuliPowerLaw(1000, 20), lambda: LazuliPowerLaw(-1000, 20),
                                  lambda: Lazuli3DFlat.from_qth(1)], ids=["alpha=1000", "alpha=-1000", "1 K lamp"])
def test_clean_errors_without_runtime_warnings(make):
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.raises(SpectrumError):
            make()


@pytest.mark.parametrize("call", [
    lambda t: t.update(nramps=math.nan),                     # ValueError: cannot convert float NaN
    lambda t: t.update(nramps=math.inf),                     # OverflowError
    lambda t: t.update(nramps=None),                         # TypeError
    lambda t: t.change_detector(max_group="x"),              # ValueError: invalid literal for int()
    lambda t: t.update(redshift="1"),                        # TypeError: ufunc 'isfinite'
    lambda t: t.update(config=None),                         # TypeError: 'NoneType' not iterable
    lambda t: t.setup_to_snr("x", (9000, 12000)),            # TypeError: ufunc 'isfinite'
    lambda t: t.simulation.get_band_snr((100, 200)),         # ValueError (doc: SpectrumError)
    lambda t: t.set_throughput("0.5"),                       # CurveError, not a SlicersimError
    lambda t: t.get_spectrum(incl_error=True, seed=-1),      # ValueError
    lambda t: t.simulation.get_cube(seed=1.5),               # TypeError
])
def test_bad_input_raises_slicersim_error(call):
    """errors.py: 'All user-facing errors derive from SlicersimError'.  These raise bare
    ValueError / TypeError / OverflowError / CurveError."""
    t = flat_target()
    assert_rejected_unchanged(t, lambda: call(t))


def test_a_configuration_leaving_the_detector_and_throughput_unset_warns_of_the_ideal_values(tmp_path):
    """A file with the dispersion but no QE, noise, throughput... ran as an ideal instrument (QE 1, no read
    noise) without a word: a file meant to amend the CBE replaced it."""
    import warnings
    from slicersim.assembly import IdealDefaultsWarning
    path = tmp_path / "mine.toml"
    path.write_text("[spectrograph]\nresolving_power = 200\n[detector]\nron = 5.0\n", encoding="utf-8")
    with pytest.warns(IdealDefaultsWarning, match=r"the configuration \(mine.toml\) leaves \[detector\] QE \(1\), "
                                                  r"\[detector\] dark \(0\).*\[spectrograph.throughput\] throughput "
                                                  r"\(1\).*does not amend it.*--config cbe --config FILE") as info:
        sim = build_simulation(str(path), "narrow")
    assert "[detector] ron" not in str(info[0].message) and sim.detector.ron == 5.0
    amend = tmp_path / "amend.toml"
    amend.write_text("[detector]\nron = 5.0\n", encoding="utf-8")
    with warnings.catch_warnings():
        warnings.simplefilter("error", IdealDefaultsWarning)
        for config in ("cbe", "eol", ["cbe", str(amend)]):         # complete, or layered on a complete one
            build_simulation(config, "narrow")
