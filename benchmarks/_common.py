"""Helpers shared by the benchmark scripts: JSON-safe values, the machine description, reference
releases run in their own venvs (configuration folder, runner subprocesses), markdown tables."""
import math
import os
import platform
from pathlib import Path

import numpy as np


def jsonable(value):
    """Recursively convert numpy values, tuples and non-finite floats for json."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, np.generic):
        return jsonable(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return str(value)


def cpu_model():
    """The CPU model name (/proc/cpuinfo), else platform.processor()."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or None


def loadavg():
    """1, 5 and 15-minute load averages, or None."""
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return None


# --------------------------------------------------------------------------- #
#  public reference releases run in their own venvs (*_vs_142.py and friends)
# --------------------------------------------------------------------------- #
BENCHMARKS = Path(__file__).resolve().parent
#: venv holding slicersim 1.4.2 (git-ignored; made on first use)
REFVENV142 = BENCHMARKS / ".refvenv142"


def reference_config_dir():
    """Folder of the reference's configuration files (``$SLICERSIM_REFERENCE_DIR/config``, default
    ``../shared/reference/config``), or None when it has no ``lazuli_cbe.toml``."""
    env = os.environ.get("SLICERSIM_REFERENCE_DIR")
    root = Path(env) if env else BENCHMARKS.parents[1] / "shared" / "reference"
    return root / "config" if (root / "config" / "lazuli_cbe.toml").is_file() else None


def reference_config():
    """Path (str) of the reference's ``lazuli_cbe.toml`` (1.4.2's own up to whitespace and its
    ``name`` key), or None."""
    folder = reference_config_dir()
    return None if folder is None else str(folder / "lazuli_cbe.toml")


def ensure_refvenv(venv=REFVENV142, requirement="slicersim==1.4.2"):
    """Python of a reference venv, created with ``pip install requirement`` when missing."""
    import subprocess
    import sys
    py = Path(venv) / "bin" / "python"
    if not py.exists():
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
        subprocess.run([str(py), "-m", "pip", "install", "-q", requirement], check=True)
    return py


def reference_env():
    """Our environment without PYTHON* variables (the reference venv must not see our package)."""
    return {k: v for k, v in os.environ.items() if not k.startswith("PYTHON")}


class RunnerJob:
    """A runner script started in a reference venv (:func:`start_runner`); :meth:`wait` returns
    (JSON result, dict of the arrays of its .npz)."""

    def __init__(self, process, tmp, paths, started):
        self.process, self._tmp, self.paths, self.started = process, tmp, paths, started

    def wait(self):
        import json
        import time
        try:
            rc = self.process.wait()
            self.seconds = time.perf_counter() - self.started
            if rc != 0:
                raise RuntimeError(f"reference runner {self.process.args[1]} failed (exit {rc})")
            result = json.loads(self.paths["json"].read_text())
            arrays = {}
            if self.paths["npz"].exists():
                with np.load(self.paths["npz"]) as data:
                    arrays = {k: data[k] for k in data.files}
            return result, arrays
        finally:
            self._tmp.cleanup()


def start_runner(runner, spec=None, venv=REFVENV142, requirement="slicersim==1.4.2",
                 argv=("{input}", "{json}", "{npz}"), nice=None):
    """Start ``runner`` (a file in benchmarks/) with the venv's Python, in a temporary folder,
    without waiting: it runs alongside our side of a comparison.  ``spec`` is written to
    ``{input}`` (JSON); ``argv`` names the runner's arguments ({input}, {json}, {npz}).
    ``nice``: niceness increment of the child (None: inherit)."""
    import json
    import subprocess
    import tempfile
    import time
    py = ensure_refvenv(venv, requirement)
    tmp = tempfile.TemporaryDirectory(prefix="slicersim_ref_")
    paths = {"input": Path(tmp.name) / "in.json", "json": Path(tmp.name) / "out.json",
             "npz": Path(tmp.name) / "out.npz"}
    if spec is not None:
        paths["input"].write_text(json.dumps(jsonable(spec)))
    args = [str(py), str(BENCHMARKS / runner)] + [a.format(**{k: str(v) for k, v in paths.items()}) for a in argv]
    preexec = (lambda: os.nice(nice)) if nice else None
    process = subprocess.Popen(args, env=reference_env(), cwd=tmp.name, preexec_fn=preexec)
    return RunnerJob(process, tmp, paths, time.perf_counter())


def run_runner(runner, spec=None, **kwargs):
    """:func:`start_runner` and wait: (JSON result, arrays)."""
    return start_runner(runner, spec, **kwargs).wait()


# --------------------------------------------------------------------------- #
#  markdown and results
# --------------------------------------------------------------------------- #
def rel_diff(value, reference):
    """value / reference − 1, or None when either is missing or the reference is 0."""
    if value is None or reference is None or reference == 0:
        return None
    return value / reference - 1


def fmt(value, spec="{:.4g}"):
    """A number formatted with ``spec``, "–" for None / non-finite."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    return spec.format(value)


def fmt_delta(delta, flag=None):
    """A relative difference as "+1.23 %" ("–" for None); bold when |Δ| > ``flag``."""
    if delta is None:
        return "–"
    text = f"{delta:+.2%}".replace("%", " %")
    return f"**{text}**" if flag is not None and abs(delta) > flag else text


def fmt_span(values, fmt, tol, sep=" … ", empty="–"):
    """``fmt(v)`` when the non-None ``values`` agree within ``tol``, else "fmt(lo) sep fmt(hi)"."""
    values = [v for v in values if v is not None]
    if not values:
        return empty
    lo, hi = min(values), max(values)
    return fmt(lo) if abs(hi - lo) < tol else f"{fmt(lo)}{sep}{fmt(hi)}"


def markdown_table(header, rows, align=None):
    """Markdown table lines; ``align`` per column: "l" or "r" (default: first left, others right)."""
    align = align or ["l"] + ["r"] * (len(header) - 1)
    sep = ["---" if a == "l" else "---:" for a in align]
    return ["| " + " | ".join(header) + " |", "|" + "|".join(sep) + "|"] + \
        ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]


def write_results(out_dir, stem, result, markdown):
    """Write ``stem``.json (:func:`jsonable`, indent 1, with :func:`metadata` under ``metadata``) and
    ``stem``.md into ``out_dir``."""
    import json
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}.json").write_text(json.dumps(jsonable(with_metadata(result)), indent=1))
    (out / f"{stem}.md").write_text(markdown)
    return out / f"{stem}.json", out / f"{stem}.md"


# --------------------------------------------------------------------------- #
#  timing of commands: wall and CPU seconds (the CPU of a loaded machine's
#  neighbours does not count; wall time does)
# --------------------------------------------------------------------------- #
def timed_command(cmd, env=None, cwd=None):
    """Run ``cmd`` (a list) to completion in ``cwd``, output discarded; returns {"wall": s, "cpu": s}:
    wall-clock seconds and the CPU seconds (user + system) of the command and its children
    (``resource.getrusage(RUSAGE_CHILDREN)`` before and after).  (``python -c`` puts its working
    directory first on the path: run such commands elsewhere than a checkout they must not import.)"""
    import resource
    import subprocess
    import time
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env, cwd=cwd)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return {"wall": wall, "cpu": (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)}


# --------------------------------------------------------------------------- #
#  timing and the metadata every result file carries (issue 32)
# --------------------------------------------------------------------------- #
class Timing:
    """What :func:`timed` measured: the last ``result``, and per call ``walls`` and ``cpus`` [s]."""

    def __init__(self, result, walls, cpus):
        self.result, self.walls, self.cpus = result, walls, cpus

    best_wall = property(lambda self: min(self.walls))
    best_cpu = property(lambda self: min(self.cpus))
    median_wall = property(lambda self: float(np.median(self.walls)))
    median_cpu = property(lambda self: float(np.median(self.cpus)))


def timed(fn, repeat=1, warmup=False):
    """Call ``fn()`` ``repeat`` times (after one untimed call when ``warmup``) and time each call.

    Parameters
    ----------
    fn : callable
        No arguments; its last return value is kept.
    repeat : int
        Timed calls.
    warmup : bool
        One untimed call first (kernels built, caches filled).

    Returns
    -------
    Timing
        ``result`` (last return value), ``walls`` and ``cpus`` (lists of ``repeat`` floats [s]:
        wall-clock ``time.perf_counter`` and process CPU ``time.process_time``, all threads of this
        process — PoCL's workers included — so the CPU time is the measure other jobs' load distorts
        least), and ``best_*`` / ``median_*`` of both.
    """
    import time
    result = fn() if warmup else None
    walls, cpus = [], []
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        result = fn()
        walls.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
    return Timing(result, walls, cpus)


def git_commit():
    """``git rev-parse HEAD`` of the repository (``+dirty`` when tracked files differ), or None."""
    import subprocess
    root = BENCHMARKS.parent
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                              check=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return head + ("+dirty" if dirty else "")


def opencl_device():
    """Name of the first OpenCL device pyopencl finds ("name [platform]"), or None."""
    try:
        import pyopencl as cl
        for platform_ in cl.get_platforms():
            for dev in platform_.get_devices():
                return f"{dev.name.strip()} [{platform_.name.strip()}]"
    except Exception:                                # no pyopencl, no ICD, no device
        return None
    return None


def metadata():
    """What every result file names: commit, machine, device, load and date.

    Returns
    -------
    dict
        ``commit`` (str or None), ``date`` (UTC, ISO 8601), ``machine`` ({cpu, cores, platform,
        node, python}), ``device`` (OpenCL device name or None), ``loadavg`` ([1, 5, 15] min or None).
    """
    import datetime
    import sys
    return {"commit": git_commit(),
            "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "machine": {"cpu": cpu_model(), "cores": os.cpu_count(), "platform": platform.platform(),
                        "node": platform.node(), "python": sys.version.split()[0]},
            "device": opencl_device(), "loadavg": loadavg()}


def with_metadata(result):
    """``result`` (a dict) with a ``metadata`` key (:func:`metadata`) unless it has one."""
    if isinstance(result, dict) and "metadata" not in result:
        result = {**result, "metadata": metadata()}
    return result


def write_json(path, result, indent=1):
    """Write ``result`` + :func:`metadata` as JSON to ``path`` (temporary name, then renamed).

    Parameters
    ----------
    path : str or Path
        Destination; its folder is created.
    result : dict
        The benchmark's result (:func:`jsonable` is applied).
    indent : int
        JSON indentation.

    Returns
    -------
    Path
        ``path``.
    """
    import json
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(jsonable(with_metadata(result)), indent=indent) + "\n")
    os.replace(tmp, path)
    return path
