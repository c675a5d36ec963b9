#!/usr/bin/env python
"""Speed of ``slicersim reduce --spectra`` (one field, defaults) against simulating the same ramp, and
speed against accuracy of the rectification choices.

1. In one run, as a user would: ``slicersim ramp --redshift Z --out RAW`` and ``slicersim reduce RAW
   --out RED --spectra --quiet`` (subprocesses, ``--repeat`` times each, alternated), each timed in
   wall and CPU seconds (user + system of the process and its threads: the machine's other load
   does not count, :func:`_common.timed_command`); then ``reduce_exposure`` in this process with
   every step timed (ramp fit, white-light start, forward extraction, rectification, writing).
   The row "reduce --spectra / simulate, one field, defaults, same run": the ratios of the means
   (goal ≤ 1).
2. ``--baseline REV``: the same reduction by the package at git revision REV (``git archive`` into a
   temporary folder, run with it first on the path), timed alike, and its spectrum compared with
   this checkout's on the same raw file: band flux (rest 4000–6800 Å) and per-bin F_λ, differences
   in units of the reported σ.
3. Rectification choices on the noiseless image of the same SN (``get_detector_image``): lsq and
   drizzle at 58 and 116 columns; accuracy = rms and max |x̂ − truth| / peak of the point source's
   cube, truth = the native scene cube summed over each coarse cell (2 native bins × 116/ncol
   columns), and the cube's band flux over the truth's; wall time of each rectification.  The
   spectrum does not depend on this choice (the forward extraction fits the pixels).

Writes ``<out>/reduce_spectra_speed.{json,md,png}``.

    .venv/bin/python benchmarks/reduce_spectra_speed.py [--redshift 0.5] [--repeat 2] [--baseline REV]
        [--out benchmarks/results]
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

from _common import cpu_model, git_commit, jsonable, loadavg, timed_command  # noqa: E402

ROOT = HERE.parent


def _cli(tree=None):
    """The ``slicersim`` command line of this checkout (or of the package tree ``tree``) and its environment."""
    env = dict(os.environ, PYTHONPATH=str(tree or ROOT))      # run with cwd outside the checkout (python -c)
    return [sys.executable, "-c", "import sys; from slicersim.app.cli import main; sys.exit(main())"], env


def _baseline_tree(rev, tmp):
    """The package at git revision ``rev``, extracted into ``tmp``/baseline (``git archive``)."""
    dest = Path(tmp) / "baseline"
    dest.mkdir()
    archive = subprocess.run(["git", "archive", rev, "slicersim"], cwd=ROOT, check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return dest


BAND = (4000.0, 6800.0)                  # rest-frame band [Å] of the band flux


def compare_spectra(path, reference, z):
    """The spectrum of ``path`` against that of ``reference`` (same raw file): band flux ratio and its
    difference over the band's σ, largest per-bin |ΔF_λ| / σ(F_λ)."""
    import h5py
    with h5py.File(path, "r") as a, h5py.File(reference, "r") as b:
        field = next(iter(a["spectra"]))
        g, h = a[f"spectra/{field}"], b[f"spectra/{field}"]
        lbda = g["LBDA"][()]
        band = (lbda / (1 + z) >= BAND[0]) & (lbda / (1 + z) <= BAND[1])
        f, fr = g["FLUX"][()], h["FLUX"][()]
        cov = h["COVARIANCE"][()] if "COVARIANCE" in h else np.diag(h["VAR"][()])
        ok = band & np.isfinite(f) & np.isfinite(fr)
        sigma_band = float(np.sqrt(cov[np.ix_(ok, ok)].sum()))
        fl, flr, vfl = g["FLUX_FLAMBDA"][()], h["FLUX_FLAMBDA"][()], h["VAR_FLAMBDA"][()]
        good = np.isfinite(fl) & np.isfinite(flr) & (vfl > 0)
        return {"field": field, "band_flux_ratio": float(f[ok].sum() / fr[ok].sum()),
                "band_flux_diff_over_sigma": float((f[ok].sum() - fr[ok].sum()) / sigma_band),
                "max_flambda_diff_over_sigma": float(np.max(np.abs(fl[good] - flr[good]) / np.sqrt(vfl[good]))),
                "bins": int(good.sum())}


def steps(raw, out):
    """reduce_exposure(raw, out=out) with its steps timed (wrappers on the module functions it calls)."""
    import slicersim.reduction.forward_extraction as fe
    import slicersim.reduction.pipeline as pl
    import slicersim.reduction.ramp_fit as rf
    import slicersim.reduction.rectify as rc
    import slicersim.reduction.white_light as wl
    spent = {}

    def wrap(mod, name, label):
        f = getattr(mod, name)

        def g(*a, **k):
            t0, c0 = time.perf_counter(), time.process_time()
            try:
                return f(*a, **k)
            finally:
                w, c = spent.get(label, (0.0, 0.0))
                spent[label] = (w + time.perf_counter() - t0, c + time.process_time() - c0)
        setattr(mod, name, g)
        return f

    saved = [(rf, "fit_ramps", wrap(rf, "fit_ramps", "ramp fit")),
             (wl, "white_light_start", wrap(wl, "white_light_start", "white-light start")),
             (fe, "extract_forward", wrap(fe, "extract_forward", "forward extraction")),
             (rc, "rectify", wrap(rc, "rectify", "rectification (lsq, 58 columns)")),
             (pl, "_write", wrap(pl, "_write", "writing"))]
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        res = pl.reduce_exposure(raw, out=out, overwrite=True)
    finally:
        for mod, name, f in saved:
            setattr(mod, name, f)
    total = (time.perf_counter() - t0, time.process_time() - c0)
    spent["other"] = tuple(total[i] - sum(v[i] for v in spent.values()) for i in (0, 1))
    spent["total (in process)"] = total
    return {k: {"wall": v[0], "cpu": v[1]} for k, v in spent.items()}, res


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


def _mean(runs, key):
    return float(np.mean([r[key] for r in runs]))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--redshift", type=float, default=0.5)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--baseline", metavar="REV", help="also reduce with the package at this git revision and "
                    "compare its time and spectrum")
    ap.add_argument("--out", default=str(HERE / "results"))
    ap.add_argument("--skip-choices", action="store_true")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    load0 = loadavg()
    cli, env = _cli()
    result = {"cpu": cpu_model(), "ncpu": os.cpu_count(), "redshift": args.redshift, "commit": git_commit(),
              "argv": " ".join(["benchmarks/reduce_spectra_speed.py", *(argv if argv is not None else sys.argv[1:])]),
              "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    with tempfile.TemporaryDirectory() as tmp:
        raw, red = os.path.join(tmp, "raw.h5"), os.path.join(tmp, "red.h5")
        ramps, reds, base = [], [], []
        base_cli = _cli(_baseline_tree(args.baseline, tmp)) if args.baseline else None
        for k in range(args.repeat):
            ramps.append(timed_command(cli + ["ramp", "--redshift", str(args.redshift), "--seed", str(k), "--out", raw,
                                              "--overwrite"], env, cwd=tmp))
            reds.append(timed_command(cli + ["reduce", raw, "--out", red, "--spectra", "--quiet", "--overwrite"], env,
                                      cwd=tmp))
            line = (f"ramp {ramps[-1]['cpu']:.1f} CPU-s / {ramps[-1]['wall']:.1f} s, reduce --spectra "
                    f"{reds[-1]['cpu']:.1f} CPU-s / {reds[-1]['wall']:.1f} s")
            if base_cli:
                ref = os.path.join(tmp, "red_baseline.h5")
                base.append(timed_command(base_cli[0] + ["reduce", raw, "--out", ref, "--spectra", "--quiet",
                                                         "--overwrite"], base_cli[1], cwd=tmp))
                base[-1]["spectrum"] = compare_spectra(red, ref, args.redshift)
                line += f", baseline {base[-1]['cpu']:.1f} CPU-s / {base[-1]['wall']:.1f} s"
            print(line, flush=True)
        spent, res = steps(raw, red)
        sp = res["spectra"]["narrow"]
        result.update(ramp=ramps, reduce=reds, baseline=base, baseline_rev=args.baseline, steps=spent,
                      ratio_cpu=_mean(reds, "cpu") / _mean(ramps, "cpu"),
                      ratio_wall=_mean(reds, "wall") / _mean(ramps, "wall"),
                      forward={"iterations": sp.diagnostics["iterations"], "pixels": sp.diagnostics["pixels"],
                               "chi2_dof": sp.diagnostics["chi2_dof"]})
    print("steps: " + ", ".join(f"{k} {v['cpu']:.1f} CPU-s" for k, v in spent.items()), flush=True)
    if not args.skip_choices:
        result["rectification"] = rectification_choices(args.redshift)
    result["load_before"], result["load_after"] = load0, loadavg()
    (out / "reduce_spectra_speed.json").write_text(json.dumps(jsonable(result), indent=1))
    lines = ["# `slicersim reduce --spectra` against `slicersim ramp` (`benchmarks/reduce_spectra_speed.py`)", "",
             f"{result['cpu']}, {result['ncpu']} cores, load {load0} → {result['load_after']}; commit "
             f"{result['commit']}, {result['date']}; Lazuli SN Ia z = {args.redshift}, narrow field, every option "
             "default (MACC(16,8,0), 1 ramp, 4096²).  CPU = user + system seconds of the command (its threads "
             "included); the machine's other load does not count in it, as it does in wall time.", "",
             "| row | ramp CPU [s] | reduce --spectra CPU [s] | CPU ratio | ramp wall [s] | reduce wall [s] | "
             "wall ratio |", "|---|---:|---:|---:|---:|---:|---:|"]
    lines += [f"| run {k + 1} | {a['cpu']:.1f} | {b['cpu']:.1f} | {b['cpu'] / a['cpu']:.2f} | {a['wall']:.1f} | "
              f"{b['wall']:.1f} | {b['wall'] / a['wall']:.2f} |" for k, (a, b) in enumerate(zip(ramps, reds))]
    lines.append(f"| **reduce --spectra / simulate, one field, defaults, same run** (means) | "
                 f"{_mean(ramps, 'cpu'):.1f} | {_mean(reds, 'cpu'):.1f} | **{result['ratio_cpu']:.2f}** | "
                 f"{_mean(ramps, 'wall'):.1f} | {_mean(reds, 'wall'):.1f} | **{result['ratio_wall']:.2f}** |")
    if base:
        lines.append(f"| baseline {args.baseline}: reduce --spectra / simulate (means) | {_mean(ramps, 'cpu'):.1f} | "
                     f"{_mean(base, 'cpu'):.1f} | {_mean(base, 'cpu') / _mean(ramps, 'cpu'):.2f} | "
                     f"{_mean(ramps, 'wall'):.1f} | {_mean(base, 'wall'):.1f} | "
                     f"{_mean(base, 'wall') / _mean(ramps, 'wall'):.2f} |")
        lines += ["", f"Spectrum of this checkout against the baseline {args.baseline} on the same raw file "
                  "(σ: the baseline's reported errors; band: rest 4000–6800 Å):", "",
                  "| run | band flux ratio | Δ band flux / σ | max per-bin \\|ΔF_λ\\| / σ | bins |",
                  "|---|---:|---:|---:|---:|"]
        lines += [f"| {k + 1} | {b['spectrum']['band_flux_ratio']:.12f} | {b['spectrum']['band_flux_diff_over_sigma']:.1e} | "
                  f"{b['spectrum']['max_flambda_diff_over_sigma']:.1e} | {b['spectrum']['bins']} |"
                  for k, b in enumerate(base)]
    lines += ["", "Steps of one reduction (in process, the last run's raw file):", "",
              "| step | CPU [s] | wall [s] |", "|---|---:|---:|"]
    lines += [f"| {k} | {v['cpu']:.2f} | {v['wall']:.2f} |" for k, v in spent.items()]
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
    lines += ["", f"Produced by `{result['argv']}`."]
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
