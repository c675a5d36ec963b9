"""A Sersic host in the scene: its light enters the cube (convolved) and the extraction noise."""
import numpy as np
import pytest

from slicersim import Host, LazuliTarget, SersicProfile

LBDA = np.arange(3000.0, 20000.0, 10.0)


@pytest.fixture(scope="module")
def pair():
    flux = np.full(LBDA.size, 3e-18)
    bare = LazuliTarget(LBDA, flux)
    hosted = LazuliTarget(LBDA, flux)
    sim = hosted.simulation
    sim.scene.host = Host(SersicProfile(1.0, 0.3, 0.7, 20.0), LBDA, np.full(LBDA.size, 5e-17))
    sim._cache.clear()
    return bare.simulation, sim


def test_host_photons_enter_the_cube_flux_conserved(pair):
    bare, sim = pair
    s0, _ = bare.get_cube(nmd=(16, 8, 0))
    s1, _ = sim.get_cube(nmd=(16, 8, 0))
    tint = sim.get_times((16, 8, 0))["integration_time_per_ramp"]
    shape, scale = sim.spectrograph.shape, sim.spectrograph.spatial_scale
    host_in_field = sim.scene.host.flux_cube(sim.lbda, shape, scale).sum(axis=(1, 2))   # erg/s/cm²/Å
    expected = host_in_field * sim.flambda_to_photon * sim.qe * tint
    added = np.nansum(s1 - s0, axis=(1, 2))
    mid = slice(20, -20)                       # away from LSF edges; PSF spill-out is < 1 % for r_eff=0.3"
    np.testing.assert_allclose(added[mid], sim.spectrograph.apply_lsf(expected)[mid], rtol=0.01)


def test_host_photon_noise_in_variance_budget(pair):
    bare, sim = pair
    band = (6000.0, 9000.0)
    with_host = sim.get_band_variance_contribution(band, nmd=(16, 8, 0))
    without = bare.get_band_variance_contribution(band, nmd=(16, 8, 0))
    assert without["host"] == 0.0
    assert with_host["host"] > 0.02 * with_host["variance"]
    assert with_host["variance"] > without["variance"]
    # the signal extracted is the point source only
    assert with_host["signal"] == pytest.approx(without["signal"], rel=1e-12)
