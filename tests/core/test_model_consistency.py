"""Model consistency: atomic updates, no stale caches, mutable_parameters, one field per
target, Philox noise for spectra and the numpy/OpenCL noisy-cube bound."""
import numpy as np
import pytest

from slicersim.errors import ETCError, ParameterError
from slicersim.sources.extended import Host, SersicProfile
from slicersim.sources.spectra import snia_spectrum
from slicersim.targets import (SPECTRUM_NOISE_STREAM, BlackBody, LazuliBlackBody, LazuliSupernova,
                               LazuliTarget, Supernova, Target)

BAND = (5000.0, 9000.0)


@pytest.fixture(scope="module")
def sn():
    return LazuliSupernova(1.0)


def _snapshot(sim):
    """Every number the getters give (for before/after comparisons)."""
    tel, det, spec = sim.telescope, sim.detector, sim.spectrograph
    lbda, signal, variance = sim.get_spectrum()
    return {"temperature": np.atleast_1d(tel.temperature).tolist(), "emissivity": list(tel.emissivity),
            "nelements": list(tel.nelements), "area": tel.area, "ron": det.ron, "gain": det.gain,
            "nmd": det.nmd, "nramps": sim.nramps, "lbda": lbda, "signal": signal, "variance": variance,
            "throughput": spec.throughput.copy(), "f2p": sim.flambda_to_photon.copy(),
            "thermal": sim.thermal_photons.copy(), "thermal_dark": sim.thermal_dark,
            "snr": sim.get_band_snr(BAND, frame="obs"), "times": sim.get_times(),
            "aperture": sim.aperture_radius_insigma, "optics": {k: list(v) for k, v in spec.optics.items()}}


def _assert_same(a, b):
    assert a.keys() == b.keys()
    for key in a:
        va, vb = a[key], b[key]
        if isinstance(va, np.ndarray):
            np.testing.assert_array_equal(va, vb, err_msg=key)
        else:
            assert va == vb, key


# --------------------------------------------------------------------------- 1. atomic update
@pytest.mark.parametrize("bad, match", [
    (dict(temperature=[350] * 5), r"temperature.*expected length 4"),
    (dict(emissivity=[0.1] * 3), r"emissivity.*expected length 4"),
    (dict(temperature=[350] * 4, ron=-1.0), r"ron"),
    (dict(temperature="hot"), r"telescope"),
    (dict(nramps=3, spatial_scale=-1.0), r"spatial_scale"),
    (dict(ron=5.0, optics={"emissivity": [0.1, 0.1]}), r"emissivity.*expected length 5"),
    (dict(ron=5.0, bogus=1), r"accepted: .*nramps.*ron.*temperature"),
    (dict(aperture_radius_insigma=-2), r"aperture_radius_insigma"),
], ids=["temp-len", "emis-len", "temp+ron", "temp-str", "nramps+scale", "optics-len", "unknown", "aperture"])
def test_failed_simulation_update_changes_nothing(sn, bad, match):
    sim = sn.simulation
    before = _snapshot(sim)
    with pytest.raises(ParameterError, match=match):
        sim.update(**bad)
    _assert_same(before, _snapshot(sim))
    # and it still works: a valid per-mirror update takes effect, then is undone exactly
    sim.update(temperature=[350.0, 293.0, 293.0, 293.0])
    assert sim.get_band_snr(BAND, frame="obs") < before["snr"]
    sim.update(temperature=293.0)
    _assert_same(before, _snapshot(sim))


def test_apply_update_refuses_a_plan_of_another_simulation(sn):
    """apply_update takes the plan_update result of the same simulation: another one's plan is a
    ParameterError naming the plan (it was a bare ValueError), and nothing changes."""
    other = LazuliSupernova(redshift=0.5)
    plan = other.simulation.plan_update(ron=3.0)
    before = _snapshot(sn.simulation)
    with pytest.raises(ParameterError, match="plan: this update was planned for another simulation"):
        sn.simulation.apply_update(plan)
    _assert_same(before, _snapshot(sn.simulation))


def test_per_mirror_temperature_list(sn):
    sim = sn.simulation
    ref = sim.thermal_photons.copy()
    sim.update(temperature=[293.0] * 4)
    try:
        np.testing.assert_allclose(sim.thermal_photons, ref, rtol=1e-13)
    finally:
        sim.update(temperature=293.0)
    np.testing.assert_array_equal(sim.thermal_photons, ref)


def test_component_updates_are_atomic(sn):
    sim = sn.simulation
    tel, det, spec = sim.telescope, sim.detector, sim.spectrograph
    state = (dict(vars(tel)), dict(vars(det)), spec.lbda.copy(), spec.throughput.copy(), dict(spec._params))
    with pytest.raises(ParameterError, match="temperature"):
        tel.update(diameter_ext=4.0, temperature=[1, 2])
    with pytest.raises(ParameterError, match="accepted: diameter_ext"):
        tel.update(diameter=4.0)
    with pytest.raises(ParameterError, match="gain"):
        det.update(ron=3.0, gain=-1.0)
    with pytest.raises(ParameterError, match="accepted: qe"):
        det.update(noise=1.0)
    with pytest.raises(ParameterError, match="spectral_range"):
        spec.update(dispersion_resolution=3.0, spectral_range=(5000, 4000))
    with pytest.raises(ParameterError, match="accepted: spectral_range"):
        spec.update(slit=1)
    assert vars(tel) == state[0]
    assert {k: v for k, v in vars(det).items() if k != "_qe_table"} == \
        {k: v for k, v in state[1].items() if k != "_qe_table"}
    np.testing.assert_array_equal(spec.lbda, state[2])
    np.testing.assert_array_equal(spec.throughput, state[3])
    assert spec._params == state[4]


# --------------------------------------------------------------------------- 2. no stale state
def test_component_changes_take_effect_at_once():
    t = LazuliSupernova(1.0)
    sim = t.simulation
    snr0, f2p0 = sim.get_band_snr(BAND, frame="obs"), sim.flambda_to_photon.copy()
    sim.spectrograph.set_throughput(0.25)                     # directly on the component
    np.testing.assert_array_equal(sim.spectrograph.throughput, 0.25)
    assert not np.array_equal(sim.flambda_to_photon, f2p0)
    assert sim.get_band_snr(BAND, frame="obs") < snr0
    t.set_throughput(1.0)
    assert sim.get_band_snr(BAND, frame="obs") > snr0
    # noptics applies to the file throughput of the Lazuli configuration
    t2 = LazuliSupernova(1.0)
    thr = t2.simulation.spectrograph.throughput.copy()
    snr = t2.simulation.get_band_snr(BAND, frame="obs")
    t2.simulation.update(noptics={"narrow": 2})
    np.testing.assert_allclose(t2.simulation.spectrograph.throughput, thr**2, rtol=1e-14)
    assert t2.simulation.get_band_snr(BAND, frame="obs") < snr
    # direct attribute assignment is seen too
    ron_snr = t2.simulation.get_band_snr(BAND, frame="obs")
    t2.simulation.detector.ron = 100.0
    assert t2.simulation.get_band_snr(BAND, frame="obs") < ron_snr


def test_host_assignment_takes_effect():
    t = LazuliSupernova(1.0)
    sim = t.simulation
    snr0 = sim.get_band_snr(BAND, frame="obs")
    lbda = np.arange(3000.0, 20000.0, 10.0)
    sim.scene.host = Host(SersicProfile(1.0, 0.3, 0.7, 20.0), lbda, np.full(lbda.size, 5e-16))
    snr_host = sim.get_band_snr(BAND, frame="obs")
    assert snr_host < snr0
    sim.scene.host.profile.offset = (0.5, 0.0)                 # moving the host far out is seen
    assert sim.get_band_snr(BAND, frame="obs") > snr_host
    sim.scene.host = None
    assert sim.get_band_snr(BAND, frame="obs") == snr0


def test_resolving_power_and_dispersion_law():
    t = LazuliSupernova(1.0)
    spec = t.simulation.spectrograph
    lbda = spec.lbda.copy()
    with pytest.raises(ParameterError, match="dispersion_law"):
        t.simulation.update(resolving_power=300.0)
    np.testing.assert_array_equal(spec.lbda, lbda)
    t.simulation.update(resolving_power=300.0, dispersion_law=None)     # explicit switch
    assert spec.lbda.size != lbda.size
    np.testing.assert_allclose(spec.resolving_power[5:-5], 300.0, rtol=2e-2)
    assert t.simulation.get_spectrum()[0].size == spec.lbda.size
    with pytest.raises(ParameterError, match="SALT"):
        snia_spectrum(1.0, source="hsiao-subsampled", x1=1.0)
    with pytest.raises(ParameterError, match="SALT"):
        Supernova(1.0, c=0.1)


def test_field_change_takes_effect():
    t = LazuliSupernova(1.0)
    t.update(nmd=(20, 8, 0), nramps=2)
    narrow = t.simulation.spectrograph.spatial_scale
    t.field = "wide"
    assert t.field == "wide" and t.simulation.spectrograph.spatial_scale == 2 * narrow
    assert t.get_readout_config() == {"nmd": (20, 8, 0), "nramps": 2}
    assert t.simulation.field == "wide"


# --------------------------------------------------------------------------- 3. API names
def test_mutable_parameters_are_exactly_the_accepted_names(sn):
    sim = sn.simulation
    names = sim.mutable_parameters
    assert isinstance(names, tuple) and len(set(names)) == len(names)
    for must in ("nramps", "aperture_radius_insigma", "nmd", "ron", "dark", "temperature", "emissivity",
                 "nelements", "noptics", "resolving_power", "spatial_scale", "dispersion_resolution"):
        assert must in names
    for name in names:       # every listed name is routed somewhere
        assert name in sim.own_parameters or any(
            name in c.mutable_parameters for c in (sim.detector, sim.spectrograph, sim.telescope))
    tnames = sn.mutable_parameters
    assert isinstance(tnames, tuple)
    assert {"redshift", "position", "field", "config"} <= set(tnames) and set(names) <= set(tnames)
    with pytest.raises(ParameterError, match="accepted: redshift, position"):
        sn.update(colour=1)


def test_paper_names_and_rest_frame():
    t = LazuliSupernova(1.0, conventions="slicersim-1.0")
    t.setup_to_snr(20)
    assert t.get_exptime() == t.get_exposure_time() == pytest.approx(5071.36)
    sim = t.simulation
    assert sim.redshift == 1.0
    assert sim.get_band_snr((4000, 6800), frame="rest") == sim.get_band_snr((8000, 13600), frame="obs")
    assert t.get_band_snr((4000, 6800), frame="rest") == sim.get_band_snr((8000, 13600), frame="obs")
    sim.redshift = None
    with pytest.raises(ETCError, match="redshift"):
        sim.get_band_snr((4000, 6800), frame="rest")


def test_update_redshift_in_place_keeps_readout():
    t = LazuliSupernova(1.0, phase=5.0, peak_absmag=-19.0)
    t.update(nmd=(30, 8, 0), nramps=2)
    ps, sim = t.pointsource, t.simulation
    t.update(redshift=0.6)
    assert t.pointsource is ps and t.simulation is sim and t.redshift == 0.6 == sim.redshift
    assert t.get_readout_config() == {"nmd": (30, 8, 0), "nramps": 2}
    ref = LazuliSupernova(0.6, phase=5.0, peak_absmag=-19.0)
    ref.update(nmd=(30, 8, 0), nramps=2)
    np.testing.assert_array_equal(t.get_spectrum()[1], ref.get_spectrum()[1])
    assert t.get_band_snr((4000, 6800), frame="rest") == ref.get_band_snr((4000, 6800), frame="rest")
    with pytest.raises(ParameterError, match="redshift"):
        t.update(redshift=-1, ron=1.0)
    assert t.redshift == 0.6 and t.simulation.detector.ron == ref.simulation.detector.ron


def test_update_position_moves_source_and_host():
    t = LazuliSupernova(1.0)
    lbda = np.arange(3000.0, 20000.0, 10.0)
    host = Host(SersicProfile(1.0, 0.3, 0.7, 20.0, offset=(0.1, 0.0)), lbda, np.full(lbda.size, 5e-17))
    t.set_host(host)                                   # offset relative to the target
    scale = t.simulation.spectrograph.spatial_scale
    snr0 = t.get_band_snr(BAND, frame="obs")   # a supernova's bands default to the rest frame
    t.update(position=(3.3, -2.1))
    assert t.simulation.position == (3.3, -2.1)
    assert t.host.profile.offset == pytest.approx((3.3 * scale + 0.1, -2.1 * scale))   # the target's copy
    assert host.profile.offset == (0.1, 0.0)                                            # the user's: untouched
    assert t.get_band_snr(BAND, frame="obs") != snr0
    fixed = Host(SersicProfile(1.0, 0.3, 0.7, 20.0, offset=(0.1, 0.0)), lbda, np.full(lbda.size, 5e-17))
    t.set_host(fixed, relative=False)
    t.update(position=(0.0, 0.0))
    assert t.host.profile.offset == (0.1, 0.0)
    with pytest.raises(ValueError):
        t.update(position=(1.0,))
    assert t.position == (0.0, 0.0)


# --------------------------------------------------------------------------- 4. one field
def test_default_field_is_narrow_not_a_product():
    plain, lazuli = Supernova(1.0, conventions="slicersim-1.0"), LazuliSupernova(1.0, conventions="slicersim-1.0")
    assert plain.field == "narrow"
    np.testing.assert_array_equal(plain.simulation.spectrograph.throughput,
                                  lazuli.simulation.spectrograph.throughput)
    assert plain.setup_to_snr(20)["exposure_time"] == pytest.approx(5071.36)
    assert plain.get_exptime() == lazuli.setup_to_snr(20)["exposure_time"]
    assert BlackBody(6000, 22).field == "narrow"
    lbda = np.linspace(3000, 20000, 200)
    assert Target(lbda, np.full(200, 1e-17)).field == LazuliTarget(lbda, np.full(200, 1e-17)).field
    with pytest.raises(ParameterError, match="several columns"):
        Target(lbda, np.full(200, 1e-17), field=None)
    assert LazuliBlackBody(6000, 22).field == "narrow"


# --------------------------------------------------------------------------- 5. noise
def test_noisy_spectrum_uses_philox(sn):
    from slicersim import rng
    lbda, s1, var = sn.get_spectrum(incl_error=True, seed=12345)
    _, s2, _ = sn.get_spectrum(incl_error=True, seed=12345)
    _, s3, _ = sn.get_spectrum(incl_error=True, seed=12346)
    np.testing.assert_array_equal(s1, s2)
    assert not np.array_equal(s1, s3)
    _, signal, _ = sn.get_spectrum()
    z = rng.normal(12345, np.arange(lbda.size, dtype=np.uint64), SPECTRUM_NOISE_STREAM)[:, 0]
    ok = np.isfinite(var) & (var > 0)
    np.testing.assert_array_equal(s1[ok], signal[ok] + np.sqrt(var[ok]) * z[ok])


@pytest.mark.slow
@pytest.mark.needs_opencl
def test_noisy_cube_numpy_vs_opencl():
    from slicersim.backends.noise import noisy_cube
    sim = LazuliSupernova(1.0).simulation
    a = sim.get_cube(seed=7, backend="numpy")
    b = sim.get_cube(seed=7, backend="opencl")
    # same signal/variance → bit-identical noise
    np.testing.assert_array_equal(noisy_cube(a[0], a[1], 7, backend="numpy"),
                                  noisy_cube(a[0], a[1], 7, backend="opencl"))
    np.testing.assert_array_equal(a[2], noisy_cube(a[0], a[1], 7, backend="numpy"))
    # across backends the expectation/variance differ by ulps: bounded difference
    scale = np.abs(a[0]) + np.sqrt(a[1])
    assert np.all(np.abs(a[2] - b[2]) <= 1e-13 * scale)


def test_field_update_atomic_and_host_follows():
    t = LazuliSupernova(1.0, position=(2.0, 1.0))
    lbda = np.arange(3000.0, 20000.0, 10.0)
    host = Host(SersicProfile(1.0, 0.3, 0.7, 20.0, offset=(0.1, 0.0)), lbda, np.full(lbda.size, 5e-17))
    t.set_host(host)
    sim, offset = t.simulation, t.host.profile.offset
    with pytest.raises(ParameterError, match="ron"):
        t.update(field="wide", ron=-1.0)
    assert t.simulation is sim and t.field == "narrow" and t.host.profile.offset == offset
    t.update(field="wide")
    scale = t.simulation.spectrograph.spatial_scale
    assert t.simulation.scene.host is t.host and t.host is not host          # the target's own copy
    assert t.host.profile.offset == pytest.approx((2.0 * scale + 0.1, 1.0 * scale))
    assert host.profile.offset == (0.1, 0.0)


def test_partial_optics_update_keeps_other_keys(sn):
    sim = sn.simulation
    optics = {k: list(v) for k, v in sim.spectrograph.optics.items()}
    th = sim.thermal_photons.copy()
    sim.update(optics={"temperature": [t + 20 for t in optics["temperature"]]})
    try:
        assert sim.spectrograph.optics["emissivity"] == optics["emissivity"]
        assert np.all(sim.thermal_photons >= th) and np.any(sim.thermal_photons > th)
    finally:
        sim.update(optics={"temperature": optics["temperature"]})
    np.testing.assert_array_equal(sim.thermal_photons, th)


# --------------------------------------------------------------------------- messages (issue 24)
def test_update_errors_name_the_parameter_and_change_nothing(sn):
    """update(): an array value is summarised (not printed whole), unknown names get a did-you-mean
    and the accepted list, unknown noptics components list the valid ones; nothing changes."""
    sim = sn.simulation
    before = _snapshot(sim)
    with pytest.raises(ParameterError, match=r"qe must be a number, a \(λ, QE\) pair of arrays or a curve file, got an array of shape \(1000,\)") as info:
        sim.update(qe=np.linspace(0.1, 0.9, 1000), ron=3.0)
    assert len(str(info.value)) < 300
    components = list(sim.spectrograph.throughput_model.components)
    with pytest.raises(ParameterError, match=rf"unknown noptics key\(s\) 'silver': .*this throughput has 1 "
                                             rf"component: one curve .*; valid keys: '{components[0]}', or one "
                                             r"integer for every component; components are named by set_throughput"):
        sim.update(noptics={"silver": 10})
    with pytest.raises(ParameterError, match=r"unknown simulation parameter\(s\) \['gian'\] \(did you mean 'gain'\?\); "
                                             r"accepted: nramps"):
        sim.update(gian=2.0)
    with pytest.raises(ParameterError, match=r"unknown target parameter\(s\) \['redshfit'\] \(did you mean 'redshift'\?\)"):
        sn.update(redshfit=2.0)
    with pytest.raises(ParameterError, match=r"gain \[adu / electron\] must be in \(0, 1000\], got 0"):
        sim.update(gain=0.0, nramps=4)
    with pytest.raises(ParameterError, match=r"guiding_sigma \[arcsec\] must be ≥ 0"):
        sim.update(guiding_sigma=-1.0, ron=1.0)
    with pytest.raises(ParameterError, match=r"spatial_scale \[arcsec\] must be > 0"):
        sim.update(spatial_scale=0.0)
    _assert_same(before, _snapshot(sim))


def test_partial_band_error_names_keyword_and_flag(sn):
    """A partly covered band: the message names the Python keyword and the CLI flag."""
    from slicersim.errors import SpectrumError
    with pytest.raises(SpectrumError, match=r"allow_partial=True in Python, --allow-partial on the command line"):
        sn.get_band_snr((7000, 9000))


def test_misspelt_get_cube_keyword_is_named():
    """get_cube(sed=1) gave build_cube's TypeError."""
    from slicersim import LazuliSupernova
    from slicersim.errors import ParameterError
    with pytest.raises(ParameterError, match=r"unknown keyword of get_cube 'sed' \(did you mean 'seed'\?\)"):
        LazuliSupernova(0.5).simulation.get_cube(sed=1)
