"""Peak memory of a full-detector ramp (issue 9: ≤ 1.5 GB; 3.2 GB before the table cache).

The command measured, in a fresh process per case (what ``slicersim ramp --redshift 1 --nmd 64
8 0 --out x.h5`` runs)::

    LazuliSupernova(1.0, config="cbe", field="narrow").get_ramps(nmd=(64, 8, 0), out="x.h5")

Cases: ``today`` (git revision ``--baseline``, default the commit before the projection-table
cache), ``cold`` (this tree, empty table cache: tables built and written), ``warm`` (this tree,
tables read back memory-mapped), and the cold/warm cases again with the ramp driver's
``memory_budget`` at ``--budget`` (default 512 MiB; the default budget is 1 GiB).

Per case: the process's peak resident set size (``ru_maxrss``, exact), and per phase (target,
detector image = projection tables and deposit, ramp) the peak and final RSS sampled every 5 ms
by a thread (psutil), and the wall time.  Writes ``results/ramp_memory.{json,md,png}``.

    .venv/bin/python benchmarks/ramp_memory.py [--baseline REV] [--budget MiB] [--out benchmarks/results]
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GOAL_GB = 1.5
_CHILD = r"""
import json, resource, sys, threading, time
import psutil
proc = psutil.Process()
state = {"peak": 0, "stop": False}
def sample():
    while not state["stop"]:
        state["peak"] = max(state["peak"], proc.memory_info().rss)
        time.sleep(0.005)
threading.Thread(target=sample, daemon=True).start()
phases = []
T0 = time.perf_counter()
def mark(name):
    rss = proc.memory_info().rss
    phases.append({"phase": name, "t_s": time.perf_counter() - T0, "peak_gb": max(state["peak"], rss) / 1e9,
                   "end_gb": rss / 1e9})
    state["peak"] = rss
import slicersim
from slicersim.backends import opencl
from slicersim.products import ramps as ramps_module
from slicersim.targets import Target, LazuliSupernova
mark("import")
real_image, real_simulate = Target.get_detector_image, ramps_module.simulate
def image(self, *a, **k):
    out = real_image(self, *a, **k)
    mark("detector image")
    return out
def simulate(*a, **k):
    mark("between")
    out = real_simulate(*a, **k)
    mark("ramp")
    return out
Target.get_detector_image, ramps_module.simulate = image, simulate
out, budget = sys.argv[1], int(sys.argv[2])
t = LazuliSupernova(1.0, config="cbe", field="narrow")
mark("target")
kwargs = {} if budget <= 0 else {"memory_budget": budget}
t.get_ramps(nmd=(64, 8, 0), out=out, progress=False, **kwargs)
state["stop"] = True
print(json.dumps({"ru_maxrss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9,
                  "wall_s": time.perf_counter() - T0, "phases": phases, "slicersim": slicersim.__file__,
                  "kernel_dir": opencl.kernel_dir(), "device": opencl.get_device().name.strip()}))
"""


def _default_baseline():
    """The parent of the commit that added the table cache (io/table_cache.py)."""
    res = subprocess.run(["git", "-C", str(ROOT), "log", "--diff-filter=A", "--format=%H", "--",
                          "slicersim/io/table_cache.py"], capture_output=True, text=True, check=True)
    first = res.stdout.split()[-1]
    return subprocess.run(["git", "-C", str(ROOT), "rev-parse", first + "^"], capture_output=True, text=True,
                          check=True).stdout.strip()


def _run(case, tree, cache, budget, tmp):
    env = dict(os.environ, SLICERSIM_CACHE=str(cache))
    if tree != ROOT:
        env["PYTHONPATH"] = str(tree) + os.pathsep + env.get("PYTHONPATH", "")
    out = Path(tmp) / f"{case}.h5"
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-c", _CHILD, str(out), str(budget)], env=env, cwd=tree,
                         capture_output=True, text=True)
    if res.returncode:
        raise RuntimeError(f"{case} failed:\n{res.stderr[-3000:]}")
    record = json.loads(res.stdout.strip().splitlines()[-1])
    record.update(case=case, budget_bytes=budget if budget > 0 else 2**30, h5_bytes=out.stat().st_size,
                  process_s=time.perf_counter() - t0)
    out.unlink()
    ph = {p["phase"]: p for p in record["phases"]}
    print(f"{case:12s} peak RSS {record['ru_maxrss_gb']:.2f} GB  (image phase peak {ph['detector image']['peak_gb']:.2f}, "
          f"before ramp {ph['between']['end_gb']:.2f}, ramp phase peak {ph['ramp']['peak_gb']:.2f}); "
          f"image at {ph['detector image']['t_s']:.1f} s, total {record['wall_s']:.1f} s", flush=True)
    return record


def _plot(records, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(8, 4))
    names = [r["case"] for r in records]
    x = range(len(records))
    ph = [{p["phase"]: p for p in r["phases"]} for r in records]
    ax.bar([i - 0.27 for i in x], [p["detector image"]["peak_gb"] for p in ph], 0.27, label="detector-image phase peak")
    ax.bar(list(x), [p["between"]["end_gb"] for p in ph], 0.27, label="resident before the ramp")
    ax.bar([i + 0.27 for i in x], [r["ru_maxrss_gb"] for r in records], 0.27, label="process peak (ru_maxrss)")
    ax.axhline(GOAL_GB, color="k", ls="--", lw=1, label=f"goal {GOAL_GB} GB")
    ax.set_xticks(list(x))
    ax.set_xticklabels(names, rotation=15)
    ax.set_ylabel("resident memory [GB]")
    ax.set_title("Full-detector MACC(64,8,0) ramp, LazuliSupernova(z=1), to HDF5")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def _markdown(record):
    m = record["machine"]
    lines = ["### Peak memory of a full-detector ramp (`benchmarks/ramp_memory.py`)", "",
             f"`LazuliSupernova(1, config=\"cbe\", field=\"narrow\").get_ramps(nmd=(64, 8, 0), out=...)` in a fresh "
             f"process per case; {m['cpu']} ({m['cores']} cores, {record['device']}), load average "
             f"{m['loadavg_before']} → {m['loadavg_after']}.  `today` = revision `{record['baseline'][:10]}`; "
             f"goal ≤ {GOAL_GB} GB.  Peak = `ru_maxrss`; phase values sampled every 5 ms (psutil).", "",
             "| case | ramp memory_budget | peak RSS [GB] | image phase peak [GB] | resident before ramp [GB] "
             "| ramp phase peak [GB] | image [s] | total [s] |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in record["cases"]:
        ph = {p["phase"]: p for p in r["phases"]}
        t_image = ph["detector image"]["t_s"] - ph["target"]["t_s"]
        lines.append(f"| {r['case']} | {r['budget_bytes'] / 2**20:.0f} MiB | {r['ru_maxrss_gb']:.2f} | "
                     f"{ph['detector image']['peak_gb']:.2f} | {ph['between']['end_gb']:.2f} | "
                     f"{ph['ramp']['peak_gb']:.2f} | {t_image:.1f} | {r['wall_s']:.1f} |")
    lines += ["", record["note"], ""]
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", help="git revision of 'today' (default: the commit before the table cache)")
    ap.add_argument("--budget", type=float, default=512, help="ramp memory_budget [MiB] of the extra cases")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from _common import cpu_model, jsonable, loadavg
    baseline = args.baseline or _default_baseline()
    budget = int(args.budget * 2**20)
    load_before = loadavg()
    records = []
    with tempfile.TemporaryDirectory(prefix="ramp_memory_") as tmp:
        base = Path(tmp) / "baseline"
        base.mkdir()
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", baseline], capture_output=True, check=True)
        subprocess.run(["tar", "-x", "-C", str(base)], input=archive.stdout, check=True)
        cache = Path(tmp) / "cache"
        records.append(_run("today", base, Path(tmp) / "unused", 0, tmp))
        records.append(_run("cold", ROOT, cache, 0, tmp))
        records.append(_run("warm", ROOT, cache, 0, tmp))
        import shutil
        shutil.rmtree(cache)
        records.append(_run(f"cold {args.budget:.0f} MiB", ROOT, cache, budget, tmp))
        records.append(_run(f"warm {args.budget:.0f} MiB", ROOT, cache, budget, tmp))
    today, warm = records[0]["ru_maxrss_gb"], records[2]["ru_maxrss_gb"]
    ph = {r["case"]: {p["phase"]: p for p in r["phases"]} for r in records}
    ramp_extra = ph["warm"]["ramp"]["peak_gb"] - ph["warm"]["between"]["end_gb"]
    note = (f"Today {today:.2f} GB → {warm:.2f} GB with warm tables at the default 1 GiB ramp budget; the "
            f"projection phase peaks at {ph['cold']['detector image']['peak_gb']:.2f} GB (cold) / "
            f"{ph['warm']['detector image']['peak_gb']:.2f} GB (warm) and leaves "
            f"{ph['warm']['between']['end_gb']:.2f} GB resident for the ramp (was "
            f"{ph['today']['between']['end_gb']:.2f} GB).  The ramp itself then adds {ramp_extra:.2f} GB "
            f"at the default 1 GiB memory_budget (the ramp driver's accounting, outside the table cache); at "
            f"{args.budget:.0f} MiB the whole run peaks at {records[3]['ru_maxrss_gb']:.2f} GB (cold) / "
            f"{records[4]['ru_maxrss_gb']:.2f} GB (warm).")
    print(note)
    record = {"machine": {"cpu": cpu_model(), "cores": os.cpu_count(), "loadavg_before": load_before,
                          "loadavg_after": loadavg()},
              "device": records[1]["device"], "baseline": baseline, "goal_gb": GOAL_GB, "note": note,
              "cases": records}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "ramp_memory.json").write_text(json.dumps(jsonable(record), indent=1))
    (out / "ramp_memory.md").write_text(_markdown(record))
    _plot(records, out / "ramp_memory.png")


if __name__ == "__main__":
    main()
