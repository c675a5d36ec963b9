"""Session-19 review (background writer lanes, device self-check, correlated noise): regression tests of
the defects a helper found, each failing before its fix."""
import os
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from slicersim.io import atomic

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # tests/io/ → repo


def _dead_pid():
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_truth_lane_error_stops_the_blocks_promptly(tmp_path, monkeypatch):
    """An exception in the background truth lane must reach the caller at the next block hand-over,
    not after every block of every ramp has been computed (it is submitted once and was only
    looked at in _Background.finish)."""
    from slicersim.products import effects, ramps
    calls = []
    real_block = ramps._effects_block

    def slow_block(*a, **k):
        calls.append(time.time())
        time.sleep(0.02)
        return real_block(*a, **k)
    real_truth = effects.EffectsPlan.write_truth

    def bad_truth(self, w, nramps, part="all"):
        if part == "rest":
            raise RuntimeError("truth lane failed")
        return real_truth(self, w, nramps, part)
    monkeypatch.setattr(ramps, "_effects_block", slow_block)
    monkeypatch.setattr(effects.EffectsPlan, "write_truth", bad_truth)
    out = tmp_path / "raw.h5"
    with pytest.raises(RuntimeError, match="truth lane failed"):
        ramps.simulate(np.full((128, 128), 5.0), (4, 2, 0), seed=1, out=str(out), effects="lazuli",
                       progress=False, memory_budget=2**19, nramps=4)          # 40 blocks
    assert len(calls) <= 5, f"{len(calls)} blocks computed after the truth lane had failed"
    assert not out.exists() and not [p for p in os.listdir(tmp_path) if atomic.is_temporary(p)]


_SIGINT_SCRIPT = textwrap.dedent("""
    import os, signal, sys, threading, time
    # a parent that ignores SIGINT (a background job of a non-interactive shell) passes SIG_IGN on,
    # and Python then installs no KeyboardInterrupt handler: give this process Python's default one
    signal.signal(signal.SIGINT, signal.default_int_handler)
    import numpy as np
    from slicersim.products import effects, ramps
    calls, sent = [], []
    real_block = ramps._effects_block
    def slow_block(*a, **k):
        calls.append(time.time()); time.sleep(0.05); return real_block(*a, **k)
    ramps._effects_block = slow_block
    inside = threading.Event()
    real_truth = effects.EffectsPlan.write_truth
    def slow_truth(self, w, nramps, part="all"):
        if part == "rest":
            w._h5(lambda: (inside.set(), time.sleep(0.5)))    # a long gzip'd truth write inside HDF5
        return real_truth(self, w, nramps, part)
    effects.EffectsPlan.write_truth = slow_truth
    def interrupt():
        inside.wait(); sent.append(time.time()); os.kill(os.getpid(), signal.SIGINT)
    threading.Thread(target=interrupt, daemon=True).start()
    out = sys.argv[1]
    try:
        ramps.simulate(np.full((128, 128), 5.0), (4, 2, 0), seed=1, out=out, effects="lazuli", progress=False,
                       memory_budget=2**19, nramps=8)                    # 80 blocks of 14 rows
        print("RETURNED")
    except KeyboardInterrupt:
        print("INTERRUPTED", sum(c > sent[0] for c in calls), len(calls), os.path.exists(out))
""")


def test_sigint_while_the_truth_lane_is_in_hdf5_stops_promptly(tmp_path):
    """SIGINT while a lane is inside HDF5 is held back and raised in the thread whose HDF5 call ends
    last; in the truth lane that KeyboardInterrupt used to wait for _Background.finish, i.e. for
    every remaining block of every ramp (Ctrl-C ignored for the rest of the run)."""
    out = tmp_path / "raw.h5"
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, "-c", _SIGINT_SCRIPT, str(out)], env=env, capture_output=True,
                          text=True, timeout=300)
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith(("INTERRUPTED", "RETURNED"))]
    assert line and line[-1].startswith("INTERRUPTED"), proc.stdout + proc.stderr
    _, after, total, exists = line[-1].split()
    assert exists == "False"
    assert int(after) <= 20, f"{after} of {total} blocks started after Ctrl-C"
    assert not [p for p in os.listdir(tmp_path) if atomic.is_temporary(p)]


@pytest.mark.parametrize("fmt", ["hdf5", "jwst-uncal"])
def test_stale_temporary_does_not_block_the_disk_space_check(tmp_path, monkeypatch, fmt):
    """A writer killed by kill -9 leaves its temporary; the next writer removes it, but only in
    __enter__, after check() has already refused for lack of disk space (the space the stale
    temporary holds): every rerun failed with 'not enough disk space' until the user found and
    deleted the hidden file by hand."""
    import shutil
    from slicersim.errors import RampFileError
    from slicersim.io.rampfile import RampWriter
    from slicersim.io.uncal import UncalWriter
    final = tmp_path / ("raw.h5" if fmt == "hdf5" else "raw.fits")
    stale = tmp_path / f".{final.name}.tmp-{_dead_pid()}-{atomic._host_tag()}0123abcd"
    stale.write_bytes(b"\0" * 3_000_000)                            # what the killed writer had written
    shape, ngroups = (256, 256), 8
    need = 3 * ngroups * shape[0] * shape[1] + 8 * shape[0] * shape[1] + 2 * (1 << 20)
    real = shutil.disk_usage

    def usage(path):                                   # a file system of `need` bytes in all
        used = sum(p.stat().st_size for p in tmp_path.iterdir() if p.is_file())
        return real(path)._replace(free=max(0, need - used))
    monkeypatch.setattr(shutil, "disk_usage", usage)
    if fmt == "hdf5":
        writer = RampWriter(str(final), 1, ngroups, shape, truth_rate=True)
    else:
        writer = UncalWriter(str(final), 1, ngroups, shape)
    try:
        writer.check()
    except RampFileError as exc:
        pytest.fail(f"refused while a dead writer's temporary holds the space: {exc}")
    assert not stale.exists()


@pytest.mark.needs_opencl
def test_failed_selfcheck_error_says_what_to_do(monkeypatch):
    """backend="opencl" on a device failing the self-check raised the bare verdict ('its noisy products
    would be wrong') without the way out: the NumPy backend, another device, or the override."""
    from slicersim.backends import dispatch, opencl
    from slicersim.errors import OpenCLUnavailableError
    monkeypatch.delenv("SLICERSIM_TRUST_DEVICE", raising=False)
    monkeypatch.setattr(dispatch, "_SELFCHECK", {})
    monkeypatch.setattr(dispatch, "device_selfcheck", lambda: (
        False, "OpenCL device 'X' fails the random-stream and ramp self-check against the NumPy twin "
               "(ramp block A: 1/388 SCI and 0/388 GROUPDQ values differ): its noisy products would be wrong"))
    with pytest.raises(OpenCLUnavailableError) as info:
        dispatch.resolve_backend("opencl")
    text = str(info.value)
    assert "ramp block A" in text
    assert "numpy" in text.lower() and "SLICERSIM_DEVICE" in text and "SLICERSIM_TRUST_DEVICE" in text


def test_kernels_come_from_the_imported_checkout():
    """With an editable install of one checkout and another checkout on PYTHONPATH (the documented
    way to review a clone with the main venv), ``slicersim.kernels`` resolved to the *installed*
    checkout's kernels/: the clone's Python ran the other tree's OpenCL sources (a kernel whose
    arguments changed fails with a TypeError; an edited kernel is silently not the one run)."""
    from pathlib import Path
    import slicersim
    from slicersim.backends import opencl
    pkg = Path(slicersim.__file__).resolve().parent
    here = pkg / "kernels"                     # package data: the one place kernels are looked up
    assert (here / "philox.cl").is_file()
    assert Path(opencl.kernel_dir()).resolve() == here.resolve()
    assert opencl.kernel_source("correlated_noise.cl") == (here / "correlated_noise.cl").read_text(encoding="utf-8")
