"""``slicersim etc --catalog T --out R`` (the batch ETC of a target table) and ``slicersim ramp
--redshift Z`` with the SN's phase, magnitude, source and an SNR goal (:mod:`slicersim.app.etc_cli`)."""
import math

import numpy as np
import pytest
from astropy.table import Table

from conftest import one_line_error, run_cli as run

#: four SNe Ia: two at peak (one brighter than the default), two off peak (rest-frame days)
CATALOG = {"target_id": [3, 1, 7, 2], "redshift": [0.3, 0.9, 1.3, 0.6], "phase": [0.0, 0.0, 8.0, -5.0],
           "peak_absmag": [-19.3, -19.0, -19.3, -19.5], "name": ["a", "b", "c", "d"]}


def _catalog(tmp_path, columns=None, name="targets.csv"):
    path = tmp_path / name
    Table(CATALOG if columns is None else columns).write(path, format="ascii.ecsv" if name.endswith(".ecsv")
                                                         else "ascii.csv")
    return path


def _single_target(z, phase, peak_absmag):
    """(nmd, nramps, exposure_time [s], snr per resolution element, data_volume [GB]) of the
    single-target ETC of the same SN (SNR 20 in 4000–6800 Å rest frame, Lazuli CBE, narrow field)."""
    from slicersim.targets import LazuliSupernova, lazuli_etc, lazuli_sn_etc
    if phase == 0 and peak_absmag == -19.3:
        res = lazuli_sn_etc(z, snr=20)
    elif phase == 0:
        res = LazuliSupernova(z, peak_absmag=peak_absmag).setup_to_snr(20)
        res["snr"], res["data_volume"] = res["snr_per_resolution"], None
    else:   # the same rest-frame phase through the model of the campaigns, as a spectrum
        from slicersim.campaign.population import snia_fluxes
        lbda = np.arange(3000.0, 20000.0, 10.0)
        flux = snia_fluxes(lbda, [z], [phase], [peak_absmag])[0]
        ok = np.isfinite(flux)
        res = lazuli_etc(lbda[ok], flux[ok], snr=20, redshift=z)
    return tuple(int(v) for v in res["nmd"]), int(res["nramps"]), res["exposure_time"], res["snr"], \
        res["data_volume"]


@pytest.mark.slow
def test_catalog_rows_are_the_single_target_etc_of_each_sn(tmp_path):
    out = tmp_path / "etc.ecsv"
    proc = run("etc", "--catalog", _catalog(tmp_path), "--snr", "20", "--out", out)
    assert proc.returncode == 0, proc.stderr
    assert "4 targets: 4 reach SNR 20, 0 failed" in proc.stdout and f"wrote {out}" in proc.stdout
    table = Table.read(out)
    assert list(table["target_id"]) == CATALOG["target_id"] and list(table["name"]) == CATALOG["name"]
    for row in table:
        nmd, nramps, exposure, snr, volume = _single_target(row["redshift"], row["phase"], row["peak_absmag"])
        assert (row["n"], row["m"], row["d"]) == nmd and row["nramps"] == nramps, row
        assert row["exposure_time"] == pytest.approx(exposure, rel=1e-12)
        assert row["exposure_time"] == pytest.approx(nramps * (nmd[0] * (nmd[1] + nmd[2]) - nmd[2]) * 2.83,
                                                     rel=1e-12)
        assert row["snr"] == pytest.approx(snr, rel=1e-9) and 20 <= row["snr"] < 21
        assert row["data_volume"] == pytest.approx(nramps * nmd[0] * 4096 * 4096 * 2 / 1e9, rel=1e-12)
        if volume is not None:
            assert row["data_volume"] == pytest.approx(volume, rel=1e-12)
        assert row["status"] == "ok" and row["field"] == "narrow"
    # fainter SNe and farther ones take longer; the units and the phase frame are in the file
    t = dict(zip(table["target_id"], table["exposure_time"]))
    assert t[3] < t[2] < t[1] < t[7]
    assert str(table["exposure_time"].unit) == "s" and table["data_volume"].unit.to("byte") == 1e9
    assert str(table["phase"].unit) == "d" and "rest-frame" in table["phase"].description
    assert table.meta["phase_frame"] == "rest" and table.meta["snr_goal"] == 20.0
    assert table.meta["source"] == "hsiao-subsampled" and table.meta["lbda_range"] == [4000.0, 6800.0]


@pytest.mark.slow
def test_unreachable_targets_are_rows_with_their_reason_and_exit_1(tmp_path):
    """A SN too faint for a year of exposure and one whose band is mostly outside the grid fail;
    the others are answered; a band partly outside the grid is refused as by ``etc --redshift``
    unless --allow-partial."""
    cat = _catalog(tmp_path, {"redshift": [0.5, 1.5, 2.5, 1.6], "phase": [0.0, 80.0, 0.0, 0.0],
                              "peak_absmag": [-19.3, -15.0, -19.3, -19.3]})
    out = tmp_path / "etc.csv"
    proc = run("etc", "--catalog", cat, "--out", out)
    assert proc.returncode == 1, proc.stderr
    assert "3 target(s) cannot reach SNR 20, e.g. target 1:" in proc.stdout
    table = Table.read(out, format="ascii.csv")
    assert list(table["status"]) == ["ok", "failed", "failed", "failed"]
    assert list(table["target_id"]) == [0, 1, 2, 3]                      # row numbers when no target_id
    assert "target 1" in table["error"][1] and "exposure limit" in table["error"][1]
    assert "target 2" in table["error"][2] and "inside the instrument grid" in table["error"][2]
    assert "target 3" in table["error"][3] and "--allow-partial" in table["error"][3]
    assert table["n"][1] == 0 and math.isnan(table["exposure_time"][1]) and math.isnan(table["data_volume"][1])
    assert table["n"][0] > 0 and table["exposure_time"][0] > 0
    proc = run("etc", "--catalog", cat, "--out", out, "--overwrite", "--allow-partial")
    assert proc.returncode == 1 and list(Table.read(out, format="ascii.csv")["status"]) == ["ok", "failed", "failed",
                                                                                            "ok"]


def test_an_existing_out_is_refused_before_any_work(tmp_path, monkeypatch):
    out = tmp_path / "etc.ecsv"
    out.write_text("mine\n")
    monkeypatch.setattr("slicersim.campaign.population.CatalogPopulation", None)     # not even read
    one_line_error(run("etc", "--catalog", tmp_path / "cat.ecsv", "--out", out), "--out", "exists", "--overwrite")
    assert out.read_text() == "mine\n"


@pytest.mark.slow
def test_overwrite_replaces_the_out_with_the_table_of_the_options_given(tmp_path, monkeypatch):
    out = tmp_path / "etc.ecsv"
    out.write_text("mine\n")
    cat = _catalog(tmp_path, {"redshift": [0.4]})
    from slicersim.app import etc_cli
    from slicersim.campaign.plan import plan_survey_with

    def solved(redshift, lbda, fluxes, options, target_ids=None):      # the ETC itself: tested above
        assert options.snr == 5.0 and options.fields == ("wide", "wide") and options.config == "eol"
        return plan_survey_with(redshift, lbda, fluxes, options, target_ids)
    monkeypatch.setattr("slicersim.campaign.plan.plan_survey_with", solved)
    proc = run("etc", "--catalog", cat, "--out", out, "--overwrite", "--snr", "5", "--field", "wide",
               "--config", "eol")
    assert proc.returncode == 0, proc.stderr
    table = Table.read(out)
    assert len(table) == 1 and table["status"][0] == "ok" and table.meta["field"] == "wide"
    # the SN parameters the table does not give: at peak, the default magnitude; first in the table
    assert table.colnames[:4] == ["target_id", "redshift", "phase", "peak_absmag"]
    assert (table["target_id"][0], table["phase"][0], table["peak_absmag"][0]) == (0, 0.0, -19.3)
    assert len(table.meta["catalog_sha256"]) == 64
    assert not [p for p in tmp_path.iterdir() if ".tmp-" in p.name]                # temp + rename
    assert etc_cli.DEFAULT_SOURCE == table.meta["source"]


@pytest.mark.parametrize("columns, words", [
    ({"z": [0.5]}, ["--catalog", "bad.csv", "'redshift' column"]),
    ({"redshift": [0.5, 0.7], "phase": [0.0, 100.0]}, ["--catalog", "bad.csv", "phase = 100", "row 1", "[-20, 85]"]),
    ({"redshift": [0.5, 0.7], "peak_absmag": ["-19", "bright"]}, ["bad.csv", "'peak_absmag'", "not numeric",
                                                                    "row 1", "bright"]),
    ({"redshift": [0.5, 0.6, 0.7], "target_id": [4, 5, 4]}, ["bad.csv", "target_id", "row 2: 4, as row 0"]),
    ({"redshift": [0.5], "x1": [0.3]}, ["bad.csv", "['x1']", "SALT", "hsiao-subsampled"]),
    ({"redshift": [0.5], "snr": [3.0]}, ["bad.csv", "['snr']", "rename"]),
    ({"redshift": [-0.5]}, ["bad.csv", "redshift = -0.5", "row 0"]),
    ({"redshift": [0.0]}, ["bad.csv", "> 0", "row 0"]),
])
def test_a_bad_table_is_one_line_naming_the_file_the_column_and_the_row(tmp_path, columns, words):
    cat = _catalog(tmp_path, columns, name="bad.csv")
    out = tmp_path / "etc.ecsv"
    one_line_error(run("etc", "--catalog", cat, "--out", out), *words)
    assert not out.exists()


def test_an_empty_cell_and_a_missing_or_unknown_file_are_named(tmp_path):
    cat = tmp_path / "holes.csv"
    cat.write_text("redshift,phase\n0.5,1\n0.6,\n")
    one_line_error(run("etc", "--catalog", cat, "--out", tmp_path / "o.ecsv"), "holes.csv", "'phase'", "empty",
                   "row 1")
    one_line_error(run("etc", "--catalog", tmp_path / "nope.ecsv", "--out", tmp_path / "o.ecsv"), "--catalog",
                   "no such file", "nope.ecsv")
    (tmp_path / "t.txt").write_text("redshift\n0.5\n")
    one_line_error(run("etc", "--catalog", tmp_path / "t.txt", "--out", tmp_path / "o.ecsv"), "--catalog", "t.txt",
                   ".ecsv, .csv or .parquet")


@pytest.mark.parametrize("argv, words", [
    (["--catalog", "CAT"], ["--catalog needs --out"]),
    (["--catalog", "CAT", "--out", "OUT.txt"], ["--out must end with .ecsv or .csv"]),
    (["--redshift", "1", "--out", "OUT.ecsv"], ["--out applies only with --catalog"]),
    (["--redshift", "1", "--overwrite"], ["--overwrite applies only with --catalog"]),
    (["--spectrum", "CAT", "--source", "salt3"], ["--source applies only with --redshift or --catalog"]),
    (["--catalog", "CAT", "--redshift", "1", "--out", "OUT.ecsv"], ["not allowed with argument"]),
    (["--catalog", "CAT", "--out", "OUT.ecsv", "--snr", "0"], ["--snr", "> 0"]),
    (["--catalog", "CAT", "--out", "OUT.ecsv", "--lbda-range", "7000", "5000"], ["--lbda-range", "lo < hi"]),
])
def test_flags_that_do_not_apply_are_one_line_errors(tmp_path, argv, words):
    cat = _catalog(tmp_path, {"redshift": [0.5]})
    subst = {"CAT": str(cat), "OUT.txt": str(tmp_path / "o.txt"), "OUT.ecsv": str(tmp_path / "o.ecsv")}
    one_line_error(run("etc", *[subst.get(a, a) for a in argv]), *words)


def test_help_lists_the_survey_flags():
    etc = " ".join(run("etc", "--help").stdout.split()).replace("- ", "-")   # argparse wraps at hyphens
    for flag in ("--catalog", "--out", "--overwrite", "--source", "rest-frame days from B-band maximum"):
        assert flag in etc, flag
    ramp = " ".join(run("ramp", "--help").stdout.split()).replace("- ", "-")
    for flag in ("--phase", "--peak-absmag", "--source", "--snr", "rest-frame days from B-band maximum",
                 "(default: (16, 8, 0))", "(default: 1)"):
        assert flag in ramp, flag


# ------------------------------------------------------------------------------ ramp of a SN Ia
@pytest.fixture
def ramps_asked(monkeypatch):
    """The (target, nmd, nramps) of each ``get_ramps`` call of ``slicersim ramp --redshift`` (the
    full-detector ramp itself is tested in test_cli.py): nothing is simulated."""
    from slicersim.targets import LazuliSupernova
    calls = []

    def get_ramps(self, out=None, nmd=None, nramps=None, **kwargs):
        calls.append((self, nmd, nramps))
        return out
    monkeypatch.setattr(LazuliSupernova, "get_ramps", get_ramps)
    return calls


@pytest.mark.slow
def test_ramp_snr_simulates_the_etc_readout_of_the_sn_it_describes(tmp_path, ramps_asked):
    from slicersim.targets import LazuliSupernova
    proc = run("ramp", "--redshift", "1.2", "--phase", "5", "--peak-absmag", "-19.1", "--snr", "20",
               "--out", tmp_path / "sn.h5", "--seed", "1")
    assert proc.returncode == 0, proc.stderr
    ((target, nmd, nramps),) = ramps_asked
    assert (target.phase, target.peak_absmag, target.source) == (5.0, -19.1, "hsiao-subsampled")
    ref = LazuliSupernova(1.2, phase=5.0, peak_absmag=-19.1)
    res = ref.setup_to_snr(20)                           # 4000–6800 Å rest frame, per resolution element
    assert nmd == tuple(res["nmd"]) and nramps == res["nramps"] and nramps > 1
    n, m, d = nmd
    assert f"readout --nmd {n} {m} {d} --nramps {nramps}," in proc.stdout
    assert f"exposure time {res['exposure_time']:.2f} s" in proc.stdout
    # without --snr: the default readout, and the default SN
    assert run("ramp", "--redshift", "1.2", "--out", tmp_path / "sn2.h5", "--seed", "1").returncode == 0
    target, nmd, nramps = ramps_asked[-1]
    assert (nmd, nramps) == ((16, 8, 0), 1) and (target.phase, target.peak_absmag) == (0.0, -19.3)
    assert "ETC:" not in run("ramp", "--redshift", "1.2", "--out", tmp_path / "sn3.h5", "--seed", "1").stdout


def test_ramp_sn_flags_pass_through_to_the_target(tmp_path, ramps_asked):
    proc = run("ramp", "--redshift", "0.5", "--phase", "-3", "--source", "hsiao-subsampled", "--nmd", "4", "2", "0",
               "--nramps", "2", "--out", tmp_path / "sn.h5", "--seed", "1")
    assert proc.returncode == 0, proc.stderr
    ((target, nmd, nramps),) = ramps_asked
    assert (target.phase, target.source, nmd, nramps) == (-3.0, "hsiao-subsampled", (4, 2, 0), 2)


@pytest.mark.parametrize("argv, words", [
    (["--snr", "20", "--nmd", "3", "1", "0"], ["--snr", "drop --nmd"]),
    (["--snr", "20", "--nramps", "2"], ["--snr", "drop --nramps"]),
    (["--snr", "20", "--tframe", "3"], ["--snr", "--tframe", "--config"]),
    (["--snr", "0"], ["--snr", "> 0"]),
    (["--phase", "200"], ["--phase", "[-20, 85]", "200"]),
    (["--peak-absmag", "-40"], ["--peak-absmag", "[-25, -10]"]),
])
def test_ramp_sn_flag_errors_are_one_line_before_any_work(tmp_path, ramps_asked, argv, words):
    one_line_error(run("ramp", "--redshift", "1", "--out", tmp_path / "sn.h5", *argv), *words)
    assert not ramps_asked


def test_ramp_sn_flags_apply_only_with_redshift(tmp_path):
    rate = tmp_path / "rate.npy"
    np.save(rate, np.ones((8, 8)))
    one_line_error(run("ramp", "--rate", rate, "--out", tmp_path / "r.h5", "--phase", "3", "--snr", "5"),
                   "--phase and --snr apply only with --redshift")
    one_line_error(run("ramp", "--rate", rate, "--out", tmp_path / "r.h5", "--peak-absmag", "-19"),
                   "--peak-absmag applies only with --redshift")
