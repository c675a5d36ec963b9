#!/usr/bin/env python
"""The benchmark runner: every benchmark of ``benchmarks/registry.py``, or those named.

    python benchmarks/run.py [NAME ...] [--smoke] [--list] [--out DIR] [--network] [--timeout S] [--budget S]

Full size (default): each script with its default arguments, results into ``--out`` (default
``benchmarks/results``).  ``--smoke``: each at its smallest size (the registry's ``smoke`` arguments)
into a temporary folder (``--out`` to keep it), with a per-benchmark timeout; benchmarks with no small
size (``smoke_only_help``) only start and parse (``--help``).  Reference releases (PyPI venvs) are
installed in smoke mode only with ``--network``; without it the reference side is skipped, or used
when its venv is already there (``benchmarks/.refvenv``, ``.refvenv142``).

Every benchmark runs in its own process (wall and CPU time of the process tree are measured); every
JSON result it writes gets the :func:`_common.metadata` (commit, machine, device, load) when it lacks
one.  Prints a table (name, seconds, status, acceptance — informational at smoke size), writes it to
``<out>/run_summary.json`` and exits 1 when any benchmark fails to run.
"""
import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _common import markdown_table, metadata, with_metadata  # noqa: E402
from registry import BENCHMARKS, BY_NAME  # noqa: E402

#: reference venvs (git-ignored) whose presence lets a smoke run use the reference side
REFVENVS = (HERE / ".refvenv", HERE / ".refvenv142")


def refvenvs_cached():
    """True when both reference venvs exist (made by an earlier full run)."""
    return all((v / "bin" / "python").exists() for v in REFVENVS)


def command(bench, smoke, network, out):
    """(argv, mode) of one benchmark: mode is "full", "smoke" or "help"."""
    script = [sys.executable, str(HERE / bench.script)]
    out = ["--out", str(out)] if bench.out_arg else []
    if not smoke:
        return script + out, "full"
    if bench.smoke_only_help:
        return script + ["--help"], "help"
    if bench.network:
        if bench.smoke_network is not None and (network or refvenvs_cached()):
            return script + list(bench.smoke_network) + out, "smoke+ref"
        if bench.smoke_network is not None and bench.smoke == bench.smoke_network:
            return script + ["--help"], "help"      # no way to skip the reference: only parse
    return script + list(bench.smoke) + out, "smoke"


def stamp(out, since):
    """Add :func:`_common.metadata` to every JSON result in ``out`` written after ``since`` that
    lacks one; returns their names."""
    names = []
    for path in sorted(Path(out).glob("*.json")):
        if path.name == "run_summary.json" or path.stat().st_mtime < since:
            continue
        try:
            data = json.loads(path.read_text())
        except ValueError:
            continue
        if isinstance(data, dict) and "metadata" not in data:
            tmp = path.with_name(path.name + ".tmp")
            tmp.write_text(json.dumps(with_metadata(data), indent=1) + "\n")
            os.replace(tmp, path)
        names.append(path.name)
    return names


def run_one(bench, smoke, network, out, timeout):
    """Run one benchmark; returns its row (dict)."""
    out.mkdir(parents=True, exist_ok=True)
    argv, mode = command(bench, smoke, network, out)
    log = out / f"{bench.name}.log"
    since = time.time()
    c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    status = "ok"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(HERE.parent),
                                                                   os.environ.get("PYTHONPATH")])),
               MPLBACKEND="Agg")
    with open(log, "w") as fh:
        proc = subprocess.Popen(argv, stdout=fh, stderr=subprocess.STDOUT, cwd=HERE.parent, env=env,
                                start_new_session=True)
        try:
            rc = proc.wait(timeout=timeout)
            if rc != 0:
                status = f"failed (exit {rc})"
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, 9)                  # the benchmark's own process group only
            proc.wait()
            status = f"failed (timeout {timeout:.0f} s)"
    wall = time.perf_counter() - t0
    c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (c1.ru_utime - c0.ru_utime) + (c1.ru_stime - c0.ru_stime)
    files = stamp(out, since) if mode != "help" else []
    accepted = None
    if bench.check is not None and mode != "help":
        path = out / f"{bench.check.result}.json"
        if path.is_file():
            accepted = bench.check.evaluate(json.loads(path.read_text()))
    if status != "ok":
        tail = log.read_text(errors="replace").splitlines()[-15:]
        print(f"--- {bench.name}: {status}; last lines of {log}:\n" + "\n".join(tail), file=sys.stderr)
    return {"name": bench.name, "mode": mode, "argv": argv[1:], "wall_s": wall, "cpu_s": cpu,
            "status": status, "accepted": accepted, "acceptance": bench.acceptance, "files": files}


def table(rows):
    """Markdown table of the rows."""
    def acc(r):
        bench = BY_NAME.get(r["name"])
        if bench is None or bench.check is None or r["mode"] == "help":
            return "–"                               # no machine-checkable acceptance, or not run
        if r["accepted"] is None:
            return "n/a (no value at this size)"
        return "met" if r["accepted"] else "not met"
    return "\n".join(markdown_table(["benchmark", "mode", "wall s", "CPU s", "status", "acceptance"],
                                    [[r["name"], r["mode"], f"{r['wall_s']:.1f}", f"{r['cpu_s']:.1f}",
                                      r["status"], acc(r)] for r in rows],
                                    ["l", "l", "r", "r", "l", "l"]))


def readme_table(benchmarks):
    """The Markdown table of ``benchmarks/README.md``: one row per registered benchmark."""
    rows = []
    for b in benchmarks:
        if b.smoke_only_help:
            smoke = f"`--help` only: {b.note}"
        else:
            smoke = "`" + " ".join(b.smoke) + "`" if b.smoke else "(defaults)"
        flags = "".join(f" [{f}]" for f, on in (("network", b.network), ("device", b.device)) if on)
        rows.append([f"`{b.name}`{flags}", b.question, b.baseline, b.acceptance, smoke])
    return "\n".join(markdown_table(["benchmark", "question", "baseline", "acceptance", "smallest size (smoke)"],
                                    rows, ["l"] * 5))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("names", nargs="*", metavar="NAME", help="benchmarks to run (default: all registered)")
    ap.add_argument("--smoke", action="store_true", help="smallest sizes, into a temporary folder")
    ap.add_argument("--list", action="store_true", help="list the registered benchmarks and exit")
    ap.add_argument("--markdown", action="store_true",
                    help="with --list: the Markdown table of benchmarks/README.md (question, baseline, acceptance, "
                         "smoke command)")
    ap.add_argument("--out", default=None,
                    help="results folder (default: benchmarks/results; with --smoke a temporary one)")
    ap.add_argument("--network", action="store_true",
                    help="with --smoke: also run the reference side (installs reference venvs from PyPI)")
    ap.add_argument("--timeout", type=float, default=None,
                    help="seconds per benchmark (default: the registry's, smoke only; full size: none)")
    ap.add_argument("--budget", type=float, default=None,
                    help="seconds for the whole run: each benchmark's timeout is cut to what is left, and "
                         "those with none left fail (CI: make bench-smoke uses 600)")
    args = ap.parse_args(argv)
    unknown = [n for n in args.names if n not in BY_NAME]
    if unknown:
        ap.error(f"not registered: {', '.join(unknown)} (see --list)")
    chosen = [BY_NAME[n] for n in args.names] if args.names else BENCHMARKS
    if args.list and args.markdown:
        print(readme_table(chosen))
        return 0
    if args.list:
        for b in chosen:
            flags = ", ".join(f for f, on in (("network", b.network), ("device", b.device),
                                             ("smoke: --help only", b.smoke_only_help)) if on)
            print(f"{b.name:26s} {b.question}" + (f"  [{flags}]" if flags else ""))
        return 0
    tmp = None
    if args.out:
        out = Path(args.out)
    elif args.smoke:
        tmp = tempfile.TemporaryDirectory(prefix="slicersim_bench_smoke_")
        out = Path(tmp.name)
    else:
        out = HERE / "results"
    rows, t0 = [], time.perf_counter()
    for bench in chosen:
        timeout = args.timeout or (bench.timeout if args.smoke else None)
        if args.smoke and bench.smoke_only_help:
            timeout = min(timeout, 120)
        if args.budget is not None:
            left = args.budget - (time.perf_counter() - t0)
            if left < 5:
                rows.append({"name": bench.name, "mode": "-", "argv": [], "wall_s": 0.0, "cpu_s": 0.0,
                             "status": "failed (no time left in --budget)", "accepted": None,
                             "acceptance": bench.acceptance, "files": []})
                continue
            timeout = left if timeout is None else min(timeout, left)
        # smoke: one folder per benchmark (no clash, no overwrite); full size: the results folder
        where = out / bench.name if args.smoke else out
        print(f"== {bench.name}", flush=True)
        row = run_one(bench, args.smoke, args.network, where, timeout)
        print(f"   {row['status']}, {row['wall_s']:.1f} s wall, {row['cpu_s']:.1f} s CPU ({row['mode']})",
              flush=True)
        rows.append(row)
    total = time.perf_counter() - t0
    text = table(rows)
    print(text)
    failed = [r["name"] for r in rows if r["status"] != "ok"]
    print(f"{len(rows)} benchmarks, {len(rows) - len(failed)} ok, {len(failed)} failed"
          + (f" ({', '.join(failed)})" if failed else "") + f"; total {total:.0f} s")
    summary = {"smoke": args.smoke, "total_s": total, "rows": rows, "metadata": metadata()}
    if args.smoke or args.out:                  # not into benchmarks/results (the docs pages read it)
        (out / "run_summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    if tmp is not None:
        tmp.cleanup()
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
