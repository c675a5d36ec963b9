"""User tables and text inputs (slicersim.io.tables): regular files of bounded size, numbers named by line."""
import os
import threading

import numpy as np
import pytest

from slicersim.errors import ConfigError, EffectsError
from slicersim.io.tables import read_file_bytes, read_spectrum_table, read_table, resolve_path


def _no_hang(call, timeout=30):
    """The exception ``call()`` raises, in a thread that must finish (a FIFO would block it)."""
    caught = []

    def run():
        try:
            call()
        except Exception as exc:                      # noqa: BLE001 (returned to the test)
            caught.append(exc)
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(timeout)
    assert not thread.is_alive(), "blocked on a FIFO"
    return caught[0] if caught else None


@pytest.mark.parametrize("reader", [
    lambda p: read_file_bytes(p, EffectsError, "effects config"),
    lambda p: read_table(p, "population.spectrum"),
    lambda p: resolve_path(p, "/", "population.spectrum"),
])
def test_fifo_device_and_directory_are_refused_before_opening(tmp_path, reader):
    fifo = tmp_path / "t.csv"
    os.mkfifo(fifo)
    for path, what in ((str(fifo), "not a regular file"), ("/dev/zero", "not a regular file"),
                       (str(tmp_path), "is a directory")):
        exc = _no_hang(lambda: reader(path))
        assert isinstance(exc, (ConfigError, EffectsError)) and path in str(exc) and what in str(exc), exc


def test_a_file_over_the_bound_is_refused(tmp_path):
    big = tmp_path / "big.toml"
    big.write_bytes(b"#" * 2000)
    with pytest.raises(ConfigError, match=r"config: .*big.toml is 2000 bytes, more than the 1000 accepted"):
        read_file_bytes(big, ConfigError, "config", max_bytes=1000)


@pytest.mark.parametrize("text, match", [
    ("lbda,flux\n4000,1e-17\n5000,x\n", r"sp.csv, line 3: flux = 'x' is not a number"),
    ("lbda,flux\n4000,1e-17\n5000,\n", r"sp.csv, line 3: flux = '--' is not a number"),
])
def test_spectrum_tables_name_the_line_of_a_bad_value(tmp_path, text, match):
    path = tmp_path / "sp.csv"
    path.write_text(text)
    with pytest.raises(ConfigError, match=match):
        read_spectrum_table(str(path), "population.spectrum")
    good = tmp_path / "ok.csv"
    good.write_text("lbda,flux\n4000,1e-17\n5000,2e-17\n")
    lbda, flux = read_spectrum_table(str(good), "population.spectrum")
    assert np.array_equal(lbda, [4000, 5000]) and np.array_equal(flux, [1e-17, 2e-17])


def test_curve_files_that_are_not_regular_files_are_named(tmp_path):
    from slicersim.io.curves import CurveError, read_curve
    fifo = tmp_path / "curve.csv"
    os.mkfifo(fifo)
    exc = _no_hang(lambda: read_curve(str(fifo)))
    assert isinstance(exc, CurveError) and "curve.csv is not a regular file" in str(exc)
    with pytest.raises(CurveError, match="curve file not found"):
        read_curve(str(tmp_path / "missing.csv"))


ECSV_HEADER = ("# %ECSV 1.0\n# ---\n# datatype:\n# - {name: lbda, datatype: float64}\n"
               "# - {name: flux, datatype: float64}\n# schema: astropy-2.0\nlbda flux\n")


@pytest.mark.parametrize("name, text, match", [
    ("sp.csv", "lbda,flux\n4000,1e-17\n5000,1e-17\n5010,1e-17\n5005,1e-17\n5020,1e-17\n",
     r"population.spectrum: .*sp.csv, line 5: lbda 5005 is below 5010 on line 4; "),
    ("sp.csv", "lbda,flux\n4000,1e-17\n\n5000,1e-17\n5000,2e-17\n",        # a blank line is not a row
     r"sp.csv, line 5: lbda 5000 equals 5000 on line 4 \(a duplicate row\)"),
    ("sp.ecsv", ECSV_HEADER + "4000 1e-17\n5000 1e-17\n\n5010 1e-17\n5005 1e-17\n",
     r"sp.ecsv, line 12: lbda 5005 is below 5010 on line 11; lbdas must be finite and strictly increasing "
     r"\(rows are never sorted or dropped\)$"),
])
def test_spectrum_table_rows_out_of_order_or_repeated_are_refused_naming_the_lines(tmp_path, name, text, match):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(ConfigError, match=match):
        read_spectrum_table(str(path), "population.spectrum")


def test_curve_rows_out_of_order_are_refused_naming_the_lines(tmp_path):
    from slicersim.io.curves import CurveError, read_curve
    path = tmp_path / "qe.csv"
    path.write_text("wavelength,QE\n5000,0.5\n5010,0.6\n\n5005,0.7\n")
    with pytest.raises(CurveError, match=r"qe.csv, line 5: wavelength 5005 is below 5010 on line 3"):
        read_curve(str(path))


def test_a_text_file_that_is_not_a_curve_names_the_first_bad_line(tmp_path):
    """/etc/passwd as a QE curve gave NumPy's list of every bad line ("Some errors were detected ! ...")."""
    from slicersim.errors import CurveError
    from slicersim.io.curves import read_curve
    path = tmp_path / "passwd"
    path.write_text("root:x:0:0:root:/root:/bin/bash\n" + "".join(f"user{i} x {i}\n" for i in range(40)))
    with pytest.raises(CurveError, match=r"^cannot read curve file .*passwd: line 2 has 3 columns where the header "
                                         r"has 1 \(a curve file is a header line of column names") as info:
        read_curve(str(path))
    assert len(str(info.value)) < 250 and "Some errors" not in str(info.value)
