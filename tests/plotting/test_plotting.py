"""The low-level plotting layer (slicersim.plotting): what it imports, the figures it builds from
arrays (cube slices, raw-ramp groups) and its argument errors."""
import ast
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import slicersim  # noqa: E402
from slicersim import layers, plotting  # noqa: E402
from slicersim.errors import ParameterError  # noqa: E402

THIRD_PARTY = {"numpy", "matplotlib", "h5py", "__future__", "os"}


@pytest.fixture(autouse=True)
def close_figures():
    yield
    plt.close("all")


def test_plotting_imports_only_numpy_matplotlib_and_lower_layers():
    """Model objects (instrument, simulation, targets) call it: it must sit below them and above
    nothing it imports (the rest of the layer rules: tests/test_layers.py)."""
    assert layers.rank("io") < layers.rank("plotting") < layers.rank("instrument")
    root = Path(slicersim.__file__).parent / "plotting"
    for path in root.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module == "slicersim":    # from slicersim import x
                names = [f"slicersim.{a.name}" for a in node.names]
            else:
                names = [node.module] if isinstance(node, ast.ImportFrom) and node.module else []
            for name in names:
                top = name.split(".")
                if top[0] == "slicersim":
                    assert len(top) > 1 and layers.rank(top[1]) <= layers.rank("plotting"), (path.name, name)
                else:
                    assert top[0] in THIRD_PARTY, (path.name, name)


def test_app_plotting_keeps_its_names():
    from slicersim.app import plotting as app_plotting
    for name in ("plot_spectrum", "plot_variance_budget", "plot_instrument", "plot_ramp_group", "SOURCE_STYLES",
                 "show_fields", "show_psf_profiles", "show_slice_map", "save_figure"):
        assert hasattr(app_plotting, name), name
    assert app_plotting.plot_spectrum is plotting.plot_spectrum


def _ramp_file(path, ngroups=4, shape=(64, 80)):
    from slicersim.products.ramps import simulate
    rate = np.full(shape, 0.5)
    rate[30:34, 40:44] = 200.0                                          # the source [e-/s]
    return simulate(rate, nmd=(ngroups, 2, 0), nramps=1, seed=5, out=str(path), overwrite=True, progress=False)


def test_plot_ramp_group_slope_and_raw_group(tmp_path):
    path = _ramp_file(tmp_path / "r.h5")
    fig = plotting.plot_ramp_group(path, zoom=(20, 44, 30, 54), title="test target", origin=(1000, 2000))
    images = [ax for ax in fig.axes if ax.get_label() != "<colorbar>"]
    bars = [ax.get_ylabel() for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert len(images) == 3 and bars == ["slope [ADU/s]"] * 2 + ["raw group [ADU]"]
    assert [ax.get_xlabel() for ax in images] == ["detector column x [px]"] * 3
    import h5py
    with h5py.File(path) as fh:
        sci, tgroup = fh["SCI"][0].astype(float), float(fh.attrs["TGROUP"])
    zoomed = images[1].get_images()[0]
    assert np.allclose(zoomed.get_array(), (sci[-1] - sci[0])[20:44, 30:54] / (3 * tgroup))
    assert zoomed.get_extent() == [2030, 2054, 1020, 1044]              # detector pixels (origin)
    assert np.array_equal(images[2].get_images()[0].get_array(), sci[-1][20:44, 30:54])
    assert fig.get_suptitle().startswith("test target\n") and "4 groups of 2 frames" in fig.get_suptitle()
    whole = plotting.plot_ramp_group(path, zoom=(0, 64, 0, 80))          # zoom = file: no overview panel
    assert len([ax for ax in whole.axes if ax.get_label() != "<colorbar>"]) == 2
    with pytest.raises(ParameterError, match="group"):
        plotting.plot_ramp_group(path, group=0)
    with pytest.raises(ParameterError, match="region"):
        plotting.plot_ramp_group(path, zoom=(0, 999, 0, 10))


def test_source_zoom_centres_on_the_source_not_the_bright_rows():
    rate = np.ones((400, 600))
    rate[:, 500:] = 50.0                                                # bright, smooth columns (thermal)
    rate[:50] = 80.0                                                    # a bright band of rows
    rate[200, 100] = 500.0
    r0, r1, c0, c1 = plotting.source_zoom(rate, half=(20, 30))
    assert (r0, r1, c0, c1) == (180, 220, 70, 130)


def test_plot_cube_slices_errors():
    class Sim:
        lbda = np.linspace(5000.0, 6000.0, 5)
        spectrograph = type("S", (), {"shape": (3, 4), "spatial_scale": 0.1})()
    cube = np.arange(60.0).reshape(5, 3, 4)
    fig = plotting.plot_cube_slices(Sim(), cube, lbda=[5500.0], unit="e-/s")
    assert fig.axes[1].get_ylabel() == "signal [e-/s]"
    assert np.allclose(fig.axes[0].get_images()[0].get_extent(), [-0.2, 0.2, -0.15, 0.15])
    with pytest.raises(ParameterError, match="cube"):
        plotting.plot_cube_slices(Sim(), cube[:, :, :, None])
    with pytest.raises(ParameterError, match="lbda"):
        plotting.plot_cube_slices(Sim(), cube, lbda=[9000.0])
    with pytest.raises(ParameterError, match="ax"):
        plotting.plot_cube_slices(Sim(), cube, lbda=[5500.0, 5600.0], ax=plt.subplots()[1])


def test_plot_ramp_group_refuses_a_file_declaring_data_it_does_not_hold(tmp_path):
    """The ramp plot read SCI with h5py directly: a forged file was 'out of memory' without its name."""
    import h5py

    from slicersim.errors import RampFileError
    with h5py.File(tmp_path / "forged.h5", "w") as fh:
        fh.create_dataset("SCI", shape=(1, 4, 100000, 100000), dtype="u2", chunks=(1, 1, 64, 64))
    with pytest.raises(RampFileError, match=r"forged.h5: dataset SCI declares shape \(1, 4, 100000, 100000\)"):
        plotting.plot_ramp_group(tmp_path / "forged.h5")


def test_plotting_arguments_are_checked_before_anything_is_drawn(tmp_path, monkeypatch):
    """ax='foo' was an AttributeError, savefile=3 a TypeError, savefile='.' wrote '..png', and show_cube with
    400 wavelengths ran for more than 5 min (its cube computed first): each is now one ParameterError."""
    class Sim:
        lbda = np.linspace(5000.0, 6000.0, 400)
        spectrograph = type("S", (), {"shape": (3, 4), "spatial_scale": 0.1})()

        def get_cube(self):
            raise AssertionError("the cube must not be computed for a refused request")
    sim = Sim()
    with pytest.raises(ParameterError, match=r"lbda: at most 12 wavelengths \(one panel each\), got 400"):
        plotting.plot_cube_slices(sim, lbda=sim.lbda)
    with pytest.raises(ParameterError, match=r"ax must be a matplotlib Axes or a sequence of them, got 'foo'"):
        plotting.plot_cube_slices(sim, lbda=[5500.0], ax="foo")
    with pytest.raises(ParameterError, match=r"ax must be a matplotlib Axes.*got 'foo'"):
        plotting.plot_curves([1.0, 2.0], {"a": [1.0, 2.0]}, "y", ax="foo")
    with pytest.raises(ParameterError, match=r"savefile must be a file path .* got 3"):
        plotting.plot_cube_slices(sim, lbda=[5500.0], savefile=3)
    monkeypatch.chdir(tmp_path)
    for folder in (".", str(tmp_path), "sub/"):
        with pytest.raises(ParameterError, match=r"savefile .* names a folder, not a file"):
            plotting.plot_curves([1.0, 2.0], {"a": [1.0, 2.0]}, "y", savefile=folder)
    with pytest.raises(ParameterError, match=r"the folder .*nowhere.* does not exist"):
        plotting.plot_curves([1.0, 2.0], {"a": [1.0, 2.0]}, "y", savefile="nowhere/f.png")
    assert list(tmp_path.iterdir()) == []                                  # nothing written, no '..png'
    fig = plotting.plot_curves([1.0, 2.0], {"a": [1.0, 2.0]}, "y", savefile="ok.png")
    assert (tmp_path / "ok.png").stat().st_size > 0 and fig is not None
