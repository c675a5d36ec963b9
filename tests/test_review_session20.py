"""Findings of the session-20 reviews (precision dial, forward weights), each a regression test."""
import os
import tomllib

import numpy as np
import pytest

from slicersim.backends import opencl
from slicersim.backends import precision as prec
from slicersim.errors import ConfigError, OpenCLForkError


@pytest.mark.needs_opencl
@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork only")
def test_forked_child_is_refused_not_silently_numpy():
    """P1: resolve_precision in a forked child silently returned NumPy (is_available swallowed the
    fork error); it must raise OpenCLForkError like resolve_backend."""
    prec.resolve_precision("auto", "auto", "cube")            # OpenCL live in this process
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(r)
        out = []
        for p in ("auto", "single", "double"):
            try:
                out.append(repr(prec.resolve_precision(p, "auto", "cube")))
            except OpenCLForkError:
                out.append("fork-error")
            except BaseException as exc:                      # noqa: BLE001
                out.append(type(exc).__name__)
        os.write(w, ";".join(out).encode())
        os._exit(0)
    os.close(w)
    got = os.read(r, 4096).decode().split(";")
    os.waitpid(pid, 0)
    assert got == ["fork-error"] * 3, got


def _readout():
    from slicersim.backends.cube import ReadoutConstants
    return ReadoutConstants(tint=100., gain=1.5, nramps=2, var_a=10., var_b=3., pixels_per_cell=2.,
                            dark=0.01, saturation=6e4)


@pytest.mark.needs_opencl
def test_detector_block_default_runs_without_fp64(monkeypatch):
    """P4: detector_block's default precision was "double", refused on a device without fp64."""
    from slicersim.backends.cube import detector_block
    monkeypatch.setattr(opencl, "device_supports_fp64", lambda: False)
    s, v = detector_block(np.array([1.0]), np.ones(4), np.ones(4), np.ones(4), _readout(), bins=(0, 4), nl=4,
                          lo=0, psf=np.full((4, 3, 5), 0.01))
    assert s.shape == (4, 3, 5) and np.all(np.isfinite(s))


@pytest.mark.needs_opencl
def test_cached_psf_cells_behaves_like_uncached_without_fp64(monkeypatch):
    """P5: the cache key resolved precision="double" even for the NumPy-only Gaussian psf_cells and
    raised where the uncached call computes."""
    from slicersim.backends import psf as P, psf_cache as pc
    monkeypatch.setattr(opencl, "device_supports_fp64", lambda: False)
    kw = dict(spatial_scale=0.04, guiding_sigma=0.01, instrumental_sigma=1.0, sigma_ref_arcsec=0.03,
              precision="double")
    args = (np.linspace(3700, 17000, 4), (3, 5), (0, 0), (np.array([0]), np.array([1])), "gaussian")
    raw = P.psf_cells(*args, **kw)
    np.testing.assert_array_equal(pc.psf_cells(*args, **kw), raw)


@pytest.mark.needs_opencl
def test_auto_stays_double_on_cpu_whatever_the_timing(monkeypatch):
    """P2: a timing on shared cores measured 0.3 … 19 and could flip "auto" to single for the whole
    process; CPUs are not timed (fp64 at half the SIMD lanes)."""
    if opencl.device_type() != "CPU":
        pytest.skip("CPU device only")
    monkeypatch.setattr(prec, "_ratios", {})
    monkeypatch.setattr(prec, "_measure_ratio", lambda: 18.9)
    assert prec.resolve_precision("auto", "auto", "cube") == ("opencl", "double")


@pytest.mark.needs_opencl
def test_cube_records_the_precision_it_ran_in():
    """P2: nothing recorded which precision a cube was computed in."""
    from slicersim import LazuliSupernova
    from slicersim.products.cube import build_cube
    sim = LazuliSupernova(0.5).simulation
    assert build_cube(sim, precision="single").paths["precision"] == "single"
    assert build_cube(sim, precision="double").paths["precision"] == "double"
    assert build_cube(sim, backend="numpy", precision="single").paths["precision"] == "double"


def test_cli_precision_override_is_written_to_the_dataset_spec(monkeypatch, tmp_path):
    """P3: `campaign run SPEC --precision single` stored the spec text without the override, so
    DIR/spec.toml could not resume its own dataset."""
    import argparse

    from slicersim.app import campaign_cli
    from slicersim.campaign import runner
    from slicersim.campaign.spec import parse_spec
    spec = tmp_path / "spec.toml"
    spec.write_text('seed = 1\n[population]\nkind = "snia"\nn = 1\n[products]\nspectrum = true\ncube = true\n'
                    'precision = "double"  # replaced\n[survey]\noverhead = 1.0\n')
    seen = {}

    def fake_run(spec, out, **kw):
        seen["spec"] = spec
        return dict(dataset=out, targets=1, done=1, failed=0, missing=0, computed=0, seconds=0.0)
    monkeypatch.setattr(runner, "run_campaign", fake_run)
    args = argparse.Namespace(spec=str(spec), out=str(tmp_path / "ds"), precision="single", workers=1,
                              scheduler=None, force=False, retry_failed=False, no_progress=True,
                              threads_per_worker=None, memory_per_task=256.0)
    assert campaign_cli.cmd_campaign_run(args) == 0
    used = seen["spec"]
    stored = parse_spec(tomllib.loads(used.text), text=used.text, base_dir=str(tmp_path))
    assert stored.canonical() == used.canonical()
    assert used.products["precision"] == "single" and used.survey["overhead"] == 1.0


def test_precision_leaves_the_identity_when_no_cube_is_written():
    """P3: products.precision changed the dataset identity even with cube = false."""
    from slicersim.campaign.spec import parse_spec, with_products
    doc = {"seed": 1, "population": {"kind": "snia", "n": 2}, "products": {"spectrum": True}}
    text = 'seed = 1\n[population]\nkind = "snia"\nn = 2\n[products]\nspectrum = true\n'
    base = parse_spec(doc, text=text)
    single = with_products(base, precision="single")
    assert single.products["precision"] == "single" and single.canonical() == base.canonical()
    with pytest.raises(ConfigError, match="products.precision"):
        with_products(base, precision="half")


@pytest.mark.needs_opencl
def test_noise_backend_refused_before_the_cube(monkeypatch):
    """P7: without fp64, build_cube(seed=…, backend="opencl") built the single-precision cube and only
    then refused the (double) noise draw.  The noise draw has single kernels now (runs without fp64:
    tests/test_noise_precision.py); a noise draw without them must still be refused before the cube."""
    from slicersim import LazuliSupernova
    from slicersim.backends import precision as prec
    from slicersim.errors import OpenCLUnavailableError
    from slicersim.products import cube as cube_module
    sim = LazuliSupernova(0.5).simulation
    monkeypatch.setattr(opencl, "device_supports_fp64", lambda: False)
    monkeypatch.delitem(prec.SINGLE_PRECISION_ERRORS, "noise")
    called = []
    monkeypatch.setattr(cube_module, "detector_chunk", lambda *a, **k: called.append(1))
    with pytest.raises(OpenCLUnavailableError):
        cube_module.build_cube(sim, psf_profile="airy", seed=3, backend="opencl")
    assert not called


# --------------------------------------------------------------------------- forward weights review
EDGES = np.linspace(9050.0, 9950.0, 13)
NCOL = 24


@pytest.fixture(scope="module")
def small():
    from conftest import small_slicer_mapper
    return small_slicer_mapper()


@pytest.fixture
def no_ramp_fit(monkeypatch):
    """Fail loudly if reduce_exposure reads any data."""
    from slicersim.reduction import ramp_fit

    def boom(*a, **k):
        raise AssertionError("fit_ramps called: options must be refused before any data are read")
    monkeypatch.setattr(ramp_fit, "fit_ramps", boom)


@pytest.mark.parametrize("bad", [
    dict(extraction="bogus"),
    dict(extraction="optimal", aperture=-1.0),
    dict(extraction="optimal", psf=np.ones((12, 12, 58, NCOL))),      # a template: GLS only
    dict(psf=np.ones((5, 58, NCOL))),                                  # wrong nλ
    dict(psf=np.zeros((12, 58, NCOL))),                                # no PSF light at all
    dict(position=(1e9, 0.0)),
    dict(rectify_method="drizzle", weights="forward"),                 # drizzle has no weights
    dict(psf="bogus"),
])
def test_options_refused_before_any_data_are_read(small, no_ramp_fit, bad):
    """F1, F6: reduce_exposure checked extraction options only after the ramp fit and two
    rectifications (20–26 s on the small layout, minutes on the detector); drizzle silently ignored
    explicit weights."""
    from slicersim.errors import ParameterError
    from slicersim.reduction import pipeline
    with pytest.raises(ParameterError):
        pipeline.reduce_exposure("unused.h5", mapper=small, lbda_edges=EDGES, ncol=NCOL, **bad)


@pytest.mark.parametrize("weights", [np.array(["model", "forward"]), np.array(["forward"]), ("forward",)])
def test_array_weights_are_a_parameter_error(small, no_ramp_fit, weights):
    """F2: an array of weights gave NumPy's ambiguous-truth error or was accepted."""
    from slicersim.errors import ParameterError
    from slicersim.reduction import pipeline
    with pytest.raises(ParameterError, match="weights"):
        pipeline.reduce_exposure("unused.h5", mapper=small, lbda_edges=EDGES, ncol=NCOL, weights=weights)


def test_reduced_file_records_the_weights(small, tmp_path):
    """F3: a reduced exposure did not say how its cubes were weighted, nor keep the pixel variance
    a template must be built with."""
    import h5py

    from slicersim.products.ramps import simulate
    from slicersim.reduction import pipeline
    from test_closed_loop import _scene
    lbda, cube, psf, F, B = _scene()
    img = small.project_fields(lbda, EDGES, narrow=cube * 20)
    raw = tmp_path / "raw.h5"
    simulate(img, (4, 2, 0), seed=1, out=str(raw), ron=5.0, dark=0.0, roic_glow=0.0)
    out = tmp_path / "red.h5"
    res = pipeline.reduce_exposure(str(raw), mapper=small, lbda_edges=EDGES, ncol=NCOL, psf=psf, out=str(out))
    with h5py.File(out) as f:
        assert f.attrs["WEIGHTS"] == "forward" and f.attrs["RECTIFY_METHOD"] == "lsq"
        np.testing.assert_allclose(f["rates/RECTIFY_VAR"][()], res["variance"].astype(np.float32))
