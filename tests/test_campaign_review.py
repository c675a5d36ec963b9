"""Findings of the adversarial review of the campaign layer, one test each (numbers refer to
the review's list)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest
from astropy.table import Table

from slicersim.errors import ConfigError, DatasetError

BIN = Path(sys.executable).parent
BASE = """seed = 2
[population]
kind = "snia"
n = 2
redshift = {distribution = "uniform", min = 0.3, max = 0.6}
[observation]
snr = 5
[products]
spectrum = true
"""


def _cli(*args, timeout=300, **kw):
    return subprocess.run([str(BIN / "slicersim"), *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, **kw)


def _one_line_error(proc, *words):
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert len(lines) == 1 and lines[0].startswith("slicersim: error:"), proc.stderr
    for w in words:
        assert w.lower() in lines[0].lower(), lines[0]


def _flat_catalog(tmp_path, flux=3e-18):
    Table({"lbda": [3000.0, 20000.0], "flux": [flux, flux]}).write(tmp_path / "flat.ecsv", overwrite=True)
    Table({"target_id": [1, 3], "redshift": [0.0, 0.2], "spectrum_file": ["flat.ecsv", "flat.ecsv"]}).write(
        tmp_path / "cat.csv", overwrite=True)
    text = BASE.replace('kind = "snia"\nn = 2\nredshift = {distribution = "uniform", min = 0.3, max = 0.6}',
                        'kind = "catalog"\nfile = "cat.csv"').replace("snr = 5", 'snr = 5\nframe = "obs"\n'
                                                                           "lbda_range = [6000, 9000]")
    return text


def _spec(text, base_dir="."):
    from slicersim.campaign.spec import parse_spec
    return parse_spec(tomllib.loads(text), text=text, base_dir=str(base_dir))


# 1 -------------------------------------------------------------------------------------------
def test_user_spectrum_file_column_survives_in_the_dataset_catalog(tmp_path):
    from slicersim.campaign.runner import _catalog_with_records, plan_campaign
    spec = _spec(_flat_catalog(tmp_path), tmp_path)
    cat, _ = plan_campaign(spec)
    rec = {1: {"status": "done", "products": {"spectrum": {"file": "spectrum.h5", "sha256": "ab", "bytes": 1}}}}
    out = _catalog_with_records(cat, rec, spec.wanted)
    assert list(out["spectrum_file"]) == ["flat.ecsv", "flat.ecsv"]              # the user's input, kept
    assert out["spectrum_product"][0] == "products/t0000001/spectrum.h5" and out["spectrum_sha256"][0] == "ab"
    with pytest.raises(ConfigError, match="computed by the campaign"):
        Table({"redshift": [0.5], "cube_product": ["x"]}).write(tmp_path / "bad.ecsv")
        _spec(BASE.replace('kind = "snia"\nn = 2\nredshift = {distribution = "uniform", min = 0.3, max = 0.6}',
                           'kind = "catalog"\nfile = "bad.ecsv"'), tmp_path)


# 2 -------------------------------------------------------------------------------------------
def test_edited_user_spectrum_changes_the_identity_and_stale_records_are_redone(tmp_path):
    from slicersim.campaign.runner import _consistent
    from slicersim.io.dataset import spec_digest
    text = _flat_catalog(tmp_path)
    before = spec_digest(_spec(text, tmp_path).canonical())
    _flat_catalog(tmp_path, flux=3e-17)
    assert spec_digest(_spec(text, tmp_path).canonical()) != before
    row = {"n": 7, "m": 1, "d": 0, "nramps": 1, "seed": 11, "ramp_seed": 12}
    rec = {"readout": [31, 1, 0, 1], "seed": 11, "ramp_seed": 12}
    state = _consistent({1: ("done", rec, "")}, {1: row})
    assert state[1][0] == "missing" and "stale" in state[1][2]
    rec["readout"] = [7, 1, 0, 1]
    assert _consistent({1: ("done", rec, "")}, {1: row})[1][0] == "done"


# 3 -------------------------------------------------------------------------------------------
def test_readouts_of_targets_with_hosts_include_the_host_light():
    from slicersim.campaign.products import build_target
    from slicersim.campaign.runner import _row_dict, plan_campaign
    text = BASE.replace("snr = 5", "snr = 5").replace("[observation]", "hosts = {absmag = -21.5}\n[observation]")
    spec = _spec(text)
    cat, plan = plan_campaign(spec)
    assert plan.totals.get("hosts_in_etc") is True
    plain, _ = plan_campaign(_spec(BASE))
    for i in range(len(cat)):
        row = _row_dict(cat[i])
        target, _ = build_target(spec, row)                     # host in the scene, catalog readout
        reached = target.get_band_snr((4000, 6800), frame="rest", per_resolution=True)
        assert reached >= 5 * (1 - 1e-9)                          # the SNR is reached with the host
        assert reached == pytest.approx(row["snr"], rel=1e-9)
        assert row["exposure_time"] >= plain["exposure_time"][i]  # the host only adds noise


# 4, 13 ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("col, values, message", [("mwebv", [-2.0], "mwebv"), ("peak_absmag", [-40.0], "peak_absmag"),
                                                  ("phase", ["abc"], "not numeric"), ("redshift", ["x"], "not numeric"),
                                                  ("host_r_eff", [1.0], "all host columns")])
def test_catalog_parameter_columns_are_checked(tmp_path, col, values, message):
    from slicersim.campaign.population import population_from_spec
    cols = {"redshift": [0.5], col: values} if col != "redshift" else {"redshift": values}
    Table(cols).write(tmp_path / "t.ecsv")
    kw = {"hosts": {}} if col.startswith("host_") else {}
    with pytest.raises(ConfigError, match=message):
        population_from_spec({"kind": "catalog", "file": "t.ecsv", **kw}, base_dir=str(tmp_path))


# 5 -------------------------------------------------------------------------------------------
def test_sigint_interrupts_a_survey_plan_with_one_line(tmp_path):
    out = tmp_path / "p.ecsv"
    proc = subprocess.Popen([str(BIN / "slicersim"), "survey", "plan", "--n", "3000", "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    time.sleep(6)                                             # inside the batch ETC (kernels running)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    last = [l for l in err.replace("\r", "\n").splitlines() if l.strip()][-1]
    assert proc.returncode == 2 and last == "slicersim: error: interrupted", err[-500:]
    assert not out.exists()


# 6 -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("edit, message", [
    (lambda s: s.replace('kind = "snia"', 'kind = ["snia"]'), "kind"),
    (lambda s: s.replace('distribution = "uniform"', 'distribution = ["uniform"]'), "distribution"),
    (lambda s: s.replace("n = 2", "n = 2\nphase = {distribution = {a = 1}}"), "distribution"),
    (lambda s: s.replace("n = 2", "n = 2\nhosts = 5"), "hosts"),
    (lambda s: s.replace("n = 2", "n = 2\nhosts = [1, 2]"), "hosts"),
    (lambda s: s.replace("n = 2", 'n = 2\nhosts = "yes"'), "hosts"),
    (lambda s: s.replace("n = 2", "n = 2\nmw_dust = 0.1"), "mw_dust"),
])
def test_wrong_types_give_one_line(tmp_path, edit, message):
    spec = tmp_path / "s.toml"
    spec.write_text(edit(BASE))
    _one_line_error(_cli("campaign", "run", spec, "--out", tmp_path / "o"), message)
    assert not (tmp_path / "o").exists()


# 7, 17 ---------------------------------------------------------------------------------------
def test_malformed_records_and_lost_spec_json(tmp_path):
    from slicersim.io.dataset import Dataset
    ds = Dataset(tmp_path / "d")
    ds.initialise("x", {"a": 1}, {})
    for tid, rec in enumerate([{"target_id": 0, "status": "done", "products": {"spectrum": {"file": "s.h5"}}},
                               {"target_id": 1, "status": "done", "products": ["x"]},
                               {"target_id": 2, "status": "done", "products": 7},
                               {"target_id": 3, "status": "done",
                                "products": {"s": {"file": "../../x", "bytes": 1, "sha256": "a"}}}]):
        ds.write_record(tid, rec)
    state = ds.state(range(4))
    assert all(st == "missing" and "malformed" in why for st, _, why in state.values())
    os.remove(ds.file("spec.json"))
    with pytest.raises(DatasetError, match="damaged.*--force"):
        Dataset.check_path(ds.path)
    assert Dataset.check_path(ds.path, force=True) == ds.path
    ds.initialise("y", {"a": 2}, {}, force=True)
    assert ds.stored_spec()[0] == {"a": 2} and not os.listdir(ds.file("records"))


# 8, 9, 15 ------------------------------------------------------------------------------------
@pytest.mark.parametrize("args, message", [(["--memory-per-task", "inf"], "memory-per-task"),
                                           (["--memory-per-task", "nan"], "memory-per-task"),
                                           (["--memory-per-task", "0"], "memory-per-task"),
                                           (["--threads-per-worker", "-2"], "threads_per_worker"),
                                           (["--workers", "0"], "workers"),
                                           (["--workers", "100000"], "at most 4"),
                                           (["--scheduler", "garbage"], "tcp://host:port"),
                                           (["--scheduler", "tcp://127.0.0.1:1"], "cannot connect")])
def test_bad_run_arguments_write_nothing(tmp_path, args, message):
    spec = tmp_path / "s.toml"
    spec.write_text(BASE)
    _one_line_error(_cli("campaign", "run", spec, "--out", tmp_path / "o", *args), message)
    assert not (tmp_path / "o").exists()


# 10, 22 --------------------------------------------------------------------------------------
@pytest.mark.parametrize("args, message", [(["--snr", "-5"], "snr"), (["--snr", "0"], "snr"), (["--snr", "nan"], "snr"),
                                           (["--lbda-range", "6800", "4000"], "lbda_range"),
                                           (["--lbda-range", "-5", "4000"], "lbda_range"),
                                           (["--out", "plan.txt"], ".ecsv"), (["--out", "."], "directory"),
                                           (["--figure", "/nonexistent/f.png"], "not writable")])
def test_survey_plan_refuses_impossible_requests(tmp_path, args, message):
    proc = _cli("survey", "plan", "--n", "3", *args, cwd=tmp_path)
    _one_line_error(proc, message)
    assert not list(tmp_path.iterdir())


def test_survey_plan_exits_1_when_targets_cannot_be_planned(tmp_path):
    proc = _cli("survey", "plan", "--n", "3", "--snr", "1e6", "--out", tmp_path / "p.ecsv")
    assert proc.returncode == 1 and "could not be planned" in proc.stdout
    t = Table.read(tmp_path / "p.ecsv")
    assert set(t["status"]) == {"failed"}
    # 11: each error names its own target id, not its position in the ETC batch
    for tid, err in zip(t["target_id"], t["error"]):
        assert f"target {tid}:" in err


# 23 ------------------------------------------------------------------------------------------
def test_population_too_large_for_memory_is_refused_before_drawing():
    from slicersim.campaign.plan import check_client_memory
    from slicersim.errors import ParameterError
    with pytest.raises(ParameterError, match="split the population"):
        check_client_memory(10_000_000, 1700)
    check_client_memory(8000, 1700)


def test_survey_plan_out_fifo_is_refused_even_with_overwrite(tmp_path):
    """--overwrite replaces only regular files: a FIFO (or a link to one) given as --out is refused, untouched."""
    import stat
    os.mkfifo(tmp_path / "p.ecsv")
    (tmp_path / "f.png").symlink_to(tmp_path / "p.ecsv")
    for args, words in ((["--out", "p.ecsv"], ("--out:", "p.ecsv is a FIFO")),
                        (["--figure", "f.png"], ("--figure:", "FIFO", "symbolic link"))):
        _one_line_error(_cli("survey", "plan", "--n", "3", "--overwrite", *args, cwd=tmp_path), *words)
    assert stat.S_ISFIFO(os.lstat(tmp_path / "p.ecsv").st_mode) and sorted(os.listdir(tmp_path)) == ["f.png", "p.ecsv"]
