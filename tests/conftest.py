"""Shared fixtures: the reference material (``../shared/reference``) and its cases.

One loader for everything under the reference folder:

* :func:`reference_dir` — the folder, or None ($SLICERSIM_REFERENCE_DIR, else ../shared/reference);
* :func:`reference_case_ids` — the case ids listed in ``index.json`` (for parametrize at collection);
* :func:`load_reference_case` — ``(meta, arrays)`` of ``cases/<case>.json`` / ``.npz``;
* :func:`reference_config` — the Lazuli TOML list of a case's configuration ("cbe" / "eol");
* :func:`reference_target` — a :class:`LazuliTarget` built as the reference built the case;
* fixtures ``refdir`` (the folder), ``reference_case`` (a loader bound to it).

Tests that use ``refdir`` (directly or through ``reference_case``) get the ``reference``
marker automatically.  Without the material they are skipped, except with ``CI=true`` in
the environment, where a missing reference is a failure (CI must never silently skip them).

Markers ``needs_opencl`` (an OpenCL device with fp64) and ``needs_opencl_device`` (any OpenCL
device: single-precision kernels) follow the same rule: skipped without the device, a failure with
``CI=true``.  :func:`have_opencl` is the one probe (for tests that branch on the device rather than
needing it).  Tests live in ``tests/<subpackage>/test_<feature>.py`` mirroring ``slicersim/``
(``tests/core/`` for the top-level modules); this folder is on ``sys.path``, so tests import
``conftest`` and ``cube_oracle`` from any subfolder.
"""
import contextlib
import io
import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def reference_dir():
    """The reference folder, or None: $SLICERSIM_REFERENCE_DIR, else ../shared/reference."""
    env = os.environ.get("SLICERSIM_REFERENCE_DIR")
    path = Path(env) if env else ROOT.parent / "shared" / "reference"
    return path if (path / "cases").is_dir() and (path / "config").is_dir() else None


def _ci():
    return os.environ.get("CI", "").strip().lower() in ("1", "true", "yes")


def missing_reference(what="reference material"):
    """Skip (or, with CI=true, fail) a test whose reference material is absent."""
    where = os.environ.get("SLICERSIM_REFERENCE_DIR") or str(ROOT.parent / "shared" / "reference")
    msg = (f"{what} not found (looked in {where}; set $SLICERSIM_REFERENCE_DIR or provide "
           "../shared/reference): reference-reproduction tests need it")
    if _ci():
        pytest.fail(f"CI=true: {msg}", pytrace=False)
    pytest.skip(msg)


def reference_case_ids(path=None):
    """Case ids of ``index.json`` ([] without reference material)."""
    path = reference_dir() if path is None else path
    if path is None or not (path / "index.json").is_file():
        return []
    with open(path / "index.json", encoding="utf-8") as fh:
        return [c["case_id"] for c in json.load(fh)["cases"]]


def load_reference_case(refdir, case):
    """(meta dict, {name: array}) of one reference case."""
    with open(Path(refdir) / "cases" / f"{case}.json", encoding="utf-8") as fh:
        meta = json.load(fh)
    with np.load(Path(refdir) / "cases" / f"{case}.npz") as npz:
        arrays = {k: npz[k] for k in npz.files}
    return meta, arrays


def reference_config(refdir, configuration):
    """The reference's Lazuli TOML files for ``configuration`` ("cbe" or "eol"), in order."""
    cfg = [str(Path(refdir) / "config" / "lazuli_cbe.toml")]
    if configuration == "eol":
        cfg.append(str(Path(refdir) / "config" / "lazuli_eol.toml"))
    return cfg


def reference_target(refdir, meta, arrays, position=True):
    """LazuliTarget of a case, configured with the reference's own TOML files and the
    slicersim 1.0 conventions (the reference's gain and blur)."""
    from slicersim.targets import LazuliTarget
    inp = meta["inputs"]
    kwargs = {}
    if position:
        kwargs["position"] = tuple(inp.get("position_cells_x_y") or (0.0, 0.0))
    return LazuliTarget(arrays["input_lbda"], arrays["input_flux"], mag=inp["mag_passed_to_reference"],
                        band=inp.get("band", "bessellb"), config=reference_config(refdir, inp["configuration"]),
                        field=inp["field"], conventions="slicersim-1.0", **kwargs)


@pytest.fixture(scope="session")
def refdir():
    path = reference_dir()
    if path is None:
        missing_reference()
    return path


@pytest.fixture(scope="session")
def reference_case(refdir):
    """``reference_case(case_id)`` → (meta, arrays); a case missing from the folder skips/fails."""
    def load(case):
        if case not in reference_case_ids(refdir):
            missing_reference(f"reference case {case!r}")
        return load_reference_case(refdir, case)
    return load


def pytest_collection_modifyitems(config, items):
    for item in items:
        if "refdir" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.reference)


_OPENCL = {}


def have_opencl(fp64=True):
    """Whether an OpenCL device is available (with fp64 unless ``fp64=False``); probed once.

    The one place the suite asks; tests mark themselves ``@pytest.mark.needs_opencl`` (fp64) or
    ``@pytest.mark.needs_opencl_device`` (any OpenCL device, single-precision kernels) instead of
    writing their own guard."""
    if not _OPENCL:
        from slicersim.backends import opencl
        device = bool(opencl.is_available())
        _OPENCL["device"] = device
        _OPENCL["fp64"] = device and bool(opencl.device_supports_fp64())
    return _OPENCL["fp64" if fp64 else "device"]


def pytest_runtest_setup(item):
    """``needs_opencl`` / ``needs_opencl_device``: skip without such a device, except with CI=true
    in the environment, where it is a failure (CI must never silently skip the OpenCL tests)."""
    for marker, fp64, what in (("needs_opencl", True, "an OpenCL device with fp64"),
                               ("needs_opencl_device", False, "an OpenCL device")):
        if item.get_closest_marker(marker) is not None and not have_opencl(fp64):
            msg = f"no {what[3:] if what.startswith('an ') else what} (run `make opencl`): this test needs {what}"
            if _ci():
                pytest.fail(f"CI=true: {msg}", pytrace=False)
            pytest.skip(msg)


@pytest.fixture(autouse=True, scope="session")
def _temporary_table_cache(tmp_path_factory):
    """The whole suite caches projection tables in a temporary directory, never in ~/.cache."""
    saved = os.environ.get("SLICERSIM_CACHE")
    os.environ["SLICERSIM_CACHE"] = str(tmp_path_factory.mktemp("slicersim-cache"))
    yield
    if saved is None:
        os.environ.pop("SLICERSIM_CACHE", None)
    else:
        os.environ["SLICERSIM_CACHE"] = saved


def wide_spot_mapper(sigma_px=1.2, **kwargs):
    """The default Lazuli layout with Gaussian spots of ``sigma_px`` applied in full
    (``cube_blur_px=0``): slices share tail pixels and a cell's light is smooth on the pixel grid,
    for tests of that geometry (the default spots, 0.2–0.53 px, sit within the aberration the
    cubes already carry, so its projection adds no blur)."""
    from slicersim.instrument.mapper import SlicerMapper
    m = SlicerMapper.default(cube_blur_px=0.0, **kwargs)
    m.values[..., 2:] = float(sigma_px)
    return m


def small_slicer_mapper():
    """116 straight, slightly tilted and sheared traces (8 tiers of 15) on a 660 × 600 detector,
    λ 9000–10000 Å over 60 px, spot σ 0.6–1.2 px growing with λ; neighbouring slices share their
    spot tails (gap ~6 px).  A layout small enough for Monte Carlo tests of the reduction."""
    from slicersim.instrument.mapper import SlicerMapper
    phi, lam = np.array([-1.0, 0.0, 1.0]), np.array([9000.0, 9500.0, 10000.0])
    ids = np.arange(1, 117)
    k, tier = (ids - 1) % 15, (ids - 1) // 15
    u = ((lam - 9000.0) / 1000.0)[None, None, :]
    values = np.empty((116, 3, 3, 4))
    values[..., 0] = 20 + 38 * k[:, None, None] - 16 * phi[None, :, None] + 1.5 * u
    values[..., 1] = 15 + 80 * tier[:, None, None] + 60 * u + 0.8 * phi[None, :, None]
    values[..., 2] = 0.6 + 0.4 * u
    values[..., 3] = 0.7 + 0.5 * u
    return SlicerMapper(ids, phi, lam, values, detector_shape=(660, 600), table_cache=None)


def run_cli(*args, cwd=None, debug=False, env=None, **_subprocess_only):
    """``slicersim ARGS`` run in this process through :func:`slicersim.app.cli.main` (no interpreter
    start-up): a :class:`subprocess.CompletedProcess` with the exit status and the captured text.

    ``cwd`` and ``env`` (variables to set; None values unset) apply for the call only; ``debug``
    sets SLICERSIM_DEBUG=1 (unset otherwise, as for a user).  Keyword arguments meant for
    :func:`subprocess.run` (``timeout``, ``check``, ...) are ignored.  A few tests per command family
    keep a real subprocess so that the console entry point stays tested."""
    from slicersim.app.cli import main
    argv = [str(a) for a in args]
    changes = dict(env or {})
    changes["SLICERSIM_DEBUG"] = "1" if debug else None
    saved = {k: os.environ.get(k) for k in changes}
    out, err = io.StringIO(), io.StringIO()
    here = os.getcwd()
    try:
        for k, v in changes.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = str(v)
        if cwd is not None:
            os.chdir(cwd)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main(argv)
            except SystemExit as exc:           # argparse: --help (0), a usage error (2)
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    finally:
        os.chdir(here)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return subprocess.CompletedProcess(["slicersim", *argv], code, out.getvalue(), err.getvalue())


def flip_chunk_byte(path, dataset, offset=5, mask=0xFF):
    """Damage an HDF5 file as a bad disk or transfer would: XOR ``mask`` into one byte at ``offset``
    inside the first stored chunk of ``dataset`` (its Fletcher-32 checksum then fails)."""
    import h5py
    with h5py.File(path, "r") as fh:
        where = fh[dataset].id.get_chunk_info(0).byte_offset + offset
    with open(path, "r+b") as fh:
        fh.seek(where)
        byte = fh.read(1)
        fh.seek(where)
        fh.write(bytes([byte[0] ^ mask]))


#: λ bin edges [Å] (12 bins) and cube width [cells] of the small test layout's reductions
SMALL_EDGES = np.arange(9050.0, 9951.0, 75.0)
SMALL_NCOL = 24


def small_point_source():
    """(mapper, λ edges [Å], PSF cube, detector image [e-/s]) of a point source (400 e-/s per bin) in the
    narrow field of :func:`small_slicer_mapper`."""
    from slicersim.physics.psf import gaussian_psf_cells
    mapper = small_slicer_mapper()
    lbda = 0.5 * (SMALL_EDGES[1:] + SMALL_EDGES[:-1])
    sig = np.linspace(1.2, 1.8, lbda.size)
    iy, ix = np.indices((58, SMALL_NCOL)).reshape(2, -1)
    psf = gaussian_psf_cells(sig, 0.8 * sig, (58, SMALL_NCOL), (0.7, -1.4), (iy, ix)).reshape(lbda.size, 58,
                                                                                              SMALL_NCOL)
    return mapper, SMALL_EDGES.copy(), psf, mapper.project_fields(lbda, SMALL_EDGES, narrow=400.0 * psf)


def small_raw_ramps(path, nmd=(4, 2, 0)):
    """Write the raw ramps of :func:`small_point_source` to ``path`` (seed 2, read noise 5 e-, no dark);
    returns (path, mapper, PSF cube)."""
    from slicersim.products.ramps import simulate
    mapper, _, psf, image = small_point_source()
    simulate(image, nmd, seed=2, out=path, ron=5.0, dark=0.0, roic_glow=0.0, progress=False)
    return path, mapper, psf


def one_line_error(proc, *words):
    """Assert that a CLI run (:func:`run_cli`) failed as a user error (exit 2) with one line that
    contains each of ``words`` (case-insensitive)."""
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert len(lines) == 1 and lines[0].startswith("slicersim: error:"), proc.stderr
    for w in words:
        assert w.lower() in lines[0].lower(), lines[0]


def fake_campaign(root, redshifts=(0.3, 0.55, 0.8, 1.05), seed=0, reduced=True):
    """A campaign dataset (``root/dataset``: spec, catalog, simulated ``spectrum.h5`` per target) and, with
    ``reduced``, its reduction directory (``root/red``) whose ``reduced.h5`` hold each target's truth (a
    Lazuli SN Ia: :func:`slicersim.targets.truth.target_truth`) and a spectrum on 2-native-bin bins: the
    truth plus Gaussian noise of the ETC variance (position off by (0.3, −0.4) native cells).  Written in
    well under a second, without simulating ramps; returns (dataset, red or None, {target id: truth})."""
    from astropy.table import Table

    from slicersim.campaign.snia_model import snia_fluxes
    from slicersim.io.atomic import AtomicH5File
    from slicersim.io.dataset import Dataset
    from slicersim.io.target_truth import write_target_truth
    from slicersim.reduction.summary import rebin
    from slicersim.targets import LazuliTarget
    from slicersim.targets.truth import target_truth
    root = Path(root)
    src = Dataset(root / "dataset")
    src.initialise("# test\n", {"seed": seed, "observation": {"lbda_range": [4000.0, 6800.0], "frame": "rest"},
                                "products": {"spectrum": True, "ramps": True}}, {})
    red = Dataset(root / "red") if reduced else None
    if red is not None:
        red.initialise("# test\n", {"kind": "slicersim reduction", "mode": "spectra"}, {})
    lb = np.arange(3000.0, 20000.0, 10.0)
    rng = np.random.default_rng(seed)
    truths, rows, red_rows = {}, [], []
    for tid, z in enumerate(redshifts):
        field = "narrow" if z < 0.8 else "wide"
        target = LazuliTarget(lb, snia_fluxes(lb, np.array([z]), np.array([2.0]), np.array([-19.3]))[0],
                              redshift=z, field=field)
        nmd, nramps = (8, 8, 0), 4
        target.change_detector(nmd=nmd, nramps=nramps)
        truth = target_truth(target, nmd, nramps, target_id=tid, phase=2.0, peak_absmag=-19.3, source="hsiao")
        truths[tid] = truth
        lbda, signal, variance = target.get_spectrum()
        os.makedirs(src.product_dir(tid))
        with AtomicH5File(os.path.join(src.product_dir(tid), "spectrum.h5")) as f:
            for name, arr in (("lbda", lbda), ("signal", signal), ("variance", variance),
                              ("noisy", signal + rng.normal(size=signal.size) * np.sqrt(variance))):
                f.write(name, arr)
        src.write_timing(tid, 10.0 + tid)
        rows.append((tid, z, 2.0, -19.3, field, "done", f"products/t{tid:07d}/spectrum.h5"))
        if red is None:
            continue
        edges = truth.edges()[::2]
        flux = rebin(truth.edges(), truth.rate, edges)
        var = rebin(truth.edges(), truth.etc_variance, edges)
        os.makedirs(red.product_dir(tid))
        with AtomicH5File(os.path.join(red.product_dir(tid), "reduced.h5")) as f:
            f.write(f"spectra/{field}/FLUX", flux + rng.normal(size=flux.size) * np.sqrt(var))
            f.write(f"spectra/{field}/VAR", var)
            f.write(f"spectra/{field}/LBDA_EDGES", edges)
            f.set_attrs({f"SPECTRUM_{field.upper()}": json.dumps({"method": "forward", "converged": True,
                                                                  "position_native_cells": [0.3, -0.4],
                                                                  "chi2_dof_pixels": 1.01})})
            write_target_truth(f, truth)
        red.write_timing(tid, 5.0)
        red_rows.append((tid, "done", f"products/t{tid:07d}/reduced.h5"))
    src.write_catalog(Table(rows=rows, names=("target_id", "redshift", "phase", "peak_absmag", "field", "status",
                                              "spectrum_product")))
    if red is not None:
        red.write_catalog(Table(rows=red_rows, names=("target_id", "status", "product")))
    return Path(src.path), (Path(red.path) if red is not None else None), truths
