"""Fast Monte Carlo (issue #8): noisy Airy cubes of a new target per draw.

The loop timed (a new ``LazuliSupernova`` per draw, so nothing cached on a model helps)::

    sn = slicersim.LazuliSupernova(redshift=1.0); sn.change_detector(nmd=(61, 8, 0), nramps=3)
    sn.simulation.get_cube(seed=0, psf_profile="airy")                  # warm-up
    for i, z in enumerate(np.linspace(0.3, 1.4, 12)):
        sn = slicersim.LazuliSupernova(redshift=float(z)); sn.change_detector(nmd=(61, 8, 0), nramps=3)
        cube = sn.simulation.get_cube(seed=i + 1, psf_profile="airy")   # (signal, variance, noisy)

Reports the median time per draw (target + cube) and of ``get_cube`` alone, in ``--runs``
fresh processes.  ``--baseline REV`` also times git revision REV (checked out in a temporary
worktree, run with this virtual environment) in alternating processes, so that machine load
affects both alike.  Writes ``results/monte_carlo.json``.

    .venv/bin/python benchmarks/monte_carlo.py [--runs 3] [--baseline REV] [--out benchmarks/results]
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


def child():
    """One process: warm-up, then the 12 timed draws; prints JSON."""
    import numpy as np
    import slicersim
    from slicersim.backends import opencl
    sn = slicersim.LazuliSupernova(redshift=1.0)
    sn.change_detector(nmd=(61, 8, 0), nramps=3)
    sn.simulation.get_cube(seed=0, psf_profile="airy")
    draw, cube = [], []
    for i, z in enumerate(np.linspace(0.3, 1.4, 12)):
        t0 = time.perf_counter()
        sn = slicersim.LazuliSupernova(redshift=float(z))
        sn.change_detector(nmd=(61, 8, 0), nramps=3)
        t1 = time.perf_counter()
        out = sn.simulation.get_cube(seed=i + 1, psf_profile="airy")
        t2 = time.perf_counter()
        assert len(tuple(out)) == 3
        draw.append(t2 - t0)
        cube.append(t2 - t1)
    print(json.dumps({"draw_s": draw, "cube_s": cube, "slicersim": slicersim.__file__,
                      "device": opencl.get_device().name.strip(), "kernel_dir": opencl.kernel_dir()}))


def _run(pythonpath=None):
    env = dict(os.environ)
    if pythonpath:
        env["PYTHONPATH"] = str(pythonpath) + os.pathsep + env.get("PYTHONPATH", "")
    res = subprocess.run([sys.executable, __file__, "--child"], env=env, capture_output=True, text=True,
                         cwd=pythonpath or ROOT, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def _median_ms(values):
    values = sorted(values)
    n = len(values)
    return 1e3 * (values[n // 2] if n % 2 else 0.5 * (values[n // 2 - 1] + values[n // 2]))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=3, help="fresh processes per revision (default 3)")
    ap.add_argument("--baseline", help="git revision to compare with (e.g. a commit before the change)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child()
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from _common import cpu_model, loadavg, write_json
    results = {"current": []}
    with tempfile.TemporaryDirectory() as tmp:
        base = None
        if args.baseline:
            base = Path(tmp) / "baseline"
            subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(base), args.baseline],
                           check=True, capture_output=True)
            results["baseline"] = []
        try:
            for _ in range(args.runs):
                if base is not None:
                    results["baseline"].append(_run(base))
                results["current"].append(_run())
        finally:
            if base is not None:
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(base)],
                               capture_output=True)
    summary = {}
    for name, runs in results.items():
        draws = [t for r in runs for t in r["draw_s"]]
        cubes = [t for r in runs for t in r["cube_s"]]
        summary[name] = {"draw_ms_median": _median_ms(draws), "cube_ms_median": _median_ms(cubes),
                         "draw_ms_median_per_run": [_median_ms(r["draw_s"]) for r in runs],
                         "cube_ms_median_per_run": [_median_ms(r["cube_s"]) for r in runs]}
        print(f"{name:9s} per draw (target + noisy Airy cube): median {summary[name]['draw_ms_median']:.1f} ms "
              f"(runs: {', '.join(f'{v:.1f}' for v in summary[name]['draw_ms_median_per_run'])}); "
              f"get_cube alone {summary[name]['cube_ms_median']:.1f} ms")
    if "baseline" in summary:
        ratio = summary["baseline"]["draw_ms_median"] / summary["current"]["draw_ms_median"]
        summary["speedup"] = ratio
        print(f"speed-up vs {args.baseline}: {ratio:.2f}x")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    record = {"machine": {"cpu": cpu_model(), "cores": os.cpu_count(), "loadavg": loadavg()},
              "baseline": args.baseline, "runs": args.runs, "summary": summary, "raw": results}
    write_json(out / "monte_carlo.json", record)


if __name__ == "__main__":
    main()
