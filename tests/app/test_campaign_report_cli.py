"""`slicersim campaign report DATASET [--reduced RED] --out DIR`: exit 0 and its files; one-line errors."""
from __future__ import annotations

import numpy as np
import pytest
from astropy.table import Table

from conftest import fake_campaign, one_line_error, run_cli


@pytest.fixture(scope="module")
def fake(tmp_path_factory):
    root = tmp_path_factory.mktemp("fake")
    dataset, red, _ = fake_campaign(root, redshifts=(0.4, 0.9))
    return root, dataset, red


def test_report_from_the_command_line(fake, tmp_path):
    _, dataset, red = fake
    proc = run_cli("campaign", "report", dataset, "--reduced", red, "--out", tmp_path / "rep")
    assert proc.returncode == 0, proc.stderr
    assert "2 targets, band flux / input" in proc.stdout and "report.md" in proc.stdout
    table = Table.read(tmp_path / "rep" / "summary.ecsv", format="ascii.ecsv")
    assert len(table) == 2 and np.all(np.abs(table["pull"]) < 5)
    assert (tmp_path / "rep" / "bias_vs_redshift.png").is_file() and (tmp_path / "rep" / "snr_vs_etc.png").is_file()
    assert "report" in run_cli("campaign", "--help").stdout


def test_bad_paths_are_one_line_errors(fake, tmp_path):
    root, dataset, red = fake
    one_line_error(run_cli("campaign", "report", tmp_path / "nowhere", "--out", tmp_path / "r"), "nowhere")
    spec = tmp_path / "spec.toml"
    spec.write_text("seed = 1\n")
    one_line_error(run_cli("campaign", "report", spec, "--out", tmp_path / "r"), "campaign run")
    one_line_error(run_cli("campaign", "report", dataset, "--reduced", spec, "--out", tmp_path / "r"), "--reduced")
    one_line_error(run_cli("campaign", "report", dataset, "--reduced", dataset, "--out", tmp_path / "r"),
                   "not a reduction directory")
    one_line_error(run_cli("campaign", "report", dataset, "--out", spec), "is a file")
    one_line_error(run_cli("campaign", "report", dataset, "--out", tmp_path / "a" / "b"), "does not exist")
    assert run_cli("campaign", "report", dataset).returncode == 2                    # --out is required
