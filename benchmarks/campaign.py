"""Campaign throughput: noisy Airy cubes per second, and the 8000-SN survey plan.

All in one run, on this machine:

* **today's loop** — the single-process loop a user wrote before the campaign layer
  (``LazuliSupernova(z)`` + ``get_cube(seed, psf_profile="airy")`` per target), run with the
  code of git revision ``--base`` (default: the commit before the campaign work) in a
  subprocess, so the baseline is measured, not remembered;
* the same loop with today's code (float64, and float32 as campaigns store);
* ``slicersim campaign run`` on an embedded LocalCluster with 1 and 2 workers, cubes written
  to a dataset (float32, with checksums): the steady-state throughput is the marginal rate
  between a small and a large campaign, (N_large − N_small) / (t_large − t_small), so the
  cluster start and the plan are not counted; the end-to-end rate is reported too;
* the 8000-SN plan (population, spectra, batch ETC of both fields) against slicersim
  1.0.0's own per-target loop timed on a few targets in ``benchmarks/.refvenv`` and
  extrapolated (skipped when that venv is absent).

Writes ``benchmarks/results/campaign.{json,md,png}``; quotes ratios (machines differ).
Usage: ``python benchmarks/campaign.py [--n-small 6] [--n-large 30] [--loop 12] [--base REV]``
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
from _common import cpu_model, loadavg, write_json  # noqa: E402

BASE_REV = "61a7a28"        # main before the campaign issue (#8)

LOOP = r"""
import json, sys, time, numpy as np, slicersim
z = np.linspace(0.3, 1.4, {n})
kw = {kw}
sn = slicersim.LazuliSupernova(redshift=1.0); sn.change_detector(nmd=(61, 8, 0), nramps=3)
sn.simulation.get_cube(seed=0, psf_profile="airy", **kw)            # warm-up: kernels compiled
times = []
for i, zi in enumerate(z):
    t = time.perf_counter()
    sn = slicersim.LazuliSupernova(redshift=float(zi)); sn.change_detector(nmd=(61, 8, 0), nramps=3)
    cube = sn.simulation.get_cube(seed=i + 1, psf_profile="airy", **kw)
    times.append(time.perf_counter() - t)
print(json.dumps({{"per_cube_s": times, "shape": list(cube[0].shape)}}))
"""

SPEC = """\
seed = 3
[population]
kind = "snia"
n = {n}
redshift = {{distribution = "uniform", min = 0.3, max = 0.79}}
[observation]
snr = 10
field = "narrow"
psf_profile = "airy"
[products]
spectrum = false
cube = true
"""


def run_loop(pythonpath, n, kw="{}", threads=None):
    env = dict(os.environ, PYTHONPATH=str(pythonpath))
    if threads:
        env["POCL_MAX_PTHREAD_COUNT"] = str(threads)
    out = subprocess.run([sys.executable, "-c", LOOP.format(n=n, kw=kw)], capture_output=True, text=True,
                         env=env, cwd=tempfile.gettempdir(), timeout=1800)
    if out.returncode:
        raise RuntimeError(out.stderr[-2000:])
    res = json.loads(out.stdout.strip().splitlines()[-1])
    t = np.array(res["per_cube_s"])
    return {"n": n, "median_ms": 1e3 * float(np.median(t)), "mean_ms": 1e3 * float(t.mean()),
            "cubes_per_s": 1.0 / float(np.median(t)), "shape": res["shape"]}


def base_checkout(rev, dest):
    """The package at git revision ``rev`` exported to ``dest`` (no .git)."""
    top = subprocess.run(["git", "-C", str(ROOT), "ls-tree", "--name-only", rev], capture_output=True, text=True,
                         check=True).stdout.split()
    paths = ["slicersim"] + (["kernels"] if "kernels" in top else [])   # kernels/ at the root before 0.1.0
    arch = subprocess.run(["git", "-C", str(ROOT), "archive", rev, *paths], capture_output=True,
                          check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=arch, check=True)
    return dest                      # kernels in <dest>/slicersim/kernels (older revisions: <dest>/kernels)


def disk_write_rate(directory, nbytes=512 * 2**20):
    """Sustained write rate [bytes/s] of ``directory`` (written, then fdatasync)."""
    path = Path(directory) / ".bench-write-rate"
    block = os.urandom(4 * 2**20)
    t = time.perf_counter()
    with open(path, "wb") as fh:
        for _ in range(nbytes // len(block)):
            fh.write(block)
        fh.flush()
        os.fdatasync(fh.fileno())
    rate = nbytes / (time.perf_counter() - t)
    path.unlink()
    return rate


def run_campaign_timed(tmp, n, workers, where=None):
    from slicersim.campaign.runner import run_campaign
    spec = Path(tmp) / f"spec{n}.toml"
    spec.write_text(SPEC.format(n=n))
    out = Path(where or tmp) / f"d{n}w{workers}"
    t = time.perf_counter()
    res = run_campaign(spec, out, workers=workers, progress=False)
    wall = time.perf_counter() - t
    if res["done"] != n:
        raise RuntimeError(f"campaign {n}/{workers}: {res}")
    subprocess.run(["rm", "-rf", str(out)], check=True)
    return wall


def plan_8000(n=8000):
    from slicersim.campaign.plan import plan_survey
    from slicersim.campaign.population import SNIaPopulation
    from slicersim.campaign.products import spectrum_grid
    t = time.perf_counter()
    pop = SNIaPopulation(n, redshift={"distribution": "uniform", "min": 0.05, "max": 1.5})
    table = pop.draw(1)
    lbda = spectrum_grid()
    fluxes = pop.spectra(table, lbda)
    t_spec = time.perf_counter() - t
    plan = plan_survey(np.asarray(table["redshift"]), lbda, np.nan_to_num(fluxes), snr=20.0,
                       target_ids=np.asarray(table["target_id"]))
    wall = time.perf_counter() - t
    return {"n": n, "seconds": wall, "spectra_seconds": t_spec,
            "duration_years": float(plan.totals.get("duration_years", np.nan))}


def reference_loop(k=12):
    """slicersim 1.0.0's per-target ETC loop (its own venv): k SNe Ia (hsiao at peak, z uniform
    0.05–1.5, spectra made here and passed as arrays: 1.0.0 downloads nothing), each
    ``LazuliTarget(lbda, flux).setup_to_snr(20, rest-frame 4000–6800 Å)``; seconds per target."""
    from etc_vs_reference import ensure_reference_venv      # creates benchmarks/.refvenv on demand
    ok, why = ensure_reference_venv()
    if not ok:
        return {"error": why}
    from slicersim.campaign.population import SNIaPopulation
    from slicersim.campaign.products import spectrum_grid
    pop = SNIaPopulation(k, redshift={"distribution": "uniform", "min": 0.05, "max": 1.5})
    tab = pop.draw(1)
    lbda = spectrum_grid()
    flux = np.nan_to_num(pop.spectra(tab, lbda))
    with tempfile.TemporaryDirectory() as tmp:
        npz = Path(tmp) / "in.npz"
        np.savez(npz, lbda=lbda, fluxes=flux, z=np.asarray(tab["redshift"]))
        code = r"""
import sys, time, warnings, contextlib, io, numpy as np
warnings.filterwarnings("ignore")
import slicersim
d = np.load(sys.argv[1])
t = time.perf_counter()
for flux, z in zip(d["fluxes"], d["z"]):
    with contextlib.redirect_stdout(io.StringIO()):
        tg = slicersim.LazuliTarget(d["lbda"], flux, mag=None, band="bessellb")
        tg.setup_to_snr(20, per_resolution=True, lbda_range=(4000 * (1 + z), 6800 * (1 + z)), frame="obs")
print((time.perf_counter() - t) / len(d["z"]))
"""
        py = HERE / ".refvenv" / "bin" / "python"
        out = subprocess.run([str(py), "-c", code, str(npz)], capture_output=True, text=True, timeout=1800,
                             cwd=tempfile.gettempdir())
    if out.returncode:
        return {"error": out.stderr.strip().splitlines()[-1] if out.stderr.strip() else "failed"}
    return {"k": k, "seconds_per_target": float(out.stdout.strip().splitlines()[-1])}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n-small", type=int, default=6)
    ap.add_argument("--n-large", type=int, default=30)
    ap.add_argument("--loop", type=int, default=12, help="targets in the single-process loops")
    ap.add_argument("--base", default=BASE_REV, help="git revision of today's loop")
    ap.add_argument("--skip-plan", action="store_true")
    ap.add_argument("--out", default=str(HERE / "results"), help="results folder (default benchmarks/results)")
    args = ap.parse_args()
    res = {"cpu": cpu_model(), "cores": os.cpu_count(), "load_before": loadavg(), "base_rev": args.base}
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "base").mkdir()
        base = base_checkout(args.base, Path(tmp) / "base")
        res["loop_today"] = run_loop(base, args.loop)
        print(f"[loop] today ({args.base}): {res['loop_today']['median_ms']:.0f} ms/cube", flush=True)
        res["loop_now_f64"] = run_loop(ROOT, args.loop)
        print(f"[loop] now float64: {res['loop_now_f64']['median_ms']:.0f} ms/cube", flush=True)
        res["loop_now_f32"] = run_loop(ROOT, args.loop, kw="{'dtype': 'float32'}")
        print(f"[loop] now float32: {res['loop_now_f32']['median_ms']:.0f} ms/cube", flush=True)
        res["campaign"], res["campaign_tmpfs"] = {}, {}
        res["disk_write_MBps"] = disk_write_rate(tmp) / 1e6
        places = [("campaign", tmp)] + ([("campaign_tmpfs", "/dev/shm")] if os.path.isdir("/dev/shm") else [])
        for key, where in places:
            for workers in (1, 2):
                with tempfile.TemporaryDirectory(dir=where) as wdir:
                    small = run_campaign_timed(tmp, args.n_small, workers, wdir)
                    large = run_campaign_timed(tmp, args.n_large, workers, wdir)
                steady = (args.n_large - args.n_small) / (large - small)
                res[key][workers] = {"n_small": args.n_small, "t_small": small, "n_large": args.n_large,
                                     "t_large": large, "steady_cubes_per_s": steady,
                                     "end_to_end_cubes_per_s": args.n_large / large,
                                     "steady_ms_per_cube": 1e3 / steady, "where": where}
                print(f"[{key}] {workers} worker(s): {steady:.2f} cubes/s steady "
                      f"({args.n_large / large:.2f} end to end)", flush=True)
    today = res["loop_today"]["cubes_per_s"]
    res["ratios_vs_today"] = {
        "loop_now_f64": res["loop_now_f64"]["cubes_per_s"] / today,
        "loop_now_f32": res["loop_now_f32"]["cubes_per_s"] / today,
        **{f"campaign_{w}w_steady": c["steady_cubes_per_s"] / today for w, c in res["campaign"].items()},
        **{f"campaign_{w}w_end_to_end": c["end_to_end_cubes_per_s"] / today for w, c in res["campaign"].items()}}
    for w, c in res["campaign_tmpfs"].items():
        res["ratios_vs_today"][f"campaign_tmpfs_{w}w_steady"] = c["steady_cubes_per_s"] / today
    res["scaling_2w_over_1w"] = res["campaign"][2]["steady_cubes_per_s"] / res["campaign"][1]["steady_cubes_per_s"]
    if res["campaign_tmpfs"]:
        res["scaling_2w_over_1w_tmpfs"] = (res["campaign_tmpfs"][2]["steady_cubes_per_s"]
                                           / res["campaign_tmpfs"][1]["steady_cubes_per_s"])
    if not args.skip_plan:
        res["plan_8000"] = plan_8000()
        print(f"[plan] 8000 SNe: {res['plan_8000']['seconds']:.1f} s", flush=True)
        ref = reference_loop()
        res["reference_1_0_0"] = ref
        if ref and "seconds_per_target" in ref:
            ref["extrapolated_8000_s"] = ref["seconds_per_target"] * 8000
            res["plan_speedup_vs_1_0_0"] = ref["extrapolated_8000_s"] / res["plan_8000"]["seconds"]
            print(f"[plan] slicersim 1.0.0 loop: {ref['seconds_per_target']:.2f} s/target → "
                  f"{ref['extrapolated_8000_s'] / 3600:.1f} h for 8000 (×{res['plan_speedup_vs_1_0_0']:.0f})")
    res["load_after"] = loadavg()
    outdir = Path(args.out)
    outdir.mkdir(parents=True, exist_ok=True)
    write_json(outdir / "campaign.json", res)
    (outdir / "campaign.md").write_text(markdown(res))
    figure(res, outdir / "campaign.png")
    print(markdown(res))


def markdown(res):
    r = res["ratios_vs_today"]
    lines = [f"Campaign throughput on {res['cpu']} ({res['cores']} cores, load {res['load_before']}); "
             f"`python benchmarks/campaign.py`; today's loop = git {res['base_rev']}.", "",
             "| path | ms per noisy Airy cube | cubes/s | × today's loop |", "|---|---|---|---|",
             f"| today's loop (float64) | {res['loop_today']['median_ms']:.0f} | "
             f"{res['loop_today']['cubes_per_s']:.2f} | 1.00 |",
             f"| loop now, float64 | {res['loop_now_f64']['median_ms']:.0f} | "
             f"{res['loop_now_f64']['cubes_per_s']:.2f} | {r['loop_now_f64']:.2f} |",
             f"| loop now, float32 | {res['loop_now_f32']['median_ms']:.0f} | "
             f"{res['loop_now_f32']['cubes_per_s']:.2f} | {r['loop_now_f32']:.2f} |"]
    for w, c in res["campaign"].items():
        lines.append(f"| campaign, {w} worker(s), steady (written, float32) | {c['steady_ms_per_cube']:.0f} | "
                     f"{c['steady_cubes_per_s']:.2f} | {r[f'campaign_{w}w_steady']:.2f} |")
        lines.append(f"| campaign, {w} worker(s), end to end ({c['n_large']} targets, incl. start and plan) | "
                     f"{1e3 / c['end_to_end_cubes_per_s']:.0f} | {c['end_to_end_cubes_per_s']:.2f} | "
                     f"{r[f'campaign_{w}w_end_to_end']:.2f} |")
    for w, c in res.get("campaign_tmpfs", {}).items():
        lines.append(f"| campaign, {w} worker(s), steady, dataset on tmpfs (no disk) | {c['steady_ms_per_cube']:.0f} | "
                     f"{c['steady_cubes_per_s']:.2f} | {r[f'campaign_tmpfs_{w}w_steady']:.2f} |")
    lines.append("")
    lines.append(f"2 workers / 1 worker (steady): {res['scaling_2w_over_1w']:.2f}× on disk"
                 + (f", {res['scaling_2w_over_1w_tmpfs']:.2f}× on tmpfs" if "scaling_2w_over_1w_tmpfs" in res else "")
                 + f".  Disk write rate (512 MiB + fdatasync): {res['disk_write_MBps']:.0f} MB/s; a cube target "
                   "writes 3 float32 cubes (~40 MB) and reads them back for its sha256.")
    if "plan_8000" in res:
        p = res["plan_8000"]
        txt = f"8000-SN plan (population, spectra, batch ETC): {p['seconds']:.1f} s (spectra {p['spectra_seconds']:.1f} s)"
        ref = res.get("reference_1_0_0")
        if ref and "seconds_per_target" in ref:
            txt += (f"; slicersim 1.0.0's loop: {ref['seconds_per_target']:.2f} s per target, "
                    f"{ref['extrapolated_8000_s'] / 3600:.1f} h extrapolated to 8000 "
                    f"(×{res['plan_speedup_vs_1_0_0']:.0f}).")
        else:
            txt += f"; slicersim 1.0.0 not measured ({ref})."
        lines.append(txt)
    return "\n".join(lines) + "\n"


def figure(res, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    labels = ["today's loop", "loop now f64", "loop now f32"] + \
        [f"campaign {w}w\ndisk" for w in res["campaign"]] + [f"campaign {w}w\ntmpfs" for w in res["campaign_tmpfs"]]
    rates = [res["loop_today"]["cubes_per_s"], res["loop_now_f64"]["cubes_per_s"],
             res["loop_now_f32"]["cubes_per_s"]] + [c["steady_cubes_per_s"] for c in res["campaign"].values()] + \
        [c["steady_cubes_per_s"] for c in res["campaign_tmpfs"].values()]
    fig, ax = plt.subplots(figsize=(8.5, 3.8))
    bars = ax.bar(labels, rates, color=["0.6", "C0", "C0"] + ["C2"] * len(res["campaign"])
                  + ["C1"] * len(res["campaign_tmpfs"]))
    for b, r in zip(bars, rates):
        ax.text(b.get_x() + b.get_width() / 2, r, f"{r / rates[0]:.1f}×", ha="center", va="bottom")
    ax.axhline(2.5 * rates[0], ls="--", color="C3", lw=1, label="goal: 2.5× today's loop")
    ax.set_ylabel("noisy Airy cubes / s")
    ax.set_title(f"{res['cpu']} ({res['cores']} cores)", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()
