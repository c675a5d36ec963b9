"""`slicersim reduce DATASET --out DIR`: every target of a real campaign reduced in a Dask task.

A real campaign (2 SNe Ia at a low SNR, raw ramps of the full H4RG, at most 2 groups: a short
readout) is run once on a 2-worker LocalCluster, then reduced with 2 workers; the other tests
work on hard-linked copies of both directories (products are replaced by rename, never edited in
place, so the copies are independent).  Spectra are tested on a dataset of the small test
layout (conftest.small_slicer_mapper): the full layout's rectification takes minutes.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from astropy.table import Table

from slicersim.errors import DatasetError, ParameterError

from conftest import run_cli

BIN = Path(sys.executable).parent
SPEC = """\
seed = 11
name = "reduce test"
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
"""
SHORT_READOUT = "[detector]\nreadout_mode = [2, 1, 0]\nmax_group = 2\n"


def _cli(*args, **kwargs):
    return subprocess.run([str(BIN / "slicersim"), *map(str, args)], capture_output=True, text=True, **kwargs)


def _linked_copy(src, dst):
    shutil.copytree(src, dst, copy_function=os.link, ignore=shutil.ignore_patterns(".lock"))
    return dst


def _replace(path, data):
    """New content for ``path`` under a new inode (the hard-linked original stays intact)."""
    tmp = path.with_name(path.name + ".new")
    tmp.write_bytes(data)
    os.replace(tmp, path)


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    from slicersim.campaign.runner import run_campaign
    root = tmp_path_factory.mktemp("campaign")
    (root / "short_readout.toml").write_text(SHORT_READOUT)
    (root / "spec.toml").write_text(SPEC)
    res = run_campaign(root / "spec.toml", root / "dataset", workers=2, progress=False)
    assert (res["done"], res["failed"]) == (2, 0)
    return root / "dataset"


@pytest.fixture(scope="module")
def reduced(campaign, tmp_path_factory):
    from slicersim.reduction.campaign import reduce_dataset
    out = tmp_path_factory.mktemp("reduced") / "red"
    res = reduce_dataset(campaign, out, workers=2, progress=False)
    assert (res["done"], res["failed"], res["missing"], res["computed"]) == (2, 0, 0, 2), res
    return out


@pytest.mark.slow
def test_campaign_ramps_carry_the_target_truth(campaign, tmp_path):
    """Each raw file holds its target's truth, equal to the catalog's values; the campaign report
    (no spectra in this campaign: flagged) runs from the command line."""
    from slicersim.io.target_truth import read_target_truth
    cat = Table.read(campaign / "catalog.ecsv", format="ascii.ecsv")
    for row in cat:
        truth = read_target_truth(campaign / row["ramps_product"])
        for key in ("target_id", "redshift", "phase", "peak_absmag", "field"):
            assert truth.attrs[key] == row[key], key
        assert truth.attrs["phase_frame"] == "rest" and truth.attrs["source"] == "hsiao-subsampled"
        assert json.loads(truth.attrs["nmd"]) == [row["n"], row["m"], row["d"]]
        assert truth.attrs["nramps"] == row["nramps"]
        # the expected rate is the simulation's: F_λ through the instrument, > 0 where the SN shines
        ok = np.isfinite(truth.flambda) & (truth.flambda > 0)
        assert ok.sum() > 100 and np.all(truth.rate[ok] >= 0) and truth.rate[ok].max() > 0
        assert np.all(truth.etc_variance > 0) and np.all(np.diff(truth.lbda) > 0)
    proc = run_cli("campaign", "report", campaign, "--out", tmp_path / "rep")
    assert proc.returncode == 0, proc.stderr
    summary = Table.read(tmp_path / "rep" / "summary.ecsv", format="ascii.ecsv")
    assert list(summary["flags"]) == ["no-spectrum"] * 2 and np.all(summary["t_simulate"] > 0)


def _record(out, tid):
    return json.loads((out / "records" / f"t{tid:07d}.json").read_text())


@pytest.mark.slow
def test_every_target_is_reduced_to_rates(campaign, reduced):
    from astropy.table import Table
    cat = Table.read(reduced / "catalog.ecsv", format="ascii.ecsv")
    assert list(cat["target_id"]) == [0, 1] and set(cat["status"]) == {"done"}
    src = Table.read(campaign / "catalog.ecsv", format="ascii.ecsv")
    for row, srow in zip(cat, src):
        tid = int(row["target_id"])
        rec = _record(reduced, tid)
        assert rec["status"] == "done" and rec["source_sha256"] == srow["ramps_sha256"] == row["source_sha256"]
        with h5py.File(reduced / row["product"], "r") as fh:
            rate, var = fh["RATE"][...], fh["VAR"][...]
            attrs = dict(fh.attrs)
        assert rate.shape == (4096, 4096)
        assert (attrs["NGROUPS"], attrs["NFRAMES"], attrs["NINTS"]) == (srow["n"], srow["m"], srow["nramps"])
        assert attrs["SOURCE"] == str(campaign / srow["ramps_product"])
        import hdf5plugin  # noqa: F401  (the campaign's ramps are lz4-compressed)
        with h5py.File(campaign / srow["ramps_product"], "r") as fh:
            truth = fh["truth/rate"][...]
        ok = np.isfinite(rate) & (var > 0)
        pulls = (rate[ok] - truth[ok]) / np.sqrt(var[ok])
        assert ok.mean() > 0.99 and abs(np.median(pulls)) < 0.1 and 0.7 < np.std(pulls) < 1.5
    # the reduction directory is a dataset: `slicersim campaign status` reads it
    proc = _cli("campaign", "status", reduced)
    assert proc.returncode == 0 and "2 done, 0 missing, 0 failed" in proc.stdout


@pytest.mark.slow
def test_resume_redoes_only_the_removed_or_truncated_output(reduced, campaign, tmp_path):
    from slicersim.reduction.campaign import reduce_dataset
    out = _linked_copy(reduced, tmp_path / "red")
    kept = (out / "products/t0000001/rates.h5").stat().st_ino
    os.remove(out / "products/t0000000/rates.h5")
    res = reduce_dataset(campaign, out, workers=2, progress=False)
    assert (res["done"], res["computed"]) == (2, 1)
    assert (out / "products/t0000001/rates.h5").stat().st_ino == kept          # untouched
    assert _record(out, 0)["products"] == _record(reduced, 0)["products"]      # same bytes again
    kept = (out / "products/t0000000/rates.h5").stat().st_ino
    # a truncated product (same record) is found by its size and reduced again; nothing else
    path = out / "products/t0000001/rates.h5"
    _replace(path, path.read_bytes()[:1 << 20])
    proc = _cli("reduce", campaign, "--out", out, "--workers", "1", "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert "2 reduced, 0 failed, 0 missing, 0 without ramps (1 reduced now" in proc.stdout
    assert (out / "products/t0000000/rates.h5").stat().st_ino == kept
    assert _record(out, 1)["products"] == _record(reduced, 1)["products"]
    # complete: nothing to do, and another set of options is refused without --force
    assert reduce_dataset(campaign, out, workers=1, progress=False)["computed"] == 0
    proc = run_cli("reduce", campaign, "--out", out, "--weighting", "ols")
    assert proc.returncode == 2 and "other options" in proc.stderr and "weighting" in proc.stderr


@pytest.mark.slow
def test_verify_finds_a_product_damaged_in_place(reduced, campaign, tmp_path):
    """Same size, other bytes: found only by the checksum (verify=True / --verify)."""
    from slicersim.reduction.campaign import reduce_dataset
    out = _linked_copy(reduced, tmp_path / "red")
    path = out / "products/t0000000/rates.h5"
    data = bytearray(path.read_bytes())
    data[-100:] = bytes(100)
    _replace(path, bytes(data))
    assert reduce_dataset(campaign, out, workers=1, progress=False)["computed"] == 0
    proc = _cli("reduce", campaign, "--out", out, "--workers", "1", "--quiet", "--verify")
    assert proc.returncode == 0 and "(1 reduced now" in proc.stdout, proc.stderr
    assert _record(out, 0)["products"] == _record(reduced, 0)["products"]


@pytest.mark.slow
def test_a_failing_target_is_recorded_and_the_others_go_on(campaign, reduced, tmp_path):
    """Target 1's ramps get an NGROUPS keyword their data contradict (the campaign's record updated
    to match): only target 1 is reduced again (its source changed), it fails with one clear line,
    target 0 stays done; --retry-failed tries it again; repaired ramps (a new source checksum)
    are reduced without being asked."""
    from slicersim.io.dataset import Dataset, product_info
    from slicersim.reduction.campaign import reduce_dataset
    ds = _linked_copy(campaign, tmp_path / "ds")
    out = _linked_copy(reduced, tmp_path / "red")
    ramps = ds / "products/t0000001/ramps.h5"
    original = ramps.read_bytes()
    _replace(ramps, original)
    with h5py.File(ramps, "r+") as fh:
        fh.attrs["NGROUPS"] = 5
    rec = _record(ds, 1)
    rec["products"]["ramps"] = product_info(ramps)
    Dataset(ds).write_record(1, rec)
    res = reduce_dataset(ds, out, workers=2, progress=False)
    assert (res["done"], res["failed"], res["computed"]) == (1, 1, 1)
    assert res["failed_targets"][0][0] == 1
    assert "inconsistent readout keywords: NGROUPS = 5 but SCI has 2" in res["failed_targets"][0][1]
    assert not list((out / "products/t0000001").glob("*.h5"))
    assert _record(out, 0) == _record(reduced, 0)
    proc = _cli("reduce", ds, "--out", out, "--workers", "1", "--quiet")
    assert proc.returncode == 1 and "(0 reduced now" in proc.stdout and "failed 1: RampFileError" in proc.stdout
    proc = _cli("reduce", ds, "--out", out, "--workers", "1", "--quiet", "--retry-failed")
    assert proc.returncode == 1 and "(1 reduced now" in proc.stdout and "1 failed" in proc.stdout
    _replace(ramps, original)                                     # repaired: the campaign's own file
    rec["products"]["ramps"] = product_info(ramps)
    Dataset(ds).write_record(1, rec)
    res = reduce_dataset(ds, out, workers=1, progress=False)
    assert (res["done"], res["failed"], res["computed"]) == (2, 0, 1)
    with h5py.File(out / "products/t0000001/rates.h5", "r") as fh, \
            h5py.File(reduced / "products/t0000001/rates.h5", "r") as ref:
        assert fh.attrs["SOURCE"] == str(ramps) and np.array_equal(fh["RATE"][...], ref["RATE"][...],
                                                                   equal_nan=True)


@pytest.mark.slow
def test_a_damaged_source_ramp_is_named_not_only_counted(campaign, reduced, tmp_path):
    """A truncated campaign ramp file was reported only as "1 without ramps"; the catalogue and the CLI now
    say which target, what is wrong with its file and the command that recomputes it."""
    ds = _linked_copy(campaign, tmp_path / "ds")
    ramps = ds / "products/t0000001/ramps.h5"
    _replace(ramps, ramps.read_bytes()[:-100])
    out = tmp_path / "red"
    proc = _cli("reduce", ds, "--out", out, "--workers", "1", "--quiet")
    assert proc.returncode == 1 and "1 without ramps" in proc.stdout, proc.stdout + proc.stderr
    line = next(x for x in proc.stdout.splitlines() if x.strip().startswith("without ramps 1:"))
    assert "damaged (ramps:" in line and "truncated" in line and "slicersim campaign run" in line
    from astropy.table import Table
    cat = Table.read(out / "catalog.ecsv")
    row = cat[cat["target_id"] == 1][0]
    assert row["status"] == "unavailable" and "damaged" in row["error"]


@pytest.mark.slow
def test_kill9_mid_write_leaves_no_partial_output(campaign, reduced, tmp_path):
    out = _linked_copy(reduced, tmp_path / "red")
    for tid in (0, 1):
        os.remove(out / f"records/t{tid:07d}.json")
        os.remove(out / f"products/t{tid:07d}/rates.h5")
    proc = subprocess.Popen([str(BIN / "slicersim"), "reduce", str(campaign), "--out", str(out), "--workers", "1",
                             "--quiet"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    seen = False
    try:
        deadline = time.time() + 120
        while time.time() < deadline and proc.poll() is None:
            if list(out.glob("products/t*/.rates.h5.tmp-*")):
                seen = True
                break
            time.sleep(0.01)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)              # the client, its scheduler and its worker
        proc.wait()
    assert seen, "the reduction must be killed while it writes for this test to mean anything"
    for path in out.glob("products/t*/rates.h5"):       # under its final name a product is complete
        with h5py.File(path, "r") as fh:
            assert fh.attrs["COMPLETE"] and fh["RATE"].shape == (4096, 4096)
    from slicersim.reduction.campaign import reduce_dataset
    res = reduce_dataset(campaign, out, workers=2, progress=False)
    assert (res["done"], res["failed"]) == (2, 0) and 1 <= res["computed"] <= 2
    assert not list(out.rglob(".*tmp-*"))               # the killed writer's temporary is gone
    for tid in (0, 1):
        assert _record(out, tid)["products"] == _record(reduced, tid)["products"]


@pytest.mark.slow
def test_bad_requests_are_refused_before_any_work(campaign, reduced, tmp_path):
    from slicersim.io.dataset import Dataset
    from slicersim.reduction.campaign import reduce_dataset
    afile = tmp_path / "file"
    afile.write_text("keep")
    cases = [((campaign, afile), {}, DatasetError, "is a file"),
             ((campaign, campaign), {}, DatasetError, "must not be the dataset"),
             ((campaign, campaign / "products" / "red"), {}, DatasetError, "must not be the dataset"),
             ((campaign, tmp_path / "alias" / "products" / "red"), {}, DatasetError, "must not be the dataset"),
             ((reduced, tmp_path / "r2"), {}, DatasetError, "is a reduction directory"),
             ((tmp_path, tmp_path / "r3"), {}, DatasetError, "not a slicersim campaign dataset"),
             ((campaign, tmp_path / "r4"), {"workers": 0}, Exception, "workers"),
             ((campaign, tmp_path / "r5"), {"ncol": 5}, ParameterError, "only with spectra"),
             ((campaign, tmp_path / "r6"), {"fit_options": {"weighting": "best"}}, ParameterError, "weighting"),
             ((campaign, tmp_path / "r7"), {"fit_options": {"jump": 3}}, ParameterError, "unknown fit_ramps"),
             ((campaign, tmp_path / "r8"), {"spectra": True, "ncol": 10**9}, ParameterError, "ncol"),
             ((campaign, tmp_path / "r12"), {"mapper": object()}, ParameterError,
              r"option\(s\) mapper apply only with spectra"),
             ((campaign, tmp_path / "r13"), {"spectra": True, "ncols": 5}, ParameterError,
              r"unknown reduction option 'ncols' \(did you mean 'ncol'\?\)"),
             ((campaign, tmp_path / "r9"), {"spectra": True, "aperture": float("nan")}, ParameterError, "aperture"),
             ((campaign, tmp_path / "r10"), {"spectra": True, "lbda_edges": [20000, 30000]}, ParameterError,
              "leaves the traces"),
             ((123, tmp_path / "r2"), {}, ParameterError, "dataset must be a path"),
             ((campaign, None), {}, ParameterError, "out must be a path")]
    os.symlink(campaign, tmp_path / "alias")
    for args, kwargs, error, message in cases:
        with pytest.raises(error, match=message):
            reduce_dataset(*args, progress=False, **kwargs)
    assert afile.read_text() == "keep" and not any((tmp_path / f"r{i}").exists() for i in range(2, 14))
    # a campaign dataset is never an output, even with force
    other = _linked_copy(campaign, tmp_path / "other")
    with pytest.raises(DatasetError, match="is a campaign dataset"):
        reduce_dataset(campaign, other, force=True, progress=False)
    assert (other / "products/t0000000/ramps.h5").exists()
    # a dataset without ramps
    noramps = _linked_copy(campaign, tmp_path / "noramps")
    doc = json.loads((noramps / "spec.json").read_text())
    doc["spec"]["products"]["ramps"] = False
    os.remove(noramps / "spec.json")
    (noramps / "spec.json").write_text(json.dumps(doc))
    with pytest.raises(DatasetError, match="no raw ramps"):
        reduce_dataset(noramps, tmp_path / "r11", progress=False)
    # two reducers on one directory: the second is refused (one line from the CLI)
    out = _linked_copy(reduced, tmp_path / "locked")
    with Dataset(out):
        proc = _cli("reduce", campaign, "--out", out, "--workers", "1")
    assert proc.returncode == 2 and "in use by another process" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


@pytest.mark.slow
@pytest.mark.parametrize("argv, message", [
    (["--overwrite"], "--overwrite applies to a single ramp file"),
    (["--workers", "0"], "--workers must be an integer ≥ 1, got 0"),
    (["--ncol", "20"], "--ncol applies only with --spectra"),
    (["--spectra", "--lbda-edges", "9000,8000,10"], "START < STOP"),
    (["--spectra", "--extraction", "gls", "--rectify", "drizzle"], "needs an lsq cube"),
    (["--scheduler", "nowhere"], "tcp://host:port"),
    (["--workers", "100000"], "workers must be ≤"),
    (["--show", "-1"], "--show must be an integer ≥ 0, got -1"),
])
def test_cli_dataset_flags_are_checked(campaign, tmp_path, argv, message):
    out = tmp_path / "red"
    proc = run_cli("reduce", campaign, "--out", out, *argv)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith("slicersim: error:"), proc.stderr
    assert message in lines[0]
    assert not out.exists()


# --------------------------------------------------------------------------- spectra (small layout)
EDGES = np.linspace(9050.0, 9950.0, 13)
NCOL = 24


def _point_source(flux):
    """(nλ, 58, NCOL) cube of a Gaussian point source with total flux ``flux`` per bin [e-/s]."""
    from slicersim.physics.psf import gaussian_psf_cells
    nl = EDGES.size - 1
    sig = np.linspace(1.2, 1.8, nl)
    iy, ix = np.indices((58, NCOL)).reshape(2, -1)
    psf = gaussian_psf_cells(sig, 0.8 * sig, (58, NCOL), (0.7, -1.4), (iy, ix)).reshape(nl, 58, NCOL)
    return flux * psf


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory):
    """A dataset with a campaign's layout whose ramps are of the small test layout: target 0 in the
    narrow field, target 1 in the wide one."""
    from astropy.table import Table
    from conftest import small_slicer_mapper

    from slicersim.io.dataset import Dataset, product_info
    from slicersim.products.ramps import simulate
    mapper = small_slicer_mapper()
    ds = Dataset(tmp_path_factory.mktemp("small") / "dataset")
    from slicersim.io.target_truth import TargetTruth
    spec = {"seed": 1, "name": "small layout", "products": {"ramps": True, "spectrum": False},
            "observation": {"lbda_range": [9125.0, 9875.0], "frame": "obs"}}
    ds.initialise("# made by the test\n", spec, {})
    lbda = 0.5 * (EDGES[1:] + EDGES[:-1])
    for tid, field in enumerate(("narrow", "wide")):
        image = mapper.project_fields(lbda, EDGES, **{field: _point_source(400.0)})
        os.makedirs(ds.product_dir(tid))
        path = os.path.join(ds.product_dir(tid), "ramps.h5")
        truth = TargetTruth({"target_id": tid, "redshift": 0.0, "phase": 1.5, "field": field}, lbda, np.diff(EDGES),
                            np.full(lbda.size, 1e-17), np.full(lbda.size, 400.0))      # 400 e-/s per bin
        simulate(image, (8, 4, 0), seed=tid, out=path, ron=5.0, dark=0.0, roic_glow=0.0, progress=False,
                 target=truth)
        ds.write_record(tid, {"target_id": tid, "status": "done", "field": field,
                              "products": {"ramps": product_info(path)}})
    ds.write_catalog(Table({"target_id": [0, 1], "field": ["narrow", "wide"], "status": ["done", "done"]}))
    return Path(ds.path), mapper


@pytest.mark.slow
def test_spectra_of_every_target_in_its_own_field(small_dataset, tmp_path):
    from slicersim.reduction.campaign import reduce_dataset
    path, mapper = small_dataset
    res = reduce_dataset(path, tmp_path / "red", spectra=True, mapper=mapper, lbda_edges=EDGES, ncol=NCOL,
                         workers=2, progress=False, fit_options={"with_truth": True})
    assert (res["done"], res["failed"]) == (2, 0), res["failed_targets"]
    for tid, field in enumerate(("narrow", "wide")):
        with h5py.File(tmp_path / "red" / f"products/t{tid:07d}/reduced.h5", "r") as fh:
            assert list(fh["cubes"]) == [field] and list(fh["spectra"]) == [field]
            flux, var = fh[f"spectra/{field}/FLUX"][...], fh[f"spectra/{field}/VAR"][...]
            assert fh["rates/TRUTH_RATE"].shape == (660, 600) and fh["cubes"][field]["FLUX"].shape[1:] == (58, NCOL)
            truth = fh["truth/target"]
            assert truth.attrs["phase"] == 1.5 and truth.attrs["field"] == field and truth.fletcher32
            assert np.all(truth["rate"] == 400.0) and truth.attrs["unit_rate"] == "electron/s"
        pulls = (flux - 400.0) / np.sqrt(var)
        assert np.all(np.abs(pulls) < 5), pulls
    # the summary against the truth: the band's 10 bins of 400 e-/s
    summary = Table.read(tmp_path / "red" / "summary.ecsv", format="ascii.ecsv")
    assert list(summary["target_id"]) == [0, 1] and list(summary["phase"]) == [1.5, 1.5]
    assert np.all(np.abs(summary["band_flux_ratio"] - 1) < 5 * summary["band_flux_ratio_error"])
    assert np.all(summary["band_flux_ratio_error"] < 0.05) and np.all(summary["t_reduce"] > 0)
    assert (tmp_path / "red" / "report.md").is_file() and (tmp_path / "red" / "bias_vs_redshift.png").is_file()
    # the same options again: nothing to do; the spectra directory is not a rates one
    again = reduce_dataset(path, tmp_path / "red", spectra=True, mapper=mapper, lbda_edges=EDGES, ncol=NCOL,
                           workers=1, progress=False, fit_options={"with_truth": True})
    assert again["computed"] == 0
    with pytest.raises(DatasetError, match="other options"):
        reduce_dataset(path, tmp_path / "red", workers=1, progress=False)


def test_progress_follows_the_keyword_convention(monkeypatch):
    """progress: None (the default) draws a bar only when stderr is a terminal; True/False as given;
    anything else is a ParameterError naming progress."""
    import io
    import sys

    from slicersim.reduction.campaign import _progress
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    assert _progress(None) is False and _progress(True) is True and _progress(False) is False
    with pytest.raises(ParameterError, match="progress must be True or False"):
        _progress("yes")


#: the fit options of a rates reduction's identity as the release before the ``ron`` / ``max_bytes``
#: keywords wrote them (spec.json of an existing reduction directory)
PREVIOUS_FIT_IDENTITY = {"gain": None, "jump_threshold": 4.0, "linearity": None, "read_noise": None,
                         "refpix": None, "saturation": None, "superbias": None, "weighting": "gls",
                         "with_truth": False}


def test_identity_of_an_earlier_release_is_resumed(tmp_path):
    """The identity is built from FIT_DEFAULTS with ``ron`` under the key ``read_noise``, the name the
    earlier release wrote: a reduction directory it made is recognised (same digest, no DatasetError)
    whether the options are given as ron/max_bytes or under their deprecated names.  Fails if the
    key mapping (reduction.campaign._IDENTITY_KEYS) is removed."""
    import warnings

    from slicersim.io.dataset import Dataset
    from slicersim.reduction.campaign import _check_identity, _identity
    from slicersim.reduction.checks import check_fit_options
    old = {"kind": "slicersim-reduction", "mode": "rates", "options": {},
           "fit_options": {**PREVIOUS_FIT_IDENTITY, "read_noise": 3.0},
           "mapper": None, "source_spec_sha256": "0" * 64}
    new = _identity("rates", {}, check_fit_options({"ron": 3.0, "max_bytes": 2**20}), "0" * 64, None)
    old["kind"] = new["kind"]
    assert new == old
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        deprecated = check_fit_options({"read_noise": 3.0, "memory_budget": 2**20})
    assert _identity("rates", {}, deprecated, "0" * 64, None) == old
    ds = Dataset(tmp_path / "red")
    digest = ds.initialise("# previous release\n", old, {})
    _check_identity(ds, new, force=False)                       # resumed: no DatasetError
    assert ds.initialise("# this release\n", new, {}) == digest
    other = _identity("rates", {}, check_fit_options({"ron": 4.0}), "0" * 64, None)
    with pytest.raises(DatasetError, match="fit_options.read_noise"):
        _check_identity(ds, other, force=False)


def test_symlinked_folders_of_a_reduction_directory_are_refused_and_untouched(reduced, campaign, tmp_path):
    """A reduction directory's records/ or products/tNNNNNNN as a link is refused (the link named) before any
    target runs; the link's target is untouched."""
    from slicersim.reduction.campaign import reduce_dataset
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "rates.h5").write_bytes(b"not yours")
    for sub in ("records", "products/t0000000"):
        out = _linked_copy(reduced, tmp_path / sub.replace("/", "-"))
        shutil.rmtree(out / sub)
        (out / sub).symlink_to(outside)
        with pytest.raises(DatasetError, match=f"{sub} is a symbolic link"):
            reduce_dataset(campaign, out, workers=1, progress=False)
        assert os.listdir(outside) == ["rates.h5"] and (outside / "rates.h5").read_bytes() == b"not yours"
