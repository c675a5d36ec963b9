"""Raw-ramp files under failure: full disk, huge requests, existing files, concurrent writers,
permissions, killed and interrupted writers, incomplete files.  Real files, real subprocesses."""
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import pytest
from conftest import flip_chunk_byte

from slicersim.errors import RampFileError
from slicersim.io.rampfile import RampWriter, is_temporary, read_ramps
from slicersim.products.ramps import simulate
from slicersim.io import atomic

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # tests/io/ → repo


def _env():
    env = dict(os.environ)
    env["PYTHONPATH"] = ROOT + os.pathsep + env.get("PYTHONPATH", "")
    env.pop("SLICERSIM_DEBUG", None)
    return env


def _script(tmp_path, body, name="writer.py"):
    path = tmp_path.parent / f"{tmp_path.name}_{name}"         # outside the output directory
    path.write_text(textwrap.dedent(body))
    return str(path)


def _hidden(directory):
    return [f for f in os.listdir(directory) if f.startswith(".")]


# --------------------------------------------------------------------------- 1. disk full
WRITE_NOISY = """
    import sys
    import numpy as np
    from slicersim.products.ramps import simulate
    rate = np.random.default_rng(0).uniform(0, 100, (256, 256))
    try:
        simulate(rate, (16, 1, 0), out=sys.argv[1], backend="numpy", compression="gzip",
                 max_bytes=256 * 8 * 60, progress=False)
    except Exception as exc:
        print(type(exc).__name__ + ": " + str(exc), file=sys.stderr)
        sys.exit(3)
    print("no error")
"""


def _check_full_disk_run(proc, directory):
    assert proc.returncode == 3, (proc.returncode, proc.stderr[-2000:])      # not 139 / -11 (SIGSEGV)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("RampFileError: ")
    assert os.listdir(directory) == []                                       # nothing left behind


@pytest.mark.slow
def test_file_size_limit_mid_write_is_a_clean_error(tmp_path):
    """RLIMIT_FSIZE makes HDF5's writes fail like a full disk (EFBIG): before the fix HDF5 crashed
    the process (SIGSEGV) when the failed file was released."""
    import resource
    out = tmp_path / "out"
    out.mkdir()

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (1 << 20, 1 << 20))
    proc = subprocess.run([sys.executable, _script(tmp_path, WRITE_NOISY), str(out / "r.h5")],
                          env=_env(), capture_output=True, text=True, timeout=300, preexec_fn=limit)
    _check_full_disk_run(proc, out)
    assert "File too large" in proc.stderr


@pytest.fixture
def tiny_tmpfs(tmp_path):
    if os.geteuid() != 0 or not sys.platform.startswith("linux"):
        pytest.skip("mounting a tmpfs needs root on Linux")
    mnt = tmp_path / "tmpfs"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2M", "tmpfs", str(mnt)],
                      capture_output=True).returncode != 0:
        pytest.skip("cannot mount a tmpfs here")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True)


@pytest.mark.slow
def test_full_disk_mid_write_is_a_clean_error(tmp_path, tiny_tmpfs):
    """A real ENOSPC on a 2 MB tmpfs (compressed output, so the free-space check cannot know)."""
    proc = subprocess.run([sys.executable, _script(tmp_path, WRITE_NOISY), str(tiny_tmpfs / "r.h5")],
                          env=_env(), capture_output=True, text=True, timeout=300)
    _check_full_disk_run(proc, tiny_tmpfs)
    assert "No space left on device" in proc.stderr


@pytest.mark.slow
def test_full_disk_cli_one_line_exit_2(tmp_path, tiny_tmpfs):
    rate = tmp_path / "rate.npy"
    np.save(rate, np.random.default_rng(0).uniform(0, 100, (512, 512)))
    proc = subprocess.run([sys.executable, "-m", "slicersim", "ramp", "--rate", str(rate), "--nmd", "16", "1", "0",
                           "--compression", "gzip", "--backend", "numpy", "--out", str(tiny_tmpfs / "r.h5")],
                          env=_env(), capture_output=True, text=True, timeout=300, cwd=str(tmp_path))
    assert proc.returncode == 2, proc.stderr[-2000:]
    errors = [ln for ln in proc.stderr.splitlines() if "error" in ln.lower()]
    assert errors == [ln for ln in errors if ln.startswith("slicersim: error: ")] and len(errors) == 1
    # 16 groups × 512² × 3 B = 12.6 MB uncompressed, ≥ 3.1 MB compressed at most 4×: refused before writing
    assert "not enough disk space" in errors[0] and "compressed at most 4×" in errors[0]
    assert "r.h5" in errors[0] and "Traceback" not in proc.stderr
    assert os.listdir(tiny_tmpfs) == []


# --------------------------------------------------------------------------- 2. sizes before allocation
def test_huge_request_refused_before_allocating(tmp_path):
    """nramps = 10⁹: refused from the sizes alone (before: a list of 10⁹ work items → host OOM).
    Run under a 3 GiB address-space limit so that a regression fails instead of exhausting the host."""
    import resource
    body = """
        import sys, numpy as np
        from slicersim.products.ramps import simulate
        try:
            simulate(np.ones((4096, 4096), np.float32), (16, 8, 0), nramps=10**9, out=sys.argv[1])
        except Exception as exc:
            print(type(exc).__name__ + ": " + str(exc), file=sys.stderr)
            sys.exit(3)
    """
    out = tmp_path / "out"
    out.mkdir()

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))
    proc = subprocess.run([sys.executable, _script(tmp_path, body), str(out / "big.h5")], env=_env(),
                          capture_output=True, text=True, timeout=300, preexec_fn=limit)
    assert proc.returncode == 3, proc.stderr[-2000:]
    assert proc.stderr.startswith("RampFileError: not enough disk space") and " GB" in proc.stderr
    assert os.listdir(out) == []


def test_huge_in_memory_request_names_the_size():
    with pytest.raises(MemoryError, match="GiB"):
        simulate(np.ones((64, 64)), (16, 8, 0), nramps=10**9)


# --------------------------------------------------------------------------- 3. existing files, races, perms
RATE = np.random.default_rng(3).uniform(0, 50, (24, 16))


def test_existing_file_is_not_overwritten(tmp_path):
    out = tmp_path / "r.h5"
    out.write_bytes(b"precious")
    with pytest.raises(RampFileError, match="exists.*overwrite"):
        simulate(RATE, (3, 1, 0), out=out)
    assert out.read_bytes() == b"precious" and _hidden(tmp_path) == []
    simulate(RATE, (3, 1, 0), seed=5, out=out, overwrite=True)
    assert np.array_equal(read_ramps(out)[0], simulate(RATE, (3, 1, 0), seed=5))


def test_file_appearing_during_the_write_wins(tmp_path):
    """Another writer finishes first: ours fails clearly at publication, its file stays intact."""
    import slicersim.products.ramps as ramps
    out = tmp_path / "r.h5"
    real = ramps.simulate_block_numpy

    def other_writer_finishes(*args, **kw):
        if not out.exists():
            out.write_bytes(b"the other writer's file")
        return real(*args, **kw)
    ramps.simulate_block_numpy, saved = other_writer_finishes, real
    try:
        with pytest.raises(RampFileError, match="exists"):
            simulate(RATE, (3, 1, 0), out=out, backend="numpy")
    finally:
        ramps.simulate_block_numpy = saved
    assert out.read_bytes() == b"the other writer's file" and _hidden(tmp_path) == []


@pytest.mark.slow
def test_two_concurrent_writers_one_wins(tmp_path):
    body = """
        import sys, numpy as np
        from slicersim.products.ramps import simulate
        rate = np.random.default_rng(0).uniform(0, 100, (512, 256))
        try:
            simulate(rate, (6, 1, 0), seed=int(sys.argv[2]), out=sys.argv[1], backend="numpy", progress=False)
        except Exception as exc:
            print(type(exc).__name__ + ": " + str(exc), file=sys.stderr)
            sys.exit(3)
    """
    script, out = _script(tmp_path, body), tmp_path / "r.h5"
    procs = [subprocess.Popen([sys.executable, script, str(out), str(seed)], env=_env(), stderr=subprocess.PIPE,
                              text=True) for seed in (1, 2)]
    results = [(p.wait(timeout=300), p.stderr.read()) for p in procs]
    codes = sorted(rc for rc, _ in results)
    assert codes == [0, 3], results
    loser = [err for rc, err in results if rc == 3][0]
    assert "RampFileError" in loser and "exists" in loser
    sci = read_ramps(out)[0]
    winner = [seed for (rc, _), seed in zip(results, (1, 2)) if rc == 0][0]
    rate = np.random.default_rng(0).uniform(0, 100, (512, 256))
    assert np.array_equal(sci, simulate(rate, (6, 1, 0), seed=winner, backend="numpy"))
    assert os.listdir(tmp_path) == ["r.h5"]


def test_files_get_the_umask_permissions(tmp_path):
    old = os.umask(0o022)
    try:
        path = simulate(RATE, (3, 1, 0), out=tmp_path / "a.h5")
        os.umask(0o027)
        path2 = simulate(RATE, (3, 1, 0), out=tmp_path / "b.h5")
    finally:
        os.umask(old)
    assert os.stat(path).st_mode & 0o777 == 0o644          # not mkstemp's 0600
    assert os.stat(path2).st_mode & 0o777 == 0o640


def test_incomplete_files_are_named_so(tmp_path):
    # a file without the completion marker (as left by a writer that stopped before the end)
    import h5py
    partial = tmp_path / "partial.h5"
    with h5py.File(partial, "w") as fh:
        fh.create_dataset("SCI", (1, 3, 2, 2), "u2")
        fh.attrs["COMPLETE"] = False
    with pytest.raises(RampFileError, match="incomplete file"):
        read_ramps(partial)
    # a truncated file
    trunc = tmp_path / "trunc.h5"
    trunc.write_bytes(open(simulate(RATE, (3, 1, 0), out=tmp_path / "full.h5"), "rb").read()[:300])
    with pytest.raises(RampFileError, match="incomplete file"):
        read_ramps(trunc)
    with pytest.raises(RampFileError, match="no such file"):
        read_ramps(tmp_path / "missing.h5")


@pytest.mark.parametrize("marker", [False, None])
def test_fully_stored_file_without_completion_marker_is_incomplete(tmp_path, marker):
    # every chunk written (so the per-dataset storage check passes) but COMPLETE false or absent, as
    # left by a writer stopped between its last block and the marker: only the marker tells
    import h5py
    path = simulate(RATE, (3, 1, 0), out=tmp_path / "r.h5")
    assert read_ramps(path)[0].shape == (1, 3) + RATE.shape
    with h5py.File(path, "r+") as fh:
        if marker is None:
            del fh.attrs["COMPLETE"]
        else:
            fh.attrs["COMPLETE"] = marker
    with pytest.raises(RampFileError, match=r"incomplete file \(no completion marker\)"):
        read_ramps(path)


SLOW_WRITER = """
    import os, sys, time
    import numpy as np
    import slicersim.products.ramps as ramps
    real = ramps.simulate_block_numpy
    def slow(*args, **kw):
        time.sleep(0.05)
        return real(*args, **kw)
    ramps.simulate_block_numpy = slow
    rate = np.random.default_rng(0).uniform(0, 100, (256, 64))
    print("start", flush=True)
    ramps.simulate(rate, (4, 1, 0), nramps=50, out=sys.argv[1], backend="numpy", progress=False,
                   max_bytes=64 * 8 * 40)
    print("done", flush=True)
"""


def _wait_for_temporary(directory, proc, timeout=120):
    t0 = time.time()
    while time.time() - t0 < timeout:
        tmps = [f for f in os.listdir(directory) if is_temporary(f)]
        if tmps:
            return tmps[0]
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.01)
    raise AssertionError("the writer never created its temporary")


def test_killed_writer_temporary_is_incomplete_and_cleaned_by_next_write(tmp_path):
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    proc = subprocess.Popen([sys.executable, _script(tmp_path, SLOW_WRITER), str(out_dir / "r.h5")], env=_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    tmp_name = _wait_for_temporary(out_dir, proc)
    time.sleep(0.5)
    proc.kill()
    proc.wait(timeout=60)
    assert tmp_name.startswith(".r.h5.tmp-") and os.listdir(out_dir) == [tmp_name]
    with pytest.raises(RampFileError, match="incomplete file"):
        read_ramps(out_dir / tmp_name)
    # a temporary of a running process (ours), or of another host, is left alone
    from slicersim.io.atomic import _host_tag
    mine = out_dir / f".x.h5.tmp-{os.getpid()}-{_host_tag()}abcd"
    other_host = out_dir / f".y.h5.tmp-{2**22 + 12345}-{'0' if _host_tag()[0] != '0' else '1'}{_host_tag()[1:]}abcd"
    for keep in (mine, other_host):
        keep.write_bytes(b"")
        assert is_temporary(keep)
    simulate(RATE, (3, 1, 0), out=out_dir / "next.h5")
    assert sorted(os.listdir(out_dir)) == sorted(["next.h5", mine.name, other_host.name])


@pytest.mark.slow
@pytest.mark.parametrize("delay", [0.0, 0.3, 1.0])
def test_sigint_during_write_aborts_and_leaves_nothing(tmp_path, delay):
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    proc = subprocess.Popen([sys.executable, _script(tmp_path, SLOW_WRITER), str(out_dir / "r.h5")], env=_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _wait_for_temporary(out_dir, proc)
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    # Python ends an uncaught KeyboardInterrupt by SIGINT (-2); never a crash
    assert proc.returncode in (-signal.SIGINT, 1) and "KeyboardInterrupt" in err, (proc.returncode, err[-2000:])
    assert "done" not in out
    assert os.listdir(out_dir) == []


def test_sigint_held_back_while_hdf5_writes(tmp_path):
    """SIGINT arriving inside an HDF5 write is delivered when the write returns, then aborts."""
    out = tmp_path / "r.h5"
    # Python's own SIGINT handler, whatever an earlier test in this process left installed (the
    # writer holds SIGINT back only over a Python-level handler: it leaves SIG_IGN / SIG_DFL alone)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        _sigint_held_back(out)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert os.listdir(tmp_path) == []


def _sigint_held_back(out):
    with pytest.raises(KeyboardInterrupt):
        with RampWriter(out, 1, 3, (8, 8)) as w:
            w._busy += 1
            # to the main thread: a process-directed signal may land on a worker thread (PoCL, h5py), and
            # the handler then runs only at the main thread's next check, which a loaded machine delays
            signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)
            deadline = time.monotonic() + 10.0
            while w._pending_signal is None and time.monotonic() < deadline:
                time.sleep(0.01)                                  # handler runs: held back
            w._busy -= 1
            assert w._pending_signal is not None
            w.write_block(0, 0, np.zeros((3, 8, 8), np.uint16))   # delivered after the write
            raise AssertionError("not interrupted")
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler      # the writer's handler removed


def test_truth_compression_only_where_it_pays(tmp_path):
    """Truth maps: shuffled gzip where a probe compresses below 75 % (sparse bad-pixel maps,
    compound tables, a bias map: 68 %), none for white-noise-like float maps (86 %: gzip would
    cost ~1 s per 64 MB for nothing); the values read back are the written ones either way."""
    import h5py

    from slicersim.io.rampfile import RampWriter, _compression_for
    rng = np.random.default_rng(3)
    noisy = rng.standard_normal((256, 256)).astype(np.float32)
    bias = (1000 + 50 * rng.standard_normal((256, 256))).astype(np.float32)
    assert _compression_for(bias)["shuffle"]
    sparse = np.ones((256, 256), np.float32)
    sparse[rng.random((256, 256)) < 0.01] = 0.5
    assert _compression_for(noisy) == {"chunks": True, "fletcher32": True}      # checksummed, not compressed
    assert _compression_for(sparse)["compression"] == "gzip" and _compression_for(sparse)["shuffle"]
    assert "compression" not in _compression_for(np.zeros(10))            # small: never
    assert _compression_for(np.zeros(0)) == {} and _compression_for(np.float32(1)) == {}   # no chunks possible
    path = tmp_path / "t.h5"
    with RampWriter(path, 1, 2, (256, 256)) as w:
        w.write_block(0, 0, np.zeros((2, 256, 256), np.uint16), np.zeros((2, 256, 256), np.uint8))
        w.write_dataset("bias", noisy)
        w.write_dataset("qe", sparse)
    with h5py.File(path) as f:
        assert f["truth/bias"].compression is None and f["truth/qe"].compression == "gzip"
        assert f["truth/bias"].fletcher32 and f["truth/qe"].fletcher32
        np.testing.assert_array_equal(f["truth/bias"][...], noisy)
        np.testing.assert_array_equal(f["truth/qe"][...], sparse)


def test_hdf5_busy_count_is_exact_with_concurrent_writer_threads(tmp_path):
    """The effects path writes blocks and truth from two background threads: the count of HDF5
    calls in flight (SIGINT is held back while it is > 0) must come back to 0, never lose an
    update, and a SIGINT held back meanwhile is delivered once the last call returns."""
    from concurrent.futures import ThreadPoolExecutor
    with RampWriter(tmp_path / "r.h5", 1, 2, (8, 8)) as w:
        seen = []

        def slow(i):
            seen.append(w._busy)                    # at least this call is in flight
            time.sleep(0.0005)
        with ThreadPoolExecutor(4) as pool:
            list(pool.map(lambda i: w._h5(slow, i), range(400)))
        assert w._busy == 0 and min(seen) >= 1 and max(seen) <= 4
        w.write_block(0, 0, np.zeros((2, 8, 8), np.uint16))
    with pytest.raises(KeyboardInterrupt):
        with RampWriter(tmp_path / "s.h5", 1, 2, (8, 8)) as w:
            def interrupted():
                w._pending_signal = (signal.SIGINT, None)        # as the handler does while busy
            with ThreadPoolExecutor(1) as pool:
                pool.submit(w._h5, interrupted).result()         # delivered in the worker, re-raised here
    assert not (tmp_path / "s.h5").exists()


# --------------------------------------------------------------------------- inputs we did not write
def _small_ramp(path, compression=None, truth=True):
    """A complete 2-ramp file written by RampWriter (SCI 2×3×8×16)."""
    sci = (np.arange(2 * 3 * 8 * 16).reshape(2, 3, 8, 16) % 1000 + 1000).astype(np.uint16)
    with RampWriter(path, 2, 3, (8, 16), attrs={"NFRAMES": 1, "GROUPGAP": 0, "TFRAME": 1.0, "GAIN": 1.0,
                                                "READNOISE": 5.0}, row_block=4, compression=compression,
                    truth_rate=truth) as w:
        for ramp in range(2):
            w.write_block(ramp, 0, sci[ramp])
        w.write_pixeldq(np.zeros((8, 16), np.uint32))
        if truth:
            w.write_truth(np.full((8, 16), 3.0))
    return sci


def _rewrite(src, dst, edit):
    """Copy the ramp file ``src`` to ``dst`` (h5py) and apply ``edit(fh)`` to the copy."""
    import h5py
    with h5py.File(src, "r") as a, h5py.File(dst, "w") as b:
        for key in a.attrs:
            b.attrs[key] = a.attrs[key]
        for name in ("SCI", "GROUPDQ", "PIXELDQ"):
            b.create_dataset(name, data=a[name][...])
        b.create_dataset("truth/rate", data=a["truth/rate"][...])
        edit(b)
    return dst


def test_written_datasets_carry_fletcher32_and_read_back_compressed(tmp_path):
    import h5py
    for comp in (None, "gzip:1", "lz4"):
        path = tmp_path / f"r_{comp}.h5"
        sci = _small_ramp(path, compression=comp)
        with h5py.File(path, "r") as fh:
            assert all(fh[n].fletcher32 for n in ("SCI", "GROUPDQ", "PIXELDQ", "truth/rate"))
            assert (fh["SCI"].compression is not None) == (comp is not None)
        assert np.array_equal(read_ramps(path)[0], sci)


def test_a_flipped_data_byte_is_a_checksum_error(tmp_path):
    path = tmp_path / "r.h5"
    _small_ramp(path)
    flip_chunk_byte(path, "SCI")
    with pytest.raises(RampFileError, match=r"checksum mismatch in dataset SCI of .*r\.h5"):
        read_ramps(path)


def _flip_attribute_value(path, value):
    """Flip one bit of the float64 attribute ``value`` where the file stores it."""
    raw = bytearray(path.read_bytes())
    where = raw.find(np.float64(value).tobytes())
    assert where > 0
    raw[where + 6] ^= 0x01
    path.write_bytes(bytes(raw))


@pytest.mark.parametrize("value", [5.0, 3.0])       # READNOISE (root attribute); the truth's fill as a check
def test_a_flipped_bit_in_an_attribute_is_a_checksum_error(tmp_path, value):
    """One flipped bit in the GAIN or READNOISE attribute changed every rate or variance with exit 0: the
    object headers (attributes, layouts) carry HDF5's metadata checksum, verified before any value is used."""
    import h5py

    from slicersim.reduction.ramp_fit import fit_ramps
    path = tmp_path / "r.h5"
    _small_ramp(path)
    with h5py.File(path, "r") as fh:                   # written in the checksummed format
        assert fh.id.get_create_plist().get_version()[0] >= 2     # superblock v2+: checksummed object headers
    if value == 5.0:
        _flip_attribute_value(path, 5.0)
        with pytest.raises(RampFileError, match=r"checksum mismatch in the metadata \(attributes, layout\) of "
                                                r".*r\.h5: the file is corrupt"):
            read_ramps(path)
        with pytest.raises(RampFileError, match=r"checksum mismatch in the metadata"):
            fit_ramps(path)
    else:                                                # a data byte is still the data checksum's
        flip_chunk_byte(path, "truth/rate")
        with pytest.raises(RampFileError, match=r"checksum mismatch in dataset truth/rate"):
            with h5py.File(path, "r") as fh:
                from slicersim.io.rampfile import read_dataset
                read_dataset(fh["truth/rate"], path)


@pytest.mark.parametrize("case", ["external_storage", "virtual", "external_link_sci", "external_link_truth",
                                  "sci_group", "soft_link_loop_sci", "soft_link_loop_truth"])
def test_hdf5_inputs_reading_outside_the_file_are_refused(tmp_path, case):
    import h5py

    from slicersim.io.uncal import write_uncal_from_hdf5
    secret = tmp_path / "secret.bin"
    secret.write_bytes(b"SECRET!!" * 16 * 8 * 16)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as fh:
        fh["x"] = np.zeros((8, 16), np.float32)
    good = tmp_path / "good.h5"
    _small_ramp(good)

    def edit(fh):
        if case == "external_storage":
            del fh["truth/rate"]
            fh.create_dataset("truth/rate", (8, 16), dtype="f4", external=[(str(secret), 0, 8 * 16 * 4)])
        elif case == "virtual":
            del fh["truth/rate"]
            layout = h5py.VirtualLayout(shape=(8, 16), dtype="f4")
            layout[:] = h5py.VirtualSource(str(other), "x", shape=(8, 16))
            fh["truth"].create_virtual_dataset("rate", layout)
        elif case == "external_link_sci":
            del fh["SCI"]
            fh["SCI"] = h5py.ExternalLink(str(other), "x")
        elif case == "external_link_truth":
            del fh["truth/rate"]
            fh["truth/rate"] = h5py.ExternalLink(str(other), "x")
        elif case.startswith("soft_link_loop"):                 # a soft link to itself: h5py's RuntimeError
            name = "SCI" if case.endswith("sci") else "truth/rate"
            del fh[name]
            fh[name] = h5py.SoftLink("/" + name)
        else:
            del fh["SCI"]
            fh.create_group("SCI")
    bad = _rewrite(good, tmp_path / "bad.h5", edit)
    what = {"external_storage": r"dataset truth/rate has external storage", "virtual": r"truth/rate is a virtual",
            "external_link_sci": r"SCI is an external link", "external_link_truth": r"truth/rate is an external link",
            "sci_group": r"SCI is a group, not a dataset",
            "soft_link_loop_sci": r"SCI is a soft link that does not resolve",
            "soft_link_loop_truth": r"truth/rate is a soft link that does not resolve"}[case]
    if case == "soft_link_loop_truth":                        # read_ramps reads no truth: the ramp fit does
        from slicersim.reduction.ramp_fit import fit_ramps
        with pytest.raises(RampFileError, match=what):
            fit_ramps(bad, with_truth=True)
        return
    with pytest.raises(RampFileError, match=what):
        read_ramps(bad)
    with pytest.raises(RampFileError, match=what):
        write_uncal_from_hdf5(bad, tmp_path / "out.fits")
    assert not (tmp_path / "out.fits").exists()


def test_inputs_that_are_not_regular_files_are_refused_without_opening(tmp_path):
    fifo = tmp_path / "fifo.h5"
    os.mkfifo(fifo)
    result = {}

    def call():
        for path in (fifo, "/dev/zero", tmp_path):
            try:
                read_ramps(path)
            except RampFileError as exc:
                result[str(path)] = str(exc)
    thread = threading.Thread(target=call, daemon=True)
    thread.start()
    thread.join(30)
    assert not thread.is_alive(), "reading a FIFO blocked"
    assert "not a regular file" in result[str(fifo)] and "fifo.h5" in result[str(fifo)]
    assert "/dev/zero is not a regular file" in result["/dev/zero"]
    assert "is a directory" in result[str(tmp_path)]


def test_compressed_output_is_checked_against_the_free_space(tmp_path, monkeypatch):
    import shutil

    from slicersim.io import rampfile
    real = shutil.disk_usage

    def tiny(path):
        usage = real(path)
        return usage._replace(free=10 << 20)              # 10 MB free
    monkeypatch.setattr(rampfile.shutil, "disk_usage", tiny)
    # 64 ramps × 4 groups × 1024² × 3 B = 805 MB uncompressed: at most 4× compression → 201 MB > 10 MB
    with pytest.raises(RampFileError, match=r"not enough disk space .*compressed at most 4×"):
        RampWriter(tmp_path / "big.h5", 64, 4, (1024, 1024), compression="gzip").check()
    assert not os.listdir(tmp_path)


def test_compressed_output_measured_after_the_first_ramp(tmp_path, monkeypatch):
    import shutil

    from slicersim.io import rampfile
    real = shutil.disk_usage
    free = {"bytes": 1 << 40}
    monkeypatch.setattr(rampfile.shutil, "disk_usage", lambda p: real(p)._replace(free=free["bytes"]))
    rng = np.random.default_rng(1)
    block = rng.integers(0, 65535, (2, 64, 64), dtype=np.uint16)        # incompressible
    with pytest.raises(RampFileError, match=r"not enough disk space .*measured compression on the first of 1000"):
        with RampWriter(tmp_path / "big.h5", 1000, 2, (64, 64), compression="gzip:1", pixeldq=False) as w:
            free["bytes"] = 2 << 20               # room for ~ a hundred ramps, not 1000
            w.write_block(0, 0, block)
    assert not os.listdir(tmp_path)


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
