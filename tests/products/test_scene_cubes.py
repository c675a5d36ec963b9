"""Per-component cubes (Simulation.get_scene_cubes) and switch_off in cubes, spectra and the budget.

The scene has all four components: a point source off-centre, a Sersic host, zodiacal
background and thermal emission (Lazuli CBE, narrow field, 510 bins).
Tolerances: sums against the fused cube 1e-12 of the peak (summation order only, measured
~4e-16); the detector terms are checked against the closed-form Rauscher et al. (2007) terms.
"""
import numpy as np
import pytest

from slicersim import Host, LazuliTarget, SersicProfile
from cube_oracle import cube_numpy
from slicersim.errors import ParameterError
from slicersim.products.components import SCENE_COMPONENTS, SWITCH_OFF_NAMES, VARIANCE_SOURCES

LBDA = np.arange(3000.0, 20000.0, 10.0)
READOUT = {"nmd": (16, 8, 0), "nramps": 2}
BACKENDS = ["numpy", pytest.param("opencl", marks=pytest.mark.needs_opencl)]


@pytest.fixture(scope="module")
def sim():
    target = LazuliTarget(LBDA, 1.0 + 0.3 * np.sin(LBDA / 700.0), mag=21.0, band="bessellb", position=(1.3, -0.6))
    target.set_host(Host(SersicProfile(1.0, 0.3, 0.7, 20.0, offset=(0.2, 0.1)), LBDA, np.full(LBDA.size, 5e-17)))
    return target.simulation


@pytest.fixture(scope="module")
def components(sim):
    return sim.get_scene_cubes(**READOUT)


def _peak_err(got, ref):
    return np.max(np.abs(got - ref)) / np.max(np.abs(ref))


@pytest.mark.parametrize("backend", BACKENDS)
def test_components_sum_to_the_noiseless_cube(sim, components, backend):
    signal, _ = sim.get_cube(**READOUT, backend=backend)
    assert set(components) == set(SCENE_COMPONENTS)
    for name, cube in components.items():
        assert cube.shape == signal.shape and cube.sum() > 0, name          # all four are present
    assert _peak_err(sum(components.values()), signal) < 1e-12
    for name in ("background", "thermal"):                                   # uniform light: flat over the field
        assert np.all(components[name] == components[name][:, :1, :1])
    # the photon cube is the same sum (host included)
    photons = sim.get_scene_cubes(unit="photon")
    assert _peak_err(sim.get_projected_scene(), sum(photons.values())) < 1e-12


@pytest.mark.slow
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("name", SCENE_COMPONENTS)
def test_switch_off_removes_exactly_that_component(sim, components, name, backend):
    signal, variance = sim.get_cube(**READOUT, backend=backend)
    s_off, v_off = sim.get_cube(**READOUT, backend=backend, switch_off=name)
    assert _peak_err(s_off, signal - components[name]) < 1e-12
    lit = components[name] > 1e-6 * components[name].max()
    assert np.all(v_off <= variance) and np.all(v_off[lit] < variance[lit])   # its photon noise is gone
    s_ref, v_ref = cube_numpy(sim, **READOUT, switch_off=name)            # NumPy oracle of the same rule
    assert _peak_err(s_off, s_ref) < 1e-12 and _peak_err(v_off, v_ref) < 1e-12
    off_cubes = sim.get_scene_cubes(**READOUT, switch_off=[name])
    assert not off_cubes[name].any()
    for other in set(SCENE_COMPONENTS) - {name}:
        assert np.array_equal(off_cubes[other], components[other])


def test_switch_off_detector_terms_closed_form(sim):
    """ron: ΔV = r · p · g² · 12(n−1)/(m n (n+1)) σ_r²; dark: ΔV = r · p · g² · b · dark with
    b = 6(n²+1)(n−1) t_g / (5n(n+1)) − 2(m²−1)(n−1) t_f / (m n (n+1)); the signal is unchanged.
    p = the detector pixels a cell owns: 1 for the slicer (physical conventions)."""
    det, ppc = sim.detector, sim.detector_pixels_per_cell
    assert ppc == 1
    (n, m, d), r = READOUT["nmd"], READOUT["nramps"]
    signal, variance = sim.get_cube(**READOUT)
    s_ron, v_ron = sim.get_cube(**READOUT, switch_off="ron")
    assert np.array_equal(s_ron, signal)
    expected = r * ppc * det.gain**2 * 12 * (n - 1) / (m * n * (n + 1)) * det.ron**2
    np.testing.assert_allclose(variance - v_ron, expected, rtol=1e-9)
    tf = det.tframe
    b = 6 * (n**2 + 1) * (n - 1) * (m + d) * tf / (5 * n * (n + 1)) - 2 * (m**2 - 1) * (n - 1) * tf / (m * n * (n + 1))
    _, v_dark = sim.get_cube(**READOUT, switch_off="DARK")                       # names are case-insensitive
    np.testing.assert_allclose(variance - v_dark, r * ppc * det.gain**2 * b * det.dark, rtol=1e-9)
    both = sim.get_cube(**READOUT, switch_off=["dark", "thermal_dark"])[1]
    assert np.array_equal(sim.get_cube(**READOUT, switch_off="effective_dark")[1], both)


def test_thermal_dark_switch_is_the_optics_emissivity(sim, components):
    """thermal_dark off = optics emissivity 0: the dispersed optics emission leaves the thermal cube too
    (the telescope's stays), as in the variance budget and slicersim 1.4.2."""
    thermal = sim.get_scene_cubes(**READOUT, switch_off="thermal_dark")["thermal"]
    telescope_only = sim.spectrograph.apply_lsf(sim._thermal_photons("telescope"))
    tint = sim.get_times(**READOUT)["integration_time_per_ramp"]
    expected = telescope_only * sim.qe * tint * sim.detector.gain * READOUT["nramps"]
    np.testing.assert_allclose(thermal[:, 0, 0], expected, rtol=1e-12)
    assert np.all(thermal[:, 0, 0] < components["thermal"][:, 0, 0])


def test_units(sim, components):
    photon = sim.get_scene_cubes(unit="photon")
    electron = sim.get_scene_cubes(unit="electron")
    flambda = sim.get_scene_cubes(unit="flambda")
    per_ramp = sim.get_scene_cubes(**READOUT, per_ramp=True)
    tint = sim.get_times(**READOUT)["integration_time_per_ramp"]
    def close(a, b):
        # rtol 1e-14, and 1e-14 of the peak absolute: the PSF's far tails (erfc) are subnormal
        # (~1e-313), where a product keeps only a few significant bits
        np.testing.assert_allclose(a, b, rtol=1e-14, atol=1e-14 * float(np.nanmax(np.abs(b))))
    for name in SCENE_COMPONENTS:
        close(electron[name], photon[name] * sim.qe[:, None, None])
        close(per_ramp[name], electron[name] * tint * sim.detector.gain)
        close(components[name], READOUT["nramps"] * per_ramp[name])
        close(flambda[name] * sim.flambda_to_photon[:, None, None], photon[name])
    # flambda of the point source summed over the field = its LSF'd spectrum (PSF loss < 1e-6)
    ps = flambda["pointsource"].sum(axis=(1, 2))
    f2p = sim.flambda_to_photon
    np.testing.assert_allclose(ps[5:-5], (sim.spectrograph.apply_lsf(sim.pointsource_flambda * f2p) / f2p)[5:-5],
                               rtol=1e-5)


def test_spectrum_switch_off_is_the_variance_budget(sim):
    """get_spectrum(switch_off=s) variance = total − the budget's contribution of s (one rule)."""
    budget = sim.get_variance_contribution(**READOUT)
    for name in VARIANCE_SOURCES:
        _, signal, variance = sim.get_spectrum(**READOUT, switch_off=name)
        np.testing.assert_allclose(variance, budget["variance"] - budget[name], rtol=1e-12)
        assert (not signal.any()) if name == "pointsource" else signal.all()
    snr = sim.get_band_snr((5000.0, 9000.0), **READOUT)
    assert sim.get_band_snr((5000.0, 9000.0), **READOUT, switch_off=["background", "ron"]) > snr


@pytest.mark.parametrize("bad", ["zodi", ["ron", "readnoise"], [3], 5, {"ron": 1}])
def test_bad_switch_off_lists_the_valid_names(sim, bad):
    for call in (lambda: sim.get_cube(**READOUT, switch_off=bad), lambda: sim.get_scene_cubes(switch_off=bad),
                 lambda: sim.get_spectrum(switch_off=bad), lambda: sim.get_projected_scene(switch_off=bad)):
        with pytest.raises(ParameterError, match="valid: " + ", ".join(SWITCH_OFF_NAMES)):
            call()


def test_bad_unit_and_readout(sim):
    with pytest.raises(ParameterError, match="adu, electron, photon, flambda"):
        sim.get_scene_cubes(unit="jansky")
    with pytest.raises(Exception, match="nramps"):
        sim.get_scene_cubes(nramps=0)


def test_scene_background_and_cube_arguments_are_parameter_errors():
    from slicersim.sources.pixels import CubeSource
    from slicersim.sources.scene import Background, Scene
    with pytest.raises(ParameterError, match=r"unknown background model 'zodiacal' \(did you mean 'zodi'\?\); valid: 'zodi'"):
        Background("zodiacal")
    with pytest.raises(ParameterError, match="background scale must be ≥ 0"):
        Background(scale=-1.0)
    with pytest.raises(ParameterError, match="host must provide flux_cube"):
        Scene(host="a galaxy")
    cube = np.ones((3, 4, 4))
    with pytest.raises(ParameterError, match=r"lbda_in \[Å\] must be an array of real numbers"):
        CubeSource(cube, ["a", "b", "c"], 0.1)
    with pytest.raises(ParameterError, match=r"pixel_scale \[arcsec\] must be > 0"):
        CubeSource(cube, [4000.0, 5000.0, 6000.0], 0.0)
    src = CubeSource(cube, [4000.0, 5000.0, 6000.0], 0.1)
    from slicersim.errors import SpectrumError
    with pytest.raises(SpectrumError, match="lbda: wavelength grid .* extends beyond"):
        src.flux_cube(np.array([3000.0, 4500.0]), (4, 4), 0.1)
