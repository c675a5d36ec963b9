#!/usr/bin/env python
"""Raw ramps with cosmic rays and IPC: slicersim against romanisim, CPU-seconds per pixel-read.

Both simulate the same rate image [e-/s] with the same readout, in one run (one after the other,
on the same machine and load):

* images: the Lazuli-like image of ``benchmarks/ramp_throughput.py`` (:func:`lazuli_rate_image`,
  ``--size``², 97 % dark pixels, 40 spectral traces 0.01–50 e-/s, 32 saturating pixels) and a flat
  image (``--flat`` e-/s, a sky-like background where every pixel collects charge);
* readout MACC(n, m, d) (default 16, 8, 0: 128 reads in 16 resultants of 8), frame time 2.83 s
  (romanisim's ``parameters.read_time`` set to it), read noise 12 e-, gain 1;
* slicersim: ``slicersim.products.ramps.simulate(rate, nmd, effects="cosmic_rays,ipc")`` in
  memory (detector terms of ramp_throughput: dark, thermal dark, ROIC glow), OpenCL backend where
  available (else the NumPy twin, recorded);
* romanisim (``benchmarks/.venv-romanisim``, git-ignored, made on first use with
  ``pip install romanisim==0.15.0``; runner ``benchmarks/_romanisim_runner.py``): the total counts
  drawn as its image step does (Poisson of rate × time of the last read) then
  ``romanisim.l1.make_l1`` with cosmic rays (``crparam``: 5 cm⁻² s⁻¹, 10 µm pixels 6 µm deep, the
  image's area) and IPC (its default kernel) on.

CPU time = process time of all threads (load-independent on the shared VM); median of
``--repeat`` runs of romanisim and of 2 × ``--repeat`` runs of slicersim (half before, half after
romanisim's), after one untimed warm-up run of slicersim on the same image (kernel builds, device workspace;
romanisim's imports are likewise outside its timing).  ``--baseline REV`` also times our side at
another git revision (a temporary worktree, in its own process) between the two.  The figure of merit is
CPU-seconds per pixel-read (pixels × reads) and the ratio romanisim / slicersim.

Writes ``<out>/ramp_vs_romanisim.json``, ``.md`` and ``.png``.

    .venv/bin/python benchmarks/ramp_vs_romanisim.py [--size 1024] [--nmd 16 8 0] [--flat 1.0]
        [--repeat 3] [--baseline REV] [--out benchmarks/results]
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import BENCHMARKS, cpu_model, loadavg, markdown_table, start_runner, write_results  # noqa: E402
from ramp_throughput import DETECTOR, lazuli_rate_image  # noqa: E402

from slicersim.backends import opencl  # noqa: E402
from slicersim.products import ramps  # noqa: E402

VENV = BENCHMARKS / ".venv-romanisim"
REQUIREMENT = "romanisim==0.15.0"
EFFECTS = "cosmic_rays,ipc"
CR = {"cr_flux": 5.0, "pixel_pitch": 10.0, "pixel_depth": 6.0}      # slicersim's CosmicRayParameters defaults


def reads(nmd):
    n, m, d = nmd
    return n * m


def ours(rate, nmd, repeat):
    """Median process CPU [s] and wall [s] of ``simulate`` with cosmic rays and IPC, and the backend."""
    kw = dict(DETECTOR, effects=EFFECTS, progress=False)
    ramps.simulate(rate, nmd, seed=99, **kw)             # warm-up: kernel builds, device workspace
    cpus, walls = [], []
    for r in range(repeat):
        c, w = time.process_time(), time.perf_counter()
        sci = ramps.simulate(rate, nmd, seed=100 + r, **kw)
        cpus.append(time.process_time() - c)
        walls.append(time.perf_counter() - w)
    backend = "opencl" if opencl.is_available() and opencl.device_supports_fp64() else "numpy"
    return {"cpu_s": float(np.median(cpus)), "wall_s": float(np.median(walls)), "cpu_runs_s": cpus,
            "backend": backend, "last_group_mean_adu": float(sci[0, -1].mean())}


_BASELINE_SNIPPET = """
import json, sys, time
import numpy as np
from slicersim.products import ramps
spec = json.loads(sys.argv[1])
rate = np.load(spec["rate_npy"])
kw = dict(spec["detector"], effects=spec["effects"], progress=False)
ramps.simulate(rate, tuple(spec["nmd"]), seed=99, **kw)
cpus = []
for r in range(spec["repeat"]):
    c = time.process_time()
    ramps.simulate(rate, tuple(spec["nmd"]), seed=100 + r, **kw)
    cpus.append(time.process_time() - c)
print(json.dumps(cpus))
"""


def baseline(rev, rate, nmd, repeat, tmp):
    """Our side at git revision ``rev`` (a temporary worktree, this venv), in its own process: median
    CPU [s] and the runs."""
    tree = Path(tmp) / f"baseline_{os.getpid()}"
    if not tree.exists():
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "-q", "--detach", str(tree), rev], check=True)
    path = Path(tmp) / f"rate_base_{id(rate)}.npy"
    np.save(path, rate)
    spec = {"rate_npy": str(path), "nmd": list(nmd), "detector": DETECTOR, "effects": EFFECTS, "repeat": repeat}
    env = {**os.environ, "PYTHONPATH": str(tree)}
    out = subprocess.run([sys.executable, "-c", _BASELINE_SNIPPET, json.dumps(spec)], env=env, cwd=str(tree),
                         capture_output=True, text=True, check=True)
    cpus = json.loads(out.stdout.strip().splitlines()[-1])
    return {"rev": rev, "cpu_s": float(np.median(cpus)), "cpu_runs_s": cpus}


def drop_worktrees(tmp):
    for tree in Path(tmp).glob("baseline_*"):
        subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)], check=False)


def theirs(rate, nmd, repeat, tmp):
    """romanisim's side (runner in its venv): median CPU [s] and the runs."""
    path = Path(tmp) / f"rate_{os.getpid()}_{id(rate)}.npy"
    np.save(path, rate)
    spec = dict(CR, rate_npy=str(path), nmd=list(nmd), tframe=DETECTOR["tframe"], ron=DETECTOR["ron"],
                gain=DETECTOR["gain"], seed=1, repeat=repeat)
    job = start_runner("_romanisim_runner.py", spec, venv=VENV, requirement=REQUIREMENT, argv=("{input}", "{json}"))
    result, _ = job.wait()
    runs = result.pop("runs")
    result.update(cpu_s=float(np.median([r["cpu_s"] for r in runs])),
                  wall_s=float(np.median([r["wall_s"] for r in runs])),
                  make_l1_cpu_s=float(np.median([r["make_l1_cpu_s"] for r in runs])), runs=runs)
    return result


def git_commit():
    out = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip()
    return out.stdout.strip() + ("+dirty" if dirty else "")


def plot(result, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rows = result["rows"]
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.2))
    xs = np.arange(len(rows))
    ax[0].bar(xs - 0.2, [r["slicersim"]["ns_per_pixel_read"] for r in rows], 0.38, label="slicersim")
    ax[0].bar(xs + 0.2, [r["romanisim"]["ns_per_pixel_read"] for r in rows], 0.38, label="romanisim")
    if all("baseline" in r for r in rows):
        ax[0].scatter(xs - 0.2, [r["baseline"]["ns_per_pixel_read"] for r in rows], color="k", marker="_", s=400,
                      zorder=3, label=f"slicersim at {rows[0]['baseline']['rev']}")
        ax[1].scatter(xs, [r["baseline_ratio_cpu"] for r in rows], color="k", marker="_", s=600, zorder=3,
                      label=f"slicersim at {rows[0]['baseline']['rev']}")
    ax[0].set_xticks(xs, [r["image"] for r in rows])
    ax[0].set_ylabel("CPU ns per pixel-read")
    ax[0].set_yscale("log")
    ax[0].legend()
    ax[0].set_title(f"MACC{tuple(result['nmd'])}, {result['shape'][0]}², cosmic rays + IPC")
    ax[1].bar(xs, [r["ratio_cpu"] for r in rows], 0.5, color="C2")
    ax[1].axhline(8, color="C3", ls="--", lw=1, label="goal 8×")
    for i, r in enumerate(rows):
        ax[1].text(i, r["ratio_cpu"] * 1.02, f"{r['ratio_cpu']:.1f}×", ha="center")
    ax[1].set_xticks(xs, [r["image"] for r in rows])
    ax[1].set_ylabel("romanisim / slicersim CPU-s per pixel-read")
    ax[1].legend()
    fig.suptitle(f"{result['machine']['cpu']}, commit {result['commit']}, load {result['machine']['load_before']} → "
                 f"{result['machine']['load_after']}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def markdown(result):
    m = result["machine"]
    lines = ["### Ramps with cosmic rays and IPC: slicersim vs romanisim (`benchmarks/ramp_vs_romanisim.py`)", "",
             f"{result['shape'][0]}² images, MACC{tuple(result['nmd'])} ({result['reads']} reads, "
             f"{result['nmd'][0]} resultants), frame time {DETECTOR['tframe']} s, read noise {DETECTOR['ron']} e-, "
             f"cosmic rays 5 cm⁻² s⁻¹ and IPC on both sides; slicersim {result['slicersim_backend']} "
             f"({m['opencl_device']}), romanisim {result['romanisim_version']} (galsim "
             f"{result['galsim_version']}, numpy {result['romanisim_numpy']}).  Commit {result['commit']}, "
             f"{m['cpu']}, {m['cores']} cores shared with other jobs (load {m['load_before']} → {m['load_after']}).  "
             f"CPU = process time of all threads, median of {result['repeat']} romanisim runs and "
             f"{2 * result['repeat']} slicersim runs (half before, half after), in one run of this script.", ""]
    rows = [[r["image"], f"{r['slicersim']['cpu_s']:.3f}", f"{r['slicersim']['ns_per_pixel_read']:.2f}",
             f"{r['romanisim']['cpu_s']:.2f}", f"{r['romanisim']['ns_per_pixel_read']:.2f}",
             f"**{r['ratio_cpu']:.1f}×**", "yes" if r["ratio_cpu"] >= 8 else "no"] for r in result["rows"]]
    lines += markdown_table(["image", "slicersim CPU [s]", "slicersim [ns / px-read]", "romanisim CPU [s]",
                             "romanisim [ns / px-read]", "romanisim / slicersim", "≥ 8×"], rows)
    lines += ["", "romanisim's CPU includes the draw of the total counts (about "
              f"{max(r['romanisim']['cpu_s'] - r['romanisim']['make_l1_cpu_s'] for r in result['rows']):.2f} s); "
              "its reads are apportioned by a binomial per pixel and read, ours are sampled per frame (bright "
              "pixels) or per group window (dark pixels, the sparse path)."]
    based = [r for r in result["rows"] if "baseline" in r]
    if based:
        lines += ["", f"The same runs of slicersim at {based[0]['baseline']['rev']} (before the sampler changes of "
                  "issue 30; own process, this venv): " + "; ".join(
                      f"{r['image']} {r['baseline']['cpu_s']:.3f} CPU-s, {r['baseline_ratio_cpu']:.1f}× romanisim"
                      for r in based) + "."]
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=1024, help="image side [px] (default 1024)")
    ap.add_argument("--nmd", type=int, nargs=3, default=[16, 8, 0], metavar=("N", "M", "D"))
    ap.add_argument("--flat", type=float, default=1.0, help="rate of the flat image [e-/s] (default 1.0; 0: none)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--baseline", default=None, metavar="REV",
                    help="also time our side at git revision REV (temporary worktree, own process)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    args = ap.parse_args()
    nmd = tuple(args.nmd)
    load0 = loadavg()
    images = [("Lazuli-like", lazuli_rate_image(args.size, args.size))]
    if args.flat > 0:
        images.append((f"flat {args.flat:g} e-/s", np.full((args.size, args.size), args.flat)))
    rows, info = [], {}
    npr = args.size * args.size * reads(nmd)
    with tempfile.TemporaryDirectory(prefix="slicersim_romanisim_") as tmp:
        for name, rate in images:
            before = ours(rate, nmd, args.repeat)              # ours before and after theirs: the load drifts
            base = baseline(args.baseline, rate, nmd, args.repeat, tmp) if args.baseline else None
            them = theirs(rate, nmd, args.repeat, tmp)
            us = ours(rate, nmd, args.repeat)
            us["cpu_runs_s"] = before["cpu_runs_s"] + us["cpu_runs_s"]
            us["cpu_s"] = float(np.median(us["cpu_runs_s"]))
            info = them
            us["ns_per_pixel_read"] = us["cpu_s"] / npr * 1e9
            them["ns_per_pixel_read"] = them["cpu_s"] / npr * 1e9
            row = {"image": name, "slicersim": us, "romanisim": {k: them[k] for k in
                                                                 ("cpu_s", "wall_s", "make_l1_cpu_s", "runs",
                                                                  "ns_per_pixel_read")},
                   "ratio_cpu": them["cpu_s"] / us["cpu_s"], "ratio_wall": them["wall_s"] / us["wall_s"]}
            if base is not None:
                base["ns_per_pixel_read"] = base["cpu_s"] / npr * 1e9
                row["baseline"] = base
                row["baseline_ratio_cpu"] = them["cpu_s"] / base["cpu_s"]
                print(f"  baseline {args.baseline}: {base['cpu_s']:.3f} CPU-s, ratio {row['baseline_ratio_cpu']:.1f}x",
                      flush=True)
            rows.append(row)
            print(f"{name}: slicersim {us['cpu_s']:.3f} CPU-s ({us['ns_per_pixel_read']:.2f} ns/px-read), romanisim "
                  f"{them['cpu_s']:.2f} CPU-s ({them['ns_per_pixel_read']:.2f}); ratio {row['ratio_cpu']:.1f}x",
                  flush=True)
        drop_worktrees(tmp)
    dev = opencl.get_device() if opencl.is_available() else None
    result = {"benchmark": "ramp_vs_romanisim", "shape": [args.size, args.size], "nmd": list(nmd),
              "reads": reads(nmd), "pixel_reads": npr, "effects": EFFECTS, "detector": DETECTOR, "cosmic_rays": CR,
              "repeat": args.repeat, "rows": rows, "commit": git_commit(),
              "slicersim_backend": rows[0]["slicersim"]["backend"],
              "romanisim_version": info.get("romanisim"), "galsim_version": info.get("galsim"),
              "romanisim_numpy": info.get("numpy"), "romanisim_ipc_kernel": info.get("ipc_kernel"),
              "machine": {"cpu": cpu_model(), "cores": os.cpu_count(), "load_before": load0, "load_after": loadavg(),
                          "opencl_device": f"{dev.name.strip()} [{dev.platform.name.strip()}]" if dev else None,
                          "python": sys.version.split()[0], "numpy": np.__version__}}
    out = Path(args.out)
    write_results(out, "ramp_vs_romanisim", result, markdown(result))
    plot(result, out / "ramp_vs_romanisim.png")
    print(f"wrote {out / 'ramp_vs_romanisim.json'}, .md, .png")


if __name__ == "__main__":
    main()
