"""OpenCL runtime for slicersim: the only module that imports :mod:`pyopencl`.

Nothing happens at import time.  The first call that needs OpenCL enumerates
the platforms, selects a device and creates one context and one in-order
queue for the current process.

Device selection (environment variable ``SLICERSIM_DEVICE``):

* unset or empty: the first GPU if there is one, otherwise the first CPU;
* ``"P:D"`` or ``"P"``: platform ``P``, device ``D`` (default 0) as listed
  by ``slicersim info``;
* ``"cpu"``, ``"gpu"``, ``"accelerator"``: first device of that type;
* any other text: first device whose platform/device name or vendor
  contains it (case-insensitive), e.g. ``"pocl"`` or ``"nvidia"``;
* ``"none"``, ``"off"`` or ``"numpy"``: disable OpenCL (NumPy fallbacks).

PoCL starts worker threads; a process forked after that can hang inside
OpenCL.  Every entry point therefore refuses to run in a forked child
(:class:`OpenCLForkError`): use ``multiprocessing`` with the ``"spawn"``
start method.

PoCL's CPU device runs one worker thread per core unless ``POCL_MAX_PTHREAD_COUNT`` says
otherwise, and reads it once, when the platform is first used: :func:`limit_cpu_threads`
sets it for this process before that (several processes sharing a machine then do not
oversubscribe its cores).
"""

from __future__ import annotations

from slicersim.errors import OpenCLUnavailableError, OpenCLForkError  # noqa: F401  (re-exported)
from slicersim import validation
from slicersim.errors import ParameterError, SlicersimError

import hashlib
import os
import re
import threading
import warnings
from pathlib import Path

import numpy as np

ENV_VAR = "SLICERSIM_DEVICE"
POCL_THREADS_VAR = "POCL_MAX_PTHREAD_COUNT"
_DISABLE = {"none", "off", "numpy", "disable", "disabled"}
_TYPES = ("cpu", "gpu", "accelerator")

INSTALL_HINT = (
    "Install an OpenCL runtime, e.g. on Debian/Ubuntu: "
    "`sudo apt-get install pocl-opencl-icd ocl-icd-libopencl1` "
    "(or run `make opencl`), then check with `slicersim info`."
)

_lock = threading.RLock()
_state: dict = {"pid": None, "spec": None, "device": None, "ctx": None, "queue": None, "threads_env": None}
_programs: dict = {}
_warned: set = set()


def _cl():
    try:
        import pyopencl
    except ImportError as exc:  # pragma: no cover - depends on install
        raise OpenCLUnavailableError(f"pyopencl cannot be imported ({exc}). {INSTALL_HINT}") from exc
    return pyopencl


def check_process() -> None:
    """Raise :class:`OpenCLForkError` if OpenCL was initialised in a parent process."""
    pid = _state["pid"]
    if pid is not None and pid != os.getpid():
        raise OpenCLForkError(
            f"OpenCL was initialised in process {pid} but is now used in forked child "
            f"process {os.getpid()}; OpenCL runtimes such as PoCL can hang after fork(). "
            "Start worker processes with the 'spawn' start method, e.g. "
            "multiprocessing.get_context('spawn') or "
            "concurrent.futures.ProcessPoolExecutor(mp_context=multiprocessing.get_context('spawn'))."
        )


def _devices() -> list:
    """All (platform_index, device_index, platform, device) tuples."""
    check_process()
    cl = _cl()
    with _lock:
        if _state["pid"] is None:
            _state["pid"] = os.getpid()  # the OpenCL runtime is now live in this process
            _state["threads_env"] = os.environ.get(POCL_THREADS_VAR)   # what PoCL reads now
    try:
        platforms = cl.get_platforms()
    except Exception as exc:  # clGetPlatformIDs fails when no ICD is installed
        raise OpenCLUnavailableError(f"No OpenCL platform found ({exc}). {INSTALL_HINT}") from exc
    found = []
    for ip, plat in enumerate(platforms):
        try:
            devs = plat.get_devices()
        except Exception:  # platform without devices
            devs = []
        found.extend((ip, idev, plat, dev) for idev, dev in enumerate(devs))
    if not found:
        raise OpenCLUnavailableError(f"OpenCL platforms exist but expose no device. {INSTALL_HINT}")
    return found


def device_type(device=None) -> str:
    """OpenCL type of *device* (default: the selected one): "GPU", "CPU", "ACCELERATOR", ..."""
    cl, dev = _cl(), device or get_device()
    for name in ("GPU", "CPU", "ACCELERATOR", "CUSTOM"):
        if dev.type & getattr(cl.device_type, name, 0):
            return name
    return cl.device_type.to_string(dev.type)


def _listing(found) -> str:
    return "; ".join(f"{ip}:{idev} {d.name.strip()} [{p.name.strip()}]" for ip, idev, p, d in found)


def select_device(spec: str | None = None):
    """Return the pyopencl device chosen by *spec* (default: ``$SLICERSIM_DEVICE``)."""
    if spec is None:
        spec = os.environ.get(ENV_VAR, "")
    spec = spec.strip()
    if spec.lower() in _DISABLE:
        raise OpenCLUnavailableError(f"OpenCL disabled by {ENV_VAR}={spec!r}.")
    found = _devices()
    cl = _cl()
    if not spec:
        for wanted in (cl.device_type.GPU, cl.device_type.CPU):
            for *_, dev in found:
                if dev.type & wanted:
                    return dev
        return found[0][3]
    m = re.fullmatch(r"(\d+)(?::(\d+))?", spec)
    for ip, idev, plat, dev in found:
        if m:
            ok = ip == int(m.group(1)) and idev == int(m.group(2) or 0)
        elif spec.lower() in _TYPES:
            ok = bool(dev.type & getattr(cl.device_type, spec.upper()))
        else:
            text = " ".join((plat.name, plat.vendor, dev.name, dev.vendor)).lower()
            ok = spec.lower() in text
        if ok:
            return dev
    raise OpenCLUnavailableError(
        f"{ENV_VAR}={spec!r} matches no OpenCL device. Use 'P:D' indices, 'cpu', 'gpu', "
        f"or a substring of a platform/device name. Available: {_listing(found)}"
    )


def reset() -> None:
    """Drop the context, queue and program cache (they are re-created on demand)."""
    with _lock:
        _state.update(spec=None, device=None, ctx=None, queue=None)
        _programs.clear()


def limit_cpu_threads(n: int) -> int:
    """Restrict this process's OpenCL CPU device (PoCL) to ``n`` worker threads; returns n.

    Sets ``POCL_MAX_PTHREAD_COUNT``, which PoCL reads once, when the OpenCL platform is first
    used in the process: call it before anything uses OpenCL (e.g. at the start of a worker
    process).  Afterwards it is a no-op when the runtime already runs with ``n`` threads (the
    variable held ``n`` when the platform started, or the selected CPU device has ``n`` compute
    units) or when the selected device is not a CPU, and otherwise raises
    :class:`~slicersim.errors.SlicersimError` (the thread count of a live runtime cannot change:
    start a new process, or set the variable in its environment).
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or int(n) < 1:
        raise ParameterError(f"limit_cpu_threads needs an integer n >= 1, got {n!r}")
    n = int(n)
    check_process()
    with _lock:
        if _state["pid"] is None:                     # PoCL not started yet: it will read this
            os.environ[POCL_THREADS_VAR] = str(n)
            return n
        at_start = _state["threads_env"]
        if at_start is not None and at_start.strip() == str(n):
            return n
        dev = _state["device"]
        if dev is not None and "CPU" not in device_type(dev):
            return n                                  # no CPU threads to limit
        units = None if dev is None else int(dev.max_compute_units)
        if units == n:
            return n
    raise SlicersimError(
        f"limit_cpu_threads({n}): the OpenCL runtime of this process already started with "
        f"{POCL_THREADS_VAR}={at_start!r}" + (f" ({units} compute units on {dev.name.strip()!r})" if units else "")
        + "; PoCL fixes its thread count when the platform is first used. Call limit_cpu_threads "
        f"before any OpenCL use, or start a new process with {POCL_THREADS_VAR}={n} in its environment.")


def _ensure() -> dict:
    check_process()
    spec = os.environ.get(ENV_VAR, "")
    with _lock:
        if _state["ctx"] is None or _state["spec"] != spec:
            reset()
            dev = select_device(spec)
            cl = _cl()
            ctx = cl.Context([dev])
            _state.update(spec=spec, device=dev, ctx=ctx, queue=cl.CommandQueue(ctx, dev))
        return _state


def get_context():
    """The process-wide pyopencl context (created on first use)."""
    return _ensure()["ctx"]


def get_queue():
    """The process-wide in-order command queue."""
    return _ensure()["queue"]


def get_device():
    """The selected pyopencl device."""
    return _ensure()["device"]


def is_available() -> bool:
    """True when a context on the selected device can be created. Never raises."""
    try:
        _ensure()
        return True
    except Exception as exc:
        spec = os.environ.get(ENV_VAR, "").strip()
        if spec and spec.lower() not in _DISABLE and spec not in _warned:
            _warned.add(spec)
            warnings.warn(f"OpenCL unavailable: {exc}", RuntimeWarning, stacklevel=2)
        return False


def _fp64(device) -> bool:
    return bool(getattr(device, "double_fp_config", 0)) or "cl_khr_fp64" in device.extensions


def device_supports_fp64() -> bool:
    """Whether the selected device supports double precision."""
    return _fp64(get_device())


#: the OpenCL C sources: ``slicersim/kernels`` beside this package (checkout, editable install or
#: wheel alike), the one place they are looked up
KERNEL_DIR = Path(__file__).resolve().parents[1] / "kernels"


def kernel_source(name: str) -> str:
    """Text of ``slicersim/kernels/<name>``."""
    path = KERNEL_DIR / name
    if not path.is_file():
        raise FileNotFoundError(f"OpenCL kernel source {name!r} not found in {KERNEL_DIR}")
    return path.read_text(encoding="utf-8")


def kernel_dir() -> str:
    """Filesystem directory of the kernel sources (the ``-I`` path for ``#include``)."""
    return str(KERNEL_DIR)


_digest: list = []


def _include_options() -> tuple:
    """``-I<kernel dir>`` plus a digest of every ``.cl`` source: kernels may ``#include``
    shared headers (philox.cl, vector_types.cl) and an edited header still rebuilds, since
    PoCL's on-disk cache keys on the main source and the options only."""
    directory = kernel_dir()
    if any(ch.isspace() for ch in directory):
        raise OpenCLUnavailableError(f"kernel directory {directory!r} contains whitespace: "
                                     "it cannot be passed as an OpenCL -I option")
    if not _digest:
        sha = hashlib.sha1()
        for path in sorted(Path(directory).glob("*.cl")):
            sha.update(path.read_bytes())
        _digest.append(sha.hexdigest()[:16])
    return (f"-I{directory}", f"-DSLICERSIM_KERNELS_SHA=0x{_digest[0]}")


_TRUE_WORDS = ("y", "yes", "t", "true", "on", "1")
_FALSE_WORDS = ("n", "no", "f", "false", "off", "0")


def _compiler_output_wanted() -> bool:
    """Whether PYOPENCL_COMPILER_OUTPUT asks for the compiler's output (unset: no).  pyopencl reads the
    variable with pytools' ``strtobool`` when a build prints anything: any other value (``garbage``, or
    set but empty) made such builds raise ``ValueError: invalid truth value`` (a traceback from every
    command projecting a cube on PoCL), ``false`` / ``no`` / ``off`` printed the warning anyway; a
    ParameterError naming the variable instead."""
    value = os.environ.get("PYOPENCL_COMPILER_OUTPUT")
    if value is None:
        return False
    if value.lower() in _TRUE_WORDS:
        return True
    if value.lower() in _FALSE_WORDS:
        return False
    raise ParameterError(f"PYOPENCL_COMPILER_OUTPUT={value!r} is not a truth value (pyopencl fails on it): "
                         f"set 1 to see the OpenCL compiler's output, 0 or unset it not to")


def get_program(name: str, options=()):
    """Built program for ``kernels/<name>``; cached per (name, options, device).

    Every program is built with the kernel directory on its include path."""
    options = tuple(options) + _include_options()
    state = _ensure()
    key = (name, options, state["device"].int_ptr)
    with _lock:
        prg = _programs.get(key)
        if prg is None:
            src = kernel_source(name)
            with warnings.catch_warnings():
                if not _compiler_output_wanted():
                    # the compiler's notes are not the user's business: PoCL on a CPU without AVX-512
                    # prints an ABI note for every 8-wide vector (each build, hundreds of lines, turned
                    # into a warning on every command); PYOPENCL_COMPILER_OUTPUT=1 shows them
                    warnings.simplefilter("ignore", _cl().CompilerWarning)
                prg = _cl().Program(state["ctx"], src).build(options=list(options), devices=[state["device"]])
            _programs[key] = prg
        return prg


def get_kernel(name: str, kernel: str, options=()):
    """A new kernel object (kernels hold their arguments: do not share across threads)."""
    return _cl().Kernel(get_program(name, options), kernel)


def device_fingerprint() -> tuple:
    """(platform, device, vendor, driver version, kernel-source digest) of the selected device:
    what a result computed by the kernels depends on besides their arguments (cache keys)."""
    dev = get_device()
    return (dev.platform.name.strip(), dev.name.strip(), dev.vendor.strip(), dev.driver_version.strip(),
            _include_options()[1])


_local = threading.local()


def _thread_cache():
    """This thread's kernels and scratch buffers; reset when the context changes."""
    ctx = get_context()
    if getattr(_local, "ctx", None) is not ctx:
        _local.ctx, _local.kernels, _local.buffers = ctx, {}, {}
    return _local


def cached_kernel(name: str, kernel: str, options=()):
    """Kernel object reused by this thread between calls (creating one costs ~1 ms of pyopencl
    set-up; a kernel holds its arguments, hence one per thread)."""
    kernels = _thread_cache().kernels
    key = (name, kernel, tuple(options))
    if key not in kernels:
        kernels[key] = get_kernel(name, kernel, tuple(options))
    return kernels[key]


def scratch_buffer(tag: str, nbytes: int):
    """Device buffer ``tag`` of at least ``nbytes``, reused by this thread between calls
    (allocating and first-touching tens of MB per call costs as much as a kernel on PoCL).
    Its content is undefined; safe because the queue is in order and every caller finishes
    with a blocking read."""
    buffers = _thread_cache().buffers
    hit = buffers.get(tag)
    if hit is None or hit[0] < nbytes:
        size = max(int(nbytes), 8)
        hit = buffers[tag] = (size, device_buffer(size))
    return hit[1]


def release_thread_resources() -> None:
    """Free this thread's cached kernels and scratch buffers (re-created on demand)."""
    _local.__dict__.clear()


def device_buffer(nbytes: int):
    """Uninitialised read-write device buffer of *nbytes* bytes."""
    cl = _cl()
    return cl.Buffer(get_context(), cl.mem_flags.READ_WRITE, size=max(int(nbytes), 1))


def to_device(array, buffer=None):
    """Copy a C-contiguous array to *buffer* (new buffer when None); blocking."""
    cl = _cl()
    if buffer is None:
        return cl.Buffer(get_context(), cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=array)
    cl.enqueue_copy(get_queue(), buffer, array, is_blocking=True)
    return buffer


def from_device(array, buffer) -> None:
    """Copy *buffer* into the C-contiguous *array*; blocking."""
    _cl().enqueue_copy(get_queue(), array, buffer, is_blocking=True)


def to_device_nowait(array, buffer):
    """Enqueue a copy of the C-contiguous *array* into *buffer* (in-order queue: the kernels queued
    after it see it); returns its event.  Keep *array* alive and unchanged until a later blocking
    call on the queue returns."""
    return _cl().enqueue_copy(get_queue(), buffer, array, is_blocking=False)


def from_device_nowait(array, buffer):
    """Enqueue a copy of *buffer* into the C-contiguous *array*, behind the kernels already queued
    (in-order queue); returns its event: wait on it before reading *array*, and keep *array* alive."""
    return _cl().enqueue_copy(get_queue(), array, buffer, is_blocking=False)


def launch_prepared(kernel, global_size, local_size=None):
    """Enqueue *kernel* with the arguments already set on it (``kernel.set_args`` / ``set_arg``:
    a launch that changes a few of many arguments skips pyopencl's per-call argument set-up);
    returns the event."""
    return _cl().enqueue_nd_range_kernel(get_queue(), kernel, tuple(global_size),
                                         None if local_size is None else tuple(local_size))


def launch(kernel, global_size, local_size, *args):
    """Enqueue *kernel* on the process queue; returns the event."""
    return kernel(get_queue(), tuple(global_size), None if local_size is None else tuple(local_size), *args)


#: elements per work item the vectorised kernels accept
VECTOR_WIDTHS = (1, 2, 4, 8, 16)


def check_vector_width(vector_width, default_cap=16, scale=1):
    """Validated elements per work item: the device's preferred width when None."""
    if vector_width is None:
        return preferred_vector_width(default_cap, scale)
    return int(validation.choice("vector_width", vector_width, VECTOR_WIDTHS))


def preferred_vector_width(cap: int = 16, scale: int = 1) -> int:
    """Doubles per vector for kernels that vectorise along a row: 1 on GPUs (one element
    per work item coalesces), else the largest power of two ≤ min(``scale`` × the device's
    preferred double width, ``cap``) (PoCL does not vectorise scalar kernels with inner loops)."""
    dev = get_device()
    if "GPU" in device_type(dev):
        return 1
    native = max(1, int(getattr(dev, "preferred_vector_width_double", 1) or 1))
    width = 1
    while width * 2 <= min(scale * native, cap):
        width *= 2
    return width


def precision_options(precision: str) -> tuple:
    """Build options of a precision-generic kernel (``real`` in ``kernels/vector_types.cl``):
    () for "double"; "single" adds -DSINGLE and makes literals float
    (-cl-single-precision-constant), so the program contains no double at all."""
    if precision == "double":
        return ()
    if precision == "single":
        return ("-DSINGLE", "-cl-single-precision-constant")
    raise ValueError(f"precision must be 'double' or 'single' here, got {precision!r}")  # internal: resolved by callers


def require_fp64() -> None:
    """Raise :class:`OpenCLUnavailableError` when the selected device lacks double precision."""
    if not device_supports_fp64():
        raise OpenCLUnavailableError(
            f"OpenCL device {get_device().name.strip()!r} lacks double precision (fp64); "
            "use backend='numpy' or select another device with SLICERSIM_DEVICE.")


def device_info() -> list[dict]:
    """Describe every OpenCL device of every platform (raises OpenCLUnavailableError)."""
    found = _devices()
    try:
        chosen = select_device().int_ptr
    except OpenCLUnavailableError:
        chosen = None
    out = []
    for ip, idev, plat, dev in found:
        out.append({
            "index": f"{ip}:{idev}",
            "platform": plat.name.strip(),
            "platform_version": plat.version.strip(),
            "name": dev.name.strip(),
            "vendor": dev.vendor.strip(),
            "version": dev.version.strip(),
            "driver_version": dev.driver_version.strip(),
            "type": device_type(dev),
            "compute_units": int(dev.max_compute_units),
            "global_mem": int(dev.global_mem_size),
            "max_work_group_size": int(dev.max_work_group_size),
            "fp64": _fp64(dev),
            "selected": dev.int_ptr == chosen,
        })
    return out


def host_buffer(array):
    """Read-write buffer over the C-contiguous NumPy *array* itself (``USE_HOST_PTR``).

    On CPU devices (PoCL) kernels then read and write the array's memory directly: no copy.
    Call :func:`sync_to_host` after the kernels that write it, before reading *array*.
    """
    cl = _cl()
    if not array.flags.c_contiguous or not array.flags.writeable:
        raise ValueError("host_buffer needs a writeable C-contiguous array")  # internal: package-made arrays
    return cl.Buffer(get_context(), cl.mem_flags.READ_WRITE | cl.mem_flags.USE_HOST_PTR, hostbuf=array)


def sync_to_host(buffer, array) -> None:
    """Make the kernels' writes to a :func:`host_buffer` visible in *array* (blocking map/unmap;
    no copy where the device uses the host memory, as PoCL does).

    The map is copied into *array* when it is not *array*'s own memory: NVIDIA's OpenCL maps a
    ``USE_HOST_PTR`` buffer at a pinned copy of its own, so the kernels' results never reached the
    array (an H200 returned whatever the freed memory held: half the uniforms and every Poisson
    count wrong, ramps 1e5 σ off)."""
    cl = _cl()
    queue = get_queue()
    mapped, _ = cl.enqueue_map_buffer(queue, buffer, cl.map_flags.READ, 0, array.shape, array.dtype,
                                      is_blocking=True)
    try:
        if mapped.__array_interface__["data"][0] != array.__array_interface__["data"][0]:
            np.copyto(array, mapped)
    finally:
        mapped.base.release(queue)
        del mapped


def workspace_buffer(workspace, name, nbytes):
    """Device buffer of ≥ nbytes, reused from ``workspace`` (a dict kept by the caller across
    launches, e.g. the row blocks of a ramp); a fresh buffer when ``workspace`` is None."""
    if workspace is None:
        return device_buffer(nbytes)
    buf, size = workspace.get(name, (None, 0))
    if size < nbytes:
        buf, size = device_buffer(nbytes), nbytes
        workspace[name] = (buf, size)
    return buf
