"""`slicersim stress` on the command line: bad inputs are one-line errors that write nothing; a run on a
small dataset prints its summary line and names the biased pipeline."""
from __future__ import annotations

import sys

import pytest

from conftest import run_cli


def test_bad_inputs_are_one_line_errors(tmp_path):
    (tmp_path / "exists").mkdir()
    for args, text in ((["stress", tmp_path / "nothing", "--out", tmp_path / "o"], "not a campaign dataset"),
                       (["stress", tmp_path, "--out", tmp_path / "exists"], "exists: pass --overwrite"),
                       (["stress", tmp_path, "--out", tmp_path / "o", "--pipeline", "jwst"], "unknown pipeline"),
                       (["stress", tmp_path, "--out", tmp_path / "o", "--workers", "0"], "--workers")):
        proc = run_cli(*args)
        assert proc.returncode != 0 and text in proc.stderr, (args, proc.stderr)
        assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exists"]


@pytest.mark.slow
def test_a_run_names_the_biased_pipeline(tmp_path):
    sys.path.insert(0, str(__import__("pathlib").Path(__file__).parents[1] / "reduction"))
    from test_stress import BIASED, make_dataset
    ds = make_dataset(tmp_path / "ds", ntargets=1)
    (tmp_path / "biased.py").write_text(BIASED)
    proc = run_cli("stress", ds, "--out", tmp_path / "out", "--workers", "1", "--quiet", "--pipeline", "slicersim",
                   "--pipeline", f"exec:{sys.executable} {tmp_path / 'biased.py'}")
    assert proc.returncode == 0, proc.stderr
    assert "1 exposure(s), 0 failed" in proc.stdout and "biased.py biased in flux bin 10to100" in proc.stdout
    again = run_cli("stress", ds, "--out", tmp_path / "out", "--pipeline", "slicersim")
    assert again.returncode != 0 and "--overwrite" in again.stderr
    assert run_cli("stress", ds, "--out", tmp_path / "out", "--pipeline", "slicersim", "--overwrite", "--quiet",
                   "--workers", "1").returncode == 0


def test_out_under_a_file_names_the_file(tmp_path):
    """Adversarial finding: --out FILE/x said "its parent folder FILE does not exist" of an existing file."""
    (tmp_path / "afile").write_text("x")
    proc = run_cli("stress", tmp_path, "--out", tmp_path / "afile" / "x", "--pipeline", "slicersim")
    assert proc.returncode == 2 and "afile is not a folder" in proc.stderr, proc.stderr
    proc = run_cli("stress", tmp_path, "--out", tmp_path / "o", "--pipeline", "slicersim", "--exec-timeout", "0")
    assert proc.returncode == 2 and "--exec-timeout" in proc.stderr and not (tmp_path / "o").exists()
