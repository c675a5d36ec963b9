"""Figures of the instrument models (slicersim 1.4.2's show_* methods): Spectrograph.show_throughput,
Detector.show_qe, Telescope.show_thermal_radiance; each a thin call of slicersim.plotting."""
import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from slicersim.errors import ParameterError  # noqa: E402
from slicersim.instrument.detector import Detector  # noqa: E402
from slicersim.instrument.spectrograph import Spectrograph  # noqa: E402
from slicersim.instrument.telescope import Telescope  # noqa: E402


@pytest.fixture(autouse=True)
def close_figures():
    yield
    plt.close("all")


def _curves(ax):
    return {line.get_label(): line.get_ydata() for line in ax.get_lines()}


def test_spectrograph_show_throughput_total_and_components(tmp_path):
    lbda = np.linspace(3000.0, 18000.0, 50)
    grating = (lbda, np.linspace(0.5, 0.8, lbda.size))
    spec = Spectrograph(resolving_power=500, throughput={"mirror": 0.9, "grating": grating}, noptics={"mirror": 3})
    out = tmp_path / "throughput.png"
    fig = spec.show_throughput(savefile=out)
    assert out.stat().st_size > 1000
    ax = fig.axes[0]
    curves = _curves(ax)
    assert np.allclose(curves["total"], spec.throughput)
    assert np.allclose(curves["mirror (× 3)"], 0.9 ** 3)
    assert ax.get_ylabel() == "throughput [fraction of photons]" and ax.get_xlabel() == "wavelength [Å]"
    fig2, ax2 = plt.subplots()
    assert Spectrograph(resolving_power=500, throughput=0.5).show_throughput(ax=ax2) is fig2
    assert list(_curves(ax2)) == ["total"]


def test_detector_show_qe_curve_and_units():
    table = (np.array([5000.0, 10000.0, 15000.0]), np.array([0.5, 0.9, 0.7]))
    fig = Detector(qe=table).show_qe()
    ax = fig.axes[0]
    line = ax.get_lines()[0]
    assert line.get_xdata()[0] == 5000.0 and line.get_xdata()[-1] == 15000.0
    assert np.allclose(line.get_ydata(), np.interp(line.get_xdata(), *table))
    assert ax.get_ylabel() == "quantum efficiency [e-/ph]" and ax.get_xlabel() == "wavelength [Å]"
    flat = Detector(qe=0.8).show_qe(lbda=[6000.0, 7000.0]).axes[0].get_lines()[0]
    assert np.array_equal(flat.get_ydata(), [0.8, 0.8])
    with pytest.raises(ParameterError, match="lbda"):
        Detector().show_qe(lbda=[[1.0]])


def test_telescope_show_thermal_radiance():
    tel = Telescope()
    lbda = np.linspace(8000.0, 17000.0, 20)
    ax = tel.show_thermal_radiance(lbda).axes[0]
    assert np.allclose(ax.get_lines()[0].get_ydata(), tel.thermal_radiance(lbda))
    assert ax.get_yscale() == "log" and ax.get_ylabel() == "thermal radiance [ph/s/m²/sr/Å]"
