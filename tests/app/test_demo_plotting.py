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


@pytest.mark.slow
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


# --------------------------------------------------------------------------- show_* methods (1.4.2)
def test_target_show_spectrum_is_plot_spectrum(target, tmp_path):
    out = tmp_path / "spectrum.png"
    fig = target.show_spectrum(seed=1, savefile=out)
    assert_png(out)
    top, bottom = fig.axes[:2]
    assert top.get_ylabel().startswith("extracted signal [ADU]") and bottom.get_ylabel() == "SNR per bin"
    assert bottom.get_xlabel() == "observed wavelength [Å]"
    fig2, ax = plt.subplots()
    assert target.show_spectrum(ax=ax) is fig2


def test_target_show_variance_contribution(target):
    fig = target.show_variance_contribution()
    top, bottom = fig.axes[:2]
    assert top.get_ylabel().startswith("variance [ADU²]") and bottom.get_ylabel() == "fraction of total variance"
    assert "read noise" in [t.get_text() for t in bottom.get_legend().get_texts()]
    fig2, axes = plt.subplots(2, 1)
    assert target.show_variance_contribution(ax=axes) is fig2


def test_simulation_show_cube_draws_the_cube_at_the_wavelengths_asked(target):
    sim = target.simulation
    fig = sim.show_cube(lbda=(9000.0, 11000.0))
    images = [ax for ax in fig.axes if ax.get_label() != "<colorbar>"]
    bars = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert len(images) == 2 and [b.get_ylabel() for b in bars] == ["signal [ADU]"] * 2
    k = int(np.abs(sim.lbda - 9000.0).argmin())
    assert images[0].get_title() == f"λ = {sim.lbda[k]:.0f} Å"
    assert np.allclose(images[0].get_images()[0].get_array(), sim.get_cube()[0][k])
    assert images[0].get_xlabel() == "x along the slices [arcsec]"
    noisy = target.show_cube(lbda=9000.0, seed=3)                     # Target → its simulation, a noisy draw
    assert np.allclose(noisy.axes[0].get_images()[0].get_array(), sim.get_cube(seed=3)[2][k])
    from slicersim.errors import ParameterError
    with pytest.raises(ParameterError, match="lbda"):
        sim.show_cube(lbda=100.0)


# --------------------------------------------------------------------------- demo reruns, raw-ramp figure
def test_demo_reruns_replace_only_its_own_files(demo):
    from slicersim.app.demo import DEMO_FILES, run_demo
    outdir, _ = demo
    mine = outdir / "notes.txt"
    mine.write_text("mine")
    before = {name: (outdir / name).stat().st_ino for name in DEMO_FILES}
    with pytest.raises(FileExistsError, match="spectrum.png.*|overwrite"):
        run_demo(str(outdir), verbose=False)                           # refused before any work
    assert {name: (outdir / name).stat().st_ino for name in DEMO_FILES} == before
    run_demo(str(outdir), verbose=False, overwrite=True)               # what `make demo` does
    after = {name: (outdir / name).stat().st_ino for name in DEMO_FILES}
    assert all(after[name] != before[name] for name in DEMO_FILES)    # each replaced (renamed in)
    assert mine.read_text() == "mine"
    assert sorted(p.name for p in outdir.iterdir()) == sorted(DEMO_FILES + ("notes.txt",))


def test_make_demo_passes_overwrite():
    from pathlib import Path
    makefile = (Path(__file__).resolve().parents[2] / "Makefile").read_text()
    recipe = makefile.split("\ndemo:", 1)[1].split("\n\n", 1)[0]
    assert "slicersim\" demo" in recipe and "--overwrite" in recipe


def test_demo_ramp_figure_shows_the_source(demo):
    """The demo's ramp has the ETC's readout on a window around the source; its figure is the
    slope (last − first group) next to a raw group, titled with the target and the readout."""
    import h5py
    outdir, summary = demo
    n, m, d = summary["nmd"]
    with h5py.File(outdir / "raw_ramp.h5") as fh:
        assert fh["SCI"].shape[:2] == (1, n) and fh.attrs["NFRAMES"] == m
        sci = fh["SCI"][0].astype(float)
        rate = fh["truth/rate"][...]
    diff = sci[-1] - sci[0]                                          # [ADU]
    r, c = np.unravel_index(np.argmax(rate - np.median(rate, axis=1, keepdims=True)), rate.shape)
    # the source stands out of the group difference: its 5 × 5 px mean is > 2σ of a pixel above the median
    assert diff[r - 2:r + 3, c - 2:c + 3].mean() > np.median(diff) + 2 * diff.std()
    fig = plotting.plot_ramp_group(outdir / "raw_ramp.h5", title="SN Ia, z = 1")
    images = [ax for ax in fig.axes if ax.get_label() != "<colorbar>"]
    bars = [ax.get_ylabel() for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert "slope" in images[0].get_title() and "raw group" in images[1].get_title()
    assert bars == ["slope [ADU/s]", "raw group [ADU]"]
    assert fig.get_suptitle().startswith("SN Ia, z = 1") and f"{n} groups of {m} frames" in fig.get_suptitle()
    from slicersim.app.demo import _ramp_title
    assert f"(n, m, d) = ({n}, {m}, {d}) × {summary['nramps']}" in _ramp_title(
        type("LazuliSupernova", (), {})(), summary, 1.0, 20.0)
