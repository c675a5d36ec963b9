#!/usr/bin/env python
"""Raw ramps with detector effects: cost of ``--effects all`` against the plain ramp, same run.

Each case runs in its own subprocess (so its peak resident memory is its own): the Lazuli-like
rate image of ``ramp_throughput.py`` (default 4096², the full H4RG), MACC(64, 8, 0), one ramp,
written to HDF5 in a temporary directory (``--tmp``), with

* ``plain``  — Poisson charge, white read noise, kTC, bias, saturation (today's ramp);
* each effect alone (``--each``, optional) and
* ``all``    — the realistic Lazuli preset (``DetectorEffects.preset("lazuli")``: every effect
  except persistence).

Reported: wall time of ``simulate`` (file written and closed), its ratio to ``plain`` measured in
the same run, peak RSS of the process (``ru_maxrss``), file size.  Goals (issue 9): ``all`` ≤ 2×
``plain``; peak memory ≤ 1.5 GB.  Writes ``<out>/ramp_effects.json``, ``.png`` and ``.md``.

    .venv/bin/python benchmarks/ramp_effects.py [--side 4096] [--nmd 64 8 0] [--each] [--repeat K] [--tmp DIR]
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))

from _common import cpu_model, jsonable, loadavg  # noqa: E402

CHILD = r"""
import json, resource, sys, time
sys.path.insert(0, {root!r}); sys.path.insert(0, {here!r})
import numpy as np
from ramp_throughput import DETECTOR, lazuli_rate_image
from slicersim.products.ramps import simulate
rate = lazuli_rate_image({side}, {side})
effects = {effects!r}
warm = simulate(rate[:16], {nmd}, seed=1, progress=False, effects=effects, **DETECTOR)   # kernel builds
t, c = time.perf_counter(), time.process_time()
simulate(rate, {nmd}, seed=1, out={out!r}, progress=False, effects=effects, **DETECTOR)
wall, cpu = time.perf_counter() - t, time.process_time() - c
import os
ru = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({{"wall_s": wall, "cpu_s": cpu, "peak_rss_bytes": ru.ru_maxrss * 1024,
                  "file_bytes": os.path.getsize({out!r})}}))
"""


def run_case(name, effects, args, tmp):
    out = str(Path(tmp) / f"{name}.h5")
    code = CHILD.format(root=str(ROOT), here=str(HERE), side=args.side, nmd=tuple(args.nmd), effects=effects,
                        out=out)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if proc.returncode:
        raise SystemExit(f"case {name} failed:\n{proc.stderr[-3000:]}")
    row = json.loads(proc.stdout.strip().splitlines()[-1])
    os.unlink(out)
    row.update(name=name, effects=effects)
    print(f"{name:18s} {row['wall_s']:7.1f} s  peak RSS {row['peak_rss_bytes'] / 1e9:5.2f} GB  "
          f"file {row['file_bytes'] / 1e9:5.2f} GB", flush=True)
    return row


def plot(result, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rows = result["rows"]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4))
    names = [r["name"] for r in rows]
    a1.barh(names, [r["ratio"] for r in rows], color="C0")
    a1.axvline(2.0, color="C3", ls="--", label="goal ≤ 2×")
    a1.set_xlabel("wall time / plain ramp (same run)")
    a1.legend()
    a2.barh(names, [r["peak_rss_bytes"] / 1e9 for r in rows], color="C1")
    a2.axvline(1.5, color="C3", ls="--", label="goal ≤ 1.5 GB")
    a2.set_xlabel("peak RSS [GB]")
    a2.legend()
    fig.suptitle(f"{result['shape'][0]}² MACC{tuple(result['nmd'])} ramp with detector effects — {result['cpu']}",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def markdown(result):
    lines = ["### Ramps with detector effects (`benchmarks/ramp_effects.py`)", "",
             f"{result['shape'][0]}² Lazuli-like image, MACC{tuple(result['nmd'])}, 1 ramp to HDF5; {result['cpu']}, "
             f"{result['device']}; load {result['load_before']} before, {result['load_after']} after. Each case in "
             f"its own process; fastest of {result['repeat']} interleaved run(s); CPU = user + system time of "
             "all the process's threads during `simulate`.", "",
             "| case | wall [s] | × plain | CPU [s] | CPU × plain | peak RSS [GB] | file [GB] |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for r in result["rows"]:
        lines.append(f"| {r['name']} | {r['wall_s']:.1f} | {r['ratio']:.2f} | {r['cpu_s']:.1f} | {r['cpu_ratio']:.2f} | "
                     f"{r['peak_rss_bytes'] / 1e9:.2f} | {r['file_bytes'] / 1e9:.2f} |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--side", type=int, default=4096)
    ap.add_argument("--nmd", type=int, nargs=3, default=(64, 8, 0))
    ap.add_argument("--each", action="store_true", help="also time each effect alone")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    ap.add_argument("--tmp", default=None)
    ap.add_argument("--repeat", type=int, default=1,
                    help="run the cases K times, interleaved, and keep each case's fastest run (robust to a "
                         "shared machine's load changing between cases)")
    args = ap.parse_args()
    from slicersim.backends import opencl
    from slicersim.physics.effects import EFFECT_NAMES
    dev = opencl.get_device()
    load0 = loadavg()
    cases = [("plain", None)]
    if args.each:
        cases += [(name, name) for name in EFFECT_NAMES if name != "persistence"]
    cases += [("all (lazuli)", "lazuli")]
    with tempfile.TemporaryDirectory(dir=args.tmp) as tmp:
        runs = [[run_case(name, fx, args, tmp) for name, fx in cases] for _ in range(max(1, args.repeat))]
    rows = []
    for i in range(len(cases)):
        tries = [run[i] for run in runs]
        best = dict(min(tries, key=lambda r: r["wall_s"]))
        best["walls_s"] = [r["wall_s"] for r in tries]
        best["cpu_s"] = min(r["cpu_s"] for r in tries)
        rows.append(best)
    for r in rows:
        r["ratio"] = r["wall_s"] / rows[0]["wall_s"]
        r["cpu_ratio"] = r["cpu_s"] / rows[0]["cpu_s"]
    result = {"benchmark": "ramp_effects", "shape": [args.side, args.side], "nmd": list(args.nmd), "rows": rows,
              "cpu": cpu_model(), "cores": os.cpu_count(), "device": f"{dev.name.strip()} [{dev.platform.name.strip()}]",
              "load_before": load0, "load_after": loadavg(), "repeat": max(1, args.repeat)}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "ramp_effects.json").write_text(json.dumps(jsonable(result), indent=1))
    plot(result, out / "ramp_effects.png")
    (out / "ramp_effects.md").write_text(markdown(result))
    print(markdown(result))


if __name__ == "__main__":
    main()
