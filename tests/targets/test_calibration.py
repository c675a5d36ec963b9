"""Calibration exposures (issue 10): QTH flats, Fabry–Perot exposures, flat-field structure.

Expectations are physics (Planck, AB magnitudes via sncosmo, the Airy function's peaks,
half-maximum points and period mean, flux conservation, readout-time scaling, lognormal
moments), never the implementation's output copied into the test.
"""
import math

import numpy as np
import pytest
from model_state import short_range_toml  # noqa: F401  (a fixture)

from slicersim.errors import ConfigError, ParameterError, SpectrumError
from slicersim.sources.lamps import (CalibrationLamp, FabryPerotEtalon, TabulatedEtalon, fabry_perot_lamp,
                                     qth_lamp)
from slicersim.targets.calibration import (DEFAULT_ETALON_FSR, FlatFieldStructure, Flat3DCalibration,
                                           Lazuli3DFlat, locate_peaks)


@pytest.fixture(scope="module")
def qth():
    return Lazuli3DFlat.from_qth()


@pytest.fixture(scope="module")
def qth_cube(qth):
    return qth.get_cube()


# --------------------------------------------------------------------------- lamp spectra
def test_qth_lamp_is_a_3000K_black_body_of_the_requested_magnitude():
    import sncosmo
    lamp = qth_lamp(mag=12.0, band="bessellr")
    lbda = np.arange(3000.0, 20000.0, 0.5)
    s = lamp.surface_brightness(lbda)
    assert sncosmo.Spectrum(lbda, s).bandmag("bessellr", "ab") == pytest.approx(12.0, abs=1e-6)
    # Wien: B_λ peaks at λ T = 2.897772e7 Å K
    assert lbda[np.argmax(s)] == pytest.approx(2.897772e7 / 3000.0, abs=1.0)
    # Planck ratio between two wavelengths, hc/k = 1.438777e8 Å K
    c2 = 1.438777e8
    ratio = (6000 / 12000) ** -5 * math.expm1(c2 / 12000 / 3000) / math.expm1(c2 / 6000 / 3000)
    assert lamp.surface_brightness(6000.0) / lamp.surface_brightness(12000.0) == pytest.approx(ratio, rel=1e-6)
    # one magnitude brighter: 10^0.4 more light
    assert qth_lamp(mag=11.0).surface_brightness(9000.0) / lamp.surface_brightness(9000.0) == \
        pytest.approx(10 ** 0.4, rel=1e-10)


def test_airy_etalon_peaks_half_maximum_and_period_mean():
    et = FabryPerotEtalon(optical_thickness=5.0, finesse=30.0, peak_transmission=0.8)
    assert et.fsr == pytest.approx(1e4 / (2 * 5.0))                       # FSR = 1/(2 n d)
    peaks = et.peak_wavelengths(4000.0, 17000.0)
    k = np.round(1e8 / peaks / et.fsr)
    np.testing.assert_allclose(1e8 / peaks, k * et.fsr, rtol=1e-13)         # σ_k = k FSR
    np.testing.assert_allclose(et.transmission(peaks), 0.8, rtol=1e-12)
    F = (2 * 30.0 / math.pi) ** 2
    trough = 1e8 / ((k[:-1] - 0.5) * et.fsr)
    np.testing.assert_allclose(et.transmission(trough), 0.8 / (1 + F), rtol=1e-9)
    half = 1e8 / (k * et.fsr + 0.5 * et.fwhm_wavenumber)
    np.testing.assert_allclose(et.transmission(half), 0.4, rtol=1e-9)
    assert et.fwhm_wavenumber == pytest.approx(et.fsr / 30.0, rel=2e-3)    # 𝓕 ≈ FSR / FWHM
    # mean over one period in σ: T_max / √(1 + F)
    sigma = np.linspace(20 * et.fsr, 21 * et.fsr, 200001)
    assert np.trapezoid(et.transmission(1e8 / sigma), sigma) / et.fsr == pytest.approx(0.8 / math.sqrt(1 + F), rel=1e-6)


@pytest.mark.parametrize("centres", [False, True])
def test_bin_deposit_conserves_the_light(centres):
    lamp = fabry_perot_lamp(FabryPerotEtalon(fsr=900.0, finesse=60.0))
    edges = np.geomspace(5000.0, 9000.0, 120)
    mid = np.sqrt(edges[1:] * edges[:-1]) if centres else None
    content = lamp.bin_average(edges, mid) * np.diff(edges)
    fine = np.linspace(5000.0, 9000.0, 2_000_001)
    total = np.trapezoid(lamp.surface_brightness(fine), fine)
    assert content.sum() == pytest.approx(total, rel=1e-7)


def test_cloud_in_cell_keeps_a_narrow_line_at_its_wavelength():
    edges = np.arange(6000.0, 6400.0 + 1e-9, 20.0)
    centres = 0.5 * (edges[1:] + edges[:-1])
    for line in (6187.0, 6193.0, 6201.5):
        lamp = CalibrationLamp(qth_lamp().continuum,
                               TabulatedEtalon([5000, line - 0.5, line, line + 0.5, 8000], [0, 0, 1, 0, 0]))
        dep = lamp.bin_average(edges, centres) * np.diff(edges)
        x = np.arange(centres.size)
        position = (dep * x).sum() / dep.sum()                     # first moment in bins
        assert position == pytest.approx(np.interp(line, centres, x), abs=2e-3)
        box = lamp.bin_average(edges) * np.diff(edges)              # plain average: centre of its bin
        assert (box * x).sum() / box.sum() == pytest.approx(round(np.interp(line, centres, x)), abs=2e-3)


# --------------------------------------------------------------------------- QTH flat cube
def test_qth_flat_is_uniform_before_and_after_the_ideal_instrument(qth, qth_cube):
    scene = qth.get_scene_cube()
    assert scene.shape == (qth.simulation.lbda.size, *qth.simulation.spectrograph.shape)
    assert np.max(np.abs(scene / scene.mean(axis=(1, 2), keepdims=True) - 1)) < 1e-12
    signal, variance = qth_cube
    for cube in (signal, variance):
        assert np.all(np.isfinite(cube))
        assert np.max(np.abs(cube / cube[:, :1, :1] - 1)) < 1e-12
    wide = qth.get_cube(which="wide", nmd=(8, 8, 0))[0]      # (16, 8, 0) saturates the wide field's red end
    assert np.all(np.isfinite(wide))
    assert np.max(np.abs(wide / wide[:, :1, :1] - 1)) < 1e-12


def test_qth_cube_saturates_where_the_detector_does(qth):
    """A cell owns one pixel row (physical conventions): a flat's pixel rate is its cell rate, so the
    cube saturates where the projected detector image does — at (16, 8, 0) the wide field's red end
    (slicersim 1.0's 2 px per cell halved the pixel rate and kept that cube finite)."""
    sim = qth.simulation
    tint = sim.get_times()["integration_time_per_ramp"]
    cube, fsim = qth.get_field_rate_cubes()["wide"]                       # e-/s per cell
    image = qth.get_detector_image()                                       # e-/s per pixel
    assert 0.95 < image.max() / np.nanmax(cube) < 1.3                      # 1.11 measured; 2 px per cell: 0.5
    charge = (image.max() + sim.effective_dark()) * tint * sim.detector.gain
    assert charge > sim.detector.saturation
    wide = qth.get_cube(which="wide")[0]
    assert np.isnan(wide).any() and np.isfinite(wide[:, 0, 0]).sum() > 0.5 * wide.shape[0]


def test_qth_cube_is_the_lamp_through_the_instrument(qth, qth_cube):
    sim = qth.simulation
    lbda, lamp = qth.get_lamp_spectrum()
    # before LSF and QE: S̄ s² f2p, f2p = A_tel T Δλ λ / hc  [ph/s/cell]
    hc = 6.62607015e-27 * 2.99792458e18                           # erg Å
    photons = lamp * sim.spectrograph.spatial_scale ** 2 * sim.telescope.area * 1e4 \
        * sim.spectrograph.throughput * sim.spectrograph.dlbda * lbda / hc
    np.testing.assert_allclose(sim.background_photons, photons, rtol=1e-12)
    t = sim.get_times()["integration_time_per_ramp"]
    expected = sim.spectrograph.apply_lsf(photons + sim.thermal_photons) * sim.qe * t * sim.detector.gain
    np.testing.assert_allclose(qth_cube[0][:, 10, 20], expected, rtol=1e-10)
    # signal ∝ integration time: (32, 8, 0) integrates (31·8)/(15·8) as long as (16, 8, 0)
    long = qth.get_cube(nmd=(32, 8, 0))[0][:, 0, 0]
    ok = long < 0.5 * sim.detector.saturation
    np.testing.assert_allclose(long[ok] / qth_cube[0][ok, 0, 0], 31 / 15, rtol=1e-12)


def test_qth_flat_noise_draw_and_products_api(qth):
    sig, var, noisy = qth.get_cube(seed=7)
    z = (noisy - sig) / np.sqrt(var)
    assert abs(z.mean()) < 5e-3 and z.std() == pytest.approx(1.0, abs=5e-3)
    np.testing.assert_array_equal(noisy, qth.get_cube(seed=7)[2])
    narrow, wide = qth.get_cube(which="both")
    assert narrow[0].shape[1:] == wide[0].shape[1:] == (58, 116)
    # same lamp per arcsec²: a wide cell (0.08″) collects 4× the lamp light of a narrow one (0.04″)
    n_ph = qth.simulation.background_photons
    w_ph = qth._simulation_for("wide").background_photons
    thr_n, thr_w = qth.simulation.spectrograph.throughput, qth._simulation_for("wide").spectrograph.throughput
    np.testing.assert_allclose(w_ph / n_ph, 4 * thr_w / thr_n, rtol=1e-12)
    with pytest.raises(NotImplementedError, match="no point source"):
        qth.get_spectrum()
    with pytest.raises(NotImplementedError):
        qth.setup_to_snr(20)


# --------------------------------------------------------------------------- Fabry–Perot
def _peak_offsets(flat, qth_signal):
    lbda = flat.simulation.lbda
    signal = flat.get_cube()[0][:, 5, 7]
    truth = flat.lamp.line_wavelengths(lbda[2], lbda[-3])
    idx, _ = locate_peaks(lbda, signal / qth_signal, truth)
    return idx - np.interp(truth, lbda, np.arange(lbda.size))


@pytest.mark.parametrize("finesse", [25.0, 100.0])
def test_fabry_perot_peaks_sit_at_the_etalon_wavelengths(qth_cube, finesse):
    flat = Lazuli3DFlat.from_fabryperot(fsr=DEFAULT_ETALON_FSR, finesse=finesse)
    offsets = _peak_offsets(flat, qth_cube[0][:, 5, 7])
    assert offsets.size >= 20 and np.all(np.isfinite(offsets))
    assert np.max(np.abs(offsets)) < 0.1                                  # bins


def test_tabulated_etalon_gives_the_airy_peaks_and_the_period_mean(qth, qth_cube):
    airy = FabryPerotEtalon(fsr=700.0, finesse=20.0)
    table = np.arange(3900.0, 17200.0, 0.25)
    tab = Lazuli3DFlat.from_fabryperot(fp_throughput=TabulatedEtalon(table, airy.transmission(table)))
    call = Lazuli3DFlat.from_febryperot(airy.transmission)             # 1.4.2's spelling: a callable
    ref = Lazuli3DFlat.from_fabryperot(fsr=700.0, finesse=20.0)
    s_ref = ref.get_cube()[0]
    for other in (tab, call):
        np.testing.assert_allclose(other.get_cube()[0], s_ref, rtol=2e-3)
    np.testing.assert_allclose(tab.lamp.line_wavelengths(5000, 9000), airy.peak_wavelengths(5000, 9000), atol=0.05)


def test_lamp_magnitude_is_set_before_the_etalon(qth):
    # a dense comb (FSR 100 cm⁻¹, ~120 periods in 5500–16000 Å): the FP/QTH ratio of the light
    # collected is the Airy function's mean over a period, T_max/√(1 + F)
    dense = Lazuli3DFlat.from_fabryperot(fsr=100.0, finesse=5.0, peak_transmission=0.9)
    sim_fp, sim_q = dense.simulation, qth.simulation
    band = (sim_q.lbda > 5500) & (sim_q.lbda < 16000)
    F = (2 * 5.0 / math.pi) ** 2
    ratio = sim_fp.background_photons[band].sum() / sim_q.background_photons[band].sum()
    assert ratio == pytest.approx(0.9 / math.sqrt(1 + F), rel=5e-3)


# --------------------------------------------------------------------------- flat-field structure
def test_structure_is_off_by_default_and_zero_scatter_is_ideal(qth, qth_cube):
    assert qth.structure.is_ideal
    zero = Lazuli3DFlat.from_qth(structure=dict(slice_scatter=0.0, pixel_scatter=0.0, seed=4))
    np.testing.assert_array_equal(zero.get_cube()[0], qth_cube[0])


def test_slice_and_pixel_structure_statistics_and_reproducibility(qth_cube):
    sig0 = qth_cube[0]
    sl = Lazuli3DFlat.from_qth(structure=dict(slice_scatter=0.05, seed=11))
    ratio = sl.get_cube()[0] / sig0
    lamp_bins = slice(150, 400)                              # thermal light negligible there
    rows = ratio[lamp_bins].mean(axis=(0, 2))
    np.testing.assert_allclose(ratio[lamp_bins], np.broadcast_to(rows[None, :, None], ratio[lamp_bins].shape),
                               rtol=1e-6)                    # one factor per slice (row)
    assert rows.std() == pytest.approx(0.05, rel=0.3) and abs(rows.mean() - 1) < 0.03
    np.testing.assert_array_equal(sl.get_cube()[0], Lazuli3DFlat.from_qth(
        structure=FlatFieldStructure(slice_scatter=0.05, seed=11)).get_cube()[0])
    assert not np.allclose(sl.get_cube()[0], Lazuli3DFlat.from_qth(
        structure=dict(slice_scatter=0.05, seed=12)).get_cube()[0])
    px = Lazuli3DFlat.from_qth(structure=dict(pixel_scatter=0.04, seed=11))
    r = (px.get_cube()[0] / sig0)[lamp_bins]
    # mean of 2 lognormal pixels (σ = 0.04) per cell: mean 1, std √((e^{σ²} − 1)/2)
    assert r.mean() == pytest.approx(1.0, abs=5e-4)
    assert r.std() == pytest.approx(math.sqrt(math.expm1(0.04 ** 2) / 2), rel=0.02)
    # the structure does not depend on the noise seed, and the noise is drawn on the structured signal
    s1, v1, n1 = px.get_cube(seed=1)
    s2, _, _ = px.get_cube(seed=2)
    np.testing.assert_array_equal(s1, s2)
    assert abs(((n1 - s1) / np.sqrt(v1)).std() - 1) < 5e-3


# --------------------------------------------------------------------------- detector products
def test_detector_image_lights_both_fields_and_conserves_the_rate(short_range_toml):
    flat = Lazuli3DFlat.from_qth(config=["cbe", short_range_toml])
    image = flat.get_detector_image()
    cubes = flat.get_field_rate_cubes()
    narrow, wide = cubes["narrow"][0].sum(), cubes["wide"][0].sum()
    assert narrow > 0 and wide > 0
    assert image.sum() == pytest.approx(narrow + wide, rel=1e-9)
    assert image[:2048].sum() == pytest.approx(wide, rel=1e-9)
    assert image[2048:].sum() == pytest.approx(narrow, rel=1e-9)
    prnu = Lazuli3DFlat.from_qth(config=["cbe", short_range_toml], structure=dict(pixel_scatter=0.03, seed=5))
    lit = image > 0.5 * np.percentile(image[image > 0], 90)
    r = prnu.get_detector_image()[lit] / image[lit]
    assert r.std() == pytest.approx(math.sqrt(math.expm1(0.03 ** 2)), rel=0.03)
    assert r.mean() == pytest.approx(1.0, abs=3e-3)


@pytest.mark.needs_opencl       # the NumPy ramp sampler needs minutes for 4096² pixels
def test_ramps_accumulate_the_flat(short_range_toml):
    flat = Lazuli3DFlat.from_qth(config=["cbe", short_range_toml])
    det, sim = flat.simulation.detector, flat.simulation
    image = flat.get_detector_image(backend="opencl")
    sci = flat.get_ramps(nmd=(3, 1, 0), nramps=1, seed=3, backend="opencl")
    assert sci.shape == (1, 3, 4096, 4096)
    lit = image > np.percentile(image, 99)
    diff = (sci[0, 2].astype(float) - sci[0, 0])[lit]
    d_eff = det.dark + sim.thermal_dark + det.roic_glow / det.tframe
    expected = (image[lit].mean() + d_eff) * 2 * det.tframe * det.gain
    assert abs(diff.mean() - expected) < 4 * diff.std() / math.sqrt(diff.size)


# --------------------------------------------------------------------------- state and bad input
def test_field_switch_readout_and_generic_class(short_range_toml):
    flat = Lazuli3DFlat.from_qth(config=["cbe", short_range_toml])
    flat.change_detector(nmd=(8, 4, 0), nramps=2)
    flat.update(field="wide")
    assert flat.field == "wide" and flat.get_readout_config() == {"nmd": (8, 4, 0), "nramps": 2}
    assert flat.simulation.spectrograph.spatial_scale == 0.08
    before = flat.get_cube()[0]
    flat.lamp = qth_lamp(mag=12.0 - 2.5 * math.log10(3.0))                 # 3× brighter, at once
    thermal = flat.simulation.spectrograph.apply_lsf(flat.simulation.thermal_photons) * flat.simulation.qe
    t = flat.simulation.get_times()["integration_time_per_ramp"] * 2 * flat.simulation.detector.gain
    np.testing.assert_allclose(flat.get_cube()[0][:, 3, 4] - thermal * t, 3 * (before[:, 3, 4] - thermal * t),
                               rtol=1e-9)
    with pytest.raises(ParameterError, match="which"):
        flat.get_cube(which="medium")
    generic = Flat3DCalibration.from_spectrum([3000.0, 20000.0], [1e-16, 1e-16], config=["cbe", short_range_toml])
    assert generic.field == "narrow"
    with pytest.raises(SpectrumError, match="covers"):
        Flat3DCalibration.from_spectrum([9500.0, 20000.0], [1e-16, 1e-16], config=["cbe", short_range_toml])


@pytest.mark.parametrize("call, error, match", [
    (lambda: Lazuli3DFlat.from_qth(temperature=-300), ParameterError, "temperature"),
    (lambda: Lazuli3DFlat.from_qth(temperature=0), ParameterError, "temperature"),
    (lambda: Lazuli3DFlat.from_fabryperot(finesse=0), ParameterError, "finesse"),
    (lambda: Lazuli3DFlat.from_fabryperot(finesse=-3), ParameterError, "finesse"),
    (lambda: Lazuli3DFlat.from_fabryperot(fsr=0), ParameterError, "free spectral range"),
    (lambda: Lazuli3DFlat.from_fabryperot(fsr=-900), ParameterError, "free spectral range"),
    (lambda: Lazuli3DFlat.from_fabryperot(optical_thickness=-1), ParameterError, "optical thickness"),
    (lambda: Lazuli3DFlat.from_fabryperot(fsr=900, optical_thickness=5), ParameterError, "not both"),
    (lambda: Lazuli3DFlat.from_fabryperot(fsr=900, fp_throughput=lambda w: w * 0), ParameterError, "not both"),
    (lambda: Lazuli3DFlat.from_fabryperot(peak_transmission=1.5), ParameterError, "peak transmission"),
    (lambda: Lazuli3DFlat.from_qth(field="medium"), ConfigError, "unknown field"),
    (lambda: Lazuli3DFlat.from_qth(structure=dict(slice_scatter=-0.1)), ParameterError, "slice_scatter"),
    (lambda: Lazuli3DFlat.from_qth(structure=dict(prnu=0.1)), ParameterError, "unknown flat-field"),
])
def test_bad_input_is_one_clear_error(call, error, match):
    with pytest.raises(error, match=match):
        call()


def test_flat_switch_off_with_and_without_structure(qth):
    structured = Lazuli3DFlat.from_qth(structure={"slice_scatter": 0.05, "seed": 4})
    for flat in (qth, structured):
        signal, variance = flat.get_cube()
        s_ron, v_ron = flat.get_cube(switch_off="ron")
        np.testing.assert_array_equal(s_ron, signal)                 # a detector term leaves the variance only
        assert np.all(v_ron < variance)
        ron_var = variance - v_ron                                   # read noise: the same for any flux
        np.testing.assert_allclose(ron_var, ron_var[0, 0, 0], rtol=1e-9)
    # the lamp off: only the instrument's thermal light is left, not scaled by the slice throughputs
    np.testing.assert_allclose(structured.get_cube(switch_off="background")[0],
                               qth.get_cube(switch_off="background")[0], rtol=1e-12)
    assert not np.allclose(structured.get_cube()[0], qth.get_cube()[0], rtol=1e-3)


def test_lamp_magnitudes_are_finite_numbers_of_any_sign():
    with pytest.raises(ParameterError, match=r"lamp magnitude .* must be finite, got nan") as err:
        Lazuli3DFlat.from_qth(mag=float("nan"))
    assert "> 0" not in str(err.value)
    assert Lazuli3DFlat.from_qth(mag=-2.0).lamp.continuum.mag == -2.0
