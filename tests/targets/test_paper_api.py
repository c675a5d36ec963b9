"""The API of the slicersim paper (sections Target, Simulation, ETC, variance sources) runs as written.

Every call below is spelled as in ``slicersim_paper.tex``: a warning other than a
DeprecationWarning fails the test (``filterwarnings``), so a renamed keyword may warn but
nothing may break or change meaning silently.  One Lazuli SN Ia at z = 1 in the narrow field.
"""
import numpy as np
import pytest

import slicersim

pytestmark = pytest.mark.filterwarnings("error", "default::DeprecationWarning")

#: the paper's band: rest-frame [400, 680] nm
BAND = (4000, 6800)
#: the paper's eight variance sources
VARIANCE_SOURCES = {"dark", "ron", "roic_glow", "thermal_dark", "thermal", "pointsource", "background", "host"}


@pytest.fixture(scope="module")
def target():
    return slicersim.LazuliSupernova(redshift=1)


def test_target_holds_a_simulation_with_its_components(target):
    """``snia = slicersim.LazuliSupernova(redshift=1)``; the Simulation's Detector has nmd, ron,
    tframe, max_group (64 groups per ramp by default), the Spectrograph lbda and throughput, every
    object its mutable parameters."""
    simulation = target.simulation
    detector = simulation.detector
    n, m, d = detector.nmd
    assert n >= 2 and m >= 1 and d >= 0
    assert detector.ron > 0 and detector.tframe > 0 and detector.max_group == 64
    assert np.all(np.diff(simulation.spectrograph.lbda) > 0)
    assert np.shape(simulation.spectrograph.throughput) == simulation.spectrograph.lbda.shape
    assert {"ron", "nmd", "noptics", "dispersion_resolution", "temperature"} <= set(simulation.mutable_parameters)


def test_update_changes_a_mutable_parameter_everywhere(target):
    """``.update`` of an object changes a mutable parameter (here the read-out noise)."""
    simulation = target.simulation
    ron = simulation.detector.ron
    try:
        simulation.detector.update(ron=2 * ron)
        assert simulation.detector.ron == 2 * ron
        assert simulation.get_variance_contribution()["ron"] is not None
    finally:
        simulation.detector.update(ron=ron)


def test_band_snr_and_fetch_snr_in_the_rest_frame(target):
    """``simulation.get_band_snr()`` of a target with a redshift is rest-frame by default;
    ``simulation.fetch_snr(20, [4000, 6800], frame="rest")`` returns the readout (nmd, nramps)
    reaching SNR 20 per resolution element."""
    simulation = target.simulation
    assert simulation.get_band_snr(BAND) == simulation.get_band_snr(BAND, frame="rest")
    res = simulation.fetch_snr(20, BAND, frame="rest")
    assert len(res["nmd"]) == 3 and res["nramps"] >= 1
    assert res["snr_per_resolution"] >= 20 * 0.99
    assert res["lbda_range_obs"] == (8000.0, 13600.0)                 # (1 + z) × the rest band


def test_setup_to_snr_and_exposure_times(target):
    """``target.setup_to_snr()`` sets the fitted readout; ``target.get_exptime()``,
    ``target.get_exposure_time()`` and ``simulation.get_times()`` give its exposure time;
    ``target.change_detector(nmd=..., nramps=...)`` sets one directly."""
    simulation = target.simulation
    fetched = simulation.fetch_snr(20, BAND, frame="rest")
    target.setup_to_snr(20, BAND)
    assert tuple(simulation.detector.nmd) == tuple(fetched["nmd"])
    times = simulation.get_times()
    assert target.get_exptime() == target.get_exposure_time() == times["exposure_time"]
    assert times["exposure_time"] == pytest.approx(fetched["exposure_time"])
    target.change_detector(nmd=(16, 8, 0), nramps=2)
    assert tuple(simulation.detector.nmd) == (16, 8, 0) and simulation.get_times()["nramps"] == 2


def test_spectrum_cube_and_variance_sources(target):
    """``target.get_spectrum()``, ``target.get_cube()`` ((signal, variance) without a seed; a seed
    adds a noisy realisation and is recorded as ``.seed``), ``simulation.get_variance_contribution()`` with the
    paper's eight variance sources, ``target.change_spectrograph(field=...)``."""
    target.change_detector(nmd=(16, 8, 0), nramps=1)
    spectrum = target.get_spectrum()
    assert isinstance(spectrum, tuple) and len(spectrum[0]) == target.simulation.spectrograph.lbda.size
    cube = target.get_cube()
    assert len(cube) == 2 and cube.seed is None and cube[0].shape == cube[1].shape
    noisy = target.get_cube(seed=3)
    assert len(noisy) == 3 and noisy.seed == 3 and noisy[2].shape == cube[0].shape
    assert np.array_equal(noisy[0], cube[0])                          # the same expected cube
    assert VARIANCE_SOURCES <= set(target.simulation.get_variance_contribution())
    target.change_spectrograph(field="wide")
    try:
        assert target.simulation.get_band_snr(BAND) > 0
    finally:
        target.change_spectrograph(field="narrow")
