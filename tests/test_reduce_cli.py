"""`slicersim reduce`: raw ramp file → rates file, and one-line errors that write nothing."""
import h5py
import numpy as np
import pytest

from slicersim.app.cli import main
from slicersim.products.ramps import simulate


@pytest.fixture(scope="module")
def raw(tmp_path_factory):
    rate = np.full((16, 32), 20.0)
    rate[4:8, 10:20] = 300.0
    path = tmp_path_factory.mktemp("raw") / "raw.h5"
    return simulate(rate, (12, 4, 0), seed=5, progress=False, out=path, ron=5.0), rate


def test_reduce_writes_rates_close_to_the_truth(raw, tmp_path, capsys):
    path, rate = raw
    out = tmp_path / "rates.h5"
    assert main(["reduce", str(path), "--out", str(out), "--with-truth", "--quiet"]) == 0
    assert "rates 16×32" in capsys.readouterr().out
    with h5py.File(out, "r") as fh:
        fitted, var, truth = fh["RATE"][...], fh["VAR"][...], fh["TRUTH_RATE"][...]
    assert fitted.shape[-2:] == rate.shape and np.allclose(truth, rate)
    pulls = (fitted - truth) / np.sqrt(var)
    assert abs(pulls.mean()) < 4 / np.sqrt(pulls.size) + 0.1 and 0.7 < pulls.std() < 1.3


@pytest.mark.parametrize("case", ["missing", "exists", "threshold", "not_a_ramp", "weighting"])
def test_reduce_bad_input_is_one_line_and_writes_nothing(raw, tmp_path, capsys, case):
    path, _ = raw
    out = tmp_path / "rates.h5"
    argv = ["reduce", str(path), "--out", str(out), "--quiet"]
    if case == "missing":
        argv[1] = str(tmp_path / "nope.h5")
    elif case == "exists":
        out.write_bytes(b"keep me")
    elif case == "threshold":
        argv += ["--jump-threshold", "-3"]
    elif case == "not_a_ramp":
        bad = tmp_path / "bad.h5"
        with h5py.File(bad, "w") as fh:
            fh["x"] = np.zeros(3)
        argv[1] = str(bad)
    if case == "weighting":
        with pytest.raises(SystemExit):
            main(argv + ["--weighting", "best"])
        return
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("slicersim: error:"), err
    if case == "exists":
        assert out.read_bytes() == b"keep me"
    else:
        assert not out.exists()
