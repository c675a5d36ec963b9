"""The ``slicersim`` command line.  Most cases run in this process through ``main(argv)``
(:func:`conftest.run_cli`); a few per command family run as a real subprocess
(``python -m slicersim``, :func:`run_subprocess`) so that the console entry point stays tested."""
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from slicersim.io.rampfile import read_ramps
from slicersim.products.ramps import simulate

from conftest import run_cli as run

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # tests/app/ → repo


def run_subprocess(*args, cwd=None, debug=False, timeout=600):
    env = dict(os.environ)
    env["PYTHONPATH"] = ROOT + os.pathsep + env.get("PYTHONPATH", "")
    env.pop("SLICERSIM_DEBUG", None)
    if debug:
        env["SLICERSIM_DEBUG"] = "1"
    return subprocess.run([sys.executable, "-m", "slicersim", *map(str, args)], env=env, capture_output=True,
                          text=True, timeout=timeout, cwd=cwd)


def one_error_line(proc):
    """The single ``slicersim: error: ...`` line of a failed run (exit 2, no traceback)."""
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-3000:])
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip() and "block/s" not in ln]
    assert len(lines) == 1 and lines[0].startswith("slicersim: error: "), proc.stderr
    return lines[0]


@pytest.fixture(scope="module")
def rate_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("rate") / "rate.npy"
    np.save(path, np.random.default_rng(11).uniform(0, 80, (24, 20)))
    return path


@pytest.mark.slow
def test_info():
    proc = run_subprocess("info")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("slicersim ") and "numpy" in proc.stdout and "pyopencl" in proc.stdout


def test_version():
    proc = run_subprocess("--version")
    assert proc.returncode == 0 and proc.stdout.startswith("slicersim ")


def _etc_values(stdout):
    rows = {}
    for line in stdout.splitlines():
        key, _, value = line.partition(" : ")
        rows[key.strip()] = value.strip()
    return rows


@pytest.mark.slow
def test_etc_redshift_states_units_and_no_object_line():
    proc = run("etc", "--redshift", "1")
    assert proc.returncode == 0, proc.stderr
    rows = _etc_values(proc.stdout)
    assert float(rows["exposure_time [s]"]) > 0 and float(rows["data_volume [GB]"]) > 0
    assert "lbda_range_obs [Angstrom]" in rows and rows["config"] == "cbe"
    assert "target" not in rows and "object at 0x" not in proc.stdout


@pytest.mark.slow
def test_etc_conventions_flag_reproduces_slicersim_1_0():
    """--conventions slicersim-1.0 gives slicersim 1.0.0's readout (56,8,0)x4, 5071.36 s for a z=1
    SN Ia (benchmarks/conventions_vs_reference.py); the physical default needs less time (smaller blur)."""
    old = _etc_values(run("etc", "--redshift", "1", "--conventions", "slicersim-1.0").stdout)
    new = _etc_values(run("etc", "--redshift", "1").stdout)
    assert float(old["exposure_time [s]"]) == pytest.approx(56 * 8 * 4 * 2.83, rel=1e-9)
    assert float(new["exposure_time [s]"]) < float(old["exposure_time [s]"])
    assert old["conventions"] == "slicersim-1.0" and new["conventions"] == "physical"


@pytest.mark.slow
def test_etc_spectrum_csv(tmp_path):
    csv = tmp_path / "spec.csv"
    csv.write_text("wavelength,flux\n3000,1e-17\n8000,1e-17\n20000,1e-17\n")
    proc = run("etc", "--spectrum", csv, "--snr", "10", "--lbda-range", "5000", "6000")
    assert proc.returncode == 0, proc.stderr
    rows = _etc_values(proc.stdout)
    assert float(rows["exposure_time [s]"]) > 0
    assert rows["lbda_range_obs [Angstrom]"] == "[5000, 6000]"


@pytest.mark.slow
def test_ramp_rate_file_writes_the_simulated_ramp(tmp_path, rate_file):
    out = tmp_path / "r.h5"
    proc = run_subprocess("ramp", "--rate", rate_file, "--nmd", "3", "1", "0", "--seed", "4", "--tframe", "3",
                          "--out", out)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == f"wrote {out} (seed 4)"
    sci, gdq, pdq, attrs = read_ramps(out)
    expect = simulate(np.load(rate_file), (3, 1, 0), seed=4, tframe=3.0)      # CLI flags honoured
    assert np.array_equal(sci, expect) and attrs["TFRAME"] == 3.0
    # an existing file is kept unless --overwrite
    mtime = os.stat(out).st_mtime_ns
    line = one_error_line(run("ramp", "--rate", rate_file, "--nmd", "3", "1", "0", "--out", out))
    assert "exists" in line and "--overwrite" in line and os.stat(out).st_mtime_ns == mtime
    proc = run("ramp", "--rate", rate_file, "--nmd", "3", "1", "0", "--seed", "5", "--out", out, "--overwrite")
    assert proc.returncode == 0, proc.stderr
    assert np.array_equal(read_ramps(out)[0], simulate(np.load(rate_file), (3, 1, 0), seed=5))
    assert os.listdir(tmp_path) == ["r.h5"]


def test_ramp_groupdq_flag(tmp_path, rate_file):
    """--groupdq: none (the level-1b default: no GROUPDQ), observed (from the DN read), HDF5 refused."""
    from slicersim.io.uncal import read_uncal
    none, obs = tmp_path / "n.fits", tmp_path / "o.fits"
    for out, extra in ((none, ()), (obs, ("--groupdq", "observed"))):
        proc = run("ramp", "--rate", rate_file, "--nmd", "3", "1", "0", "--seed", "4", "--out", out, *extra)
        assert proc.returncode == 0, proc.stderr
    assert read_uncal(none)[1] is None
    sci, gdq, _, header = read_uncal(obs)
    assert gdq is not None and header["INSTRUME"] == "LAZULI_IFS" and header["READPATT"] == "MACC_1_0"
    line = one_error_line(run("ramp", "--rate", rate_file, "--nmd", "3", "1", "0", "--out", tmp_path / "x.h5",
                              "--groupdq", "observed"))
    assert "level-1b" in line and not (tmp_path / "x.h5").exists()


def test_ramp_window_flag(tmp_path, rate_file):
    """--window X0 Y0 NX NY: the window's pixels of the full ramp of the same seed, placed by SUBSTRT."""
    from slicersim.io.uncal import read_uncal
    out = tmp_path / "w.fits"
    proc = run("ramp", "--rate", rate_file, "--nmd", "3", "1", "0", "--seed", "4", "--out", out,
               "--window", "2", "5", "8", "10")
    assert proc.returncode == 0, proc.stderr
    sci, _, _, h = read_uncal(out)
    full = simulate(np.load(rate_file), (3, 1, 0), seed=4)
    np.testing.assert_array_equal(sci, full[:, :, 5:15, 2:10])
    assert (h["SUBSTRT1"], h["SUBSTRT2"], h["SUBSIZE1"], h["SUBSIZE2"]) == (3, 6, 8, 10)
    line = one_error_line(run("ramp", "--rate", rate_file, "--nmd", "3", "1", "0", "--out", tmp_path / "x.fits",
                              "--window", "15", "0", "8", "4"))
    assert "--window" in line and "not inside" in line


def test_ramp_default_seed_is_fresh_printed_and_recorded(tmp_path, rate_file):
    """Without --seed each run draws a new seed, printed in the summary and recorded in SEED; passing it
    back with --seed repeats the run."""
    seeds = []
    for name in ("a.h5", "b.h5"):
        proc = run("ramp", "--rate", rate_file, "--nmd", "3", "1", "0", "--out", tmp_path / name)
        assert proc.returncode == 0, proc.stderr
        match = re.fullmatch(rf"wrote {re.escape(str(tmp_path / name))} \(seed (\d+)\)", proc.stdout.strip())
        assert match, proc.stdout
        seeds.append(int(match.group(1)))
        assert int(read_ramps(tmp_path / name)[3]["SEED"]) == seeds[-1]
    assert seeds[0] != seeds[1]
    assert np.array_equal(read_ramps(tmp_path / "a.h5")[0], simulate(np.load(rate_file), (3, 1, 0), seed=seeds[0]))


def test_ramp_help_says_what_effects_all_contains():
    """'--effects all' leaves persistence out unless --previous-charge is given: the help says so and
    lists every effect 'all' contains."""
    from slicersim.physics.effects import EFFECT_NAMES
    text = " ".join(run("ramp", "--help").stdout.split())
    contents = text.split("'all' (and 'lazuli') =", 1)[1].split(")", 1)[0]
    for name in EFFECT_NAMES:
        assert name in contents, name
    assert "persistence only when --previous-charge is given" in contents


@pytest.mark.slow
def test_ramp_effects_all_includes_persistence_with_previous_charge(tmp_path):
    import h5py
    rate, prev = tmp_path / "rate.npy", tmp_path / "prev.npy"
    np.save(rate, np.full((64, 64), 3.0))                 # 64 columns: the 32 outputs of reference pixels
    np.save(prev, np.full((64, 64), 5e4))
    for extra, expect in (([], False), (["--previous-charge", prev], True)):
        out = tmp_path / f"r{len(extra)}.h5"
        proc = run("ramp", "--rate", rate, "--nmd", "3", "1", "0", "--seed", "1", "--effects", "all",
                   "--out", out, *extra)
        assert proc.returncode == 0, proc.stderr
        with h5py.File(out) as fh:
            assert ("persistence" in fh.attrs["EFFECTS"]) is expect


@pytest.mark.slow
def test_ramp_redshift_full_detector(tmp_path):
    """The --redshift path (full 4096² detector) once, with the shortest readout."""
    out = tmp_path / "sn.h5"
    proc = run("ramp", "--redshift", "1", "--nmd", "2", "1", "0", "--tframe", "3", "--out", out)
    assert proc.returncode == 0, proc.stderr
    import h5py
    with h5py.File(out, "r") as fh:
        assert fh["SCI"].shape == (1, 2, 4096, 4096) and bool(fh.attrs["COMPLETE"])
        assert fh.attrs["TFRAME"] == 3.0                                        # --tframe honoured
    from slicersim.io.target_truth import read_target_truth
    truth = read_target_truth(out)                                             # the target's truth beside the ramps
    assert (truth.attrs["redshift"], truth.attrs["phase"], truth.attrs["field"]) == (1.0, 0.0, "narrow")
    assert truth.attrs["phase_frame"] == "rest" and truth.attrs["nmd"] == "[2, 1, 0]" and truth.rate.max() > 0


@pytest.mark.slow
@pytest.mark.parametrize("args, match", [
    (["etc", "--redshift", "-1"], "--redshift must be in (0, 50], got -1"),
    (["etc", "--redshift", "1", "--snr", "0"], "--snr: the target SNR must be a finite number > 0"),
    (["etc", "--redshift", "1", "--lbda-range", "7000", "5000"], "--lbda-range must be (lo, hi)"),
    (["etc", "--redshift", "1", "--config", "/no/such/config.toml"], "not found"),
    (["etc", "--spectrum", "/no/such/spectrum.csv"], "No such file"),
    (["etc", "--redshift", "1", "--snr", "abc"], "invalid float"),
    (["etc"], "required"),
    (["ramp", "--rate", "RATE", "--nmd", "1", "1", "0", "--out", "OUT"], "nmd[0] (n, groups per ramp) must be"),
    (["ramp", "--rate", "RATE", "--nmd", "3", "1", "0", "--seed", "-3", "--out", "OUT"], "seed must be in"),
    (["ramp", "--rate", "RATE", "--nramps", "0", "--nmd", "3", "1", "0", "--out", "OUT"],
     "--nramps must be an integer in [1, 2147483647], got 0"),
    (["ramp", "--rate", "RATE", "--config", "eol", "--out", "OUT"], "--config applies only with --redshift"),
    (["ramp", "--rate", "RATE", "--field", "wide", "--out", "OUT"], "--field applies only with --redshift"),
    (["ramp", "--rate", "RATE", "--conventions", "physical", "--out", "OUT"], "--conventions applies only"),
    (["etc", "--redshift", "1", "--conventions", "slicersim-2"], "invalid choice"),
    (["ramp", "--rate", "/no/such/rate.npy", "--out", "OUT"], "No such file"),
    (["ramp", "--rate", "RATE", "--nmd", "3", "1", "0", "--out", "/no/such/dir/r.h5"], "directory does not exist"),
    (["ramp", "--rate", "BADRATE", "--nmd", "3", "1", "0", "--out", "OUT"], "--rate must be ≥ 0"),
    (["nosuchcommand"], "invalid choice"),
    # argparse took "-1e300" for a flag ("expected 2 arguments"); a negative wavelength was a band
    (["etc", "--redshift", "1", "--lbda-range", "-1e300", "1e300"], "--lbda-range[0] [Angstrom] must be > 0"),
    (["etc", "--redshift", "1", "--lbda-range", "-.5", "6800"], "--lbda-range[0] [Angstrom] must be > 0, got -0.5"),
    (["etc", "--redshift", "-1e-3"], "--redshift must be in (0, 50], got -0.001"),
])
def test_user_errors_are_one_line_exit_2(tmp_path, rate_file, args, match):
    bad = tmp_path / "bad.npy"
    np.save(bad, -np.ones((4, 4)))
    subst = {"RATE": str(rate_file), "BADRATE": str(bad), "OUT": str(tmp_path / "o.h5")}
    line = one_error_line(run(*[subst.get(a, a) for a in args]))
    assert match in line, line
    assert not (tmp_path / "o.h5").exists()


@pytest.mark.slow
def test_spectrum_with_one_row_is_a_user_error(tmp_path):
    csv = tmp_path / "one.csv"
    csv.write_text("5000 1e-17\n")
    assert "need at least two rows of two numbers" in one_error_line(run("etc", "--spectrum", csv))


@pytest.mark.slow
def test_debug_env_shows_the_traceback():
    proc = run_subprocess("etc", "--redshift", "-1", debug=True)
    assert proc.returncode == 1 and "Traceback" in proc.stderr
    assert "redshift" in proc.stderr.splitlines()[-1]


@pytest.mark.slow
@pytest.mark.parametrize("command, expected", [
    ("etc", ["(default: 20.0)", "(default: 4000 6800)"]),
    ("ramp", ["(default: (16, 8, 0))", "(default: 1)", "default: a fresh seed", "(default: 2.83", "(default: auto)",
              "--overwrite"]),
    ("demo", ["(default: demo_output)", "--overwrite"]),
    ("info", []),
])
def test_help_shows_defaults(command, expected):
    proc = run(command, "--help")
    assert proc.returncode == 0, proc.stderr
    text = " ".join(proc.stdout.split())
    for item in expected:
        assert item in text, (item, proc.stdout)


@pytest.mark.slow
def test_demo_refuses_existing_outputs(tmp_path):
    (tmp_path / "spectrum.png").write_bytes(b"mine")
    line = one_error_line(run("demo", "--outdir", tmp_path))
    assert "spectrum.png" in line and "exists" in line and "--overwrite" in line
    assert (tmp_path / "spectrum.png").read_bytes() == b"mine"


def test_demo_outdir_that_is_a_file_is_named(tmp_path):
    """`demo --outdir FILE` said only "FILE: File exists"."""
    (tmp_path / "notadir").write_bytes(b"mine")
    line = one_error_line(run("demo", "--outdir", tmp_path / "notadir"))
    assert "notadir: --outdir (outdir) must be a directory, not a file" in line, line
    assert (tmp_path / "notadir").read_bytes() == b"mine"


@pytest.mark.slow
def test_ctrl_c_during_ramp_is_one_line_and_leaves_nothing(tmp_path):
    import signal
    import time
    from slicersim.io.rampfile import is_temporary
    rate = tmp_path / "big.npy"
    np.save(rate, np.random.default_rng(0).uniform(0, 100, (2048, 2048)))
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("SLICERSIM_DEBUG", None)
    proc = subprocess.Popen([sys.executable, "-m", "slicersim", "ramp", "--rate", str(rate), "--nmd", "40", "1", "0",
                             "--backend", "numpy", "--out", str(out_dir / "r.h5")], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.time()
    while not any(is_temporary(f) for f in os.listdir(out_dir)):
        assert proc.poll() is None and time.time() - t0 < 300, proc.communicate()
        time.sleep(0.01)
    time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=300)
    assert one_error_line(subprocess.CompletedProcess(proc.args, proc.returncode, "", err)) == \
        "slicersim: error: interrupted"
    assert os.listdir(out_dir) == []


# --------------------------------------------------------------------------- in-process: user vs internal errors
def _main_error(capsys, argv, monkeypatch):
    """(exit status, stderr) of ``main(argv)`` run in this process, without SLICERSIM_DEBUG."""
    from slicersim.app.cli import main
    monkeypatch.delenv("SLICERSIM_DEBUG", raising=False)
    status = main([str(a) for a in argv])
    return status, capsys.readouterr().err


def _one_line(status, err):
    assert status == 2, err
    assert "Traceback" not in err and err.count("\n") == 1 and err.startswith("slicersim: error: "), err
    return err


@pytest.fixture
def user_files(tmp_path):
    """Files a user may give by mistake: binary data, a text file named .npy, a bad spectrum row."""
    files = {"binary": tmp_path / "data.bin", "text_npy": tmp_path / "image.npy", "bad_row": tmp_path / "sp.txt",
             "negative": tmp_path / "neg.txt", "strings_npy": tmp_path / "s.npy", "empty_npy": tmp_path / "e.npy",
             "no_pixels_npy": tmp_path / "z.npy", "line_npy": tmp_path / "l.npy", "image_npy": tmp_path / "i.npy",
             "spectrum": tmp_path / "flat.txt", "spot_header": tmp_path / "spots.csv",
             "spot_short_row": tmp_path / "short.txt"}
    files["binary"].write_bytes(bytes(range(128, 256)) * 4)
    files["text_npy"].write_text("1 2\n3 4\n")
    files["bad_row"].write_text("# wavelength flux\n4000 1e-17\n5000 1e-17\n6000 oops\n")
    files["negative"].write_text("4000 1e-17\n5000 -1e-17\n")
    np.save(files["strings_npy"], np.array(["a", "b"]))
    files["empty_npy"].write_bytes(b"")
    np.save(files["no_pixels_npy"], np.ones((0, 4)))
    np.save(files["line_npy"], np.ones(4))
    np.save(files["image_npy"], np.ones((4, 4)))
    files["spectrum"].write_text("3000 1e-17\n20000 1e-17\n")
    files["spot_header"].write_text("slice fieldpos lbda x y rmsx_um rmsy_um\n")
    files["spot_short_row"].write_text("slice fieldpos lbda x y rmsx_um rmsy_um\n1 0 4000 1 2 3 4\n\n2 0 4000 1 2\n")
    return files


def test_spectrum_csv_with_quoted_numbers_is_read_and_too_few_rows_name_a_line(tmp_path, capsys, monkeypatch):
    """Quoted CSV numbers ("4000","1e-17") were not numbers ("need at least two numeric rows", no line)."""
    from slicersim.app.cli import main
    quoted, plain = tmp_path / "q.csv", tmp_path / "p.csv"
    quoted.write_text('wavelength,flux\n"4000","1e-17"\n"5000","1e-17"\n"9000","1e-17"\n')
    plain.write_text("wavelength,flux\n4000,1e-17\n5000,1e-17\n9000,1e-17\n")
    outs = []
    for path in (quoted, plain):
        assert main(["etc", "--spectrum", str(path), "--snr", "10"]) == 0
        outs.append(capsys.readouterr().out.replace(str(path), ""))
    assert outs[0] == outs[1]
    words = tmp_path / "w.csv"
    words.write_text("wavelength,flux\nabc,def\n4000,1e-17\n")
    err = _one_line(*_main_error(capsys, ["etc", "--spectrum", str(words), "--snr", "10"], monkeypatch))
    assert "w.csv: need at least two rows of two numbers 'wavelength flux', found 1; line 2 'abc,def'" in err, err


@pytest.mark.parametrize("argv, needles", [
    (["etc", "--spectrum", "{binary}"], ["--spectrum", "data.bin", "not a text file"]),
    (["etc", "--spectrum", "{bad_row}"], ["--spectrum", "sp.txt", "line 4", "'6000 oops'"]),
    (["etc", "--spectrum", "{negative}"], ["--spectrum", "neg.txt", "negative"]),
    (["etc", "--redshift", "1", "--config", "{binary}"], ["data.bin", "cannot parse TOML"]),
    (["footprints", "--out", "{tmp}/fp", "--spot-table", "{bad_row}"], ["--spot-table", "sp.txt", "header must be"]),
    (["footprints", "--out", "{tmp}/fp", "--spot-table", "{spot_short_row}"],   # was NumPy's "use `usecols`" advice
     ["--spot-table: ", "short.txt, line 4: 5 numbers where a spot-table row has 7 numbers"]),
    (["footprints", "--out", "{tmp}/fp", "--spot-table", "{binary}"], ["--spot-table", "data.bin"]),
    (["footprints", "--out", "{tmp}/fp", "--spot-table", "{spot_header}"],     # was "index 1 is out of bounds"
     ["spots.csv", "no rows of 7 numbers under the header"]),
    (["footprints", "--out", "{tmp}/fp", "--truncate", "nan"], ["--truncate"]),
    (["footprints", "--out", "{tmp}/fp", "--truncate", "1e300"],                # ran for ever
     ["--truncate [spot rms] must be in [0, 100]"]),
    (["plot", "fields", "--out", "{tmp}/f.png", "--seed", "-1"], ["--seed"]),
    (["ramp", "--rate", "{text_npy}", "--nmd", "3", "1", "0", "--out", "{tmp}/r.h5"], ["image.npy", "not a NumPy .npy"]),
    (["ramp", "--rate", "{strings_npy}", "--nmd", "3", "1", "0", "--out", "{tmp}/r.h5"], ["s.npy", "real numbers"]),
    (["ramp", "--rate", "{binary}", "--nmd", "3", "1", "0", "--out", "{tmp}/r.h5"], ["data.bin", "not a text file"]),
    (["ramp", "--rate", "{empty_npy}", "--nmd", "3", "1", "0", "--out", "{tmp}/r.h5"], ["--rate", "e.npy", "empty"]),
    (["ramp", "--rate", "{no_pixels_npy}", "--nmd", "3", "1", "0", "--out", "{tmp}/r.h5"],
     ["--rate must be a non-empty"]),
    (["ramp", "--rate", "{image_npy}", "--nmd", "3", "1", "0", "--out", "{tmp}/r.h5", "--effects", "persistence",
      "--previous-charge", "{line_npy}"], ["--previous-charge must be", "got shape (4,)"]),
    (["etc", "--spectrum", "{spectrum}", "--frame", "rest"], ["--frame rest needs a target redshift", "(--frame obs)"]),
])
def test_files_given_by_mistake_are_one_line_user_errors_naming_them(tmp_path, user_files, capsys, monkeypatch,
                                                                      argv, needles):
    subst = {k: str(v) for k, v in user_files.items()} | {"tmp": str(tmp_path)}
    err = _one_line(*_main_error(capsys, [a.format(**subst) for a in argv], monkeypatch))
    for needle in needles:
        assert needle in err, (needle, err)
    assert not (tmp_path / "r.h5").exists() and not (tmp_path / "fp").exists()


def test_a_user_error_is_exit_2_and_one_line(capsys, monkeypatch):
    err = _one_line(*_main_error(capsys, ["etc", "--redshift", "-1"], monkeypatch))
    assert "redshift" in err and "please report" not in err


@pytest.mark.parametrize("exc", [RuntimeError("boom in a kernel"), ValueError("operands could not be broadcast"),
                                 TypeError("unsupported operand"), KeyError("lbda")])
def test_an_internal_error_is_exit_3_with_traceback_and_please_report(capsys, monkeypatch, exc):
    """Only SlicersimError, OSError, MemoryError and ^C are user errors: a bare ValueError or
    TypeError (NumPy's, say) is a defect, shown with its traceback and a please-report line."""
    from slicersim.app import cli

    def broken(args):
        raise exc
    monkeypatch.setattr(cli, "cmd_info", broken)
    status, err = _main_error(capsys, ["info"], monkeypatch)
    assert status == 3, err
    assert "Traceback (most recent call last)" in err and "in broken" in err
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"slicersim: internal error ({type(exc).__name__})") and "please report" in last
    assert "slicersim: error:" not in err


def test_ramp_out_fifo_link_and_new_directory_are_refused(tmp_path, rate_file):
    """`--overwrite` replaces only regular files (a FIFO, a link to one: refused, untouched); `--out newdir/`
    is a directory, never written as a file named newdir."""
    import stat
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    (tmp_path / "link.h5").symlink_to(fifo)
    for out, message in ((fifo, "FIFO"), (tmp_path / "link.h5", "FIFO .*symbolic link"),
                         (f"{tmp_path / 'newdir'}/", "names a directory")):
        line = one_error_line(run("ramp", "--rate", rate_file, "--nmd", "3", "1", "0", "--out", out, "--overwrite"))
        assert "--out" in line and re.search(message, line), line
    assert sorted(os.listdir(tmp_path)) == ["link.h5", "pipe"] and stat.S_ISFIFO(os.lstat(fifo).st_mode)


# --------------------------------------------------------------------------- issue 26: inputs are regular files
def _main_no_hang(capsys, argv, monkeypatch, timeout=60):
    """(status, stderr) of main(argv) in a thread that must finish (a FIFO read would block forever)."""
    import threading

    from slicersim.app.cli import main
    monkeypatch.delenv("SLICERSIM_DEBUG", raising=False)
    result = []
    thread = threading.Thread(target=lambda: result.append(main([str(a) for a in argv])), daemon=True)
    thread.start()
    thread.join(timeout)
    assert not thread.is_alive(), f"{argv} blocked"
    return result[0], capsys.readouterr().err


@pytest.mark.parametrize("kind", ["fifo", "zero", "dir"])
@pytest.mark.parametrize("argv", [
    ["etc", "--spectrum", "{input}"],
    ["etc", "--redshift", "1", "--config", "{input}"],
    ["ramp", "--rate", "{input}", "--nmd", "3", "1", "0", "--out", "{tmp}/r.h5"],
    ["ramp", "--rate", "{rate}", "--nmd", "3", "1", "0", "--effects", "all", "--effects-config", "{input}",
     "--out", "{tmp}/r.h5"],
    ["ramp", "--rate", "{rate}", "--nmd", "3", "1", "0", "--effects", "persistence", "--previous-charge", "{input}",
     "--out", "{tmp}/r.h5"],
    ["campaign", "run", "{input}", "--out", "{tmp}/ds"],
    ["footprints", "--out", "{tmp}/fp", "--spot-table", "{input}"],
    ["plot", "slice-map", "--out", "{tmp}/map.png", "--spot-table", "{input}"],
    ["etc", "--redshift", "1", "--config", "{curve_config}"],
])
def test_fifos_devices_and_directories_are_refused_before_reading(tmp_path, capsys, monkeypatch, kind, argv):
    rate = tmp_path / "rate.npy"
    np.save(rate, np.full((8, 8), 5.0))
    if kind == "fifo":
        path = tmp_path / "input.toml"
        os.mkfifo(path)
    elif kind == "zero":
        path = "/dev/zero"
    else:
        path = tmp_path / "folder.toml"
        path.mkdir()
    curve_config = tmp_path / "curve.toml"                  # a curve file that is not a regular file
    curve_config.write_text(f'[detector]\nQE = "{path}"\n')
    subst = {"input": str(path), "tmp": str(tmp_path), "rate": str(rate), "curve_config": str(curve_config)}
    err = _one_line(*_main_no_hang(capsys, [a.format(**subst) for a in argv], monkeypatch))
    assert str(path) in err and ("not a regular file" in err or "directory" in err), err
    assert not (tmp_path / "r.h5").exists() and not (tmp_path / "ds").exists()


@pytest.mark.parametrize("text, needles", [
    ("lbda,flux\n4000,1e-17\n5000,x\n6000,1e-17\n", ["sp.csv", "line 3", "5000,x"]),
    ("lbda;flux\n4000,5;1,2e-17\n5000,5;1,3e-17\n", ["sp.csv", "line 2", "decimal"]),
    ("4000 1,5e-17\n5000 1,6e-17\n", ["sp.csv", "line 1", "decimal"]),
])
def test_malformed_and_decimal_comma_spectra_name_the_line(tmp_path, capsys, monkeypatch, text, needles):
    path = tmp_path / "sp.csv"
    path.write_text(text)
    err = _one_line(*_main_error(capsys, ["etc", "--spectrum", path, "--snr", "10"], monkeypatch))
    for needle in needles:
        assert needle in err, (needle, err)


@pytest.mark.parametrize("argv, needle", [
    (["--nmd", "4", "1", "1000000000"], "--nmd[2] (d, dropped frames between groups)"),
    (["--nmd", "5000", "1", "0"], "--nmd[0] (n, groups per ramp)"),
    (["--nmd", "3", "1", "0", "--ron", "1e300"], "--ron [electron]"),
    (["--nmd", "3", "1", "0", "--ron", "9000"], "more than 1/8 of the 16-bit ADC range"),
    (["--nmd", "3", "1", "0", "--gain", "1e-300"], "--gain [ADU/e-]"),
    (["--nmd", "3", "1", "0", "--tframe", "1e300"], "--tframe [s]"),
])
def test_ramp_detector_options_out_of_their_physical_range_are_refused(tmp_path, capsys, monkeypatch, argv, needle):
    rate = tmp_path / "rate.npy"
    np.save(rate, np.full((8, 8), 5.0))
    err = _one_line(*_main_error(capsys, ["ramp", "--rate", rate, "--out", tmp_path / "r.h5", *argv], monkeypatch))
    assert needle in err and not (tmp_path / "r.h5").exists()


def test_cli_etc_prints_units_and_no_object_repr():
    """`slicersim etc --redshift 1 --snr 20` prints exposure_time / data_volume /
    lbda_range_obs without units and 'target : <slicersim.targets.LazuliSupernova object at 0x..>'."""
    out = subprocess.run([sys.executable, "-m", "slicersim", "etc", "--redshift", "1.0", "--snr", "20"],
                         capture_output=True, text=True, timeout=30, check=True).stdout
    assert "object at 0x" not in out
    # the CLI now prints units in brackets after the key ("exposure_time [s]", "data_volume [GB]")
    assert "[GB]" in out and "[s]" in out and "[Angstrom]" in out


# --------------------------------------------------------------------------- messages name the flags
@pytest.mark.parametrize("argv, needle", [
    (["ramp", "--rate", "{rate}", "--nmd", "3", "1", "0", "--effects", "cosmic_rays", "--cr-rate", "-1",
      "--out", "{tmp}/r.h5"], "--cr-rate [cm⁻² s⁻¹] must be in [0, 1e+06], got -1"),
    (["ramp", "--rate", "{tmp}/missing.npy", "--out", "{tmp}/r.h5"], "--rate: {tmp}/missing.npy: No such file"),
    (["ramp", "--rate", "{rate}", "--nmd", "3", "1", "0", "--effects", "all", "--effects-config",
      "{tmp}/missing.toml", "--out", "{tmp}/r.h5"], "--effects-config: {tmp}/missing.toml: No such file"),
    (["ramp", "--redshift", "1", "--effects", "persistence", "--previous-charge", "{tmp}/missing.npy",
      "--out", "{tmp}/r.h5"], "--previous-charge: {tmp}/missing.npy: No such file"),
    (["ramp", "--redshift", "-1", "--out", "{tmp}/r.h5"], "--redshift must be in (0, 50], got -1"),
    (["plot", "fields", "--redshift", "-1", "--out", "{tmp}/f.png"], "--redshift must be in (0, 50], got -1"),
    (["etc", "--redshift", "1", "--lbda-range", "1000", "6000"], "use the covered part (--allow-partial)"),
])
def test_messages_name_the_command_line_flags_not_python_keywords(tmp_path, capsys, monkeypatch, argv, needle):
    rate = tmp_path / "rate.npy"
    np.save(rate, np.full((8, 8), 5.0))
    subst = {"tmp": str(tmp_path), "rate": str(rate)}
    err = _one_line(*_main_error(capsys, [a.format(**subst) for a in argv], monkeypatch))
    assert needle.format(**subst) in err, err
    message = err.partition("error: ")[2]
    assert not re.search(r"(?<![-\w.])(nramps|lbda_range|redshift|snr|cr_rate|cosmic_rays\.rate|image file|"
                         r"effects config|allow_partial)\b", message), err
    assert not (tmp_path / "r.h5").exists()


# --------------------------------------------------------------------------- spectra: rows are never reordered
@pytest.mark.parametrize("text, needle", [
    ("wavelength,flux\n4000,1e-17\n5000,1e-17\n5010,1e-17\n5005,1e-17\n5020,1e-17\n9000,1e-17\n",
     "sp.csv, line 5: wavelength 5005 is below 5010 on line 4"),
    ("# my spectrum\nwavelength flux\n\n4000 1e-17\n5000 1e-17\n5000 2e-17\n9000 1e-17\n",
     "sp.csv, line 6: wavelength 5000 equals 5000 on line 5 (a duplicate row)"),
])
def test_spectrum_rows_out_of_order_or_repeated_are_refused_naming_the_lines(tmp_path, capsys, monkeypatch, text,
                                                                               needle):
    path = tmp_path / "sp.csv"
    path.write_text(text)
    err = _one_line(*_main_error(capsys, ["etc", "--spectrum", path, "--snr", "10"], monkeypatch))
    assert "--spectrum" in err and needle in err and "never sorted or dropped" in err, err


# --------------------------------------------------------------------------- partial or misplaced configurations
@pytest.mark.parametrize("argv", [
    ["etc", "--redshift", "1", "--config", "{partial}"],
    ["ramp", "--redshift", "1", "--config", "{partial}", "--out", "{tmp}/r.h5"],
    ["survey", "plan", "--n", "2", "--config", "{partial}"],
    ["footprints", "--out", "{tmp}/fp", "--config", "{partial}"],
])
def test_a_partial_configuration_names_the_missing_key_and_the_complete_default(tmp_path, capsys, monkeypatch,
                                                                                 argv):
    partial = tmp_path / "partial.toml"
    partial.write_text("[detector]\ngain = 2.0\n")
    subst = {"partial": str(partial), "tmp": str(tmp_path)}
    err = _one_line(*_main_error(capsys, [a.format(**subst) for a in argv], monkeypatch))
    for needle in ("partial.toml", "[spectrograph] dispersion_law", "lazuli_cbe.toml",
                   "--config cbe --config FILE"):
        assert needle in err, (needle, err)


def test_config_is_repeatable_on_ramp_and_survey_plan(tmp_path, capsys, monkeypatch):
    """Layering (--config cbe --config FILE) applies every file: the last one is not the only one."""
    wrong = tmp_path / "wrong.toml"
    wrong.write_text("[telescope]\ngain = 2.0\n")
    for argv in (["ramp", "--redshift", "1", "--config", wrong, "--config", "cbe", "--out", tmp_path / "r.h5"],
                 ["survey", "plan", "--n", "2", "--config", wrong, "--config", "cbe"]):
        err = _one_line(*_main_error(capsys, argv, monkeypatch))
        assert "wrong.toml: [telescope] has no key(s) 'gain': 'gain' belongs in [detector]" in err, err
HUGE = "1" + "0" * 300


@pytest.mark.parametrize("argv, needle", [
    (["etc", "--redshift", HUGE], "--redshift must be ≤ 50, got 1e+300"),
    (["ramp", "--redshift", HUGE, "--out", "{tmp}/r.h5"], "--redshift must be ≤ 50, got 1e+300"),
    (["plot", "fields", "--redshift", HUGE, "--out", "{tmp}/f.png"], "--redshift must be ≤ 50, got 1e+300"),
    (["survey", "plan", "--n", "3", "--zmax", HUGE], "--zmax must be in [0, 10] (redshifts above 10 are outside any SN Ia model), got 1e+300"),
    (["survey", "plan", "--n", "3", "--z-switch", HUGE], "--z-switch must be ≤ 50, got 1e+300"),
    (["etc", "--redshift", "1", "--frame", "obs", "--lbda-range", "4000", HUGE], "band 4000–1e+300 Å"),
    (["reduce", "{tmp}/raw.h5", "--out", "{tmp}/o.h5", "--spectra", "--lbda-edges", f"{HUGE},1,1"],
     "--lbda-edges START,STOP,STEP needs finite START < STOP and STEP > 0, got 1e+300,1,1"),
])
def test_a_300_digit_number_is_refused_and_printed_short(tmp_path, capsys, monkeypatch, argv, needle):
    (tmp_path / "raw.h5").write_bytes(b"")
    err = _one_line(*_main_error(capsys, [a.format(tmp=tmp_path) for a in argv], monkeypatch))
    assert needle in err and "0000000000" not in err, err


def _raising(exc):
    def command(args):
        raise exc
    return command


@pytest.mark.parametrize("command, argv, needles", [
    ("reduce_cli.cmd_reduce", ["reduce", "raw.h5", "--out", "o.h5"],
     ["out of memory (host): Unable to allocate 74.5 GiB for an array with shape (100000, 100000)", "--max-bytes"]),
    ("cli.cmd_ramp", ["ramp", "--rate", "r.npy", "--out", "o.h5"], ["out of memory (host)", "--max-bytes"]),
    ("campaign_cli.cmd_campaign_run", ["campaign", "run", "spec.toml", "--out", "d"], ["--memory-per-task"]),
])
def test_out_of_memory_is_one_line_naming_the_allocation_and_the_option(capsys, monkeypatch, command, argv, needles):
    """A MemoryError (NumPy's) is a user error, exit 2, one line: what was allocated and which option bounds it."""
    import importlib
    module, name = command.split(".")
    raised = MemoryError("Unable to allocate 74.5 GiB for an array with shape (100000, 100000) and data type float64")
    monkeypatch.setattr(importlib.import_module(f"slicersim.app.{module}"), name, _raising(raised))
    err = _one_line(*_main_error(capsys, argv, monkeypatch))
    for needle in needles:
        assert needle in err, (needle, err)


def test_opencl_device_out_of_memory_is_a_user_error(capsys, monkeypatch):
    """pyopencl's MemoryError is not Python's: it was an internal error with a traceback (exit 3)."""
    cl = pytest.importorskip("pyopencl")
    from slicersim.app import cli
    monkeypatch.setattr(cli, "cmd_ramp", _raising(cl.MemoryError("clEnqueueNDRangeKernel failed: "
                                                                   "MEM_OBJECT_ALLOCATION_FAILURE")))
    err = _one_line(*_main_error(capsys, ["ramp", "--rate", "r.npy", "--out", "o.h5"], monkeypatch))
    assert "out of memory (OpenCL device): clEnqueueNDRangeKernel failed: MEM_OBJECT_ALLOCATION_FAILURE" in err
    assert "--max-bytes" in err


def test_a_too_small_max_bytes_names_the_flag(tmp_path, capsys, monkeypatch):
    rate = tmp_path / "rate.npy"
    np.save(rate, np.full((8, 8), 5.0))
    err = _one_line(*_main_error(capsys, ["ramp", "--rate", rate, "--nmd", "3", "1", "0", "--max-bytes", "10",
                                          "--out", tmp_path / "r.h5"], monkeypatch))
    assert "--max-bytes 10 B is below" in err and not (tmp_path / "r.h5").exists()


def _forged_npy(path, shape=(100000, 100000)):
    """A .npy file whose header declares ``shape`` float64 and which holds 64 bytes."""
    with open(path, "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, {"descr": "<f8", "fortran_order": False, "shape": shape})
        fh.write(b"\0" * 64)
    return path


@pytest.mark.parametrize("argv, flag", [
    (["ramp", "--rate", "{npy}", "--out", "{tmp}/r.h5"], "--rate"),
    (["ramp", "--rate", "{ok}", "--effects", "persistence", "--previous-charge", "{npy}", "--out", "{tmp}/r.h5"],
     "--previous-charge"),
    (["reduce", "{h5}", "--out", "{tmp}/r.h5", "--spectra", "--dark", "{npy}"], "--dark"),
    (["reduce", "{h5}", "--out", "{tmp}/r.h5", "--spectra", "--lbda-edges", "{npy}"], "--lbda-edges"),
    (["reduce", "{h5}", "--out", "{tmp}/r.h5"], None),
])
def test_inputs_declaring_more_data_than_they_hold_are_named_before_allocating(tmp_path, capsys, monkeypatch, argv,
                                                                                flag):
    """A .npy header or an HDF5 SCI declaring 10⁵ × 10⁵ values in a few bytes was 'out of memory' (74.5 GiB)."""
    import h5py
    npy = _forged_npy(tmp_path / "forged.npy")
    np.save(tmp_path / "ok.npy", np.ones((8, 8)))
    with h5py.File(tmp_path / "forged.h5", "w") as fh:
        fh.create_dataset("SCI", shape=(1, 4, 100000, 100000), dtype="u2", chunks=(1, 1, 64, 64))
        fh.attrs["COMPLETE"] = True
    subst = {"npy": npy, "ok": tmp_path / "ok.npy", "h5": tmp_path / "forged.h5", "tmp": tmp_path}
    err = _one_line(*_main_error(capsys, [a.format(**subst) for a in argv], monkeypatch))
    if flag is None:
        assert "forged.h5: dataset SCI declares shape (1, 4, 100000, 100000) uint16 (74.5 GiB)" in err, err
    else:
        assert f"{flag}: {npy} declares an array of shape (100000, 100000) float64 (74.5 GiB) but holds 64 bytes" \
            in err, err
    assert not (tmp_path / "r.h5").exists()


def test_absurd_rates_and_fluxes_are_one_line_range_errors(tmp_path, capsys, monkeypatch):
    """--rate at 1e300 e-/s gave NumPy overflow warnings; --spectrum at 1e100 erg/s/cm²/Å 'no signal in the band?'."""
    np.save(tmp_path / "hot.npy", np.full((8, 8), 1e300))
    err = _one_line(*_main_error(capsys, ["ramp", "--rate", tmp_path / "hot.npy", "--nmd", "3", "1", "0", "--out",
                                          tmp_path / "r.h5"], monkeypatch))
    assert "--rate image reaches 1e+300 e-/s" in err and "more than the 1e+09 e- accepted" in err, err
    assert "warning" not in err and not (tmp_path / "r.h5").exists()
    (tmp_path / "sp.txt").write_text("".join(f"{w} 1e100\n" for w in range(3000, 20000, 100)))
    err = _one_line(*_main_error(capsys, ["etc", "--spectrum", tmp_path / "sp.txt"], monkeypatch))
    assert "F_λ reaches 1e+100 erg/s/cm²/Å, above 1000" in err, err


def test_the_read_noise_unit_is_spelled_electron_everywhere_a_user_reads_it(tmp_path, capsys, monkeypatch):
    """CLI help, messages and docs said e-/read, e-/frame, e- and e⁻: one astropy-readable spelling."""
    from pathlib import Path

    import astropy.units as u

    from slicersim.app.cli import build_parser
    from slicersim.errors import ParameterError
    from slicersim.instrument.detector import Detector
    from slicersim.physics.ramp import RampParameters
    from slicersim.reduction.checks import check_fit_options
    from slicersim.reduction.ramp_fit import FitOptions
    assert u.Unit("electron") == u.electron
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command").choices
    for command in ("ramp", "reduce"):
        ron = next(a for a in sub[command]._actions if a.dest == "ron")
        assert "read noise per frame [electron]" in ron.help and "e-" not in ron.help, ron.help
    messages = []
    for make in (lambda: RampParameters(nmd=(3, 1, 0), ron=-1), lambda: Detector(ron=-1), lambda: FitOptions(ron=-1),
                 lambda: check_fit_options({"ron": -1})):
        with pytest.raises(ParameterError) as info:
            make()
        messages.append(str(info.value))
    rate = tmp_path / "rate.npy"
    np.save(rate, np.full((8, 8), 5.0))
    messages.append(_one_line(*_main_error(capsys, ["ramp", "--rate", rate, "--ron", "-1", "--out", tmp_path / "r.h5"],
                                           monkeypatch)))
    messages.append(_one_line(*_main_error(capsys, ["ramp", "--rate", rate, "--ron", "9000", "--out",
                                                    tmp_path / "r.h5"], monkeypatch)))
    (tmp_path / "raw.h5").write_bytes(b"")
    messages.append(_one_line(*_main_error(capsys, ["reduce", tmp_path / "raw.h5", "--ron", "-1", "--out",
                                                    tmp_path / "o.h5"], monkeypatch)))
    root = Path(__file__).resolve().parents[2]
    entries = [line.split("`ron`", 1)[1].split("`")[0] for doc in ("docs/units.md", "docs/api_conventions.md")
               for line in (root / doc).read_text(encoding="utf-8").splitlines() if "`ron`" in line]
    messages += [entry for entry in entries if "[" in entry]          # the entries giving its unit
    assert len(messages) == 9
    for text in messages:
        assert "electron" in text and not re.search(r"e-/read|e-/frame|e⁻|\[e-\]|e- per frame", text), text


def test_an_ascii_terminal_gets_escapes_not_a_unicode_error(monkeypatch):
    """Under LC_ALL=C without UTF-8 mode stdout is ASCII: a result line with "≥" or "σ" raised
    UnicodeEncodeError (exit 3) after a successful reduce.  The CLI writes such characters as escapes."""
    import io

    from slicersim.app import cli
    out = io.TextIOWrapper(io.BytesIO(), encoding="ascii")
    monkeypatch.setattr(sys, "stdout", out)
    cli._tolerant_streams()
    print("SNR ≥ 20 σ")
    out.flush()
    assert out.buffer.getvalue() == b"SNR \\u2265 20 \\u03c3\n"
    env = {**os.environ, "LC_ALL": "C", "PYTHONUTF8": "0", "PYTHONCOERCECLOCALE": "0"}
    proc = subprocess.run([sys.executable, "-c", "import sys; from slicersim.app.cli import main, _tolerant_streams;"
                           "_tolerant_streams(); print('band 4000\\u20136800 \\u00c5'); sys.exit(main(['info']))"],
                          capture_output=True, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert b"\\u2013" in proc.stdout
