"""Spectrographs (slicersim.instrument.spectrograph): spectral range and dispersion law, optics,
MLA pixels per cell, wavelength grids from a resolving power."""
import math

import numpy as np
import pytest

import slicersim
from slicersim.errors import ParameterError, SlicersimError
from slicersim.instrument.spectrograph import MLASpectrograph, SlicerSpectrograph, Spectrograph, wavelength_grid_from_resolving_power
from slicersim.physics.readout import readout_times
from slicersim.simulation import Simulation
from slicersim.targets import LazuliTarget
from model_state import (STATE_BAND as BAND, STATE_FLUX as FLUX, STATE_LBDA as LBDA_500,  # noqa: F401
                         assert_rejected_unchanged, flat_target as target, model_state as state)


LBDA = np.arange(3000.0, 20000.0, 10.0)


def flat(level=1e-17):
    return np.full(LBDA.size, level)


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


def test_spectral_range_huge_is_parameter_error():
    """spectrograph.update(spectral_range=(4000, 1e9)) -> MemoryError (151 PiB array)."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.simulation.spectrograph.update(spectral_range=(4000, 1e9)))


def test_spectral_range_outside_dispersion_law():
    """spectral_range=(100, 200) silently gives a 4000-5374 Å grid; (4000, 30000) gives
    943 bins with throughput extrapolated to -169 and NaN spectra."""
    for rng in ((100.0, 200.0), (4000.0, 30000.0)):
        t = target()
        spec = t.simulation.spectrograph
        assert_rejected_unchanged(t, lambda: spec.update(spectral_range=rng), ParameterError,
                                  rf"spectral_range \({rng[0]}, {rng[1]}\) Å lies outside the dispersion law's "
                                  r"wavelength coverage \[4000, 17000.1\] Å \(no extrapolation\)")


def test_optics_negative_emissivity_rejected():
    """spectrograph optics emissivity -1 accepted: negative thermal photons lower the variance."""
    t = target()
    k = len(t.simulation.spectrograph.optics["emissivity"])
    assert_rejected_unchanged(t, lambda: t.simulation.spectrograph.update(optics={"emissivity": [-1.0] * k}))


def test_partial_spectral_range_starts_at_its_own_wavelength():
    """A spectral_range that does not begin where the dispersion law's offset is 0 gave (like slicersim
    1.0) the right number of bins at the wrong wavelengths (47 bins at 4000–4255 Å for 9000–11000 Å).
    Now the bins are the sub-grid of the full grid that covers the range."""
    import numpy as np

    from slicersim import LazuliTarget
    t = LazuliTarget(np.linspace(3000, 18000, 100), np.full(100, 1e-17))
    full = t.simulation.spectrograph.lbda.copy()
    full_edges = t.simulation.spectrograph.lbda_edges.copy()
    t.update(spectral_range=(9000, 11000))
    part = t.simulation.spectrograph.lbda
    edges = t.simulation.spectrograph.lbda_edges
    assert part[0] - 9000 < np.diff(edges)[0] and 11000 - part[-1] < np.diff(edges)[-1]
    i = np.argmin(abs(full - part[0]))
    np.testing.assert_allclose(part, full[i:i + part.size], rtol=1e-12)
    np.testing.assert_allclose(edges, full_edges[i:i + part.size + 1], rtol=1e-12)


def test_unknown_noptics_keys_list_every_valid_key_and_say_what_they_are():
    """update(noptics={'silver': 10}) listed only 'narrow' (the single curve of the field), unexplained."""
    from slicersim.instrument.spectrograph import OpticalThroughput
    t = target()
    with pytest.raises(ParameterError, match=r"unknown noptics key\(s\) 'silver': noptics counts the elements of each "
                                             r"throughput component, and this throughput has 1 component: one curve "
                                             r".*valid keys: 'narrow', or one integer for every component"):
        t.update(noptics={"silver": 10})
    curves = {"mirror": 0.9, "grating": 0.8, "silver_coating": 0.97}
    with pytest.raises(ParameterError, match=r"unknown noptics key\(s\) 2, 'silver' \(did you mean 'silver_coating'\?\)"
                                             r".*has 3 components; valid keys: 'mirror', 'grating', 'silver_coating'"):
        OpticalThroughput(curves, {"silver": 2, 2: 1, "mirror": 3})
    assert OpticalThroughput(curves, {"mirror": 3}).noptics == {"mirror": 3, "grating": 1, "silver_coating": 1}
