"""``slicersim reffiles``: the reference files of a detector or of a ramp file; user errors in one line."""
import numpy as np
import pytest

from slicersim.app.cli import main
from slicersim.io.reference_files import REFERENCE_TYPES, read_reference_files, reference_file_names


def _run(capsys, monkeypatch, *argv):
    monkeypatch.delenv("SLICERSIM_DEBUG", raising=False)
    status = main([str(a) for a in argv])
    out = capsys.readouterr()
    return status, out.out, out.err


def _one_line_error(status, err):
    assert status == 2 and "Traceback" not in err and err.count("\n") == 1 and err.startswith("slicersim: error: "), err
    return err


@pytest.mark.slow
def test_reffiles_writes_the_eight_files_of_the_detector_flags(tmp_path, capsys, monkeypatch):
    status, out, err = _run(capsys, monkeypatch, "reffiles", "--out", tmp_path / "ref", "--shape", 8, 32, "--seed", 4,
                            "--gain", 0.5, "--ron", 6, "--effects", "ipc")
    assert status == 0, err
    assert out.count("wrote ") == len(REFERENCE_TYPES)
    assert sorted(p.name for p in (tmp_path / "ref").iterdir()) == sorted(reference_file_names().values())
    ref = read_reference_files(tmp_path / "ref")
    assert np.allclose(ref["gain"], 2.0)                                  # e-/DN of 0.5 ADU/e-
    assert np.allclose(ref["readnoise"], np.sqrt(2 * (3.0 ** 2 + 1 / 12)))
    assert ref["ipc"][1, 1] == pytest.approx(1 - 4 * 0.016 - 4 * 0.002)
    # existing files: refused unless --overwrite
    status, _, err = _run(capsys, monkeypatch, "reffiles", "--out", tmp_path / "ref", "--shape", 8, 32, "--seed", 4)
    assert "--overwrite" in _one_line_error(status, err)
    status, _, err = _run(capsys, monkeypatch, "reffiles", "--out", tmp_path / "ref", "--shape", 8, 32, "--seed", 4,
                          "--overwrite")
    assert status == 0, err
    assert np.allclose(read_reference_files(tmp_path / "ref")["gain"], 1.0)     # the default gain now


@pytest.mark.parametrize("argv, message", [
    (["--shape", 8, 32], "--seed is needed"),
    (["--seed", 1], "--shape NY NX is needed"),
    (["--seed", 1, "--shape", 8, 32, "--gain", 0], "--gain"),
    (["--seed", 1, "--shape", 8, 32, "--effects", "moon"], "unknown effect"),
    (["--seed", 1, "--shape", 8, 32, "--field", "wide"], "--field applies only with --config"),
    (["--seed", 1, "--shape", 8, 32, "--dark-frames", 1], "--dark-frames"),
    (["--ramps", "missing.h5"], "no such file"),
    (["--ramps", "missing.h5", "--seed", 3], "drop --seed"),
])
def test_reffiles_user_errors_are_one_line(tmp_path, capsys, monkeypatch, argv, message):
    status, _, err = _run(capsys, monkeypatch, "reffiles", "--out", tmp_path / "ref", *argv)
    assert message in _one_line_error(status, err)
    assert not (tmp_path / "ref").exists() or not any((tmp_path / "ref").iterdir())


@pytest.mark.slow
def test_reffiles_of_a_ramp_file_match_it(tmp_path, capsys, monkeypatch):
    from slicersim.products.ramps import simulate
    path = simulate(np.full((40, 64), 30.0), (3, 1, 0), seed=8, out=tmp_path / "raw.fits", gain=1.5,
                    effects="bad_pixels,reference_pixels")
    status, _, err = _run(capsys, monkeypatch, "reffiles", "--ramps", path, "--out", tmp_path / "ref")
    assert status == 0, err
    ref = read_reference_files(tmp_path / "ref")
    from slicersim.io.uncal import read_uncal
    _, _, pdq, _ = read_uncal(path)
    assert np.array_equal(ref["mask"], pdq) and np.allclose(ref["gain"], 1 / 1.5)
