#!/usr/bin/env python
"""Speed of ``slicersim reduce --spectra`` (one field, defaults) against simulating the same ramp, and
speed against accuracy of the rectification choices.

1. In one run, as a user would: ``slicersim ramp --redshift Z --out RAW`` and ``slicersim reduce RAW
   --out RED --spectra --quiet`` (subprocesses, wall time, ``--repeat`` times each, alternated), then
   ``reduce_exposure`` in this process with every step timed (ramp fit, white-light start, forward
   extraction, rectification, writing).  Ratio = reduce / ramp (goal ≤ 1).
2. Rectification choices on the noiseless image of the same SN (``get_detector_image``): lsq and
   drizzle at 58 and 116 columns; accuracy = rms and max |x̂ − truth| / peak of the point source's
   cube, truth = the native scene cube summed over each coarse cell (2 native bins × 116/ncol
   columns), and the cube's band flux over the truth's; wall time of each rectification.  The
   spectrum does not depend on this choice (the forward extraction fits the pixels).

Writes ``<out>/reduce_spectra_speed.{json,md,png}``.

    .venv/bin/python benchmarks/reduce_spectra_speed.py [--redshift 0.5] [--repeat 2] [--out benchmarks/results]
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

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

from _common import cpu_model, jsonable, loadavg  # noqa: E402


def _exe():
    exe = Path(sys.executable).parent / "slicersim"
    return str(exe) if exe.exists() else "slicersim"


def timed(cmd):
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def steps(raw, out):
    """reduce_exposure(raw, out=out) with its steps timed (wrappers on the module functions it calls)."""
    import slicersim.reduction.forward_extraction as fe
    import slicersim.reduction.pipeline as pl
    import slicersim.reduction.ramp_fit as rf
    import slicersim.reduction.rectify as rc
    spent = {}

    def wrap(mod, name, label):
        f = getattr(mod, name)

        def g(*a, **k):
            t0 = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                spent[label] = spent.get(label, 0.0) + time.perf_counter() - t0
        setattr(mod, name, g)
        return f

    saved = [(rf, "fit_ramps", wrap(rf, "fit_ramps", "ramp fit")),
             (fe, "white_light_start", wrap(fe, "white_light_start", "white-light start")),
             (fe, "extract_forward", wrap(fe, "extract_forward", "forward extraction")),
             (rc, "rectify", wrap(rc, "rectify", "rectification (lsq, 58 columns)")),
             (pl, "_write", wrap(pl, "_write", "writing"))]
    t0 = time.perf_counter()
    try:
        res = pl.reduce_exposure(raw, out=out, overwrite=True)
    finally:
        for mod, name, f in saved:
            setattr(mod, name, f)
    spent["total (in process)"] = time.perf_counter() - t0
    spent["other"] = spent["total (in process)"] - sum(v for k, v in spent.items() if k != "total (in process)")
    return spent, res


def rectification_choices(z):
    from slicersim.reduction.checks import default_lbda_edges
    from slicersim.reduction.rectify import _default_mapper, rectify
    from slicersim.targets import LazuliSupernova
    sn = LazuliSupernova(z)
    sim = sn.simulation
    mapper = _default_mapper()
    image = sn.get_detector_image(mapper)
    ps = np.nan_to_num(sim.get_scene_cubes(unit="electron")["pointsource"])      # (510, 58, 116) e-/s
    full = np.nan_to_num(sn.get_field_rate_cubes()["narrow"][0])
    tint = sim.get_times()["integration_time"]
    var = 2 * 12 * sim.read_noise() ** 2 / (16 * 8 * tint ** 2) + (image + 0.004) / tint
    edges = default_lbda_edges(mapper)
    nl, ny, nx = ps.shape
    rows = []
    for method in ("lsq", "drizzle"):
        for ncol in (58, 116):
            f = nx // ncol
            truth = full[: 2 * (nl // 2)].reshape(nl // 2, 2, ny, ncol, f).sum(axis=(1, 4))
            src = ps[: 2 * (nl // 2)].reshape(nl // 2, 2, ny, ncol, f).sum(axis=(1, 4))
            t0 = time.perf_counter()
            try:
                cube = rectify(image, var, mapper=mapper, field="narrow", lbda_edges=edges, ncol=ncol, method=method)
            except Exception as exc:                       # a grid the rectification refuses: recorded
                rows.append({"method": method, "ncol": ncol, "error": str(exc).splitlines()[0]})
                continue
            dt = time.perf_counter() - t0
            x = np.nan_to_num(np.asarray(cube.flux)[: truth.shape[0]])
            peak = src.max()
            err = (x - truth)
            rows.append({"method": method, "ncol": ncol, "seconds": dt,
                         "rms_err_over_peak": float(np.sqrt(np.mean(err ** 2)) / peak),
                         "max_err_over_peak": float(np.abs(err).max() / peak),
                         "total_flux_ratio": float(x.sum() / truth.sum())})
            print(f"  {method} {ncol}: {dt:.1f} s, rms/peak {rows[-1]['rms_err_over_peak']:.2e}, "
                  f"max/peak {rows[-1]['max_err_over_peak']:.2e}", flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--redshift", type=float, default=0.5)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--out", default=str(HERE / "results"))
    ap.add_argument("--skip-choices", action="store_true")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    load0 = loadavg()
    exe = _exe()
    result = {"cpu": cpu_model(), "ncpu": os.cpu_count(), "redshift": args.redshift}
    with tempfile.TemporaryDirectory() as tmp:
        raw, red = os.path.join(tmp, "raw.h5"), os.path.join(tmp, "red.h5")
        ramp_t, red_t = [], []
        for k in range(args.repeat):
            ramp_t.append(timed([exe, "ramp", "--redshift", str(args.redshift), "--seed", str(k), "--out", raw,
                                 "--overwrite"]))
            red_t.append(timed([exe, "reduce", raw, "--out", red, "--spectra", "--quiet", "--overwrite"]))
            print(f"ramp {ramp_t[-1]:.1f} s, reduce --spectra {red_t[-1]:.1f} s, ratio {red_t[-1] / ramp_t[-1]:.2f}",
                  flush=True)
        spent, res = steps(raw, red)
        sp = res["spectra"]["narrow"]
        result.update(ramp_seconds=ramp_t, reduce_seconds=red_t,
                      ratio=[r / s for r, s in zip(red_t, ramp_t)], steps=spent,
                      forward={"iterations": sp.diagnostics["iterations"], "pixels": sp.diagnostics["pixels"],
                               "chi2_dof": sp.diagnostics["chi2_dof"]})
    print("steps: " + ", ".join(f"{k} {v:.1f} s" for k, v in spent.items()), flush=True)
    if not args.skip_choices:
        result["rectification"] = rectification_choices(args.redshift)
    result["load_before"], result["load_after"] = load0, loadavg()
    (out / "reduce_spectra_speed.json").write_text(json.dumps(jsonable(result), indent=1))
    lines = [f"# `slicersim reduce --spectra` against `slicersim ramp` (`benchmarks/reduce_spectra_speed.py`)", "",
             f"{result['cpu']}, {result['ncpu']} cores, load {load0} → {result['load_after']}; Lazuli SN Ia "
             f"z = {args.redshift}, narrow field, every option default (MACC(16,8,0), 1 ramp, 4096²).", "",
             "| run | ramp [s] | reduce --spectra [s] | reduce / ramp |", "|---|---:|---:|---:|"]
    lines += [f"| {k + 1} | {a:.1f} | {b:.1f} | {b / a:.2f} |" for k, (a, b) in enumerate(zip(ramp_t, red_t))]
    lines += ["", "Steps of one reduction (in process):", "", "| step | wall [s] |", "|---|---:|"]
    lines += [f"| {k} | {v:.2f} |" for k, v in spent.items()]
    if "rectification" in result:
        lines += ["", "Rectification choices (noiseless image; the spectrum does not depend on them):", "",
                  "| method | columns | wall [s] | rms err / peak | max err / peak | cube flux / truth |",
                  "|---|---:|---:|---:|---:|---:|"]
        for r in result["rectification"]:
            if "error" in r:
                lines.append(f"| {r['method']} | {r['ncol']} | refused: {r['error']} | | | |")
            else:
                lines.append(f"| {r['method']} | {r['ncol']} | {r['seconds']:.1f} | {r['rms_err_over_peak']:.2e} | "
                             f"{r['max_err_over_peak']:.2e} | {r['total_flux_ratio']:.4f} |")
        _plot(result["rectification"], out / "reduce_spectra_speed.png")
    (out / "reduce_spectra_speed.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def _plot(rows, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 4))
    for r in rows:
        if "error" in r:
            continue
        ax.scatter(r["seconds"], r["rms_err_over_peak"], s=40)
        ax.annotate(f"{r['method']} {r['ncol']}", (r["seconds"], r["rms_err_over_peak"]), fontsize=8,
                    xytext=(4, 4), textcoords="offset points")
    ax.set_xlabel("rectification wall time [s] (one field)")
    ax.set_ylabel("rms |cube − truth| / peak (noiseless)")
    ax.set_yscale("log")
    ax.set_title("Rectification: speed against accuracy")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()
