"""Findings of the adversarial review of issue 10 (/work/notes/review10_findings.md), one test each.

Each test reproduces the finding's call and checks the fixed behaviour: conflicting or
impossible updates are refused with nothing changed, user objects are never modified, hosts
lose no light silently and are never negative, CubeSource hosts are resampled once, host cubes
are bit-identical across chunkings, 1.4.2's names work, and clean errors come without warnings.
"""
import pydoc
import warnings

import numpy as np
import pytest
from astropy.io import fits

import slicersim.products.cube as cube_module
from slicersim.errors import ParameterError, ReadoutError, SpectrumError
from slicersim.products.components import SCENE_COMPONENTS
from slicersim.sources.extended import CubeSource, Host, SersicProfile
from slicersim.sources.galaxies import GalaxyModel
from slicersim.targets import Lazuli3DFlat, LazuliGalaxy, LazuliSupernova, LazuliTarget
from slicersim.targets.sources import LazuliCalSpec, LazuliPowerLaw

LBDA = np.arange(2000.0, 40000.0, 10.0)


@pytest.fixture(scope="module")
def sn_host():
    return LazuliSupernova(0.5, host="sersic")


@pytest.fixture(scope="module")
def qth():
    return Lazuli3DFlat.from_qth()


def _state(target):
    params = None if target.host_model is None else dict(target.host_model.params)
    return target.redshift, params, target.host, target.host_centre(), target.get_readout_config()


# --------------------------------------------------------------------------- 3
@pytest.mark.parametrize("pair", [dict(host__mag=20, host__magabs=-20), dict(host__offset=(0.1, 0), host__position=(1, 1)),
                                  dict(host__r_kpc=2, host__r_eff=0.3), dict(host__ellip=0.2, host__axis_ratio=0.5),
                                  dict(host__n=1, host__sersic_index=3), dict(host__theta=5, host__position_angle=9)])
def test_finding03_update_refuses_conflicting_host_parameters(sn_host, pair):
    before = _state(sn_host)
    with pytest.raises(ParameterError, match="not both"):
        sn_host.update(redshift=0.6, **pair)
    after = _state(sn_host)
    assert after[0] == before[0] and after[1] == before[1] and after[2] is before[2] and after[3] == before[3]
    with pytest.raises(ParameterError, match="not both"):           # the constructor's rule, the same
        GalaxyModel("sersic", **{k[len("host__"):]: v for k, v in pair.items()})


# --------------------------------------------------------------------------- 4
def test_finding04_update_checks_the_aperture_in_the_combined_state():
    g = LazuliGalaxy(0.5)
    with pytest.raises(ParameterError, match="extends beyond the field"):
        g.update(aperture="5-arcsec", redshift=0.6)
    assert (g.aperture, g.redshift) == ("1-arcsec", 0.5)
    # a kpc aperture that fits at z = 0.5 (0.49″) but not at z = 0.1 (1.65″ > 1.16″)
    k = LazuliGalaxy(0.5, aperture="3-kpc")
    r_eff = k.host.profile.r_eff
    with pytest.raises(ParameterError, match="extends beyond the field"):
        k.update(redshift=0.1)
    assert k.redshift == 0.5 and k.host.profile.r_eff == r_eff and k.simulation.redshift == 0.5
    assert np.all(np.isfinite(k.get_spectrum()[1]))                 # still usable
    k.update(redshift=0.1, aperture="1-kpc")                         # a fitting combination is accepted
    assert (k.aperture, k.redshift) == ("1-kpc", 0.1)
    np.testing.assert_array_equal(k.get_spectrum()[1],                # and is the one extracted
                                  k.get_spectrum(aperture="1-kpc", method="aperture")[1])


# --------------------------------------------------------------------------- 9
@pytest.mark.parametrize("nramps", [0, -1, 1.5, "2", True])
def test_finding09_get_ramps_refuses_bad_ramp_counts(qth, nramps):
    with pytest.raises(ReadoutError, match="nramps must be an integer"):
        qth.get_ramps(nramps=nramps)


# --------------------------------------------------------------------------- 10
def test_finding10_flat_switch_off_with_and_without_structure(qth):
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


# --------------------------------------------------------------------------- 11
class _CountingCube:
    """An array-like cube counting its reads."""

    def __init__(self, array):
        self.array, self.shape, self.reads = array, array.shape, 0

    def __getitem__(self, key):
        self.reads += 1
        return self.array[key]


def test_finding11_cubesource_host_is_resampled_once_per_grid_position_redshift():
    rng = np.random.default_rng(3)
    counting = _CountingCube(rng.random((24, 40, 40)) * 1e-20)
    source = CubeSource(counting, np.linspace(3000.0, 20000.0, 24), 0.02, redshift=0.5)
    t = LazuliSupernova(0.5, host=source)
    counting.reads = 0
    first = t.get_scene_cubes()["host"]
    reads = counting.reads
    assert reads > 0
    t.get_spectrum(of_host=True, method="aperture", aperture="0.5-arcsec")
    t.get_spectrum()
    again = t.get_scene_cubes()["host"]
    t.get_cube(max_bytes=2 * 10**7, progress=False)                # chunks: parts of the cached grid
    assert counting.reads == reads                                  # no new resampling
    np.testing.assert_array_equal(again, first)
    t.update(redshift=0.6)
    t.get_scene_cubes()
    assert counting.reads > reads                                   # another redshift: resampled
    reads = counting.reads
    t.update(redshift=0.5)
    np.testing.assert_array_equal(t.get_scene_cubes()["host"], first)
    assert counting.reads == reads                                  # back: served from the cache
    t.update(position=(5.0, 0.0))                                   # the host follows: another placement
    t.get_scene_cubes()
    assert counting.reads > reads


# --------------------------------------------------------------------------- 12
def test_finding12_user_models_and_hosts_are_never_changed():
    m = GalaxyModel("sersic", r_eff=0.5)
    params = dict(m.params)
    LazuliSupernova(0.2, host=m)
    assert m.params == params and "r_kpc" not in m.params
    assert LazuliSupernova(1.0, host=m).host.profile.r_eff == 0.5    # r_eff at the redshift it is used at
    host = Host(SersicProfile(1.0, 0.3, 0.8, 10.0, offset=(0.1, 0.0)), LBDA, np.full(LBDA.size, 3e-17))
    t = LazuliSupernova(0.5, host=host, position=(5.0, 2.0))
    t.update(position=(-3.0, 1.0), redshift=0.7)
    assert host.profile.offset == (0.1, 0.0) and host.profile.r_eff == 0.3
    cube = CubeSource(np.full((5, 8, 8), 1e-20), np.linspace(3000.0, 20000.0, 5), 0.05, centre=(0.2, 0.0))
    LazuliSupernova(0.5, host=cube, position=(4.0, 0.0))
    assert cube.centre == (0.2, 0.0)


# --------------------------------------------------------------------------- 13
def test_finding13_names_of_slicersim_142(sn_host):
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


# --------------------------------------------------------------------------- 14
def test_finding14_hosts_outside_the_field_negative_light_and_conflicts(sn_host):
    for host in ({"refmodel": "sersic", "offset": (100, 100)}, {"refmodel": "sersic", "position": (1e9, 0)}):
        with pytest.raises(ParameterError, match="light in the field"):
            LazuliSupernova(0.5, host=host)
    with pytest.raises(ParameterError, match="light in the field"):
        LazuliSupernova(0.5, host=CubeSource(np.ones((3, 4, 4)) * 1e-20, [3000.0, 9000.0, 20000.0], 0.05,
                                             centre=(30.0, 0.0)))
    before = _state(sn_host)
    with pytest.raises(ParameterError, match="light in the field"):
        sn_host.update(host__offset=(100.0, 0.0))
    assert _state(sn_host)[1:4] == before[1:4]
    # never negative: a compact Gaussian host (the exact integration cancels to −5e-17 far out)
    host = Host(SersicProfile(0.5, 0.1), LBDA, np.full(LBDA.size, 3e-17))
    assert host.flux_cube(LBDA[1000:1002], (58, 116), 0.04).min() >= 0
    assert SersicProfile(2.0, 0.8, offset=(100.0, 100.0)).cell_fractions((58, 116), 0.04).min() >= 0
    target = LazuliTarget(LBDA, np.full(LBDA.size, 1e-18), redshift=0.5, host=host)
    assert target.get_scene_cubes(unit="photon")["host"].min() >= 0
    # a dict's redshift must agree with the target's; a temperature given twice must agree
    with pytest.raises(ParameterError, match="redshift 3 but the target is at 0.5"):
        LazuliSupernova(0.5, host={"refmodel": "sersic", "redshift": 3.0})
    assert LazuliSupernova(0.5, host={"refmodel": "sersic", "redshift": 0.5}).host.redshift == 0.5
    with pytest.raises(ParameterError, match="6000 K black body but temperature=8000"):
        LazuliSupernova(0.5, host={"refmodel": "sersic:bb-6000", "temperature": 8000})
    assert GalaxyModel("sersic:bb-6000", temperature=6000).params["temperature"] == 6000
    assert GalaxyModel("sersic:bb-6000").updated(refmodel="sersic:bb-7000").params["temperature"] == 7000


# --------------------------------------------------------------------------- 15
def test_finding15_types_and_error_messages(sn_host, qth, tmp_path):
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


# --------------------------------------------------------------------------- 16
def test_finding16_lamp_magnitudes_are_finite_numbers_of_any_sign():
    with pytest.raises(ParameterError, match=r"lamp magnitude .* must be finite, got nan") as err:
        Lazuli3DFlat.from_qth(mag=float("nan"))
    assert "> 0" not in str(err.value)
    assert Lazuli3DFlat.from_qth(mag=-2.0).lamp.continuum.mag == -2.0


# --------------------------------------------------------------------------- 18
def test_finding18_the_host_is_seen_in_both_fields():
    # 1.4.2's layout: the narrow field (2.32″ high) sits 0.06″ above the wide one (4.64″ high), so a
    # round host 3.54″ below the narrow field's centre is centred on the wide field
    dy = 4.64 / 2 + 0.06 + 2.32 / 2
    t = LazuliSupernova(0.5, host={"refmodel": "sersic", "offset": (0.0, -dy), "axis_ratio": 1.0, "r_kpc": 8.0})
    bare = LazuliSupernova(0.5)
    wide = t.get_field_rate_cubes()["wide"][0]
    wide_bare = bare.get_field_rate_cubes()["wide"][0]
    host = wide - wide_bare
    assert host.min() >= 0 and host.sum() > 0.01 * wide_bare.sum()      # the host lights the wide field
    np.testing.assert_allclose(host[:, ::-1, :], host, rtol=1e-9, atol=1e-12 * host.max())   # centred there
    np.testing.assert_allclose(host[:, :, ::-1], host, rtol=1e-9, atol=1e-12 * host.max())


# --------------------------------------------------------------------------- 19
def test_finding19_host_cubes_bit_identical_across_chunkings_no_bar_for_short_runs(sn_host, capfd, monkeypatch):
    monkeypatch.setattr(cube_module, "PROGRESS_DELAY_S", 1e9)        # a "short" run on any machine
    full = cube_module.build_cube(sn_host.simulation, progress=False)
    chunked = cube_module.build_cube(sn_host.simulation, max_bytes=2 * 10**7)   # 15 chunks, progress=None
    assert chunked.chunks > 4
    assert "cube" not in capfd.readouterr().err
    assert np.array_equal(chunked.signal, full.signal, equal_nan=True)
    assert np.array_equal(chunked.variance, full.variance)


# --------------------------------------------------------------------------- 20
@pytest.mark.parametrize("cls, names", [(LazuliGalaxy, ("aperture__position", "method", "model")),
                                        (Lazuli3DFlat, ("structure", "lamp", "conventions"))])
def test_finding20_help_shows_the_parameters(cls, names):
    text = pydoc.render_doc(cls, renderer=pydoc.plaintext)
    head = text[:text.index("Method resolution order")]
    for name in names:
        assert f"{name} :" in head


# --------------------------------------------------------------------------- 22
@pytest.mark.parametrize("make", [lambda: LazuliPowerLaw(1000, 20), lambda: LazuliPowerLaw(-1000, 20),
                                  lambda: Lazuli3DFlat.from_qth(1)], ids=["alpha=1000", "alpha=-1000", "1 K lamp"])
def test_finding22_clean_errors_without_runtime_warnings(make):
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.raises(SpectrumError):
            make()


def test_host_and_aperture_defaults_follow_1_4_2():
    """scenes_vs_142 finding: get_spectrum(of_host=True) used the PSF-weighted "core" fit (91.6–98.8 %
    low against 1.4.2's 1-arcsec sum), and method="aperture" summed the core radius, not 1"."""
    import numpy as np

    import slicersim as S
    sn = S.LazuliSupernova(0.5, host="sersic:bb-5000")
    host_default = sn.get_spectrum(of_host=True)[1]
    host_sum = sn.get_spectrum(of_host=True, aperture="1-arcsec", method="aperture")[1]
    np.testing.assert_array_equal(host_default, host_sum)
    assert not np.allclose(host_default, sn.get_spectrum(of_host=True, aperture="core")[1])
    np.testing.assert_array_equal(sn.get_spectrum(method="aperture")[1],
                                  sn.get_spectrum(method="aperture", aperture="1-arcsec")[1])
    np.testing.assert_array_equal(sn.get_spectrum()[1], sn.simulation.get_spectrum()[1])   # the ETC's
