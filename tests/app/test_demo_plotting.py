"""Demo run (ETC report, figures, JSON) and the diagnostic plots."""

import json
import struct

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from slicersim.app import plotting  # noqa: E402
from slicersim.targets import LazuliTarget  # noqa: E402

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def assert_png(path, min_bytes=10_000):
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC, f"{path.name} is not a PNG"
    assert len(data) > min_bytes, f"{path.name} is only {len(data)} bytes"
    width, height = struct.unpack(">II", data[16:24])   # IHDR
    assert width >= 400 and height >= 300, (width, height)


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    from slicersim.app.demo import run_demo

    outdir = tmp_path_factory.mktemp("demo")
    return outdir, run_demo(str(outdir), verbose=False)


def test_demo_writes_figures(demo):
    outdir, _ = demo
    for name in ("spectrum.png", "variance_budget.png", "instrument.png"):
        assert_png(outdir / name)


def test_demo_json(demo):
    outdir, summary = demo
    data = json.loads((outdir / "etc_result.json").read_text(encoding="utf-8"))
    for key in ("nmd", "nramps", "exposure_time", "snr_per_resolution", "snr_target_per_resolution",
                "data_volume_gb", "variance_budget", "reference"):
        assert key in data, key
    n, m, d = data["nmd"]
    assert n >= 2 and m in (1, 4, 8) and d >= 0
    assert data["nramps"] >= 1 and data["exposure_time"] > 0
    assert data["snr_per_resolution"] >= data["snr_target_per_resolution"] == 20.0
    assert data["snr_per_bin"] >= data["snr_target_per_bin"]
    fracs = data["variance_budget"]
    assert set(fracs) == {"dark", "roic_glow", "thermal_dark", "ron", "pointsource", "background", "host",
                          "thermal"}
    assert 0.9 < sum(fracs.values()) < 1.1
    assert data["reference"]["search"] == "reference" and data["reference"]["exposure_time"] > 0
    # the returned summary is what was written (plus the run time)
    assert {k: v for k, v in summary.items() if k != "elapsed_s"} == data
    json.dumps(summary)


def test_cli_demo_wiring(monkeypatch, tmp_path):
    from slicersim.app import cli, demo as demo_module

    calls = []
    monkeypatch.setattr(demo_module, "run_demo", lambda *a, **k: calls.append((a, k)) or {})
    assert cli.main(["demo", "--outdir", str(tmp_path)]) == 0
    assert calls == [((str(tmp_path),), {})]


@pytest.fixture(scope="module")
def target():
    lbda = np.linspace(3000.0, 20000.0, 400)
    t = LazuliTarget(lbda, np.full_like(lbda, 1e-18), mag=23.0)
    t.setup_to_snr(10, lbda_range=(9000, 12000))
    return t


def test_plot_spectrum(target, tmp_path):
    out = tmp_path / "spectrum.png"
    fig = plotting.plot_spectrum(target, seed=0, savefile=out)
    assert_png(out)
    top, bottom = fig.axes[:2]
    assert "ADU" in top.get_ylabel() and "SNR" in bottom.get_ylabel()
    assert "Å" in bottom.get_xlabel()
    labels = [t.get_text() for t in bottom.get_legend().get_texts()]
    assert any("target" in s for s in labels)
    assert "ramp" in fig.get_suptitle() and " s " in fig.get_suptitle()


def test_plot_spectrum_on_simulation_and_axes(target):
    fig = plotting.plot_spectrum(target.simulation)           # no last_etc: no band, still fine
    assert len(fig.axes) == 2
    fig2, ax = plt.subplots()
    assert plotting.plot_spectrum(target, ax=ax, seed=1) is fig2


def test_plot_variance_budget(target, tmp_path):
    out = tmp_path / "variance.png"
    fig = plotting.plot_variance_budget(target, savefile=out)
    assert_png(out)
    top, bottom = fig.axes[:2]
    assert top.get_yscale() == "log"
    labels = [t.get_text() for t in bottom.get_legend().get_texts()]
    assert "read noise" in labels and "point source (photon noise)" in labels


def test_plot_instrument(target, tmp_path):
    out = tmp_path / "instrument.png"
    fig = plotting.plot_instrument(target.simulation, savefile=out)
    assert_png(out)
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert "throughput × QE" in labels
    plotting.plot_instrument(target)                           # a Target works too


def test_rejects_other_objects():
    from slicersim.errors import ParameterError
    with pytest.raises(ParameterError, match="target_or_sim must be a Target or a Simulation"):
        plotting.plot_spectrum(object())
