"""JWST reference files of the simulated detector (:mod:`slicersim.io.reference_files`,
:mod:`slicersim.products.reference`): every file validates with stdatamodels, its values follow
the ramps' parameters in JWST units, and stcal calibrates a slicersim ramp with these files alone."""
import numpy as np
import pytest
from stdatamodels.jwst import datamodels                  # [test] dependencies (pyproject): never skipped
from stdatamodels.jwst.datamodels import dqflags

from slicersim.errors import RampFileError
from slicersim.io.rampfile import read_ramps
from slicersim.io.reference_files import REFERENCE_TYPES, read_reference_files, reference_file_names
from slicersim.physics.effects import DetectorEffects
from slicersim.physics.ramp import RampParameters
from slicersim.products.ramps import simulate
from slicersim.products.reference import reference_arrays, write_reference_files, write_reference_files_for_ramps

EFFECTS = "nonlinearity,bad_pixels,reference_pixels"
SHAPE = (40, 64)                      # nx a multiple of the 32 outputs of the reference pixels
GAIN, RON = 0.8, 10.0                 # ADU/e-, e- per frame


def _ramps(tmp_path, rate, nmd=(10, 1, 0), effects=EFFECTS, seed=11, name="r.h5"):
    return simulate(rate, nmd, seed=seed, out=tmp_path / name, ron=RON, gain=GAIN, dark=0.05, roic_glow=0.0,
                    effects=effects)


@pytest.fixture(scope="module")
def lazuli_files(tmp_path_factory):
    out = tmp_path_factory.mktemp("ref")
    p = RampParameters(nmd=(4, 1, 0), gain=GAIN, ron=RON)
    return write_reference_files(out / "reference", p, "lazuli", 5, SHAPE), p


def test_every_file_validates_with_stdatamodels(lazuli_files):
    paths, _ = lazuli_files
    assert sorted(paths) == sorted(REFERENCE_TYPES)
    models = {"gain": datamodels.GainModel, "readnoise": datamodels.ReadnoiseModel,
              "saturation": datamodels.SaturationModel, "superbias": datamodels.SuperBiasModel,
              "linearity": datamodels.LinearityModel, "dark": datamodels.DarkModel, "mask": datamodels.MaskModel,
              "ipc": datamodels.IPCModel}
    for kind, path in paths.items():
        assert path.endswith(reference_file_names()[kind]) and f"_{kind}." in path   # CRDS-like names
        with models[kind](path, strict_validation=True) as model:
            model.validate()
            assert model.meta.reftype == kind.upper() and model.meta.pedigree == "SIMULATION"
            assert model.meta.instrument.name == "N/A"            # as the level-1b files
            assert model.meta.filename == reference_file_names()[kind]


def test_values_follow_the_detector_in_jwst_units(lazuli_files):
    paths, p = lazuli_files
    ref = read_reference_files(paths["gain"].rsplit("/", 1)[0])
    assert np.allclose(ref["gain"], 1 / GAIN)                                     # e-/DN
    # CDS of two single-frame reads [DN]: √2 · √(gain² σ² + 1/12)
    assert np.allclose(ref["readnoise"], np.sqrt(2 * ((GAIN * RON) ** 2 + 1 / 12)), rtol=1e-6)
    fx = DetectorEffects.preset("lazuli")
    kernel = fx.params("ipc").matrix()
    assert np.allclose(ref["ipc"], kernel) and abs(ref["ipc"].sum() - 1) < 1e-6
    # saturation: below the full-well value of every pixel, within the ADC
    sat, bias = ref["saturation"], ref["superbias"]
    a2a3 = _truth_nonlinearity(p, fx, 5)
    full = bias + GAIN * p.full_well * (1 + a2a3[0] * p.full_well + a2a3[1] * p.full_well ** 2)
    assert np.all(sat < full) and np.all(sat < 65535) and np.all(sat > bias + 0.85 * GAIN * p.full_well * 0.9)
    # the reference pixels: flagged, no dark; a dark ramp linear in frames
    assert np.all(ref["mask"][:4] & dqflags.pixel["REFERENCE_PIXEL"])
    assert ref["dark_nframes"] == 1 and ref["dark_groupgap"] == 0
    assert np.all(ref["dark"][:, :4] == 0)
    steps = np.diff(ref["dark"], axis=0)
    assert np.allclose(steps, steps[0], atol=1e-4) and np.allclose(ref["dark"][0], steps[0], atol=1e-4)


def _truth_nonlinearity(p, fx, seed):
    from slicersim.physics.nonlinearity import nonlinearity_coefficients
    return nonlinearity_coefficients(seed, SHAPE, fx.params("nonlinearity"), p.full_well)


@pytest.mark.slow
def test_files_match_the_ramps_truth(tmp_path):
    rate = np.full(SHAPE, 50.0)
    path = _ramps(tmp_path, rate, nmd=(3, 1, 0))
    paths = write_reference_files_for_ramps(path, tmp_path / "ref")
    ref = read_reference_files(tmp_path / "ref")
    _, _, pdq, attrs = read_ramps(path)
    import h5py
    with h5py.File(path) as fh:
        truth = {k: fh["truth/" + k][()] for k in ("bias", "nonlinearity/inverse_coefficients",
                                                    "bad_pixels/extra_dark")}
    assert np.array_equal(ref["mask"], pdq)                             # dq_init gives the ramps' PIXELDQ
    assert np.allclose(ref["superbias"], truth["bias"])
    assert np.allclose(ref["linearity"], truth["nonlinearity/inverse_coefficients"])
    hot = (pdq & dqflags.pixel["HOT"]) != 0
    slope = ref["dark"][1] - ref["dark"][0]                              # [DN/frame]
    expect = GAIN * (0.05 + truth["bad_pixels/extra_dark"]) * float(attrs["TFRAME"])
    live = (pdq & (dqflags.pixel["DEAD"] | dqflags.pixel["REFERENCE_PIXEL"])) == 0
    assert hot.any() and np.allclose(slope[live], expect[live], rtol=1e-5)
    with pytest.raises(RampFileError, match="exists"):
        write_reference_files_for_ramps(path, tmp_path / "ref")
    assert write_reference_files_for_ramps(path, tmp_path / "ref", overwrite=True) == paths


def calibrate_with_stcal(path, refdir, linearity=True):
    """level-1 calibration of a slicersim ramp file by stcal with the reference files alone: dq_init,
    saturation, superbias, linearity, dark, ramp fit (OLS). Returns (rate [e-/s], err [e-/s], pixeldq)."""
    import stcal.ramp_fitting.ramp_fit as stcal_fit
    from stcal.dark_current.dark_class import DarkData, ScienceData
    from stcal.dark_current.dark_sub import do_correction_data
    from stcal.linearity.linearity import linearity_correction
    from stcal.ramp_fitting.ramp_fit_class import RampData
    from stcal.saturation.saturation import flag_saturated_pixels
    names = reference_file_names()
    model = lambda kind, cls: cls(str(refdir / names[kind]), strict_validation=True)   # noqa: E731
    sci, gdq, pdq, attrs = read_ramps(path)
    data = sci.astype(np.float32)
    flags = dqflags.pixel
    with model("mask", datamodels.MaskModel) as m:
        pdq = pdq | m.dq                                                             # dq_init
    with model("saturation", datamodels.SaturationModel) as m:
        gdq, pdq, _ = flag_saturated_pixels(data, gdq.copy(), pdq, m.data, m.dq, 65535, flags,
                                            n_pix_grow_sat=0)
    with model("superbias", datamodels.SuperBiasModel) as m:
        data -= m.data
    if linearity:
        with model("linearity", datamodels.LinearityModel) as m:
            data, pdq, _ = linearity_correction(data, gdq, pdq, m.coeffs, m.dq, flags)
    with model("dark", datamodels.DarkModel) as m:
        science = ScienceData()
        science.data, science.groupdq, science.pixeldq = data, gdq, pdq
        science.exp_nframes, science.exp_groupgap, science.exp_intstart, science.cal_step = (
            int(attrs["NFRAMES"]), int(attrs["GROUPGAP"]), None, None)
        out, _ = do_correction_data(science, DarkData(dark_model=m))
        data = out.data
    with model("gain", datamodels.GainModel) as m:
        gain = np.array(m.data)
    with model("readnoise", datamodels.ReadnoiseModel) as m:
        readnoise = np.array(m.data)
    ramp = RampData()
    ramp.set_arrays(data.astype(np.float32), gdq, pdq, np.zeros(pdq.shape, np.float32))
    ramp.set_meta(name="NIRSPEC", frame_time=float(attrs["TFRAME"]), group_time=float(attrs["TGROUP"]),
                  groupgap=int(attrs["GROUPGAP"]), nframes=int(attrs["NFRAMES"]), drop_frames1=None)
    ramp.set_dqflags(dict(flags))
    ramp.start_row, ramp.num_rows = 0, data.shape[2]
    ramp.suppress_one_group_ramps = False
    image, _, _ = stcal_fit.ramp_fit_data(ramp, False, readnoise, gain, "OLS_C", "optimal", "none")
    slope, dq, _, _, err = (image["slope"], image["dq"], None, None, image["err"]) if isinstance(image, dict) \
        else image
    return slope * gain, err * gain, pdq                                  # DN/s × e-/DN


@pytest.mark.slow
def test_stcal_calibrates_with_only_these_files(tmp_path):
    """The acceptance test: the rate recovered by stcal (saturation + superbias + linearity + dark +
    ramp fit) from the reference files alone agrees with the input within stcal's errors, up to
    near the full well (where the uncorrected nonlinearity biases it), and saturating pixels stay
    unbiased (their saturated groups flagged)."""
    ny, nx = SHAPE
    rate = np.empty(SHAPE)
    rows = np.clip(np.arange(ny) - 4, 0, ny - 9) / (ny - 9)         # the rows inside the reference border
    rate[:, : nx // 2] = np.repeat(10 ** (rows * np.log10(2500.0)), nx // 2).reshape(ny, nx // 2)
    rate[:, nx // 2:] = 6000.0                       # full well (79 ke-) reached within ~5 of the 10 groups
    path = _ramps(tmp_path, rate)
    write_reference_files_for_ramps(path, tmp_path / "ref")
    slope, err, pdq = calibrate_with_stcal(path, tmp_path / "ref")
    good = pdq == 0                                              # no bad or reference pixel
    lin = good & (np.arange(nx) < nx // 2)[None, :]
    pull = ((slope - rate) / err)[lin]
    assert pull.size > 500 and np.all(np.isfinite(pull))
    assert abs(pull.mean()) < 5 / np.sqrt(pull.size) + 0.03, f"pull mean {pull.mean():.3f}"
    assert abs(pull.std() - 1.0) < 0.08, f"pull width {pull.std():.3f}"
    bright = lin & (rate > 800)                                    # 23–71 ke- by the last group: nonlinear
    assert bright.sum() > 100 and np.abs(((slope - rate) / err)[bright].mean()) < 0.3
    sat = good & (np.arange(nx) >= nx // 2)[None, :]
    rel = (slope[sat] - 6000.0) / 6000.0
    assert abs(rel.mean()) < 3 * rel.std() / np.sqrt(rel.size) + 1e-3, f"saturating pixels biased {rel.mean():.4f}"
    # without the linearity file the bright pixels are biased low: the test can fail
    raw, raw_err, _ = calibrate_with_stcal(path, tmp_path / "ref", linearity=False)
    assert ((raw - rate) / raw_err)[bright].mean() < -3


def test_bad_input_is_refused_before_writing(tmp_path):
    p = RampParameters(nmd=(4, 1, 0))
    with pytest.raises(RampFileError, match="parent"):
        write_reference_files(tmp_path / "no" / "such", p, None, 1, (8, 8))
    with pytest.raises(RampFileError, match="detector label"):
        reference_file_names("a/b")
    arrays = reference_arrays(p, None, 1, (8, 8))
    assert np.array_equal(arrays["linearity"][1], np.ones((8, 8))) and not arrays["mask"].any()
    assert np.allclose(arrays["saturation"], 65535 - 5 * np.sqrt(12.0 ** 2 + 1 / 12), atol=0.01)


@pytest.mark.slow
def test_a_campaign_writes_the_reference_files_beside_its_ramps(tmp_path):
    """The campaign hook: a target's ramps get ``reference/`` beside them, keyed by the ramps' own
    seed, parameters and effects (a small ramp stands in for the full detector)."""
    from types import SimpleNamespace

    from slicersim.campaign import products

    class Target:
        def get_ramps(self, out, seed, effects, **kwargs):
            return simulate(np.full(SHAPE, 20.0), (3, 1, 0), seed=seed, out=out, effects=effects, overwrite=True)

    spec = SimpleNamespace(products={"compression": "none", "effects": "lazuli", "reference_files": True},
                           population=None, keeps_ramps=lambda tid: tid == 0)
    path = tmp_path / "t0000000" / "ramps.h5"
    path.parent.mkdir()
    products._write_ramps(str(path), Target(), {"target_id": 0}, 77, spec, 1 << 26)
    ref = read_reference_files(path.parent / products.REFERENCE_DIR)
    _, _, pdq, _ = read_ramps(path)
    assert np.array_equal(ref["mask"], pdq) and (pdq != 0).any()      # the maps of seed 77
    other = reference_arrays(RampParameters(nmd=(3, 1, 0)), DetectorEffects.preset("lazuli"), 78, SHAPE)
    assert not np.array_equal(other["mask"], pdq)
    gone = tmp_path / "t0000001" / "ramps.h5"                        # ramps deleted after the reduction:
    gone.parent.mkdir()                                              # no reference files
    products._write_ramps(str(gone), Target(), {"target_id": 1}, 78, spec, 1 << 26)
    assert not (gone.parent / products.REFERENCE_DIR).exists()


def test_campaign_reference_files_are_asked_for_and_need_stdatamodels(tmp_path, monkeypatch):
    """`[products] reference_files = true` (off by default: a full-detector set is ~1.2 GB and a minute of CPU per
    target) needs the ramps and stdatamodels (the [jwst] extra), refused at the spec; off, nothing is written."""
    import tomllib
    from types import SimpleNamespace

    from slicersim.campaign import products
    from slicersim.campaign.spec import parse_spec
    from slicersim.errors import ConfigError
    from slicersim.products import reference

    class Target:
        def get_ramps(self, out, **kwargs):
            np.save(str(out) + ".npy", np.zeros(1))

    spec = SimpleNamespace(products={"compression": "none", "effects": "none"}, population=None,
                           keeps_ramps=lambda tid: True)
    products._write_ramps(str(tmp_path / "ramps.h5"), Target(), {"target_id": 0}, 1, spec, 1 << 26)
    assert (tmp_path / "ramps.h5.npy").exists() and not (tmp_path / products.REFERENCE_DIR).exists()
    text = '[population]\nkind = "snia"\nn = 1\n[products]\nramps = true\nreference_files = true\n'
    assert parse_spec(tomllib.loads(text), text=text).canonical()["products"]["reference_files"] is True
    with pytest.raises(ConfigError, match="reference_files = true describes the raw ramps"):
        bad = text.replace("ramps = true\n", "")
        parse_spec(tomllib.loads(bad), text=bad)
    monkeypatch.setattr(reference, "available", lambda: False)
    with pytest.raises(ConfigError, match=r"needs stdatamodels: pip install 'slicersim\[jwst\]'"):
        parse_spec(tomllib.loads(text), text=text)


@pytest.mark.slow
def test_saturation_level_flags_every_full_pixel_even_an_isolated_one_under_ipc(tmp_path):
    """With IPC a full pixel whose neighbours are empty reads only the kernel's centre share of its
    signal: the saturation level allows for it, so stcal flags every group after the full well, for
    an isolated pixel as for a flat, and none before 60 % of it."""
    from stcal.saturation.saturation import flag_saturated_pixels
    rate = np.full((8, 32), 5.0)
    rate[4, 8] = rate[3, 20] = 8000.0                                 # isolated bright pixels
    rate[:, 26:] = 8000.0                                             # a bright flat band
    path = simulate(rate, (8, 1, 0), seed=2, out=tmp_path / "r.h5", effects="ipc,nonlinearity")
    write_reference_files_for_ramps(path, tmp_path / "ref")
    sci, gdq, pdq, attrs = read_ramps(path)
    with datamodels.SaturationModel(str(tmp_path / "ref" / reference_file_names()["saturation"])) as m:
        gdq, _, _ = flag_saturated_pixels(sci.astype(np.float32), np.zeros_like(gdq), pdq, m.data, m.dq, 65535,
                                          dqflags.pixel, n_pix_grow_sat=0)
    charge = 8000.0 * float(attrs["TFRAME"]) * np.arange(1, 9)          # at each group (m = 1) [e-]
    full = charge >= float(attrs["FULLWELL"])
    for y, x in ((4, 8), (3, 20), (2, 28), (5, 30)):
        flagged = (gdq[0, :, y, x] & dqflags.pixel["SATURATED"]) != 0
        assert flagged[full].all(), (y, x, flagged, full)
        assert not flagged[charge < 0.6 * float(attrs["FULLWELL"])].any(), (y, x, flagged)
