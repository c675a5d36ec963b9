"""Validation: ETC search bounds, aperture checks on every backend, physical configuration
checks, band coverage, max_group everywhere, offline sncosmo sources."""
import subprocess
import sys
import threading
import warnings

import numpy as np
import pytest

from slicersim.errors import ConfigError, ETCError, ParameterError, ReadoutError, SpectrumError
from slicersim.snr import search as S
from slicersim.etc import solve_many
from slicersim.snr.bands import BandCoverageWarning
from slicersim.io.config import builtin_config_dir, load_config
from slicersim.targets import LazuliSupernova, LazuliTarget

BACKENDS = ["numpy", pytest.param("opencl", marks=pytest.mark.needs_opencl)]


def within(seconds, func, *args, **kwargs):
    """Run func in a daemon thread; fail (instead of hanging) when it takes longer."""
    box = {}

    def run():
        try:
            box["value"] = func(*args, **kwargs)
        except BaseException as exc:  # noqa: BLE001
            box["error"] = exc
    th = threading.Thread(target=run, daemon=True)
    th.start()
    th.join(seconds)
    assert not th.is_alive(), f"{getattr(func, '__name__', func)} still running after {seconds} s"
    if "error" in box:
        raise box["error"]
    return box.get("value")


@pytest.fixture(scope="module")
def sn():
    return LazuliSupernova(1.0)


# --------------------------------------------------------------------------- 1. ETC bounds
def test_exact_choice_same_as_former_loop():
    rng = np.random.default_rng(12)
    n, m, d = S.candidate_readouts(2, 64, 0)
    shape = np.sqrt(np.tile(np.arange(2, 65), 3)) * np.repeat([1.0, 0.9, 0.7], 63)
    for case in range(200):
        N = int(rng.integers(1, 5))
        snr1 = rng.uniform(0.5, 50, (N, 1)) * shape[None] * rng.uniform(0.9, 1.1, (N, n.size))
        if case % 7 == 0:
            snr1[:, rng.integers(0, n.size, 5)] = np.nan
        if case % 11 == 0:
            snr1[0] = np.nan
        if case % 5 == 0:   # exact boundaries snr1_k √r = target
            k, r = rng.integers(n.size), rng.integers(1, 300)
            target = np.full(N, snr1[0, k] * np.sqrt(r))
        else:
            target = rng.uniform(1, 300, N) * 10 ** rng.uniform(-1, 0.5)
        old = S.exact_choice_loop(snr1, n, m, d, target)
        new = S.exact_choice(snr1, n, m, d, target)
        for key in old:
            np.testing.assert_array_equal(new[key], old[key], err_msg=f"case {case} {key}")


def test_exact_choice_cost_independent_of_ramps():
    n, m, d = S.candidate_readouts(2, 64, 0)
    snr1 = np.ones((1, n.size))
    out = within(10, S.exact_choice, snr1, n, m, d, np.array([2000.0]))     # 4e6 ramps: fine
    assert out["nramps"][0] == 4_000_000 and out["n"][0] > 0
    out = within(10, S.exact_choice, snr1, n, m, d, np.array([1e9]), max_frames=1e7)
    assert out["n"][0] == 0 and out["limited"][0]


def test_setup_to_snr_1e9_raises(sn):
    with pytest.raises(ETCError, match=r"1e\+09.*8000–13600 Å.*MAX_TOTAL_EXPOSURE"):
        within(60, sn.setup_to_snr, 1e9)


def test_solve_many_1e9_raises():
    lb = np.linspace(3000, 20000, 300)
    fl = np.full((2, lb.size), 1e-17)
    with pytest.raises(ETCError, match=r"target 1: .*1e\+09.*6000–8000 Å.*MAX_TOTAL_EXPOSURE"):
        within(60, solve_many, lb, fl, [20, 1e9], (6000, 8000))


@pytest.mark.parametrize("snr", [1e6, 1e9])
def test_reference_walk_below_target_raises(sn, snr):
    with pytest.raises(ETCError, match="exposure limit"):
        within(60, sn.setup_to_snr, snr, search="reference")


def test_reference_walk_normal_target_unchanged(sn):
    res = sn.setup_to_snr(20, search="reference")
    assert res["nramps"] >= 1 and res["exposure_time"] < S.MAX_TOTAL_EXPOSURE


def test_cli_etc_huge_snr_fails_fast():
    proc = subprocess.run([sys.executable, "-m", "slicersim", "etc", "--redshift", "1", "--snr", "1e9"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode != 0
    assert "MAX_TOTAL_EXPOSURE" in proc.stdout + proc.stderr


# --------------------------------------------------------------------------- 2. aperture
BAD_APERTURES = [dict(position=(100.0, 0.0)), dict(position=(0.0, -40.0)), dict(position=(np.nan, 0.0)),
                 dict(ap=0.0), dict(ap=-1.0), dict(ap=np.nan), dict(ap=1e-3, position=(0.2, 0.2))]


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("case", BAD_APERTURES, ids=str)
def test_bad_aperture_same_error_on_every_backend(backend, case):
    """Refused before any kernel, with the same ParameterError on every backend: at
    construction / update when the value itself is invalid (NaN position, radius ≤ 0), at
    the first use when only the combination is (out of field, an aperture with no cell)."""
    case = dict(case)
    ap = case.pop("ap", None)
    with pytest.raises(ParameterError, match="position|aperture"):
        tgt = LazuliSupernova(1.0, **case)
        if ap is not None:
            tgt.simulation.update(aperture_radius_insigma=ap)
        tgt.setup_to_snr(20, backend=backend)


def test_aperture_near_edge_still_fine():
    tgt = LazuliSupernova(1.0, position=(20.0, 10.0))
    assert tgt.setup_to_snr(20)["nramps"] >= 1


# --------------------------------------------------------------------------- 3. configuration
def _layer(tmp_path, text, name="bad.toml"):
    path = tmp_path / name
    path.write_text(text)
    return ["cbe", str(path)]


BAD_CONFIG = [
    ("[telescope]\nemissivity = [0.05, 1.2, 0.02, 0.02]", r"\[telescope\] emissivity = .*\[0\.05, 1\.2"),
    ("[spectrograph.optics]\nemissivity = [0.05, -0.1, 0.03, 0.03, 0.03]", r"\[spectrograph.optics\] emissivity"),
    ("[telescope]\ntemperature = -3", r"\[telescope\] temperature = -3: must be ≥ 0"),
    ("[spectrograph.optics]\ntemperature = [230, -1, 228, 226, 229]", r"\[spectrograph.optics\] temperature"),
    ("[detector]\nQE = 1.3", r"\[detector\] QE = 1.3: QE must lie in \[0, 1\]"),
    ("[detector]\nQE = -0.1", r"\[detector\] QE"),
    ("[spectrograph.throughput]\nthroughput = 1.5", r"\[spectrograph.throughput\] throughput = 1.5"),
    ("[detector]\nsaturation = 0", r"\[detector\] saturation = 0: must be > 0"),
    ("[detector]\nsaturation = -5", r"\[detector\] saturation"),
    ("[detector]\ntframe = 0", r"\[detector\] tframe = 0"),
    ("[detector]\ntframe = nan", r"\[detector\] tframe = nan: must be finite"),
    ("[detector]\ntframe = inf", r"\[detector\] tframe = inf: must be finite"),
    ("[detector]\nshape = [0, 4096]", r"\[detector\] shape = \[0, 4096\]"),
    ("[detector]\ndark = -1e-3", r"\[detector\] dark"),
    ("[detector]\nron = -1", r"\[detector\] ron"),
    ("[detector]\nroic_glow = -1", r"\[detector\] roic_glow"),
    ("[detector]\ngain = 0", r"\[detector\] gain = 0: must be > 0"),
    ("[detector]\ngain = -1", r"\[detector\] gain"),
    ("[telescope]\ndiameter_int = 3.0", r"\[telescope\] diameter_int = 3.0: must be smaller than diameter_ext"),
    ("[telescope]\ndiameter_int = 3.5", r"\[telescope\] diameter_int"),
    ("[detector]\nreadout_mode = [70, 8, 0]", r"\[detector\] readout_mode = \[70, 8, 0\]: n = 70 exceeds max_group"),
    ("[extraction]\naperture_radius_insigma = 0", r"\[extraction\] aperture_radius_insigma = 0"),
    # issue 26: bounded by the readout (validation.MAX_GROUPS), used or refused
    ("[detector]\nmax_group = 1e9", r"\[detector\] max_group = 1000000000.0: must be ≤ 4096"),
    ("[detector]\nmin_group = 5000", r"\[detector\] min_group = 5000: must be ≤ 4096"),
    ("[detector]\nreadout_mode = [4, 1, 1000000000]", r"\[detector\] readout_mode = .*d, dropped frames"),
    ("[spectrograph]\nanamorphosis = 0", r"\[spectrograph\] anamorphosis = 0: must be one or two integers ≥ 1"),
    ("[spectrograph]\nspatial_shape = [58.5, 58]", r"\[spectrograph\] spatial_shape\[0\]"),
    ("[spectrograph.psf.spatial]\npsf_profile = \"foo\"",
     r"\[spectrograph.psf.spatial\] psf_profile 'foo'; valid: 'normal', 'gaussian'"),
    ("[spectrograph.psf.spatial]\nguiding_profile = \"airy\"", r"\[spectrograph.psf.spatial\] guiding_profile"),
    # a read noise of 1e300 squared overflowed the variance model (OverflowError, exit 3)
    ("[detector]\nron = 1e300", r"\[detector\] ron = 1e\+300: must be ≤ 10000"),
    ("[detector]\ngain = 1e300", r"\[detector\] gain = 1e\+300: must be ≤ 1000"),
    ("[detector]\ndark = 1e300", r"\[detector\] dark = 1e\+300: must be ≤ 1e\+06"),
    ("[detector]\ntframe = 1e300", r"\[detector\] tframe = 1e\+300: must be ≤ 10000"),
    ("[detector]\nshape = [100000000, 100000000]", r"\[detector\] shape = .*two integers in \[1, 65536\]"),
    # the spectrograph's own check named neither the table nor the key's place ("dispersion_scale must be > 0")
    ("[spectrograph]\ndispersion_scale = -1", r"\[spectrograph\] dispersion_scale = -1: must be > 0"),
    ("[spectrograph]\nspectral_range = [9000, 4000]",
     r"\[spectrograph\] spectral_range = \[9000, 4000\]: must be \[min, max\] with 0 < min < max"),
]


@pytest.mark.parametrize("text, match", [
    ("[spectrograph]\nspatial_scale = 0.1", r"\[spectrograph\] spatial_scale = 0.1: the narrow field's cells are 0.04"),
    ("[spectrograph]\nanamorphosis = [1, 1]", r"\[spectrograph\] anamorphosis = \[1, 1\]: the slicer spectrograph's "
                                             r"anamorphosis is \[1, 2\]"),
])
def test_config_keys_a_field_or_the_spectrograph_would_ignore_are_refused(tmp_path, text, match):
    """Issue 26: a key replaced by the field (spatial_scale) or fixed by the spectrograph kind
    (anamorphosis) is refused, not silently ignored; the values they would take are accepted."""
    from slicersim.assembly import build_simulation
    cfg = _layer(tmp_path, text)
    with pytest.raises(ConfigError, match=match):
        build_simulation(cfg, "narrow")
    ok = _layer(tmp_path, "[spectrograph]\nspatial_scale = 0.08\nanamorphosis = [1, 2]")
    assert build_simulation(ok, "wide").spectrograph.spatial_scale == 0.08


@pytest.mark.parametrize("text, match", BAD_CONFIG)
def test_unphysical_config_refused(tmp_path, text, match):
    cfg = _layer(tmp_path, text)
    with pytest.raises(ConfigError, match=match):
        load_config(cfg)
    with pytest.raises(ConfigError, match=match):
        LazuliTarget(np.linspace(3000, 20000, 50), np.full(50, 1e-17), config=cfg)


@pytest.mark.parametrize("table, key, column", [("spectrograph.throughput", "throughput", "narrow,wide"),
                                                ("detector", "QE", "qe")])
@pytest.mark.parametrize("bad", [1.2, -0.05])
def test_curve_values_outside_unit_interval_refused(tmp_path, table, key, column, bad):
    cols = column.split(",")
    rows = [f"{lb}," + ",".join("0.5" for _ in cols) for lb in range(3000, 20001, 1000)]
    rows[5] = rows[5].rsplit(",", 1)[0] + f",{bad}"
    (tmp_path / "curve.csv").write_text("wavelength," + column + "\n" + "\n".join(rows) + "\n")
    cfg = _layer(tmp_path, f'[{table}]\n{key} = "curve.csv"')
    with pytest.raises(ConfigError, match=rf"\[{table}\] {key} = .*curve.csv.*must lie in \[0, 1\]"):
        load_config(cfg)


def test_builtin_configs_valid():
    for name in ("cbe", "eol"):
        load_config(name)
    assert builtin_config_dir()


def test_failed_change_configuration_keeps_old(tmp_path):
    tgt = LazuliSupernova(1.0)
    sim, cfg = tgt.simulation, tgt.config
    with pytest.raises(ConfigError):
        tgt.change_configuration(_layer(tmp_path, "[detector]\ngain = -1"))
    assert tgt.simulation is sim and tgt.config == cfg
    assert tgt.setup_to_snr(20)["nramps"] >= 1


# --------------------------------------------------------------------------- 4. bands, max_group
def test_band_mostly_outside_grid_refused(sn):
    with pytest.raises(SpectrumError, match=r"only 25\.1 % inside the instrument grid"):
        sn.setup_to_snr(20, lbda_range=(16000, 20000), frame="obs")
    # allow_partial cannot lower the floor, and the message says so
    with pytest.raises(SpectrumError, match=r"at least 50 % needed, even with allow_partial=True"):
        sn.setup_to_snr(20, lbda_range=(16000, 20000), frame="obs", allow_partial=True)
    with pytest.raises(SpectrumError, match=r"% inside the instrument grid"):
        sn.simulation.get_band_snr((1000, 4500))
    lb = np.linspace(3000, 20000, 300)
    with pytest.raises(SpectrumError, match=r"target\(s\) \[1\].*% inside the instrument grid"):
        solve_many(lb, np.full((2, lb.size), 1e-17), 20, [[6000, 8000], [16000, 20000]])


def test_band_partly_outside_grid_warns(sn):
    # single-target calls refuse a partly covered band unless allow_partial=True (snr/bands.py)
    with pytest.raises(SpectrumError, match=r"only 66\.9 % inside the instrument grid"):
        sn.setup_to_snr(20, lbda_range=(15000, 18000), frame="obs")
    with pytest.warns(BandCoverageWarning, match=r"only 66\.9 % inside the instrument grid"):
        sn.setup_to_snr(20, lbda_range=(15000, 18000), frame="obs", allow_partial=True)
    lb = np.linspace(3000, 20000, 300)
    with pytest.warns(BandCoverageWarning, match=r"target\(s\) \[1\].*66\.9 % inside the instrument grid"):
        solve_many(lb, np.full((2, lb.size), 1e-17), 20, [[6000, 8000], [15000, 18000]])


def test_band_partly_covered_by_spectrum_warns():
    lb = np.linspace(3000, 9000, 300)
    tgt = LazuliTarget(lb, np.full(lb.size, 1e-17))
    with pytest.raises(SpectrumError, match=r"covers only 50\.0 %"):
        tgt.setup_to_snr(5, lbda_range=(8000, 10000))
    with pytest.warns(BandCoverageWarning, match=r"covers only 50\.0 %"):
        tgt.setup_to_snr(5, lbda_range=(8000, 10000), allow_partial=True)
    with pytest.warns(BandCoverageWarning, match=r"covers only 50\.0 %"):
        solve_many(lb, np.full((1, lb.size), 1e-17), 5, (8000, 10000))
    with warnings.catch_warnings():
        warnings.simplefilter("error", BandCoverageWarning)
        tgt.setup_to_snr(5, lbda_range=(6000, 8000))


def test_nmd_beyond_max_group_refused_everywhere():
    tgt = LazuliSupernova(1.0)
    sim = tgt.simulation
    with pytest.raises(ReadoutError, match="max_group"):
        sim.update(nmd=(70, 8, 0))
    with pytest.raises(ReadoutError, match="max_group"):
        sim.get_band_snr((8000, 9000), nmd=(70, 8, 0))
    with pytest.raises(ReadoutError, match="max_group"):
        sim.update(max_group=10)          # current nmd (16, 8, 0) would exceed it
    with pytest.raises(ReadoutError, match="max_group"):
        tgt.get_ramps(nmd=(70, 8, 0), nramps=1)
    assert tuple(sim.detector.nmd) == (16, 8, 0)


# --------------------------------------------------------------------------- 5. sncosmo offline
def test_offline_sncosmo_source_named(tmp_path, monkeypatch):
    """salt2 needs files sncosmo downloads: with an empty data directory and the network cut (the
    download raises at once: no real request, no timeout), the error names the source, what is
    missing and where to put it."""
    import urllib.error
    import sncosmo.utils
    from sncosmo.builtins import DATADIR
    from sncosmo.models import _SOURCES

    def no_network(*args, **kwargs):
        raise urllib.error.URLError("network disabled in this test")
    monkeypatch.setattr(DATADIR, "_checked_rootdir", str(tmp_path))      # an empty data directory
    monkeypatch.setattr(DATADIR, "_get_url", no_network)
    monkeypatch.setattr(sncosmo.utils, "_download_file", no_network)
    monkeypatch.setattr(_SOURCES, "_instances", type(_SOURCES._instances)())  # nothing loaded before
    # (salt2 T23, salt3 and salt3-nir load offline from jax-bandflux's files: an older version needs them)
    with pytest.raises(SpectrumError, match=r'sncosmo source "salt2, version 2.4" could not be loaded \(needs '
                                            r'download; offline\?\) — available offline: hsiao-subsampled') as err:
        LazuliSupernova(1.0, source=("salt2", "2.4"))
    msg = str(err.value)
    assert "put sncosmo's 'models/salt2/" in msg                                 # the files it needs
    assert str(tmp_path) in msg and "SNCOSMO_DATA_DIR" in msg                   # where to put them
    assert "URLError" in msg and "network disabled in this test" in msg         # why it failed
    assert not list(tmp_path.iterdir())                                         # nothing written


def test_reference_walk_beyond_max_group_refused():
    with pytest.raises(ETCError, match=r"readout \(70, 8, 0\), beyond max_group = 64"):
        S.check_reference_result(20.0, (8000, 9000), 13.0, 13.1, 100.0, 2.83, nmd=(70, 8, 0), max_group=64)
    S.check_reference_result(20.0, (8000, 9000), 13.0, 13.1, 100.0, 2.83, nmd=(64, 8, 0), max_group=64)


def test_nan_position_psf_parameter_error():
    """A NaN position is refused where it enters (the point source), so no PSF path — NumPy
    or the OpenCL cube builder — ever sees it; the PSF functions also refuse it themselves."""
    with pytest.raises(ParameterError, match="position must be finite"):
        LazuliSupernova(1.0, position=(np.nan, 0.0))
    tgt = LazuliSupernova(1.0)
    with pytest.raises(ParameterError, match="position must be finite"):
        tgt.update(position=(0.0, np.inf))
    from slicersim.physics.psf import gaussian_psf_fractions
    with pytest.raises(ParameterError, match="position must be finite"):
        gaussian_psf_fractions(np.ones(2), np.ones(2), (5, 5), (np.nan, 0.0))
