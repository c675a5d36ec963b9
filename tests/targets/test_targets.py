"""Target API (slicersim.targets): update / change_* keep a consistent state or refuse with a
SlicersimError and leave the target unchanged; 1.4.2 names; detector products."""
import math
import pydoc

import numpy as np
import pytest

import slicersim
from slicersim.errors import ConfigError, ParameterError, ReadoutError, SlicersimError, SpectrumError
from slicersim.products.components import SCENE_COMPONENTS
from slicersim.targets import Lazuli3DFlat, LazuliGalaxy, LazuliSupernova, LazuliTarget
from model_state import (STATE_BAND as BAND_9_12, STATE_FLUX as FLUX, STATE_LBDA as LBDA_500,  # noqa: F401
                         assert_rejected_unchanged, flat_target as target, model_state as state)


@pytest.fixture(scope="module")
def sn_host():
    return LazuliSupernova(0.5, host="sersic")


def test_names_of_slicersim_142(sn_host):
    sim = sn_host.simulation
    _, s_off, v_off = sn_host.get_spectrum(switch_off="host")        # Target.get_spectrum(switch_off=)
    _, s_ref, v_ref = sim.get_spectrum(switch_off="host")
    np.testing.assert_array_equal(s_off, s_ref)
    np.testing.assert_array_equal(v_off, v_ref)
    _, s_host, _ = sn_host.get_spectrum(of_host=True, method="aperture", aperture="0.5-arcsec", switch_off="host")
    assert np.all(s_host == 0)                                       # the extracted component switched off
    default = sn_host.get_cube(psf_profile="default")               # Target.get_cube(psf_profile=)
    np.testing.assert_array_equal(default[0], sn_host.get_cube()[0])
    cubes = sn_host.get_scene_cubes(unit="ph")
    assert cubes["host_cube"] is cubes["host"] and cubes["thermal_cube"] is cubes["thermal"]
    assert "host_cube" in cubes and sorted(cubes) == sorted(SCENE_COMPONENTS)
    np.testing.assert_array_equal(sn_host.get_scene_cubes(unit="photons")["host"], cubes["host"])
    np.testing.assert_array_equal(sn_host.get_scene_cubes(unit="photon")["host"], cubes["host"])
    stack = sim.get_scene_cubes(unit="photon", as_dict=False)
    assert stack.shape == (4,) + cubes["host"].shape
    np.testing.assert_array_equal(stack[2], cubes["host"])


@pytest.mark.parametrize("cls, names", [(LazuliGalaxy, ("aperture__position", "method", "model")),
                                        (Lazuli3DFlat, ("structure", "lamp", "conventions"))])
def test_help_shows_the_parameters(cls, names):
    text = pydoc.render_doc(cls, renderer=pydoc.plaintext)
    head = text[:text.index("Method resolution order")]
    for name in names:
        assert f"{name} :" in head


from model_state import (BACKENDS, LBDA, TFRAME, short_range_toml, short_target,  # noqa: E402,F401
                         sloped)


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


@pytest.mark.parametrize("params", [dict(config="eol", nramps=2), dict(field="wide", nmd=(20, 8, 0))])
def test_update_config_or_field_with_readout_crashes(params):
    """Target.update(config=..., nramps=...) / (field=..., nmd=...) raises
    TypeError "dict() got multiple values for keyword argument" for ANY (even valid)
    readout: _new_simulation builds dict(nmd=old, nramps=old, **upd)."""
    t = target()
    t.update(**params)
    assert t.simulation.nramps == params.get("nramps", 1)
    assert t.simulation.detector.nmd == params.get("nmd", (16, 8, 0))


def test_throughput_curve_not_covering_grid_is_not_extrapolated():
    """set_throughput(curve on 8000-9000 Å) is cubic-extrapolated over 4000-17000 Å:
    throughput from -2168 to 258 -> negative signal/variance, NaN band SNR, no error."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.set_throughput(([8e3, 8.3e3, 8.6e3, 9e3], [0.1, 0.5, 0.9, 0.5])),
                              ParameterError, r"throughput curve total covers 8000-9000 Å only, not the "
                              r"instrument's 4000-16984.4 Å \(curves are not extrapolated\)")


@pytest.mark.parametrize("values", [[-0.5] * 4, [5.0] * 4])
def test_throughput_curve_outside_0_1_rejected(values):
    """A scalar throughput outside [0, 1] raises, but a curve of -0.5 (negative signal
    and variance, NaN SNR) or 5 (SNR x4.4) is accepted."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.set_throughput(([1e3, 2e3, 3e3, 4e4], values)))


def test_noptics_negative_rejected():
    """set_throughput(0.5, noptics=-1) gives T = 0.5**-1 = 2 (SNR 9.6 -> 25.2)."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.set_throughput(0.5, noptics=-1))


@pytest.mark.parametrize("qe", [([1e3, 3e4], [-1.0, -1.0]), ([1e3, 3e4], [np.nan, np.nan]),
                                ([1.0, 2.0], [3.0]), 5.0])
def test_qe_validated(qe):
    """QE curves are not validated at all: negative QE gives band SNR -55.9, NaN QE NaN
    spectra, mismatched lengths are accepted and break every later call; a scalar QE up
    to 10 e-/ph is accepted."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.update(qe=qe))


@pytest.mark.parametrize("params", [dict(gain=math.inf), dict(tframe=math.inf), dict(pixel_size=math.inf),
                                    dict(saturation=math.nan), dict(saturation=-5.0),
                                    dict(diameter_ext=math.inf), dict(spatial_scale=math.nan),
                                    dict(spatial_scale=math.inf), dict(emissivity=5.0)])
def test_nonfinite_or_unphysical_instrument_values_rejected(params):
    """Accepted silently; results become inf/NaN SNRs, SNR 0 (all cells 'saturated') or
    no saturation at all (saturation=nan), emissivity 5."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.update(**params))


@pytest.mark.parametrize("rng", [(5.0, 1.0), "x", (math.nan, 1.0)])
def test_thermal_dark_range_validated(rng):
    """Reversed range silently gives thermal dark 0; 'x' / NaN are accepted and every
    later get_spectrum raises a bare ValueError (object broken)."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.update(thermal_dark_range=rng))


def test_max_group_enforced_by_simulation_update():
    """change_detector checks max_group but Simulation.update(nmd=(100, 8, 0)) does not
    (max_group 64): the ETC and the current readout disagree."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.simulation.update(nmd=(100, 8, 0)), ReadoutError)


def test_max_group_below_current_n_rejected():
    """update(max_group=5) with nmd n = 16 is accepted: inconsistent state."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.update(max_group=5))


@pytest.mark.parametrize("value", [0, -5, 1.5])
def test_max_group_invalid_values(value):
    """max_group 0 / -5 silently mean 'no limit' (None); change_detector(max_group=1.5)
    truncates to 1."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.change_detector(max_group=value))


@pytest.mark.parametrize("z", [-1.0, math.nan, "x"])
def test_target_constructor_validates_redshift(z):
    """Target.update rejects these redshifts, the constructor accepts them; frame='rest'
    then maps bands to (0, 0) / (nan, nan) Å."""
    with pytest.raises(SlicersimError):
        target(redshift=z)


def test_mag_nan_rejected():
    """LazuliTarget(..., mag=nan) is accepted: every spectrum is NaN, band SNR nan."""
    with pytest.raises(SpectrumError):
        target(mag=math.nan)


def test_position_outside_field_rejected():
    """position=(1000, 0) is accepted: empty aperture, variance inf, band SNR 0.0 while the
    signal stays the full spectrum."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.update(position=(1000.0, 0.0)))


def test_empty_aperture_rejected():
    """aperture_radius_insigma=1e-9: no aperture cell, band SNR 0.0, no error."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.update(aperture_radius_insigma=1e-9))


def test_spectrum_outside_instrument_is_spectrum_error():
    """A spectrum at 30000-40000 Å raises a bare ValueError from Simulation._check_overlap."""
    with pytest.raises(SpectrumError):
        slicersim.LazuliTarget(np.linspace(30000, 40000, 10), np.full(10, 1e-17))


def test_supernova_out_of_range_redshift_message():
    """LazuliSupernova(redshift=50) says 'pointsource: empty wavelength array'."""
    with pytest.raises(SlicersimError, match="redshift"):
        slicersim.LazuliSupernova(redshift=50)


def test_misspelt_supernova_keyword_is_named():
    """LazuliSupernova(redshift=1, feild="narrow") gave snia_spectrum's TypeError (an internal name)."""
    from slicersim.errors import ParameterError
    with pytest.raises(ParameterError, match=r"unknown keyword of LazuliSupernova 'feild' \(did you mean 'field'\?\)"):
        slicersim.LazuliSupernova(redshift=1, feild="narrow")


@pytest.mark.parametrize("make", [
    lambda z: LazuliTarget(LBDA_500, FLUX, redshift=z),
    lambda z: LazuliSupernova(z),
    lambda z: target().update(redshift=z),
])
def test_absurd_redshift_is_a_short_range_error(make):
    """A 300-digit redshift was printed back in full (the sncosmo coverage at z = 1e300): now a range
    check naming the bound; redshifts a user may simulate still work."""
    with pytest.raises(SlicersimError, match=r"redshift must be ≤ 50, got 1e\+300") as info:
        make(float("1" + "0" * 300))
    assert len(str(info.value)) < 200
    assert LazuliTarget(LBDA_500, FLUX, redshift=20.0).redshift == 20.0


def test_out_of_grid_wavelengths_are_printed_short():
    """A band or spectrum at 1e300 Å was printed as 300 digits ({:.0f})."""
    t = target()
    with pytest.raises(SpectrumError, match=r"band 4000–1e\+300 Å") as info:
        t.get_band_snr((4000, 1e300))
    assert len(str(info.value)) < 300
    with pytest.raises(SpectrumError, match=r"point-source spectrum \(3e\+299–2e\+300 Å\)") as info:
        LazuliTarget(LBDA_500 * 1e296, FLUX)
    assert len(str(info.value)) < 300
