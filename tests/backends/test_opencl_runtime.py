"""Tests of the OpenCL runtime layer (slicersim.backends.opencl)."""

import os
import time

import pytest

from slicersim.backends import opencl
from slicersim.errors import OpenCLForkError, ParameterError
from slicersim.backends import precision as prec


@pytest.fixture
def fresh(monkeypatch):
    """Default device selection before and after the test."""
    monkeypatch.delenv(opencl.ENV_VAR, raising=False)
    opencl.reset()
    yield monkeypatch
    opencl.reset()


def test_is_available_returns_bool():
    assert isinstance(opencl.is_available(), bool)


def test_disable_with_env(fresh):
    fresh.setenv(opencl.ENV_VAR, "none")
    assert opencl.is_available() is False
    with pytest.raises(opencl.OpenCLUnavailableError, match="disabled"):
        opencl.get_context()


def test_kernel_source_found():
    src = opencl.kernel_source("band_variance.cl")
    assert "__kernel void band_variance" in src
    with pytest.raises(FileNotFoundError):
        opencl.kernel_source("no_such_kernel.cl")


@pytest.mark.needs_opencl_device
def test_device_info_lists_devices(fresh):
    info = opencl.device_info()
    assert info
    keys = {"index", "platform", "name", "vendor", "version", "type", "compute_units",
            "global_mem", "max_work_group_size", "fp64", "selected"}
    for d in info:
        assert keys <= set(d)
        assert d["compute_units"] >= 1 and d["global_mem"] > 0 and d["max_work_group_size"] >= 1
    assert sum(d["selected"] for d in info) == 1
    # the selected entry is the context's device
    sel = next(d for d in info if d["selected"])
    assert opencl.get_device().name.strip() == sel["name"]
    assert isinstance(opencl.device_supports_fp64(), bool)


@pytest.mark.needs_opencl_device
def test_context_and_program_are_cached(fresh):
    assert opencl.get_context() is opencl.get_context()
    assert opencl.get_queue() is opencl.get_queue()
    p1 = opencl.get_program("band_variance.cl", ("-DVW=1",))
    p2 = opencl.get_program("band_variance.cl", ["-DVW=1"])
    assert p1 is p2
    p3 = opencl.get_program("band_variance.cl", ("-DVW=2",))
    assert p3 is not p1


@pytest.mark.needs_opencl_device
def test_select_by_index_and_name(fresh):
    info = opencl.device_info()
    first = info[0]
    fresh.setenv(opencl.ENV_VAR, first["index"])
    assert opencl.is_available()
    assert opencl.get_device().name.strip() == first["name"]
    # platform index alone means device 0 of that platform
    assert opencl.select_device(first["index"].split(":")[0]).name.strip() == first["name"]
    # case-insensitive substring of the device name, and of the type
    assert opencl.select_device(first["name"].swapcase()[:6]).name.strip() == first["name"]
    typ = first["type"].lower()
    if typ in ("cpu", "gpu"):
        assert opencl.device_type(opencl.select_device(typ.upper())) == first["type"]


@pytest.mark.needs_opencl_device
def test_env_change_switches_context(fresh):
    ctx = opencl.get_context()
    fresh.setenv(opencl.ENV_VAR, opencl.device_info()[0]["index"])
    assert opencl.get_context() is not ctx


@pytest.mark.needs_opencl_device
@pytest.mark.parametrize("spec", ["no-such-device-xyz", "99:0", "0:99"])
def test_bogus_selection_is_a_clear_error(fresh, spec):
    fresh.setenv(opencl.ENV_VAR, spec)
    with pytest.warns(RuntimeWarning, match="matches no OpenCL device"):
        opencl._warned.discard(spec)
        assert opencl.is_available() is False
    with pytest.raises(opencl.OpenCLUnavailableError, match="SLICERSIM_DEVICE") as err:
        opencl.get_context()
    assert "Available:" in str(err.value)


def test_fork_guard_simulated(fresh):
    fresh.setitem(opencl._state, "pid", os.getpid() + 1)  # pretend a parent initialised OpenCL
    assert opencl.is_available() is False
    with pytest.raises(opencl.OpenCLForkError, match="spawn"):
        opencl.get_context()
    with pytest.raises(opencl.OpenCLForkError):
        opencl.device_info()


@pytest.mark.needs_opencl_device
@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork")
@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_fork_guard_real_fork(fresh):
    opencl.get_queue()  # OpenCL live in this process
    pid = os.fork()
    if pid == 0:  # child: must refuse before touching the OpenCL runtime
        code = 1
        try:
            opencl.get_context()
        except opencl.OpenCLForkError as exc:
            code = 0 if "spawn" in str(exc) else 2
        except BaseException:
            code = 3
        os._exit(code)
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            assert os.waitstatus_to_exitcode(status) == 0
            return
        time.sleep(0.02)
    os.kill(pid, 9)
    os.waitpid(pid, 0)
    pytest.fail("forked child hung instead of raising OpenCLForkError")


@pytest.mark.needs_opencl_device
def test_sync_to_host_copies_a_map_that_is_not_the_array():
    """A driver may map a USE_HOST_PTR buffer at memory of its own (NVIDIA does): sync_to_host then
    copies the map into the array.  Exercised with a buffer that does not wrap the array."""
    import numpy as np
    from slicersim.backends import opencl
    src = np.arange(1000, dtype=np.float64)
    buf = opencl.to_device(src)                      # COPY_HOST_PTR: its own memory
    dst = np.full(1000, -1.0)
    opencl.sync_to_host(buf, dst)
    np.testing.assert_array_equal(dst, src)


@pytest.mark.needs_opencl
def test_device_failing_the_selfcheck_is_never_used_silently(monkeypatch):
    """A device whose random draws differ from the twin: "auto" falls back to NumPy with a warning
    naming it, an explicit backend="opencl" raises; the real device passes the check."""
    import warnings
    import numpy as np
    from slicersim.backends import dispatch, noise, opencl
    from slicersim.errors import OpenCLUnavailableError
    ok, msg = dispatch.device_validated()
    assert ok, msg
    key = opencl.device_fingerprint()
    monkeypatch.setitem(dispatch._SELFCHECK, key, (False, "OpenCL device 'X' fails the random-stream self-check"))
    monkeypatch.setattr(dispatch, "_warned", set())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert dispatch.resolve_backend("auto") == "numpy"
    assert any("self-check" in str(w.message) and "NumPy" in str(w.message) for w in caught)
    with pytest.raises(OpenCLUnavailableError, match="self-check"):
        noise.poisson_draw(np.ones(10), 1, backend="opencl")
    monkeypatch.setenv("SLICERSIM_TRUST_DEVICE", "1")
    assert dispatch.resolve_backend("auto") == "opencl"


@pytest.mark.needs_opencl
def test_selfcheck_detects_wrong_draws(monkeypatch):
    """device_selfcheck fails when the kernels' uniforms, Gaussians or counts come back wrong, and
    passes on the real device; it uses the same launches as the products (bit-identical here)."""
    import numpy as np
    from slicersim.backends import opencl, selfcheck
    assert selfcheck.device_selfcheck()[0]
    real = selfcheck._opencl_draws
    for i, what in ((0, "uniforms differ"), (1, "Gaussians differ"), (2, "Poisson counts differ")):
        def broken(i=i):
            draws = list(real())
            draws[i] = draws[i] * 0.5 + 1.0
            return tuple(draws)
        monkeypatch.setattr(selfcheck, "_opencl_draws", broken)
        ok, msg = selfcheck.device_selfcheck()
        assert not ok and what in msg, msg
    monkeypatch.setattr(selfcheck, "_opencl_draws", lambda: 1 / 0)
    ok, msg = selfcheck.device_selfcheck()
    assert not ok and "could not run" in msg


@pytest.mark.needs_opencl
def test_selfcheck_review_findings(monkeypatch):
    """Review findings: the check runs once for concurrent first calls (a lock), warns once per
    process, reads SLICERSIM_TRUST_DEVICE case-insensitively (unknown values warn and check), and a
    check that could not run is not cached."""
    import threading
    import warnings
    import numpy as np
    from slicersim.backends import dispatch, opencl, selfcheck
    key = opencl.device_fingerprint()
    calls = []
    real = selfcheck.device_selfcheck

    def counted():
        calls.append(1)
        return real()
    monkeypatch.setattr(dispatch, "device_selfcheck", counted)
    monkeypatch.setattr(dispatch, "_SELFCHECK", {})
    threads = [threading.Thread(target=dispatch.device_validated) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1
    # a failing device warns once per process, whatever the thread
    monkeypatch.setattr(dispatch, "_SELFCHECK", {key: (False, "OpenCL device 'X' fails the self-check")})
    monkeypatch.setattr(dispatch, "_warned", set())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        th = [threading.Thread(target=dispatch.resolve_backend) for _ in range(4)]
        for t in th:
            t.start()
        for t in th:
            t.join()
        dispatch.resolve_backend("auto")
    assert sum("fails the self-check" in str(w.message) for w in caught) == 1
    for value, trusted in (("TRUE", True), (" On ", True), ("0", False), ("False", False)):
        monkeypatch.setenv("SLICERSIM_TRUST_DEVICE", value)
        assert (dispatch.resolve_backend("auto") == "opencl") is trusted, value
    monkeypatch.setenv("SLICERSIM_TRUST_DEVICE", "maybe")
    with pytest.warns(RuntimeWarning, match="SLICERSIM_TRUST_DEVICE"):
        assert dispatch.resolve_backend("auto") == "numpy"
    monkeypatch.delenv("SLICERSIM_TRUST_DEVICE")
    # a check that could not run is retried
    monkeypatch.setattr(dispatch, "_SELFCHECK", {})
    monkeypatch.setattr(dispatch, "device_selfcheck", lambda: (False, "OpenCL device self-check could not run (X)"))
    assert not dispatch.device_validated()[0] and key not in dispatch._SELFCHECK
    monkeypatch.setattr(dispatch, "device_selfcheck", real)
    assert dispatch.device_validated()[0]
    assert np.array_equal(*[selfcheck._uniform_normal(w)[0] for w in (1, opencl.preferred_vector_width())])


@pytest.mark.needs_opencl
def test_selfcheck_catches_a_wrong_ramp_kernel(monkeypatch):
    """The random streams alone passed on the H200 while its 4096² reduction was wrong: the self-check
    also runs the ramp sampler (both kernels) on two small blocks against the twin, bit for bit.  One SCI
    value off by 1 ADU, one GROUPDQ flag lost, or a ramp launch that fails makes the device fail the
    check; through dispatch, "auto" then falls back to NumPy with one warning and an explicit
    backend="opencl" raises."""
    import re
    import warnings
    import numpy as np
    from slicersim.backends import dispatch, opencl, selfcheck
    from slicersim.backends import ramp as ramp_backend
    from slicersim.errors import OpenCLUnavailableError
    ok, msg = selfcheck.device_selfcheck()
    assert ok and "ramp" in msg, msg
    real = ramp_backend.simulate_block_opencl

    def corrupt(which):
        def broken(mu, dead, pixel0, *args, **kw):
            sci, gdq = real(mu, dead, pixel0, *args, **kw)
            if pixel0 >= 2**31 or which == "sci":     # block B (pixel indices above 2^31), or SCI of A
                if which == "sci":
                    sci[1, 7] ^= 1
                else:
                    gdq[-1, np.flatnonzero(gdq[-1])[0]] = 0
            return sci, gdq
        return broken
    for which, what in (("sci", "SCI"), ("gdq", "GROUPDQ")):
        monkeypatch.setattr(ramp_backend, "simulate_block_opencl", corrupt(which))
        ok, msg = selfcheck.device_selfcheck()
        assert not ok and re.search(rf"ramp block [AB]: [^;]*\b1/\d+ {what}", msg), msg
    # through dispatch: a fresh check of this device fails
    monkeypatch.delenv("SLICERSIM_TRUST_DEVICE", raising=False)
    monkeypatch.setattr(dispatch, "_SELFCHECK", {})
    monkeypatch.setattr(dispatch, "_warned", set())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert dispatch.resolve_backend("auto") == "numpy"
        assert dispatch.resolve_backend("auto") == "numpy"
    assert sum("ramp block" in str(w.message) and "NumPy" in str(w.message) for w in caught) == 1
    with pytest.raises(OpenCLUnavailableError, match="ramp block"):
        dispatch.resolve_backend("opencl")

    def failing(*args, **kw):
        raise RuntimeError("clBuildProgram failed")
    monkeypatch.setattr(ramp_backend, "simulate_block_opencl", failing)
    ok, msg = selfcheck.device_selfcheck()
    assert not ok and msg.startswith(selfcheck.NOT_RUN), msg


def test_selfcheck_ramp_blocks_take_every_kernel_path(monkeypatch):
    """The self-check's ramp blocks keep covering what they claim (selfcheck._ramp_cases): sparse
    windows with several events and windows crossing the full well (the clipped read sum), dense
    inversion, PTRS and the Gaussian approximation unsaturated, charge saturating at the full well,
    ADU clipped at 0 and 65535, saturation flags, dead pixels, pixel indices of a 4096² detector's
    last rows and above 2^31 — and they are small: a few hundred pixels, MACC(4,2,1)."""
    import numpy as np
    from slicersim import rng
    from slicersim.backends import selfcheck
    from slicersim.backends import ramp as ramp_backend
    from slicersim.physics.ramp import sparse_threshold
    clipped = []
    real_clip = ramp_backend._clipped_read_sum

    def counting(before, *args):
        clipped.append(before.size)
        return real_clip(before, *args)
    monkeypatch.setattr(ramp_backend, "_clipped_read_sum", counting)
    cases = selfcheck._ramp_cases()
    blocks = selfcheck._ramp_blocks(ramp_backend.simulate_block_numpy)
    assert sum(c[0].size for c in cases) < 200 and all(c[4].nmd == (4, 2, 1) for c in cases)
    assert sum(clipped) > 0, "no sparse window crossed the full well"
    paths = set()
    for (mu, dead, pixel0, ramp, p), (sci, gdq) in zip(cases, blocks):
        n, m, d = p.nmd
        live = mu[~dead]
        sparse = live * (m + d) < sparse_threshold(p)
        paths |= {"sparse" if s else ("gauss" if x >= p.gauss_min_mean else "ptrs" if x >= rng.PTRS_MIN_MEAN
                                      else "inversion") for s, x in zip(sparse, live)}
        if (live * (m + d) > 4).any() and sparse.any():
            paths.add("sparse, many events")
        assert dead.any() and (gdq != 0).any()
        if (sci == 65535).any():
            paths.add("ADU 65535")
        if (sci == 0).any():
            paths.add("ADU 0")
        if (live * (n * (m + d)) >= p.full_well).any():
            paths.add("full well")
        if pixel0 >= 2**31:
            paths.add("pixel >= 2^31")
        elif pixel0 >= 4000 * 4096:
            paths.add("last rows of 4096²")
    # unsaturated PTRS and Gaussian pixels (their values are not hidden by the full well)
    mu_a, _, _, _, p_a = cases[0]
    assert ((mu_a >= 10) & (mu_a < p_a.gauss_min_mean) & (mu_a * 11 < p_a.full_well)).any()
    assert ((mu_a >= p_a.gauss_min_mean) & (mu_a * 2 < p_a.full_well)).any()
    assert paths == {"sparse", "sparse, many events", "inversion", "ptrs", "gauss", "ADU 65535", "ADU 0",
                     "full well", "pixel >= 2^31", "last rows of 4096²"}, paths


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


def test_compiler_notes_are_not_warnings_unless_asked(fresh):
    """PoCL on a CPU without AVX-512 notes an ABI change for every 8-wide vector: pyopencl turned that
    into a CompilerWarning on every build, so every command printed "slicersim: warning: Non-empty
    compiler output" (and the CLI's one-line errors became two lines: two tests failed on such a
    machine).  Builds no longer warn; PYOPENCL_COMPILER_OUTPUT=1 shows the compiler's output."""
    import warnings
    if not opencl.is_available():
        pytest.skip("no OpenCL platform")
    cl = opencl._cl()
    real = cl.Program

    class Noisy:
        def __init__(self, ctx, src):
            self.program = real(ctx, src)

        def build(self, **kwargs):
            warnings.warn("Non-empty compiler output encountered", cl.CompilerWarning)
            return self.program.build(**kwargs)

    fresh.setattr(cl, "Program", Noisy)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        opencl.get_program("noise.cl", ("-DNOTE_TEST=1",))
    assert not [w for w in seen if issubclass(w.category, cl.CompilerWarning)]
    fresh.setenv("PYOPENCL_COMPILER_OUTPUT", "1")
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        opencl.get_program("noise.cl", ("-DNOTE_TEST=2",))
    assert [w for w in seen if issubclass(w.category, cl.CompilerWarning)]


@pytest.mark.parametrize("value", ["garbage", "", " 1"])
def test_a_compiler_output_setting_pyopencl_cannot_read_is_one_parameter_error(fresh, value):
    """pyopencl reads PYOPENCL_COMPILER_OUTPUT with pytools' strtobool when a build prints anything
    (PoCL: project.cl, project_transpose.cl, correlated_noise.cl print notes): ``garbage``, or the
    variable set but empty, made those builds a ``ValueError: invalid truth value`` traceback.  Now one
    ParameterError naming the variable, whatever the kernel; ``false`` hides the notes as ``0`` does."""
    import warnings
    if not opencl.is_available():
        pytest.skip("no OpenCL platform")
    fresh.setenv("PYOPENCL_COMPILER_OUTPUT", value)
    with pytest.raises(ParameterError, match="PYOPENCL_COMPILER_OUTPUT"):
        opencl.get_program("project.cl", ("-DBAD_OUTPUT_TEST=1",))
    fresh.setenv("PYOPENCL_COMPILER_OUTPUT", "false")
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        opencl.get_program("project.cl", ("-DBAD_OUTPUT_TEST=2",))
    assert not [w for w in seen if issubclass(w.category, opencl._cl().CompilerWarning)]
