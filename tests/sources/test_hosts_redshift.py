"""Hosts at target level, redshift-consistent (issue 10).

Physics checked
---------------
* angular size: the Sersic half-light radius and an NGC image's half-light radius scale as
  1/D_A(z) (proper size fixed), to 1e-12;
* flux: F_bol × 4π D_L² is the same luminosity at every z, and the mean surface brightness
  inside r_eff dims as (1+z)⁻⁴ (bolometric) and (1+z)⁻⁵ (F_λ at a fixed rest wavelength),
  to 1e-6, with D_A, D_L from astropy (Planck18) independently of the code;
* ``update(redshift=)`` moves source and host together: the host equals the model rendered at
  the new redshift and a relative host offset keeps its proper length;
* a host at the field centre adds to the cube exactly f2p · QE · g · t · LSF[F_host ⊛ PSF]
  (independent FFT convolution with the reference Gaussian PSF kernels), to 1e-10 of the peak.
"""
import math

import numpy as np
import pytest
from astropy.cosmology import Planck18
from scipy.signal import fftconvolve

from slicersim.errors import ParameterError
from slicersim.sources.cosmology import redshift_scalings
from slicersim.sources.extended import CubeSource, Host, SersicProfile
from slicersim.sources.galaxies import GalaxyModel
from slicersim.targets.base import LazuliSupernova, LazuliTarget

ZS = (0.1, 0.5, 1.0, 2.0)
ARCSEC_PER_RAD = 180 * 3600 / math.pi


def has_galaxy_data():
    try:
        import lazuli_astrosim_data  # noqa: F401
        return True
    except ImportError:
        return False


needs_data = pytest.mark.skipif(not has_galaxy_data(), reason="lazuli-astrosim-data not installed")


def d_a_kpc(z):
    return Planck18.angular_diameter_distance(z).to_value("kpc")


def test_sersic_half_light_radius_scales_as_one_over_angular_diameter_distance():
    model = GalaxyModel("sersic:bb-5000", r_kpc=3.0)
    for z in ZS:
        r_eff = model.host(z).profile.r_eff                          # arcsec
        assert r_eff / ARCSEC_PER_RAD * d_a_kpc(z) == pytest.approx(3.0, rel=1e-12)
    # the same through a host moved from z = 0.5
    base = model.host(0.5)
    for z in ZS:
        assert base.at_redshift(z).profile.r_eff * d_a_kpc(z) == pytest.approx(base.profile.r_eff * d_a_kpc(0.5),
                                                                              rel=1e-12)


def _bolometric(host):
    return np.trapezoid(host.flux_in, host.lbda_in)


def test_total_flux_is_dimmed_surface_brightness_times_area():
    model = GalaxyModel("sersic:bb-6000", r_kpc=2.0, magabs=-20.0)
    hosts = {z: model.host(z) for z in ZS}
    lum = {z: _bolometric(h) * 4 * math.pi * Planck18.luminosity_distance(z).to_value("cm") ** 2
           for z, h in hosts.items()}
    for z in ZS:
        assert lum[z] == pytest.approx(lum[ZS[0]], rel=1e-6)
    # mean surface brightness inside the half-light ellipse: half the flux over π q r_eff²
    sb = {z: 0.5 * _bolometric(h) / (math.pi * h.profile.axis_ratio * h.profile.r_eff ** 2) for z, h in hosts.items()}
    rest = 5000.0
    sb_lambda = {z: 0.5 * np.interp(rest * (1 + z), h.lbda_in, h.flux_in)
                 / (math.pi * h.profile.axis_ratio * h.profile.r_eff ** 2) for z, h in hosts.items()}
    for z in ZS:
        dim = ((1 + ZS[0]) / (1 + z))
        assert sb[z] / sb[ZS[0]] == pytest.approx(dim ** 4, rel=1e-6)
        assert sb_lambda[z] / sb_lambda[ZS[0]] == pytest.approx(dim ** 5, rel=1e-6)
        area = math.pi * hosts[z].profile.axis_ratio * hosts[z].profile.r_eff ** 2
        assert 0.5 * _bolometric(hosts[z]) == pytest.approx(sb[ZS[0]] * dim ** 4 * area, rel=1e-6)
    # the wavelengths are stretched by (1 + z)
    np.testing.assert_allclose(hosts[2.0].lbda_in / hosts[0.5].lbda_in, 3.0 / 1.5, rtol=1e-14)


def test_moving_a_host_equals_rendering_it_there():
    model = GalaxyModel("sersic:bb-5000", r_kpc=4.0, n=1.5, ellip=0.4, theta=20.0)
    moved = model.host(0.3).at_redshift(1.2)
    fresh = model.host(1.2)
    assert moved.profile.r_eff == pytest.approx(fresh.profile.r_eff, rel=1e-12)
    np.testing.assert_allclose(moved.lbda_in, fresh.lbda_in, rtol=1e-14)
    np.testing.assert_allclose(moved.flux_in, fresh.flux_in, rtol=1e-10)
    # user objects move too: a CubeSource keeps its array and scales its flux
    cube = np.ones((3, 4, 4))
    src = CubeSource(cube, [3000.0, 9000.0, 20000.0], 0.05, redshift=0.5)
    a, w, f = redshift_scalings(0.5, 1.0)
    out = src.at_redshift(1.0)
    assert out.cube is cube and out.pixel_scale == pytest.approx(0.05 * a) and out.flux_scale == pytest.approx(f)
    np.testing.assert_allclose(out.lbda_in, src.lbda_in * 2.0 / 1.5)
    with pytest.raises(ParameterError, match="no redshift"):
        CubeSource(cube, [3000.0, 9000.0, 20000.0], 0.05).at_redshift(1.0)


def test_update_redshift_moves_source_and_host_together():
    t = LazuliSupernova(0.5, host={"refmodel": "sersic:bb-5000", "offset": (0.2, 0.0), "r_kpc": 3.0})
    assert t.host.redshift == 0.5 and t.host_model.name == "sersic:bb-5000"
    scale = t.simulation.spectrograph.spatial_scale
    assert t.host.profile.offset == pytest.approx((0.2, 0.0))
    sn_flux = t.pointsource.flux_in.copy()
    t.update(redshift=1.0)
    assert t.redshift == 1.0 and t.host.redshift == 1.0
    fresh = GalaxyModel("sersic:bb-5000", r_kpc=3.0).host(1.0)
    assert t.host.profile.r_eff == pytest.approx(fresh.profile.r_eff, rel=1e-12)
    np.testing.assert_allclose(t.host.flux_in, fresh.flux_in, rtol=1e-10)
    a = d_a_kpc(0.5) / d_a_kpc(1.0)
    assert t.host.profile.offset == pytest.approx((0.2 * a, 0.0), rel=1e-12)     # same proper offset
    assert t.pointsource.flux_in.max() < 0.5 * sn_flux.max()             # the SN moved too (dimmer)
    assert t.simulation.scene.host is t.host
    # host__ parameters (1.4.2) re-render at the current redshift, keeping the offset
    t.update(host__r_kpc=1.5, position=(2.0, 1.0))
    assert t.host.profile.r_eff == pytest.approx(fresh.profile.r_eff / 2, rel=1e-12)
    assert t.host.profile.offset == pytest.approx((2 * scale + 0.2 * a, scale), rel=1e-12)
    # atomic: a bad host parameter changes nothing
    with pytest.raises(ParameterError, match="Sersic index"):
        t.update(redshift=0.7, host__n=-2)
    assert t.redshift == 1.0 and t.host.redshift == 1.0
    with pytest.raises(ParameterError, match="host__"):
        LazuliSupernova(0.5).update(host__r_kpc=2)


def test_user_host_without_redshift_is_taken_at_the_target_redshift():
    lbda = np.arange(2000.0, 40000.0, 10.0)
    host = Host(SersicProfile(1.0, 0.4, 0.8, 10.0), lbda, np.full(lbda.size, 3e-17))
    t = LazuliSupernova(0.5, host=host)
    assert t.host is not host and t.host.profile.r_eff == 0.4        # the target's own copy (host untouched)
    t.update(redshift=0.8)
    a, w, f = redshift_scalings(0.5, 0.8)
    assert t.host.profile.r_eff == pytest.approx(0.4 * a, rel=1e-12)
    assert t.host.flux_in[0] == pytest.approx(3e-17 * f, rel=1e-12)
    t.update(redshift=0.5)
    assert t.host.profile.r_eff == 0.4 and t.host.flux_in[0] == 3e-17    # back at its own redshift


def test_host_at_field_centre_adds_exactly_its_psf_convolved_flux():
    lbda = np.arange(3000.0, 20000.0, 10.0)
    t = LazuliTarget(lbda, np.full(lbda.size, 1e-18), redshift=1.0, host="sersic:bb-5000",
                     field="narrow")
    t.update(host__r_kpc=1.0)
    sim = t.simulation
    with_host = sim.get_cube(backend="numpy")[0]
    host = sim.scene.host
    sim.scene.host = None
    without = sim.get_cube(backend="numpy")[0]
    sim.scene.host = host
    added = with_host - without
    # independent: reference Gaussian PSF kernels, scipy FFT convolution, the spectrograph's LSF
    from slicersim.physics.psf import gaussian_psf_fractions
    shape, s = sim.spectrograph.shape, sim.spectrograph.spatial_scale
    flux = host.flux_cube(sim.lbda, shape, s)                    # erg/s/cm²/Å per cell
    sig_y, sig_x = sim.psf_sigmas
    kernels = gaussian_psf_fractions(sig_y, sig_x, (41, 41), (0.0, 0.0))
    blurred = np.array([fftconvolve(f, k, mode="same") for f, k in zip(flux, kernels)])
    tint = sim.get_times()["integration_time"]
    expected = sim.spectrograph.apply_lsf(sim.flambda_to_photon[:, None, None] * blurred, axis=0) \
        * (sim.qe * sim.detector.gain * tint)[:, None, None]
    assert np.max(np.abs(added - expected)) < 1e-10 * expected.max()
    # and its total is the host light in the field, less the PSF spill out of it (< 1 %)
    ratio = added.sum(axis=(1, 2)) / expected.sum(axis=(1, 2))
    assert np.allclose(ratio, 1.0, atol=1e-10)
    total = sim.spectrograph.apply_lsf(flux.sum(axis=(1, 2)) * sim.flambda_to_photon) * sim.qe \
        * sim.detector.gain * tint
    frac = added.sum(axis=(1, 2))[20:-20] / total[20:-20]
    assert np.all(frac <= 1 + 1e-12) and np.all(frac > 0.99)
    assert host.profile.r_eff < 0.2 and flux.sum(axis=(1, 2))[0] / host.total_flux(sim.lbda[:1])[0] > 0.97


def test_host_call_forms_of_slicersim_142():
    forms = {"sersic": "sersic:bb-5000", "sersic:bb-5000": "sersic:bb-5000", "sersic:bb": "sersic:bb-5000",
             "SERSIC:BB-6000": "sersic:bb-6000", "blackbody": None}
    for form, name in forms.items():
        if name is None:
            with pytest.raises(ParameterError, match="not understood"):
                GalaxyModel(form)
            continue
        assert GalaxyModel(form).name == name
    form = {"refmodel": "sersic:bb-5000", "redshift": 2.0, "band": "bessellr", "n": 1,
            "ellip": 0.5, "theta": 10, "magabs": -20, "position": (3, -2)}
    with pytest.raises(ParameterError, match="redshift 2 but the target is at 0.5"):   # 1.4.2 ignored it
        LazuliTarget(np.arange(3000.0, 20000.0, 10.0), np.full(1700, 1e-18), redshift=0.5, host=form)
    t = LazuliTarget(np.arange(3000.0, 20000.0, 10.0), np.full(1700, 1e-18), redshift=0.5,
                     host={**form, "redshift": 0.5})
    assert t.host.redshift == 0.5
    p = t.host.profile
    assert (p.sersic_index, p.axis_ratio, p.position_angle) == (1.0, 0.5, 10.0)
    s = t.simulation.spectrograph.spatial_scale
    assert p.offset == pytest.approx((3 * s, -2 * s))              # 1.4.2 position: cells, absolute
    t.update(position=(1.0, 1.0))
    assert p.offset == pytest.approx((3 * s, -2 * s))
    with pytest.raises(ParameterError, match="needs a redshift"):
        LazuliTarget(np.arange(3000.0, 20000.0, 10.0), np.full(1700, 1e-18), host="sersic")
    with pytest.raises(ParameterError, match="unknown host parameter"):
        GalaxyModel("sersic", radius=3)


@needs_data
def test_named_real_galaxies_forms_and_image_size():
    for form, name in {"ngc0628": "ngc0628:ngc0628", "NGC628:bb-5000": "ngc0628:bb-5000",
                       "sersic:ngc2403": "sersic:ngc2403", "ngc_4321:ngc0628": "ngc4321:ngc0628"}.items():
        assert GalaxyModel(form).name == name
    t = LazuliSupernova(0.5, host="ngc0628")
    r05 = t.host.profile.r_eff
    t.update(redshift=1.5)
    assert t.host.profile.r_eff * d_a_kpc(1.5) == pytest.approx(r05 * d_a_kpc(0.5), rel=1e-12)
    # image pixel scale: PIXSCALE · D_A(z_gal) / D_A(z)
    from slicersim.sources.galaxies import load_galaxy_image
    _, pixscale, z_gal, _, _ = load_galaxy_image("ngc0628")
    assert t.host.profile.pixel_scale == pytest.approx(pixscale * d_a_kpc(z_gal) / d_a_kpc(1.5), rel=1e-12)
    with pytest.raises(ParameterError, match="larger"):
        GalaxyModel("ngc0628").host(z_gal / 2)


def test_host_parameter_names_and_values_name_the_parameter():
    """An unknown parameter lists the valid ones with a "did you mean"; ellip, offsets and angles
    are checked numbers; a failed update leaves the model as it was."""
    with pytest.raises(ParameterError, match=r"unknown host parameter 'magabss' \(did you mean 'magabs'\?\); valid:"):
        GalaxyModel("sersic", magabss=-20)
    with pytest.raises(ParameterError, match=r"ellip \(= 1 − b/a\) must be in \[0, 1\)"):
        GalaxyModel("sersic", ellip=1.0)
    with pytest.raises(ParameterError, match=r"host offset\[1\] \(y\) must be finite"):
        GalaxyModel("sersic", offset=(0.0, float("inf")))
    with pytest.raises(ParameterError, match="host position_angle must be a number"):
        GalaxyModel("sersic", position_angle="north")
    model = GalaxyModel("sersic", r_kpc=3.0)
    with pytest.raises(ParameterError, match="unknown host parameter 'radius'"):
        model.updated(radius=4.0)
    assert model.params["r_kpc"] == 3.0
