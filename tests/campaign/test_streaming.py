"""Streaming campaigns (``[products] reduce``): each target's ramps reduced in its own task right
after they are simulated, kept only where ``keep_ramps`` asks, the catalog saying what exists.

One real campaign (2 SNe Ia, full-H4RG ramps of 2 groups, reduced to rates, the ramps of target 0
kept, those of target 1 deleted) runs once on a 1-worker LocalCluster; it is compared with
`slicersim reduce DATASET` of its kept ramps and with a run resumed after an interruption.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import tomllib
from pathlib import Path

import numpy as np
import pytest
from astropy.table import Table

from slicersim.errors import ConfigError, ParameterError

SPEC = """\
seed = 11
name = "streaming test"
[population]
kind = "snia"
n = 2
redshift = {distribution = "uniform", min = 0.8, max = 1.2}
[observation]
snr = 0.15
config = ["cbe", "short_readout.toml"]
[products]
spectrum = false
ramps = true
compression = "lz4"
reduce = "rates"
keep_ramps = 2
"""
SHORT_READOUT = "[detector]\nreadout_mode = [2, 1, 0]\nmax_group = 2\n"
PLAIN = 'seed = 1\n[population]\nkind = "snia"\nn = 2\n[products]\nspectrum = false\nramps = true\n'


def _spec(text):
    from slicersim.campaign.spec import parse_spec
    return parse_spec(tomllib.loads(text), text=text)


def _files(root):
    """{relative path: sha256} of every non-hidden file under root."""
    out = {}
    for path in sorted(Path(root).rglob("*")):
        rel = path.relative_to(root)
        if path.is_file() and not any(part.startswith(".") for part in rel.parts):
            out[str(rel)] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


# ----------------------------------------------------------------------------- the spec keys
@pytest.mark.parametrize("extra, message", [
    ('reduce = "cube"', "products.reduce must be"),
    ("reduce = 1", "products.reduce must be"),
    ('reduce = true\nkeep_ramps = "some"', "products.keep_ramps must be"),
    ("reduce = true\nkeep_ramps = 0", "products.keep_ramps must be"),
    ("reduce = true\nkeep_ramps = true", "products.keep_ramps must be"),
    ('keep_ramps = "none"', "applies only with products.reduce"),
])
def test_bad_streaming_keys_give_one_clear_error(extra, message):
    with pytest.raises(ConfigError, match=message):
        _spec(PLAIN + extra + "\n")


def test_reduce_needs_the_ramps():
    with pytest.raises(ConfigError, match="set products.ramps = true"):
        _spec(PLAIN.replace("ramps = true", "ramps = false\ncube = true") + "reduce = true\n")


def test_streaming_keys_leave_the_identity_of_earlier_datasets_and_enter_it_when_on():
    plain = _spec(PLAIN)
    assert _spec(PLAIN + 'reduce = false\nkeep_ramps = "all"\n').canonical() == plain.canonical()
    assert "reduce" not in plain.canonical()["products"] and plain.recorded == ["ramps"]
    on = _spec(PLAIN + "reduce = true\n")
    assert on.products["reduce"] == "spectra" and on.canonical() == _spec(PLAIN + 'reduce = "spectra"\n').canonical()
    assert on.canonical() != plain.canonical() and on.recorded == ["ramps", "reduced"]
    assert _spec(PLAIN + 'reduce = true\nkeep_ramps = "none"\n').canonical() != on.canonical()


def test_keep_ramps_keeps_all_none_or_every_nth_target():
    ids = range(7)
    assert [t for t in ids if _spec(PLAIN).keeps_ramps(t)] == list(ids)
    assert [t for t in ids if _spec(PLAIN + "reduce = true\n").keeps_ramps(t)] == list(ids)
    assert not any(_spec(PLAIN + 'reduce = true\nkeep_ramps = "none"\n').keeps_ramps(t) for t in ids)
    assert [t for t in ids if _spec(PLAIN + "reduce = true\nkeep_ramps = 3\n").keeps_ramps(t)] == [0, 3, 6]


def test_the_reduction_is_registered_by_the_reduction_layer():
    import slicersim  # noqa: F401  (the facade imports slicersim.reduction.streaming)
    from slicersim.campaign.products import registered_reducer
    from slicersim.reduction.streaming import reduce_ramps
    assert registered_reducer() is reduce_ramps
    with pytest.raises(ParameterError, match="mode must be"):
        reduce_ramps("r.h5", "o.h5", "cube", "narrow")


def test_reduce_cubes_streams_spectra_and_cubes_as_reduce_spectra_cubes(monkeypatch):
    """``reduce = "cubes"`` (issue 30: the cube is made only when asked) reduces as `slicersim reduce
    DATASET --spectra --cubes`: the same reduced.h5, with cubes=True passed; "spectra" passes no cube
    option (the forward extraction makes none)."""
    from slicersim.campaign.products import REDUCED_FILES
    from slicersim.reduction import campaign, streaming
    on = _spec(PLAIN + 'reduce = "cubes"\n')
    assert on.products["reduce"] == "cubes" and REDUCED_FILES["cubes"] == REDUCED_FILES["spectra"] == "reduced.h5"
    assert on.canonical() != _spec(PLAIN + 'reduce = "spectra"\n').canonical()
    calls = []
    monkeypatch.setattr(campaign, "reduce_file", lambda raw, out, **kw: calls.append(kw))
    streaming.reduce_ramps("r.h5", "o.h5", "cubes", "wide")
    streaming.reduce_ramps("r.h5", "o.h5", "spectra", "")
    assert calls[0]["spectra"] and calls[0]["cubes"] is True and calls[0]["field"] == "wide"
    assert calls[1]["spectra"] and "cubes" not in calls[1] and calls[1]["field"] == "narrow"


# ----------------------------------------------------------------------------- a real campaign
@pytest.fixture(scope="module")
def streamed(tmp_path_factory):
    from slicersim.campaign.runner import run_campaign
    root = tmp_path_factory.mktemp("stream")
    (root / "short_readout.toml").write_text(SHORT_READOUT)
    (root / "spec.toml").write_text(SPEC)
    res = run_campaign(root / "spec.toml", root / "dataset", workers=1, progress=False)
    assert (res["done"], res["failed"], res["computed"]) == (2, 0, 2), res
    return root


@pytest.mark.slow
def test_streaming_keeps_only_what_is_asked_and_the_catalog_says_so(streamed):
    from slicersim.campaign.runner import campaign_status
    ds = streamed / "dataset"
    assert sorted(os.listdir(ds / "products/t0000000")) == ["ramps.h5", "rates.h5"]      # 0 % 2 == 0: kept
    assert sorted(os.listdir(ds / "products/t0000001")) == ["rates.h5"]                  # deleted once reduced
    cat = Table.read(ds / "catalog.ecsv", format="ascii.ecsv")
    assert list(cat["reduced_product"]) == ["products/t0000000/rates.h5", "products/t0000001/rates.h5"]
    assert [str(v) if v is not np.ma.masked else "" for v in cat["ramps_product"]] == \
        ["products/t0000000/ramps.h5", ""]
    assert all(len(s) == 64 for s in cat["reduced_sha256"])
    assert campaign_status(ds)["done"] == 2                                              # checksums verified


@pytest.mark.slow
def test_streamed_rates_are_those_of_simulating_then_reducing(streamed, tmp_path):
    """`slicersim reduce DATASET` of the kept ramps gives the streamed product byte for byte."""
    from slicersim.reduction.campaign import reduce_dataset
    res = reduce_dataset(streamed / "dataset", tmp_path / "red", workers=1, progress=False)
    assert (res["done"], res["unavailable"]) == (1, 1), res                            # target 1: no ramps left
    a = (streamed / "dataset/products/t0000000/rates.h5").read_bytes()
    assert a == (tmp_path / "red/products/t0000000/rates.h5").read_bytes()


@pytest.mark.slow
def test_an_interrupted_target_is_redone_and_the_dataset_is_the_same(streamed):
    """Killed after its ramps were written but before its reduction finished (no record, the ramps
    and a torn product left behind): the rerun redoes that target only, to the same bytes, and
    deletes its ramps again.  In place (the reduced products name their source by its absolute
    path), last in this file: the dataset ends as it began."""
    from slicersim.campaign.runner import run_campaign
    ds = streamed / "dataset"
    ref = _files(ds)
    os.remove(ds / "records/t0000001.json")
    shutil.copy(ds / "products/t0000000/ramps.h5", ds / "products/t0000001/ramps.h5")
    (ds / "products/t0000001/rates.h5").write_bytes(b"half")
    res = run_campaign(streamed / "spec.toml", ds, workers=1, progress=False)
    assert (res["done"], res["computed"]) == (2, 1), res
    assert _files(ds) == ref


def test_a_target_task_reduces_its_ramps_in_its_field_and_deletes_them(tmp_path, monkeypatch):
    """reduce = true: the reducer gets the target's ramps, "spectra", the target's field and
    reduced.h5; keep_ramps = "none" deletes the ramps; the record lists the reduced product only.
    (The ramps are a stand-in file here: the real reduction is compared above.)"""
    from slicersim.campaign import products
    from slicersim.campaign.runner import plan_campaign
    from slicersim.io.dataset import Dataset
    spec = _spec(PLAIN.replace("n = 2", "n = 1") + 'reduce = true\nkeep_ramps = "none"\n')
    cat, _ = plan_campaign(spec)
    row = {k: (cat[0][k].item() if hasattr(cat[0][k], "item") else cat[0][k]) for k in cat.colnames}
    monkeypatch.setattr(products, "_write_ramps", lambda path, *a: Path(path).write_bytes(b"ramps"))
    calls = []

    def reducer(ramps, out, mode, field):
        calls.append((os.path.basename(ramps), os.path.basename(out), mode, field, Path(ramps).read_bytes()))
        Path(out).write_bytes(b"reduced")
    ds = Dataset(tmp_path / "d")
    digest = ds.initialise(spec.text, spec.canonical(), {}, False)
    rec = products.run_target(spec, row, ds.path, digest, reducer=reducer)
    assert rec["status"] == "done", rec.get("error")
    assert calls == [("ramps.h5", "reduced.h5", "spectra", str(row["field"]), b"ramps")]
    assert list(rec["products"]) == ["reduced"] and os.listdir(ds.product_dir(0)) == ["reduced.h5"]
    assert ds.verify(rec) == ""
    # a failing reduction: recorded, nothing left behind (the ramps included)
    rec = products.run_target(spec, row, ds.path, digest, reducer=lambda *a: 1 / 0)
    assert rec["status"] == "failed" and "ZeroDivisionError" in rec["error"]
    assert not os.path.exists(ds.product_dir(0)) or os.listdir(ds.product_dir(0)) == []


# ----------------------------------------------------------------------------- only the rows reduced
ROWS_SPEC = """\
seed = 4
name = "streaming rows"
[population]
kind = "snia"
n = 1
redshift = {{distribution = "uniform", min = 0.2, max = 0.21}}
[observation]
snr = 2
config = ["cbe", "short_readout.toml"]
[products]
spectrum = false
ramps = true
effects = "lazuli"
reduce = "spectra"
keep_ramps = {keep}
"""


def test_only_the_rows_a_streamed_spectrum_needs_are_simulated():
    """reduce = "spectra" or "cubes" and the ramps not kept: the rows the field's reduction reads (its
    footprints ± 16 rows and the reference rows); every row otherwise."""
    import slicersim
    from slicersim.campaign.products import reduced_rows
    from slicersim.campaign.runner import plan_campaign
    spec = _spec(PLAIN + 'reduce = "spectra"\nkeep_ramps = 2\n')
    cat, _ = plan_campaign(spec)
    row = {k: (cat[1][k].item() if hasattr(cat[1][k], "item") else cat[1][k]) for k in cat.colnames}
    target = slicersim.LazuliSupernova(0.5, field=row["field"])
    rows = reduced_rows(spec, row, target)
    assert rows[0] == (0, 4) and rows[-1] == (4092, 4096) and 1000 < sum(b - a for a, b in rows) < 1200
    assert reduced_rows(spec, {**row, "target_id": 0}, target) is None                  # kept: every row
    for text in ('reduce = "rates"\nkeep_ramps = "none"\n', 'reduce = "spectra"\n'):
        assert reduced_rows(_spec(PLAIN + text), row, target) is None


@pytest.mark.slow
def test_a_streamed_spectrum_from_some_rows_is_the_full_ramps(tmp_path):
    """The same target streamed with its ramps kept (the whole detector simulated) and not kept (only the
    rows its reduction reads): the same spectrum, to rounding (the forward fit's sums see no other row)."""
    import h5py
    from slicersim.campaign.runner import run_campaign
    spectra = {}
    for keep in ('"all"', '"none"'):
        root = tmp_path / keep.strip('"')
        root.mkdir()
        (root / "short_readout.toml").write_text(SHORT_READOUT)
        (root / "spec.toml").write_text(ROWS_SPEC.format(keep=keep))
        res = run_campaign(root / "spec.toml", root / "dataset", workers=1, progress=False)
        assert (res["done"], res["failed"]) == (1, 0), res
        with h5py.File(root / "dataset/products/t0000000/reduced.h5", "r") as fh:
            field = list(fh["spectra"])[0]
            spectra[keep] = (fh[f"spectra/{field}/FLUX"][...], fh[f"spectra/{field}/VAR"][...],
                             np.isnan(fh["rates/RATE"][...]).mean())
    (f_all, v_all, _), (f_rows, v_rows, nan_rows) = spectra['"all"'], spectra['"none"']
    np.testing.assert_allclose(f_rows, f_all, rtol=1e-9, atol=1e-9 * np.abs(f_all).max())
    np.testing.assert_allclose(v_rows, v_all, rtol=1e-9)
    assert nan_rows > 0.7                                        # the rate image: NaN outside the rows
