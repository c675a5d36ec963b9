"""Raw ramps with detector effects through :func:`slicersim.products.ramps.simulate`: backends,
chunking, independence of the random streams, truth layout, formats and bad input."""
import h5py
import numpy as np
import pytest

from slicersim.errors import EffectsError
from slicersim.io.rampfile import read_ramps
from slicersim.physics.effects import EFFECT_NAMES, DetectorEffects
from slicersim.products.ramps import simulate

NMD = (6, 4, 1)


def _rate(ny=48, nx=128):
    rate = np.full((ny, nx), 3.0)
    rate[10:20, 30:40] = 400.0
    return rate


def _truth(path, name):
    with h5py.File(path, "r") as fh:
        return fh[f"truth/{name}"][...]


@pytest.mark.slow
@pytest.mark.parametrize("effects", ["lazuli", "cosmic_rays,ipc,nonlinearity"])
def test_backends_and_chunking_give_the_same_integers(effects):
    rate = _rate()
    kw = dict(seed=3, effects=effects, progress=False, return_dq=True)
    ref = simulate(rate, NMD, backend="numpy", **kw)
    for extra in ({}, {"max_bytes": 128 * 200 * 50}):                  # one block, ~7-row blocks
        got = simulate(rate, NMD, backend="opencl", **extra, **kw)
        assert np.array_equal(ref[0], got[0]) and np.array_equal(ref[1], got[1])


def test_cosmic_rays_change_only_the_pixels_they_hit(tmp_path):
    """One stream per effect: with cosmic rays on, every pixel without a hit keeps the plain ramp's
    integers, and a hit pixel keeps them before its first hit group."""
    rate = _rate()
    plain = simulate(rate, NMD, seed=5, progress=False)
    path = simulate(rate, NMD, seed=5, progress=False, out=tmp_path / "cr.h5",
                    effects={"effects": {"enabled": ["cosmic_rays"], "cosmic_rays": {"rate": 2000.0}}})
    sci = read_ramps(path)[0]
    hits = _truth(path, "cosmic_rays")
    assert hits.dtype.names == ("ramp", "frame", "y", "x", "electrons") and hits.size > 50
    n, m, d = NMD
    changed = np.any(sci != plain, axis=1)[0]
    hit = np.zeros(rate.shape, bool)
    hit[hits["y"], hits["x"]] = True
    assert not np.any(changed & ~hit)
    first = np.full(rate.shape, n)
    np.minimum.at(first, (hits["y"], hits["x"]), np.minimum(hits["frame"] // (m + d), n))
    g = np.arange(n)[:, None, None]
    before = g < first[None]
    assert np.array_equal(sci[0][before], plain[0][before])
    big = hits["electrons"] > 200                                 # ≫ read noise: the pixel changed
    assert changed[hits["y"][big], hits["x"][big]].all()


def test_switching_an_effect_leaves_the_others_draws(tmp_path):
    """IPC on or off: the same charge (b = IPC(a) within the ±½ ADU roundings, no read noise);
    other effects on or off: the same cosmic rays and nonlinearity coefficients."""
    rate = _rate()
    kw = dict(seed=9, progress=False, ron=0.0)
    a = simulate(rate, NMD, effects="cosmic_rays,nonlinearity", **kw)[0].astype(float) - 2000.0
    with_ipc = DetectorEffects.from_names("cosmic_rays,nonlinearity,ipc")
    b = simulate(rate, NMD, effects=with_ipc, **kw)[0].astype(float) - 2000.0
    from slicersim.physics.ipc import apply_ipc
    diff = b - apply_ipc(a, with_ipc.params("ipc").matrix())
    assert np.abs(diff[:, 1:-1, 1:-1]).max() <= 1.0
    alone = simulate(rate, NMD, out=tmp_path / "cr.h5", effects="cosmic_rays,nonlinearity", **kw)
    every = simulate(rate, NMD, out=tmp_path / "all.h5", effects="lazuli", **kw)
    for name in ("nonlinearity/coefficients", "nonlinearity/inverse_coefficients"):
        assert np.array_equal(_truth(alone, name), _truth(every, name))
    cr_alone, cr_all = _truth(alone, "cosmic_rays"), _truth(every, "cosmic_rays")
    with h5py.File(every, "r") as fh:
        flags = fh["PIXELDQ"][...]
    collecting = (flags & np.uint32(2**31 | 1024)) == 0
    keep = collecting[cr_alone["y"], cr_alone["x"]]
    assert np.array_equal(cr_alone[keep], cr_all)


def test_truth_datasets_and_uncal_export_agree(tmp_path):
    rate = _rate()
    h5 = simulate(rate, NMD, seed=4, progress=False, out=tmp_path / "a.h5", effects="lazuli")
    fits = simulate(rate, NMD, seed=4, progress=False, out=tmp_path / "a.fits", effects="lazuli")
    from slicersim.io.uncal import read_uncal, read_uncal_truth
    assert np.array_equal(read_ramps(h5)[0], read_uncal(fits)[0])
    truth = read_uncal_truth(fits)
    with h5py.File(h5, "r") as fh:
        names = []
        fh["truth"].visititems(lambda k, v: names.append(k) if isinstance(v, h5py.Dataset) else None)
        for k in names:
            assert np.array_equal(fh["truth"][k][...], truth[f"truth/{k}"]), k
        assert {"rate", "cosmic_rays", "ipc_kernel", "nonlinearity/coefficients",
                "nonlinearity/inverse_coefficients", "bias"} <= set(names)
        pixeldq = fh["PIXELDQ"][...]
    ref = np.zeros(rate.shape, bool)
    ref[:4], ref[-4:], ref[:, :4], ref[:, -4:] = True, True, True, True
    assert np.all(pixeldq[ref] & np.uint32(2**31)) and not np.any(pixeldq[~ref] & np.uint32(2**31))


def test_reference_pixels_collect_no_charge():
    rate = np.full((32, 128), 50.0)
    sci = simulate(rate, (4, 2, 0), seed=1, progress=False, ron=0.0, effects="reference_pixels")
    ramp = sci[0].astype(float)
    slope = ramp[-1] - ramp[0]
    assert np.all(np.abs(slope[:4]) <= 1) and np.all(np.abs(slope[:, -4:]) <= 1)
    assert np.all(slope[8:-8, 8:-8] > 100)


def test_ipc_alpha_recovered_from_a_flat_ramp():
    """The autocorrelation of a flat field simulated through the ramp gives back α and α_d."""
    from slicersim.physics.ipc import ipc_alpha_from_autocorrelation
    rate = np.full((256, 256), 2000.0)
    sci = simulate(rate, (2, 1, 0), seed=11, progress=False, ron=0.0, effects="ipc", tframe=10.0)
    flat = sci[0, 1].astype(float) - sci[0, 0].astype(float)
    alpha, alpha_d = ipc_alpha_from_autocorrelation(flat, noise_variance=2 / 12.0)
    sigma = 0.46 / np.sqrt(2 * (254 ** 2))                         # (c/2)/√(2N), c = kernel centre
    assert abs(alpha - 0.016) < 4 * sigma and abs(alpha_d - 0.002) < 4 * sigma


@pytest.mark.parametrize("bad, message", [
    ("cosmic_ray", "unknown"), ("ipc,bogus", "bogus"),
    ({"effects": {"enabled": ["cosmic_rays"], "cosmic_rays": {"rate": -1.0}}}, "rate"),
    ({"effects": {"enabled": ["bad_pixels"], "bad_pixels": {"hot_fraction": -0.1}}}, "hot"),
    ({"effects": {"enabled": ["ipc"], "ipc": {"alpha": 0.2, "alpha_diag": 0.1}}}, "centre"),
    ({"effects": {"enabled": ["ipc"], "ipc": {"kernel": [[0, 0.2, 0], [0.2, 0.5, 0.2], [0, 0.2, 0]]}}}, "sum"),
    ({"effects": {"enabled": ["nonlinearity"], "nonlinearity": {"deficit": 0.3, "deficit_scatter": 0.1}}},
     "not invertible"),
    ({"effects": {"enabled": ["correlated_noise"], "correlated_noise": {"method": "fancy"}}}, "method"),
    (3.5, "effects must be"),
])
def test_bad_effects_one_clear_error(tmp_path, bad, message):
    with pytest.raises(EffectsError, match=message):
        simulate(_rate(), NMD, seed=1, progress=False, effects=bad, out=tmp_path / "x.h5")
    assert not list(tmp_path.iterdir())


def test_effect_names_are_the_documented_ones():
    assert EFFECT_NAMES == ("cosmic_rays", "ipc", "nonlinearity", "correlated_noise", "reference_pixels",
                            "bad_pixels", "persistence")
    assert set(DetectorEffects.from_names("all").enabled) == set(EFFECT_NAMES) - {"persistence"}


# ------------------------------------------------------------------ review findings (issue 9)
def test_cli_effects_names_and_presets(tmp_path):
    """Finding 1: --effects NAMES / all / lazuli ran into an AttributeError."""
    from slicersim.app.cli import main
    rate = tmp_path / "r.npy"
    np.save(rate, _rate())
    for k, names in enumerate(("cosmic_rays,ipc", "all", "lazuli")):
        assert main(["ramp", "--rate", str(rate), "--nmd", "3", "2", "0", "--out", str(tmp_path / f"{k}.h5"),
                     "--effects", names]) == 0
    assert main(["ramp", "--rate", str(rate), "--nmd", "3", "2", "0", "--out", str(tmp_path / "x.h5"),
                 "--effects", "cosmic_rays", "--cr-rate", "-1"]) == 2


def test_previous_charge_enables_persistence_with_all_and_presets(tmp_path):
    """Finding 2: "all"/"lazuli" with previous_charge silently left persistence off; previous_charge
    without persistence was silently ignored."""
    prev = np.zeros((48, 128))
    prev[5:9, 50:60] = 60000.0
    path = simulate(_rate(), NMD, seed=2, progress=False, out=tmp_path / "p.h5", effects="all",
                    previous_charge=prev)
    assert _truth(path, "persistence").size > 0
    with pytest.raises(EffectsError, match="persistence"):
        simulate(_rate(), NMD, seed=2, progress=False, effects="ipc", previous_charge=prev)


def test_user_dead_pixels_collect_no_cosmic_rays(tmp_path):
    """Finding 3: dead_pixels= were flagged DEAD but still got cosmic-ray charge and truth rows."""
    dead = np.zeros((48, 128), bool)
    dead[::2] = True
    path = simulate(_rate(), NMD, seed=3, progress=False, out=tmp_path / "d.h5", dead_pixels=dead,
                    effects={"effects": {"enabled": ["cosmic_rays"], "cosmic_rays": {"rate": 2000.0}}})
    hits = _truth(path, "cosmic_rays")
    assert hits.size and not dead[hits["y"], hits["x"]].any()
    sci = read_ramps(path)[0]
    assert np.all(np.abs(np.diff(sci[0].astype(int), axis=0))[:, dead] < 80)      # read noise only


def test_reference_pixels_carry_only_the_reference_flag(tmp_path):
    """Finding 4: reference pixels were also flagged DEAD/DO_NOT_USE (and HOT/WARM/LOW_QE)."""
    path = simulate(_rate(), NMD, seed=3, progress=False, out=tmp_path / "r.h5", effects="reference_pixels,bad_pixels")
    with h5py.File(path, "r") as fh:
        flags = fh["PIXELDQ"][...]
    border = np.zeros(flags.shape, bool)
    border[:4], border[-4:], border[:, :4], border[:, -4:] = True, True, True, True
    assert np.all(flags[border] == np.uint32(2**31))


@pytest.mark.parametrize("section, key", [("correlated_noise", "n_outputs"), ("correlated_noise", "nroh"),
                                          ("correlated_noise", "c_pink"), ("correlated_noise", "acn"),
                                          ("reference_pixels", "border")])
@pytest.mark.parametrize("value", [float("inf"), float("nan"), 1e300, True, "3"])
def test_non_finite_huge_or_wrong_type_parameters_refused(section, key, value):
    """Finding 5/6: inf, 1e300 (TOML accepts them) or booleans/strings raised OverflowError or passed."""
    with pytest.raises(EffectsError):
        DetectorEffects.from_config({"effects": {"enabled": [section], section: {key: value}}})


def test_config_sections_without_enabled_list_enable_their_effects():
    """Finding 7: sections without an "enabled" list silently gave a plain ramp."""
    fx = DetectorEffects.from_config({"effects": {"cosmic_rays": {"rate": 7.0}, "ipc": {}}})
    assert fx.enabled == ("cosmic_rays", "ipc") and fx.params("cosmic_rays").rate == 7.0


def test_asymmetric_user_ipc_kernel_follows_the_documented_convention():
    """Finding 13: K[1+dy, 1+dx] is the fraction of a pixel's signal seen at offset (dy, dx)."""
    rate = np.zeros((16, 128))
    rate[8, 40] = 1000.0
    kernel = [[0, 0.1, 0], [0, 0.8, 0.1], [0, 0, 0]]
    sci = simulate(rate, (2, 1, 0), seed=1, progress=False, ron=0.0, dark=0.0, roic_glow=0.0,
                   effects={"effects": {"enabled": ["ipc"], "ipc": {"kernel": kernel}}})[0].astype(float)
    signal = sci[1] - sci[0]
    assert signal[7, 40] > 200 and signal[8, 41] > 200                # offsets (−1, 0) and (0, +1)
    assert signal[9, 40] < 20 and signal[8, 39] < 20


def test_telegraph_pixels_have_truth(tmp_path):
    """Finding 12: telegraph pixels were flagged but had no truth."""
    path = simulate(np.full((64, 128), 1.0), NMD, seed=2, progress=False, out=tmp_path / "t.h5",
                    effects={"effects": {"enabled": ["bad_pixels"], "bad_pixels": {"telegraph_fraction": 0.01}}})
    tele = _truth(path, "bad_pixels/telegraph")
    with h5py.File(path, "r") as fh:
        flags = fh["PIXELDQ"][...]
    flagged = np.argwhere(flags & np.uint32(32768))
    assert tele.size and {tuple(v) for v in flagged} == set(zip(tele["y"].tolist(), tele["x"].tolist()))


def test_cli_previous_charge_gives_persistence(tmp_path):
    """Finding 11: persistence was offered by the CLI with no way to give the previous charge."""
    from slicersim.app.cli import main
    rate, prev = tmp_path / "r.npy", tmp_path / "prev.npy"
    np.save(rate, _rate())
    charge = np.zeros((48, 128))
    charge[5:9, 50:60] = 60000.0
    np.save(prev, charge)
    out = tmp_path / "p.h5"
    assert main(["ramp", "--rate", str(rate), "--nmd", "6", "4", "1", "--out", str(out), "--effects", "all",
                 "--previous-charge", str(prev)]) == 0
    assert _truth(out, "persistence").size > 0


def test_effect_names_are_case_insensitive_like_presets():
    """Finding 15: "Lazuli" was accepted but "IPC" was not."""
    assert DetectorEffects.from_names("IPC, Cosmic_Rays").enabled == ("cosmic_rays", "ipc")


def test_persistence_ramp_limit_refused_before_any_file(tmp_path):
    """Review finding 15: persistence keyed 12 bits of ramp failed mid-run at ramp 4096; now refused
    before anything is written."""
    prev = np.zeros((16, 32))
    out = tmp_path / "many.h5"
    with pytest.raises(EffectsError, match="4096 ramps"):
        simulate(_rate(16, 32), (2, 1, 0), nramps=4097, seed=1, progress=False, out=out, effects="persistence",
                 previous_charge=prev)
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_bias_too_low_for_reference_offsets_is_refused():
    """Review finding 9: a bias map reaching below 0 ADU was clipped at 0 in every read, unflagged."""
    with pytest.raises(EffectsError, match="bias .* too low"):
        simulate(_rate(), NMD, seed=1, progress=False, effects="reference_pixels", bias=5.0)
    simulate(_rate(), NMD, seed=1, progress=False, effects="reference_pixels")      # default bias: fine


def test_disk_check_counts_the_effects_truth(tmp_path, monkeypatch):
    """Review finding 8: the free-space check ignored the truth of the effects (e.g. nonlinearity
    coefficients, 40 B per pixel)."""
    import collections
    import shutil

    from slicersim.io.rampfile import RampWriter
    from slicersim.physics.ramp import RampParameters
    from slicersim.products.effects import EffectsPlan
    shape = (48, 128)
    plain = RampWriter(tmp_path / "a.h5", 1, NMD[0], shape, truth_rate=True).expected_bytes()
    fx = DetectorEffects.from_names("nonlinearity")
    extra = EffectsPlan.truth_nbytes(fx, RampParameters(nmd=NMD), shape)
    assert extra == 48 * 128 * (16 + 4 * (fx.params("nonlinearity").degree + 1))
    usage = collections.namedtuple("usage", "total used free")
    free = plain + 2**20 + extra // 2                  # room for the data and margin, not the truth
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10**12, 10**12 - free, free))
    simulate(_rate(), NMD, seed=1, progress=False, out=tmp_path / "plain.h5")
    from slicersim.errors import RampFileError
    with pytest.raises(RampFileError, match="not enough disk space"):
        simulate(_rate(), NMD, seed=1, progress=False, out=tmp_path / "fx.h5", effects="nonlinearity")
    assert not (tmp_path / "fx.h5").exists()


def test_background_writes_equal_the_in_memory_ramp(tmp_path):
    """HDF5 with effects: truth and block writes run in background threads; many small blocks give
    the in-memory ramp's integers and the truth of a file written without threads (FITS)."""
    rate = _rate(ny=40)
    kw = dict(seed=5, effects="lazuli", progress=False, max_bytes=128 * 200 * 50)
    ref = simulate(rate, NMD, return_dq=True, **kw)
    path = simulate(rate, NMD, out=tmp_path / "b.h5", **kw)
    sci, gdq = read_ramps(path)[:2]
    assert np.array_equal(sci, ref[0]) and np.array_equal(gdq, ref[1])


def test_background_write_error_reaches_the_caller(tmp_path, monkeypatch):
    from slicersim.io.rampfile import RampWriter
    calls = []

    def failing(self, ramp, row0, sci, groupdq=None):
        calls.append(row0)
        if len(calls) == 2:
            raise OSError("disk full (test)")
    monkeypatch.setattr(RampWriter, "write_block", failing)
    with pytest.raises(OSError, match="disk full"):
        simulate(_rate(), NMD, seed=5, effects="lazuli", progress=False, max_bytes=128 * 200 * 50,
                 out=tmp_path / "c.h5")
    assert not (tmp_path / "c.h5").exists()


def test_correlated_noise_across_ramps_and_small_blocks():
    """The correlated noise's segment cache across row blocks and ramps: two ramps in many small
    blocks give the NumPy backend's integers (one block per call there)."""
    rate = _rate(ny=40)
    kw = dict(seed=9, effects="lazuli", progress=False, nramps=2, return_dq=True)
    ref = simulate(rate, NMD, backend="numpy", **kw)
    got = simulate(rate, NMD, backend="opencl", max_bytes=128 * 200 * 50, **kw)
    assert np.array_equal(ref[0], got[0]) and np.array_equal(ref[1], got[1])
    assert not np.array_equal(got[0][0], got[0][1])                       # the two ramps differ
