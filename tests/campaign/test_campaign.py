"""Campaigns on Dask: real LocalCluster and real `dask scheduler` / `dask worker` processes.

One small campaign (6 SNe Ia, spectra + noisy Airy cubes) is run once with 1 worker as the
reference; every other run (2 workers, an external scheduler, a run killed with SIGKILL and
resumed, a corrupted dataset repaired) must give the same files, byte for byte.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from slicersim.errors import ConfigError, DatasetError
import tomllib
from astropy.table import Table

from conftest import one_line_error, run_cli

SPEC = """\
seed = 11
name = "test campaign"
[population]
kind = "snia"
n = 6
redshift = {distribution = "uniform", min = 0.3, max = 1.2}
[observation]
snr = 8
psf_profile = "airy"
[products]
spectrum = true
cube = true
"""

BIN = Path(sys.executable).parent


def _files(root):
    """{relative path: sha256} of every non-hidden file under root."""
    out = {}
    for path in sorted(Path(root).rglob("*")):
        rel = path.relative_to(root)
        if path.is_file() and not any(part.startswith(".") for part in rel.parts):
            out[str(rel)] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def _cli(*args, **kwargs):
    return subprocess.run([str(BIN / "slicersim"), *args], capture_output=True, text=True, **kwargs)


@pytest.fixture(scope="module")
def spec_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("spec") / "campaign.toml"
    path.write_text(SPEC)
    return path


@pytest.fixture(scope="module")
def reference(spec_path, tmp_path_factory):
    """The campaign run once, uninterrupted, on a 1-worker LocalCluster."""
    from slicersim.campaign.runner import run_campaign
    out = tmp_path_factory.mktemp("ref") / "dataset"
    res = run_campaign(spec_path, out, workers=1, progress=False)
    assert (res["done"], res["failed"], res["missing"], res["computed"]) == (6, 0, 0, 6)
    return out


@pytest.mark.slow
def test_reference_dataset_layout_and_catalog(reference, spec_path):
    from astropy.table import Table
    files = _files(reference)
    assert {"spec.toml", "spec.json", "versions.json", "catalog.ecsv"} <= set(files)
    assert (reference / "spec.toml").read_text() == spec_path.read_text()      # the spec as given
    cat = Table.read(reference / "catalog.ecsv", format="ascii.ecsv")
    assert list(cat["target_id"]) == list(range(6))
    assert set(cat["status"]) == {"done"}
    for row in cat:
        for product in ("spectrum", "cube"):
            path = reference / row[f"{product}_product"]
            assert hashlib.sha256(path.read_bytes()).hexdigest() == row[f"{product}_sha256"]
        assert int(row["n"]) >= 1 and float(row["exposure_time"]) > 0 and float(row["snr"]) >= 8 * (1 - 1e-9)
    # seeds: distinct per target, from (campaign seed, target id) only
    from slicersim.campaign.products import target_seeds
    noise, ramps = target_seeds(11, np.arange(6))
    assert list(cat["seed"]) == [int(s) for s in noise] and len(set(noise)) == 6
    assert target_seeds(11, [5, 2])[0].tolist() == [int(noise[5]), int(noise[2])]


def test_cube_products_are_float32_noisy_airy_cubes(reference):
    import h5py
    with h5py.File(reference / "products" / "t0000003" / "cube.h5", "r") as f:
        sig, var, noisy = f["signal"][...], f["variance"][...], f["noisy"][...]
        assert sig.dtype == np.float32 and f.attrs["psf_profile"] == "airy"
        seed = int(f.attrs["seed"])
    ok = var > 0
    pulls = (noisy[ok].astype(float) - sig[ok]) / np.sqrt(var[ok].astype(float))
    # 3.4e5 Gaussian pulls: mean within 5σ/√N, width 1 within 5·√(2/N)·... (float32 rounding ≪ 1e-3)
    assert abs(pulls.mean()) < 5 / np.sqrt(pulls.size) + 1e-3
    assert abs(pulls.std() - 1) < 5 / np.sqrt(2 * pulls.size) + 1e-3
    assert seed > 0


@pytest.mark.slow
def test_two_workers_give_identical_files(reference, spec_path, tmp_path):
    from slicersim.campaign.runner import run_campaign
    res = run_campaign(spec_path, tmp_path / "d2", workers=2, progress=False)
    assert res["done"] == 6
    assert _files(tmp_path / "d2") == _files(reference)
    # resuming a complete dataset computes nothing and changes nothing
    res = run_campaign(spec_path, tmp_path / "d2", workers=2, progress=False)
    assert res["computed"] == 0 and _files(tmp_path / "d2") == _files(reference)


@pytest.mark.slow
def test_damaged_dataset_is_detected_and_repaired(reference, spec_path, tmp_path):
    from slicersim.campaign.runner import campaign_status, run_campaign
    d = tmp_path / "damaged"
    shutil.copytree(reference, d)
    cube = d / "products" / "t0000001" / "cube.h5"
    data = bytearray(cube.read_bytes())
    data[len(data) // 2] ^= 0xFF                                   # one flipped byte: corrupted
    cube.write_bytes(bytes(data))
    spec = d / "products" / "t0000004" / "spectrum.h5"
    spec.write_bytes(spec.read_bytes()[:1000])                     # truncated
    (d / "records" / "t0000005.json").unlink()                     # never finished
    st = campaign_status(d)
    assert (st["done"], st["missing"], st["failed"]) == (3, 3, 0)
    reasons = dict(st["missing_targets"])
    assert "checksum" in reasons[1] and "truncated" in reasons[4] and "no record" in reasons[5]
    res = run_campaign(spec_path, d, workers=1, progress=False)
    assert res["computed"] == 3
    assert _files(d) == _files(reference)
    proc = _cli("campaign", "status", str(d))
    assert proc.returncode == 0 and "6 done, 0 missing, 0 failed" in proc.stdout


class _ExternalCluster:
    """A real `dask scheduler` and `dask worker` processes on 127.0.0.1 (each in its own session)."""

    def __init__(self, tmp_path, nworkers=2):
        self.sched_file = tmp_path / "scheduler.json"
        self.env = dict(os.environ, POCL_MAX_PTHREAD_COUNT="1")
        self.procs = [self._start("scheduler", "--host", "127.0.0.1", "--port", "0",
                                  "--no-dashboard", "--scheduler-file", str(self.sched_file))]
        deadline = time.time() + 60
        while not self.sched_file.exists() and time.time() < deadline:
            time.sleep(0.2)
        self.address = json.loads(self.sched_file.read_text())["address"]
        self.workers = [self._start("worker", self.address, "--nthreads", "1", "--nworkers", "1",
                                    "--no-dashboard", "--host", "127.0.0.1") for _ in range(nworkers)]
        from distributed import Client
        with Client(self.address, timeout="30s") as client:
            client.wait_for_workers(nworkers, timeout=60)

    def _start(self, *args):
        proc = subprocess.Popen([str(BIN / "dask"), *args], stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, env=self.env, start_new_session=True)
        self.procs = getattr(self, "procs", []) + [proc]
        return proc

    def close(self):
        for p in self.procs[::-1]:
            try:
                os.killpg(p.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
        for p in self.procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)


@pytest.mark.slow
def test_external_scheduler_and_workers(reference, spec_path, tmp_path):
    """A real `dask scheduler` and two `dask worker` processes on 127.0.0.1, via --scheduler."""
    cluster = _ExternalCluster(tmp_path)
    try:
        assert cluster.address.startswith("tcp://127.0.0.1:")
        out = tmp_path / "ext"
        proc = _cli("campaign", "run", str(spec_path), "--out", str(out), "--scheduler", cluster.address,
                    "--no-progress", timeout=300)
        assert proc.returncode == 0, proc.stderr
        assert "6 done, 0 failed, 0 missing" in proc.stdout
        assert _files(out) == _files(reference)
    finally:
        cluster.close()


@pytest.mark.slow
def test_worker_killed_mid_campaign(reference, spec_path, tmp_path):
    """kill -9 of one worker (and its nanny) while it works: the other finishes the campaign."""
    cluster = _ExternalCluster(tmp_path)
    out = tmp_path / "wk"
    try:
        client = subprocess.Popen([str(BIN / "slicersim"), "campaign", "run", str(spec_path), "--out", str(out),
                                   "--scheduler", cluster.address, "--no-progress"],
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        deadline = time.time() + 240
        while time.time() < deadline and client.poll() is None:
            if (out / "records").is_dir() and list((out / "records").glob("t*.json")):
                break
            time.sleep(0.05)
        os.killpg(cluster.workers[0].pid, signal.SIGKILL)
        stdout, stderr = client.communicate(timeout=300)
        assert client.returncode == 0, stderr
        assert "6 done, 0 failed, 0 missing" in stdout
        assert _files(out) == _files(reference)
    finally:
        cluster.close()


@pytest.mark.slow
def test_kill9_then_resume_equals_uninterrupted_run(reference, spec_path, tmp_path):
    out = tmp_path / "killed"
    proc = subprocess.Popen([str(BIN / "slicersim"), "campaign", "run", str(spec_path), "--out", str(out),
                             "--workers", "2", "--no-progress"], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.time() + 240
        while time.time() < deadline and proc.poll() is None:
            if (out / "records").is_dir() and len(list((out / "records").glob("t*.json"))) >= 2:
                break
            time.sleep(0.05)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)                 # the client, its scheduler and its workers
        proc.wait()
    done_before = len(list((out / "records").glob("t*.json")))
    assert 1 <= done_before < 6, "the run must be interrupted part-way for this test to mean anything"
    time.sleep(0.5)
    res = _cli("campaign", "run", str(spec_path), "--out", str(out), "--workers", "2", "--no-progress",
               timeout=300)
    assert res.returncode == 0, res.stderr
    computed = int(res.stdout.split("(")[1].split()[0])
    assert computed <= 6 - done_before + 2                 # only what was missing (+ targets in flight)
    assert _files(out) == _files(reference)
    assert not [p for p in out.rglob(".*tmp-*")]            # no temporaries left behind


# --------------------------------------------------------------------------- failures
class _FailingPopulation:
    """Wraps a population; target 2's spectrum raises (a target that cannot be simulated)."""

    def __init__(self, inner):
        self.inner = inner

    def __getattr__(self, name):
        if name == "inner":                    # while unpickling, before __dict__ is filled
            raise AttributeError(name)
        return getattr(self.inner, name)

    def spectrum(self, row, lbda):
        if int(row["target_id"]) == 2:
            raise RuntimeError("synthetic failure of target 2")
        return self.inner.spectrum(row, lbda)


@pytest.mark.slow
def test_failing_target_is_recorded_and_does_not_stop_the_campaign(spec_path, tmp_path):
    import cloudpickle

    from slicersim.campaign.runner import campaign_status, run_campaign
    from slicersim.campaign.spec import load_spec
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    spec = load_spec(spec_path)
    spec.products["cube"] = False
    spec.population = _FailingPopulation(spec.population)
    res = run_campaign(spec, tmp_path / "f", workers=1, progress=False)
    assert (res["done"], res["failed"]) == (5, 1)
    st = campaign_status(tmp_path / "f")
    assert st["failed_targets"][0][0] == 2 and "synthetic failure" in st["failed_targets"][0][1]
    assert not list((tmp_path / "f" / "products" / "t0000002").glob("*.h5"))


# --------------------------------------------------------------------------- bad input
@pytest.mark.slow
@pytest.mark.parametrize("edit, message", [
    (lambda s: s.replace("snr = 8", "snr = 8\nsnrr = 3"), "observation.'snrr'"),
    (lambda s: s.replace("cube = true", "cube = true\nspectra = true"), "products.'spectra'"),
    (lambda s: s + "\n[extra]\nx = 1\n", "'extra'"),
    (lambda s: s.replace("n = 6", "n = 0"), "n"),
    (lambda s: s.replace("min = 0.3, max = 1.2", "min = 1.2, max = 0.3"), "min"),
    (lambda s: s.replace("min = 0.3", "min = -0.3"), "negative"),
    (lambda s: s.replace("snr = 8", "snr = -8"), "observation.snr"),
    (lambda s: s.replace("seed = 11", "seed = 1.5"), "seed"),
    (lambda s: s.replace("spectrum = true\ncube = true", "spectrum = false"), "nothing"),
    (lambda s: s.replace('psf_profile = "airy"', 'psf_profile = "moffat"'), "psf_profile"),
    (lambda s: s + "\n[survey]\nefficiency = 1.5\n", "survey.efficiency"),
    (lambda s: s.replace("[products]", "[products"), "TOML"),
    (lambda s: s.replace("cube = true", 'cube = true\nprecision = "half"'), "products.precision"),
])
def test_bad_specs_give_one_clear_error_and_write_nothing(tmp_path, edit, message):
    spec = tmp_path / "bad.toml"
    spec.write_text(edit(SPEC))
    out = tmp_path / "never"
    proc = _cli("campaign", "run", str(spec), "--out", str(out))
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("slicersim: error:"), proc.stderr
    assert message.lower() in lines[0].lower(), lines[0]
    assert not out.exists()


def test_output_path_that_is_a_file_and_changed_spec_are_refused(reference, spec_path, tmp_path):
    from slicersim.campaign.runner import run_campaign
    afile = tmp_path / "file"
    afile.write_text("x")
    with pytest.raises(DatasetError, match="is a file"):
        run_campaign(spec_path, afile, workers=1, progress=False)
    d = tmp_path / "copy"
    shutil.copytree(reference, d)
    before = _files(d)
    changed = tmp_path / "changed.toml"
    changed.write_text(SPEC.replace("snr = 8", "snr = 9"))
    proc = _cli("campaign", "run", str(changed), "--out", str(d))
    assert proc.returncode == 2 and "different spec" in proc.stderr and "observation.snr" in proc.stderr
    assert _files(d) == before                                  # nothing touched
    notds = tmp_path / "notds"
    notds.mkdir()
    (notds / "mine.txt").write_text("keep")
    with pytest.raises(DatasetError, match="not a slicersim dataset"):
        run_campaign(spec_path, notds, workers=1, progress=False)


def test_two_clients_on_one_dataset_are_refused(reference, spec_path, tmp_path):
    from slicersim.campaign.runner import run_campaign
    from slicersim.io.dataset import Dataset
    d = tmp_path / "locked"
    shutil.copytree(reference, d)
    with Dataset(d):
        with pytest.raises(DatasetError, match="in use"):
            run_campaign(spec_path, d, workers=1, progress=False)


def test_unknown_population_key_is_named(tmp_path):
    from slicersim.campaign.spec import parse_spec
    import tomllib
    doc = tomllib.loads(SPEC.replace("n = 6", "n = 6\nzmax = 3"))
    with pytest.raises(ConfigError, match="zmax"):
        parse_spec(doc)


def test_status_of_non_dataset(tmp_path):
    proc = run_cli("campaign", "status", str(tmp_path / "nope"))
    assert proc.returncode == 2 and "no such dataset" in proc.stderr


def test_status_of_a_spec_file_says_what_status_takes_and_how_to_run_the_spec(tmp_path):
    from slicersim.campaign.runner import campaign_status
    spec = tmp_path / "spec.toml"
    spec.write_text(SPEC)
    proc = run_cli("campaign", "status", spec)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    for needle in (f"{spec} is a file", "'slicersim campaign status' takes a dataset directory",
                   f"'slicersim campaign run {spec} --out DIR'"):
        assert needle in lines[0], (needle, lines[0])
    assert "no such" not in lines[0]
    with pytest.raises(DatasetError, match=r"spec.toml is a file, not a dataset directory \(.*looks like a campaign "
                                           r"spec; run_campaign\(spec, out\) writes the dataset directory out\)"):
        campaign_status(spec)
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    proc = run_cli("campaign", "status", fifo)
    assert proc.returncode == 2 and "is not a directory (a FIFO, device or socket)" in proc.stderr, proc.stderr


def test_run_of_a_dataset_directory_says_what_run_takes(tmp_path):
    dataset = tmp_path / "ds"
    dataset.mkdir()
    (dataset / "spec.json").write_text("{}")
    proc = run_cli("campaign", "run", dataset, "--out", tmp_path / "other")
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    for needle in (f"{dataset} is a dataset directory, not a campaign spec", "takes SPEC.toml",
                   f"'slicersim campaign run SPEC.toml --out {dataset}'", f"'slicersim campaign status {dataset}'"):
        assert needle in lines[0], (needle, lines[0])
    assert not (tmp_path / "other").exists()


@pytest.mark.parametrize("kind", ["fifo", "zero"])
def test_a_spec_configuration_that_is_not_a_regular_file_is_named_so(tmp_path, kind):
    from slicersim.campaign.spec import parse_spec
    path = tmp_path / "c.toml"
    if kind == "fifo":
        os.mkfifo(path)
    else:
        path.symlink_to("/dev/zero")
    doc = tomllib.loads(SPEC)
    doc["observation"]["config"] = str(path)
    with pytest.raises(ConfigError, match=rf"observation.config: {path} is not a regular file"):
        parse_spec(doc)


def _one_target(tmp_path, products):
    """One low-SNR target (short readout) of SPEC with the ``[products]`` lines ``products``, run in-process:
    (record, dataset, its product folder)."""
    import tomllib

    from slicersim.campaign.products import run_target
    from slicersim.campaign.runner import plan_campaign
    from slicersim.campaign.spec import parse_spec
    from slicersim.io.dataset import Dataset
    text = SPEC.replace("n = 6", "n = 1").replace("snr = 8", "snr = 1").replace("spectrum = true\ncube = true",
                                                                                products)
    spec = parse_spec(tomllib.loads(text), text=text)
    cat, _ = plan_campaign(spec)
    ds = Dataset(tmp_path / "r")
    digest = ds.initialise(spec.text, spec.canonical(), {}, False)
    row = {k: (cat[0][k].item() if hasattr(cat[0][k], "item") else cat[0][k]) for k in cat.colnames}
    rec = run_target(spec, row, ds.path, digest)
    assert rec["status"] == "done", rec.get("error")
    return rec, ds, row, tmp_path / "r" / "products" / "t0000000"


@pytest.mark.slow
def test_ramps_and_detector_image_products(tmp_path):
    """One low-SNR target (short readout) with the full-detector products, in-process."""
    import h5py

    from slicersim.io.rampfile import read_ramps
    rec, ds, row, pdir = _one_target(tmp_path, 'spectrum = false\ndetector_image = true\nramps = true\n'
                                               'compression = "lz4"')
    assert ds.verify(rec) == ""
    sci, gdq, pixdq, attrs = read_ramps(pdir / "ramps.h5")
    n, m, d, nramps = rec["readout"]
    assert sci.shape == (nramps, n, 4096, 4096) and int(attrs["SEED"]) == row["ramp_seed"]
    assert int(attrs["NFRAMES"]) == m
    with h5py.File(pdir / "detector_image.h5", "r") as f:
        rate = f["rate"][...]
    assert rate.dtype == np.float32 and rate.shape == (4096, 4096) and rate.max() > 0


@pytest.mark.parametrize("effects, message", [("lazuli", None), ("cosmic_rays, ipc", None), ("none", None),
                                             ("moonlight", "products.effects: "), (3, "products.effects")])
def test_a_campaign_chooses_the_detector_effects_of_its_ramps(effects, message):
    """`[products] effects` takes what `slicersim ramp --effects` takes (campaigns could only make ramps
    without detector effects: "unknown key products.'effects'"); "none" keeps the identity of earlier datasets."""
    import tomllib

    from slicersim.campaign.spec import parse_spec
    base = SPEC.replace("spectrum = true\ncube = true", "spectrum = false\nramps = true")
    text = base.replace("ramps = true", f"ramps = true\neffects = {effects!r}".replace("'", '"'))
    if message:
        with pytest.raises(ConfigError, match=message):
            parse_spec(tomllib.loads(text), text=text)
        return
    spec = parse_spec(tomllib.loads(text), text=text)
    plain = parse_spec(tomllib.loads(base), text=base)
    if effects == "none":
        assert spec.canonical() == plain.canonical()
    else:
        assert spec.canonical()["products"]["effects"] == effects and spec.canonical() != plain.canonical()
    with pytest.raises(ConfigError, match="applies to the raw ramps: set products.ramps = true"):
        bad = SPEC.replace("cube = true", 'cube = true\neffects = "lazuli"')
        parse_spec(tomllib.loads(bad), text=bad)


def test_ramp_format_jwst_uncal_spec():
    """products.ramp_format: "jwst-uncal" enters the identity (the default "hdf5" does not), needs
    uncompressed ramps; anything else is one clear error."""
    import tomllib

    from slicersim.campaign.spec import parse_spec
    base = SPEC.replace("spectrum = true\ncube = true", 'spectrum = false\nramps = true\neffects = "lazuli"')
    fits = base.replace("ramps = true", 'ramps = true\nramp_format = "jwst-uncal"')
    plain = parse_spec(tomllib.loads(base), text=base)
    same = base.replace("ramps = true", 'ramps = true\nramp_format = "hdf5"')
    assert parse_spec(tomllib.loads(same), text=same).canonical() == plain.canonical()
    assert parse_spec(tomllib.loads(fits), text=fits).canonical()["products"]["ramp_format"] == "jwst-uncal"
    for bad, says in ((fits.replace("ramp_format", 'compression = "gzip"\nramp_format'), "uncompressed"),
                      (base.replace("ramps = true", 'ramps = true\nramp_format = "fits"'), "ramp_format")):
        with pytest.raises(ConfigError, match=says):
            parse_spec(tomllib.loads(bad), text=bad)


@pytest.mark.slow
def test_campaign_level1b_ramps_validate_and_fit(tmp_path):
    """`ramp_format = "jwst-uncal"` with `effects = "lazuli"`: the target's ramps.fits opens in
    stdatamodels (only the four instrument names outside JWST's enumerations) and our reduction fits it."""
    import warnings

    from stdatamodels.jwst import datamodels
    _, _, _, pdir = _one_target(tmp_path, 'spectrum = false\nramps = true\neffects = "lazuli"\n'
                                          'ramp_format = "jwst-uncal"')
    path = pdir / "ramps.fits"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = datamodels.RampModel(str(path))
        model.validate()
    assert {str(w.message).split()[2] for w in caught} <= {"meta.instrument.name", "meta.instrument.detector",
                                                           "meta.exposure.type", "meta.exposure.readpatt"}
    assert model.data.shape[-2:] == (4096, 4096) and not model.groupdq.any()


@pytest.mark.slow
def test_campaign_ramps_carry_the_effects_asked_for(tmp_path):
    """`effects = "lazuli"`: the target's ramps hold the effects and their truth (cosmic rays, ...)."""
    import h5py

    _, _, _, pdir = _one_target(tmp_path, 'spectrum = false\nramps = true\neffects = "lazuli"')
    with h5py.File(pdir / "ramps.h5", "r") as fh:
        enabled = json.loads(fh.attrs["EFFECTS"])["effects"]["enabled"]
        assert {"cosmic_rays", "ipc", "nonlinearity", "correlated_noise"} <= set(enabled)
        assert "cosmic_rays" in fh["truth"]


def test_spec_without_seed_draws_one_records_it_and_resumes_with_it(tmp_path):
    """seed follows the package rule: an integer, or none given → a fresh seed drawn and written into the
    spec's text (the dataset's spec.toml repeats the campaign); the same seedless spec resumes the dataset
    it made with the recorded seed (each load draws another one)."""
    import tomllib

    from slicersim.campaign.runner import _resumed_seed
    from slicersim.campaign.spec import load_spec, parse_spec, seed_was_drawn, with_seed
    from slicersim.io.dataset import Dataset
    path = tmp_path / "noseed.toml"
    path.write_text(SPEC.replace("seed = 11\n", ""))
    first, second = load_spec(path), load_spec(path)
    assert seed_was_drawn(first) and first.seed != second.seed and 0 <= first.seed < 2**64
    assert first.text.startswith(f"seed = {first.seed}")
    stored = parse_spec(tomllib.loads(first.text), text=first.text)        # the dataset's spec.toml
    assert stored.seed == first.seed and stored.canonical() == first.canonical()
    assert with_seed(second, first.seed).canonical() == first.canonical()
    ds = Dataset(Dataset.check_path(tmp_path / "d"))
    with ds:
        ds.initialise(first.text, first.canonical(), {})
    assert _resumed_seed(second, ds, force=False).seed == first.seed
    assert _resumed_seed(second, ds, force=True).seed == second.seed       # --force: a new campaign
    path.write_text(SPEC.replace("seed = 11\n", "").replace("snr = 8", "snr = 9"))
    other = load_spec(path)
    assert _resumed_seed(other, ds, force=False).seed == other.seed        # another spec: refused later
    with pytest.raises(ConfigError, match="seed"):
        parse_spec(tomllib.loads(SPEC.replace("seed = 11", "seed = -1")))


@pytest.mark.parametrize("no_progress,expected", [(True, False), (False, None)])
def test_campaign_run_progress_flag(monkeypatch, tmp_path, no_progress, expected):
    """``campaign run --no-progress`` passes progress=False; without it progress=None (the package's
    default: a bar only when stderr is a terminal), no longer always True."""
    import argparse

    from slicersim.app import campaign_cli
    from slicersim.campaign import runner
    seen = {}

    def fake_run(spec, out, **kw):
        seen.update(kw)
        return dict(dataset=out, targets=1, done=1, failed=0, missing=0, computed=0, seconds=0.0)
    monkeypatch.setattr(runner, "run_campaign", fake_run)
    args = argparse.Namespace(spec=str(tmp_path / "spec.toml"), out=str(tmp_path / "ds"), precision=None, workers=1,
                              scheduler=None, force=False, retry_failed=False, no_progress=no_progress,
                              threads_per_worker=None, memory_per_task=256.0)
    assert campaign_cli.cmd_campaign_run(args) == 0
    assert seen["progress"] is expected


@pytest.mark.parametrize("retry_failed", [False, True])
def test_campaign_run_with_failures_says_how_to_run_them_again(monkeypatch, tmp_path, capsys, retry_failed):
    """After a full disk, a rerun printed "0 computed ... 40 failed" and nothing about --retry-failed."""
    import argparse

    from slicersim.app import campaign_cli
    from slicersim.campaign import runner
    monkeypatch.setattr(runner, "run_campaign", lambda spec, out, **kw: dict(
        dataset=out, targets=3, done=1, failed=2, missing=0, computed=0, seconds=0.0))
    args = argparse.Namespace(spec=str(tmp_path / "spec.toml"), out=str(tmp_path / "ds"), precision=None, workers=1,
                              scheduler=None, force=False, retry_failed=retry_failed, no_progress=True,
                              threads_per_worker=None, memory_per_task=256.0)
    assert campaign_cli.cmd_campaign_run(args) == 1
    out = capsys.readouterr().out
    assert ("2 failed target(s) are kept as failed on a rerun" in out and "--retry-failed runs them again" in out
            and f"slicersim campaign status {tmp_path / 'ds'}" in out) != retry_failed, out


INTRUDER = """\
import sys
from distributed import Client, Security
kw = {"security": Security.temporary()} if sys.argv[2] == "own-credentials" else {}
try:
    client = Client(sys.argv[1], timeout="3s", **kw)
    client.submit(open, sys.argv[3], "w").result(timeout=10)     # would write a file as the campaign's user
except Exception as exc:
    print("refused", type(exc).__name__)
    sys.exit(0)
print("ACCEPTED")
sys.exit(1)
"""


def _http_sockets(server):
    return [s.getsockname() for s in server._sockets.values()]


def test_embedded_cluster_uses_tls_refuses_other_processes_and_has_no_dashboard(tmp_path):
    """Adversarial finding: the embedded cluster listened on TCP without authentication (a task submitted
    from another process ran as the campaign's user) and served its dashboard on :8787.  Now: TLS with
    temporary credentials on 127.0.0.1; a client without them (plain TCP, or TLS with its own credentials)
    is refused; the HTTP server serves nothing unless the dashboard is asked for, on 127.0.0.1."""
    import operator
    import urllib.error
    import urllib.request

    from slicersim.campaign.runner import dask_client
    client, cluster = dask_client(1, None, 1)
    try:
        address = cluster.scheduler_address
        assert address.startswith("tls://127.0.0.1:")
        assert all(w.startswith("tls://127.0.0.1:") for w in cluster.scheduler.workers)
        assert client.submit(operator.add, 40, 2).result(timeout=60) == 42       # our own client works
        script = tmp_path / "intruder.py"
        script.write_text(INTRUDER)
        for target, how in ((address, "no-credentials"), (address.replace("tls://", "tcp://"), "plain-tcp"),
                            (address, "own-credentials")):
            victim = tmp_path / f"written-by-{how}"
            t0 = time.monotonic()
            proc = subprocess.run([sys.executable, str(script), target, how, str(victim)], capture_output=True,
                                  text=True, timeout=120)
            assert proc.returncode == 0 and "refused" in proc.stdout, (how, proc.stdout, proc.stderr[-2000:])
            assert time.monotonic() - t0 < 60 and not victim.exists()
        socks = _http_sockets(cluster.scheduler.http_server)
        assert socks and all(host == "127.0.0.1" and port != 8787 for host, port in socks)
        for path in ("/status", "/health", "/info/main/workers.html", "/json/identity.json"):
            with pytest.raises(urllib.error.HTTPError, match="404"):
                urllib.request.urlopen(f"http://127.0.0.1:{socks[0][1]}{path}", timeout=10)
    finally:
        client.close()
        cluster.close()
    client, cluster = dask_client(1, None, 1, dashboard="127.0.0.1:0")          # asked for: this machine only
    try:
        socks = _http_sockets(cluster.scheduler.http_server)
        assert socks and all(host == "127.0.0.1" for host, _ in socks)
        assert urllib.request.urlopen(f"http://127.0.0.1:{socks[0][1]}/health", timeout=10).status == 200
    finally:
        client.close()
        cluster.close()


def test_dashboard_and_tls_flags_are_checked(tmp_path):
    from slicersim.campaign.cluster import dashboard_address as _dashboard_address, tls_security
    from slicersim.errors import ParameterError
    assert _dashboard_address(False) is None and _dashboard_address(True) == "127.0.0.1:8787"
    assert _dashboard_address("localhost:9000") == "127.0.0.1:9000"
    with pytest.raises(ParameterError, match="dashboard must be True or an address 127.0.0.1:PORT"):
        _dashboard_address("0.0.0.0:8787")
    assert tls_security() is None
    with pytest.raises(ParameterError, match="--tls-ca-file"):
        tls_security(tmp_path / "missing-ca.pem", tmp_path / "missing-cert.pem")
    ca = tmp_path / "ca.pem"
    ca.write_text("x")
    with pytest.raises(ParameterError, match="--tls-ca-file and --tls-cert are both needed"):
        tls_security(ca)
    proc = _cli("campaign", "run", "x.toml", "--out", str(tmp_path / "d"), "--tls-ca-file", str(ca))
    assert proc.returncode == 2 and "apply to --scheduler only" in proc.stderr, proc.stderr


def test_symlinked_target_folder_refuses_the_campaign_and_its_target_is_untouched(reference, spec_path, tmp_path):
    """Adversarial finding: products/tNNNNNNN as a link → the rerun deleted the link target's files and wrote
    there.  Now the campaign is refused (the link named) before any target runs; the target is untouched."""
    from slicersim.campaign.runner import run_campaign
    d = tmp_path / "linked"
    shutil.copytree(reference, d)
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "spectrum.h5").write_bytes(b"not yours")
    (outside / "precious.txt").write_bytes(b"keep")
    shutil.rmtree(d / "products" / "t0000002")
    (d / "products" / "t0000002").symlink_to(outside)
    (d / "records" / "t0000002.json").unlink()
    with pytest.raises(DatasetError, match="t0000002 is a symbolic link"):
        run_campaign(spec_path, d, workers=1, progress=False)
    assert sorted(os.listdir(outside)) == ["precious.txt", "spectrum.h5"]
    assert (outside / "spectrum.h5").read_bytes() == b"not yours"


def test_failed_new_campaign_leaves_no_dataset_folder(spec_path, tmp_path, monkeypatch):
    """Adversarial finding: a full disk gave `[Errno 28]` without the path and left an empty dataset folder."""
    import errno

    from slicersim.campaign import runner
    from slicersim.io import dataset as dataset_module
    real = dataset_module.atomic_bytes

    def full(path, *args, **kwargs):
        if str(path).endswith("spec.json"):
            raise DatasetError(f"cannot write {path}: {dataset_module.one_line(OSError(errno.ENOSPC, 'No space'))}")
        return real(path, *args, **kwargs)
    monkeypatch.setattr(dataset_module, "atomic_bytes", full)
    monkeypatch.setattr(runner, "_plan_and_connect", lambda spec, run: (None, None, None))     # no planning
    out = tmp_path / "new"
    with pytest.raises(DatasetError, match=r"cannot write .*new/spec\.json: \[Errno 28\]"):
        runner.run_campaign(spec_path, out, workers=1, progress=False)
    assert not out.exists()


def test_a_refused_run_never_removes_what_another_run_created(spec_path, tmp_path, monkeypatch):
    """Two `campaign run` on one new --out at the same time: the refused one deleted the folder, lock and spec
    the other had just created (4 of 4 tries).  The folder is created atomically; only its creator may remove
    it, and only under the dataset's lock."""
    from slicersim.campaign import runner
    from slicersim.io.dataset import Dataset
    monkeypatch.setattr(runner, "_plan_and_connect", lambda spec, run: (None, None, None))     # no planning
    out = tmp_path / "new"
    winner = Dataset(out)
    assert winner.create() and not Dataset(out).create()         # exactly one creator
    winner.lock()
    (out / "spec.toml").write_text("the winner's spec\n")
    with pytest.raises(DatasetError, match=r"new is in use by another process \(pid \d+ on "):
        runner.run_campaign(spec_path, out, workers=1, progress=False)
    assert sorted(os.listdir(out)) == [".lock", "spec.toml"] and (out / "spec.toml").read_text() == "the winner's spec\n"
    # the creator failing while another run holds the folder leaves it to that run
    other = Dataset(tmp_path / "other")
    assert other.create()
    holder = Dataset(tmp_path / "other")
    holder.lock()
    other.remove_new()
    assert (tmp_path / "other" / ".lock").exists()
    holder.unlock()
    other.remove_new()                                           # free now: the creator cleans up
    assert not (tmp_path / "other").exists()
    winner.unlock()


def test_tls_scheduler_is_reached_with_the_tls_files(tmp_path):
    """`--scheduler tls://...` with --tls-ca-file/--tls-cert/--tls-key: the Client gets them as a Security;
    without them the connection is refused, with a hint naming the flags."""
    import operator

    from distributed import LocalCluster, Security

    from slicersim.campaign.runner import dask_client, tls_security
    creds = Security.temporary()
    files = {}
    for name, pem in (("ca", creds.tls_ca_file), ("cert", creds.tls_client_cert), ("key", creds.tls_client_key)):
        files[name] = tmp_path / f"{name}.pem"
        files[name].write_text(pem)
    cluster = LocalCluster(n_workers=1, threads_per_worker=1, processes=False, host="127.0.0.1", protocol="tls",
                           security=creds, dashboard_address=None)
    try:
        client, none = dask_client(1, cluster.scheduler_address, 1,
                                   tls_security(files["ca"], files["cert"], files["key"]))
        try:
            assert none is None and client.submit(operator.add, 1, 2).result(timeout=60) == 3
        finally:
            client.close()
        with pytest.raises(DatasetError, match="cannot connect to the Dask scheduler .*--tls-ca-file"):
            dask_client(1, cluster.scheduler_address, 1)
    finally:
        cluster.close()


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


BASE = """seed = 2
[population]
kind = "snia"
n = 2
redshift = {distribution = "uniform", min = 0.3, max = 0.6}
[observation]
snr = 5
[products]
spectrum = true
"""


def _run_cli(*args, **kw):
    """`slicersim ARGS` in this process (error cases; the real command runs above)."""
    return run_cli(*args, **kw)


def _flat_catalog(tmp_path, flux=3e-18):
    Table({"lbda": [3000.0, 20000.0], "flux": [flux, flux]}).write(tmp_path / "flat.ecsv", overwrite=True)
    Table({"target_id": [1, 3], "redshift": [0.0, 0.2], "spectrum_file": ["flat.ecsv", "flat.ecsv"]}).write(
        tmp_path / "cat.csv", overwrite=True)
    text = BASE.replace('kind = "snia"\nn = 2\nredshift = {distribution = "uniform", min = 0.3, max = 0.6}',
                        'kind = "catalog"\nfile = "cat.csv"').replace("snr = 5", 'snr = 5\nframe = "obs"\n'
                                                                           "lbda_range = [6000, 9000]")
    return text


def _spec(text, base_dir="."):
    from slicersim.campaign.spec import parse_spec
    return parse_spec(tomllib.loads(text), text=text, base_dir=str(base_dir))


# 1 -------------------------------------------------------------------------------------------
def test_user_spectrum_file_column_survives_in_the_dataset_catalog(tmp_path):
    from slicersim.campaign.runner import _catalog_with_records, plan_campaign
    spec = _spec(_flat_catalog(tmp_path), tmp_path)
    cat, _ = plan_campaign(spec)
    rec = {1: {"status": "done", "products": {"spectrum": {"file": "spectrum.h5", "sha256": "ab", "bytes": 1}}}}
    out = _catalog_with_records(cat, rec, spec.wanted)
    assert list(out["spectrum_file"]) == ["flat.ecsv", "flat.ecsv"]              # the user's input, kept
    assert out["spectrum_product"][0] == "products/t0000001/spectrum.h5" and out["spectrum_sha256"][0] == "ab"
    with pytest.raises(ConfigError, match="computed by the campaign"):
        Table({"redshift": [0.5], "cube_product": ["x"]}).write(tmp_path / "bad.ecsv")
        _spec(BASE.replace('kind = "snia"\nn = 2\nredshift = {distribution = "uniform", min = 0.3, max = 0.6}',
                           'kind = "catalog"\nfile = "bad.ecsv"'), tmp_path)


# 2 -------------------------------------------------------------------------------------------
def test_edited_user_spectrum_changes_the_identity_and_stale_records_are_redone(tmp_path):
    from slicersim.campaign.runner import _consistent
    from slicersim.io.dataset import spec_digest
    text = _flat_catalog(tmp_path)
    before = spec_digest(_spec(text, tmp_path).canonical())
    _flat_catalog(tmp_path, flux=3e-17)
    assert spec_digest(_spec(text, tmp_path).canonical()) != before
    row = {"n": 7, "m": 1, "d": 0, "nramps": 1, "seed": 11, "ramp_seed": 12}
    rec = {"readout": [31, 1, 0, 1], "seed": 11, "ramp_seed": 12}
    state = _consistent({1: ("done", rec, "")}, {1: row})
    assert state[1][0] == "missing" and "stale" in state[1][2]
    rec["readout"] = [7, 1, 0, 1]
    assert _consistent({1: ("done", rec, "")}, {1: row})[1][0] == "done"


# 3 -------------------------------------------------------------------------------------------
def test_readouts_of_targets_with_hosts_include_the_host_light():
    from slicersim.campaign.products import build_target
    from slicersim.campaign.runner import _row_dict, plan_campaign
    text = BASE.replace("snr = 5", "snr = 5").replace("[observation]", "hosts = {absmag = -21.5}\n[observation]")
    spec = _spec(text)
    cat, plan = plan_campaign(spec)
    assert plan.totals.get("hosts_in_etc") is True
    plain, _ = plan_campaign(_spec(BASE))
    for i in range(len(cat)):
        row = _row_dict(cat[i])
        target, _ = build_target(spec, row)                     # host in the scene, catalog readout
        reached = target.get_band_snr((4000, 6800), frame="rest", per_resolution=True)
        assert reached >= 5 * (1 - 1e-9)                          # the SNR is reached with the host
        assert reached == pytest.approx(row["snr"], rel=1e-9)
        assert row["exposure_time"] >= plain["exposure_time"][i]  # the host only adds noise


# 6 -------------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("edit, message", [
    (lambda s: s.replace('kind = "snia"', 'kind = ["snia"]'), "kind"),
    (lambda s: s.replace('distribution = "uniform"', 'distribution = ["uniform"]'), "distribution"),
    (lambda s: s.replace("n = 2", "n = 2\nphase = {distribution = {a = 1}}"), "distribution"),
    (lambda s: s.replace("n = 2", "n = 2\nhosts = 5"), "hosts"),
    (lambda s: s.replace("n = 2", "n = 2\nhosts = [1, 2]"), "hosts"),
    (lambda s: s.replace("n = 2", 'n = 2\nhosts = "yes"'), "hosts"),
    (lambda s: s.replace("n = 2", "n = 2\nmw_dust = 0.1"), "mw_dust"),
])
def test_wrong_types_give_one_line(tmp_path, edit, message):
    spec = tmp_path / "s.toml"
    spec.write_text(edit(BASE))
    one_line_error(_run_cli("campaign", "run", spec, "--out", tmp_path / "o"), message)
    assert not (tmp_path / "o").exists()


# 7, 17 ---------------------------------------------------------------------------------------
def test_malformed_records_and_lost_spec_json(tmp_path):
    from slicersim.io.dataset import Dataset
    ds = Dataset(tmp_path / "d")
    ds.initialise("x", {"a": 1}, {})
    for tid, rec in enumerate([{"target_id": 0, "status": "done", "products": {"spectrum": {"file": "s.h5"}}},
                               {"target_id": 1, "status": "done", "products": ["x"]},
                               {"target_id": 2, "status": "done", "products": 7},
                               {"target_id": 3, "status": "done",
                                "products": {"s": {"file": "../../x", "bytes": 1, "sha256": "a"}}}]):
        ds.write_record(tid, rec)
    state = ds.state(range(4))
    assert all(st == "missing" and "malformed" in why for st, _, why in state.values())
    os.remove(ds.file("spec.json"))
    with pytest.raises(DatasetError, match="damaged.*--force"):
        Dataset.check_path(ds.path)
    assert Dataset.check_path(ds.path, force=True) == ds.path
    ds.initialise("y", {"a": 2}, {}, force=True)
    assert ds.stored_spec()[0] == {"a": 2} and not os.listdir(ds.file("records"))


# 8, 9, 15 ------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("args, message", [(["--memory-per-task", "inf"], "memory-per-task"),
                                           (["--memory-per-task", "nan"], "memory-per-task"),
                                           (["--memory-per-task", "0"], "memory-per-task"),
                                           (["--threads-per-worker", "-2"], "threads_per_worker"),
                                           (["--workers", "0"], "workers"),
                                           (["--workers", "100000"], "at most 4"),
                                           (["--scheduler", "garbage"], "tcp://host:port"),
                                           (["--scheduler", "tcp://127.0.0.1:1"], "cannot connect")])
def test_bad_run_arguments_write_nothing(tmp_path, args, message):
    spec = tmp_path / "s.toml"
    spec.write_text(BASE)
    one_line_error(_run_cli("campaign", "run", spec, "--out", tmp_path / "o", *args), message)
    assert not (tmp_path / "o").exists()


def test_run_campaign_with_a_spec_or_an_out_of_the_wrong_kind_names_it(spec_path, tmp_path):
    """run_campaign(5, out) and run_campaign(spec, None) were os.fspath's TypeError."""
    from slicersim.campaign.runner import run_campaign
    from slicersim.errors import ConfigError, DatasetError
    with pytest.raises(ConfigError, match=r"campaign spec must be a CampaignSpec or the path of its TOML file, got 5"):
        run_campaign(5, tmp_path / "ds")
    with pytest.raises(DatasetError, match=r"the dataset directory must be a path \(str or os.PathLike\), got None"):
        run_campaign(spec_path, None)
    assert not (tmp_path / "ds").exists()


def test_a_broken_dask_configuration_is_one_config_error(tmp_path):
    """A malformed file under DASK_CONFIG and encryption required with a tcp:// scheduler were internal errors
    (exit 3, 'this is a bug')."""
    import dask

    from slicersim.campaign.runner import dask_client
    with dask.config.set({"distributed.comm.require-encryption": True}):
        with pytest.raises(ConfigError, match=r"requires encryption .*scheduler tcp://127.0.0.1:9 is plain tcp://.*--tls-ca-file"):
            dask_client(1, "tcp://127.0.0.1:9", 1)
    folder = tmp_path / "dask"
    folder.mkdir()
    (folder / "bad.yaml").write_text("this: [is: not yaml\n")
    spec = tmp_path / "s.toml"
    spec.write_text('seed = 1\n[population]\nkind = "snia"\nn = 1\nredshift = 0.3\n[observation]\nsnr = 5\n')
    proc = subprocess.run([sys.executable, "-m", "slicersim", "campaign", "run", str(spec), "--out", str(tmp_path / "d")],
                          capture_output=True, text=True, env={**os.environ, "DASK_CONFIG": str(folder)}, timeout=300)
    one_line_error(proc, "Dask configuration", "bad.yaml", "is malformed", "DASK_CONFIG")


def test_bad_tls_files_are_named_not_pem_lib(tmp_path):
    """Bad TLS files gave OpenSSL's "PEM lib" without saying which file."""
    from distributed import Security

    from slicersim.campaign.runner import tls_security
    from slicersim.errors import ParameterError
    creds = Security.temporary()
    ca, cert, key, junk = (tmp_path / n for n in ("ca.pem", "cert.pem", "key.pem", "junk.pem"))
    ca.write_text(creds.tls_ca_file)
    cert.write_text(creds.tls_client_cert)
    key.write_text(creds.tls_client_key)
    junk.write_text("not a certificate\n")
    assert tls_security(ca, cert, key) is not None
    with pytest.raises(ParameterError, match=r"--tls-cert .*junk.pem is not a PEM file"):
        tls_security(ca, junk, key)
    with pytest.raises(ParameterError, match=r"--tls-ca-file .*key.pem holds no usable CA certificate"):
        tls_security(key, cert, key)
    other = Security.temporary()
    (tmp_path / "other.pem").write_text(other.tls_client_key)
    with pytest.raises(ParameterError, match=r"--tls-cert .*cert.pem and --tls-key .*other.pem do not load"):
        tls_security(ca, cert, tmp_path / "other.pem")
