#!/usr/bin/env python
"""Benchmark: rectification of the full 4096² detector into both fields' cubes, LSQ vs drizzle.

1. **Conditioning** of the projection P on the default Lazuli layout, per output grid
   (λ bins of 1–3 native bins, 116/58/39 columns per slice): κ₂(P) from the singular values
   of one slice's P (slice 30, 24 native bins) at the blue end, the middle and the red end.
2. **Accuracy and speed** on a realistic scene: the narrow and wide photo-electron rate
   cubes of a Lazuli SN Ia (z = 1, CBE, SN in the narrow field, background and thermal
   light in both; ``target.get_field_rate_cubes()``, 510 bins × 58 × 116).  The truth on the
   rectification grid (2 bins × 2 columns: 255 × 58 × 58) is the native cube summed over
   its sub-cells.  Images: (a) P_grid · truth (the model of ``rectify``: exact recovery
   expected for lsq), (b) (a) + Gaussian noise of variance (rate + dark)/T + (RON/T)²
   (T = 3600 s, dark 0.005 e-/s, RON 5 e-; illustrative), (c) the native image P_native ·
   cube (light distributed inside the coarse cells as the fine cube says: the grid's model
   error).  lsq (with the variance) and drizzle rectify the stack (a, b, c) of both fields in
   one call each; drizzle also runs on the native grid (510 × 58 × 116) on (c).

Metrics: max and rms |x̂ − truth| / peak (per field), rms per λ bin / mean flux of the bin
(the chart), pull width of (b), total flux, wall time per field and peak RSS.

    .venv/bin/python benchmarks/rectify_speed_accuracy.py [--skip-conditioning] [--out benchmarks/results]
"""
import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

from _common import cpu_model, loadavg, write_json  # noqa: E402

from slicersim.backends.projection_transpose import matrix_entries  # noqa: E402
from slicersim.instrument.mapper import SlicerMapper  # noqa: E402
from slicersim.reduction.rectify import rectify  # noqa: E402

GRIDS = [(1, 116), (1, 58), (2, 116), (2, 58), (3, 39)]       # (native bins per bin, columns)
WINDOWS = {"blue": 0, "middle": 250, "red": 480}             # first native bin of a 24-bin window
EXPOSURE, DARK, RON = 3600.0, 0.005, 5.0


def conditioning(mapper, edges):
    """κ₂(P) of slice 30 for every grid and λ window (dense SVD of the explicit matrix)."""
    out = {}
    for step, ncol in GRIDS:
        row = {}
        for name, lo in WINDOWS.items():
            e = edges[lo:lo + 25:step]
            t = mapper.projection_tables([30], ncol, e)
            pix, cell, w = matrix_entries(t, 0, t.ncell)
            upix, r = np.unique(pix, return_inverse=True)
            P = np.zeros((upix.size, t.ncell))
            np.add.at(P, (r, cell), w)
            s = np.linalg.svd(P, compute_uv=False)
            row[name] = float(s[0] / s[-1])
        out[f"{step}x{ncol}"] = row
        print(f"κ(P) {step} bin(s) × {ncol} columns: " + ", ".join(f"{k} {v:.2g}" for k, v in row.items()),
              flush=True)
    return out


def rebin(cube, step, factor):
    n, r, c = cube.shape
    return cube.reshape(n // step, step, r, c // factor, factor).sum(axis=(1, 4))


def per_bin_rms(err, truth):
    return np.sqrt((err ** 2).mean(axis=(1, 2))) / np.maximum(truth.mean(axis=(1, 2)), 1e-300)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--skip-conditioning", action="store_true")
    ap.add_argument("--out", default=str(HERE / "results"))
    args = ap.parse_args()
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    from slicersim.targets import LazuliSupernova

    mapper = SlicerMapper.default()
    sn = LazuliSupernova(redshift=1.0)
    cubes = sn.get_field_rate_cubes()
    sim = cubes["narrow"][1]
    lbda, edges = sim.lbda, sim.spectrograph.lbda_edges
    result = {"machine": {"cpu": cpu_model(), "loadavg_start": loadavg()},
              "scene": "LazuliSupernova(z=1), CBE, get_field_rate_cubes() [e-/s per cell per bin]",
              "noise": {"exposure_s": EXPOSURE, "dark_e_per_s": DARK, "ron_e": RON}}
    previous = out_dir / "rectify_speed_accuracy.json"
    if not args.skip_conditioning:
        result["condition_P"] = conditioning(mapper, edges)
    elif previous.is_file():                       # keep the table of an earlier run
        result["condition_P"] = json.loads(previous.read_text()).get("condition_P")

    native = {f: cubes[f][0] for f in ("narrow", "wide")}
    step, ncol = 2, 58
    g_edges = edges[::step]
    g_lbda = 0.5 * (g_edges[1:] + g_edges[:-1])
    truth = {f: rebin(c, step, 116 // ncol) for f, c in native.items()}
    t0 = time.perf_counter()
    img_grid = mapper.project_fields(g_lbda, g_edges, **truth)
    img_native = mapper.project_fields(lbda, edges, **native)
    result["projection_s"] = time.perf_counter() - t0
    var = (img_grid + DARK) / EXPOSURE + (RON / EXPOSURE) ** 2
    rng = np.random.default_rng(11)
    noisy = img_grid + np.sqrt(var) * rng.standard_normal(img_grid.shape)
    stack = np.stack([img_grid, noisy, img_native])
    del noisy
    runs, result["wall_s"] = {}, {}
    for method in ("lsq", "drizzle"):
        t0 = time.perf_counter()
        runs[method] = rectify(stack, var, mapper=mapper, field="both", lbda=g_lbda, lbda_edges=g_edges,
                               ncol=ncol, method=method)
        result["wall_s"][method] = time.perf_counter() - t0
        print(f"{method}: {result['wall_s'][method]:.1f} s (both fields, stack of 3, with variance)", flush=True)
    t0 = time.perf_counter()
    runs["drizzle_native"] = rectify(img_native, var, mapper=mapper, field="both", lbda=lbda, lbda_edges=edges,
                                     ncol=116, method="drizzle")
    print(f"drizzle on the native grid: {time.perf_counter() - t0:.1f} s", flush=True)
    metrics, chart = {}, {}
    for field in ("narrow", "wide"):
        tr = truth[field]
        peak = tr.max()
        for method in ("lsq", "drizzle"):
            p = runs[method][field]
            e = p.flux - tr[None]
            sig = np.sqrt(p.variance)
            metrics[f"{field}/{method}"] = {
                "time_s": p.diagnostics["time_s"],
                "noiseless_max_rel_peak": float(np.abs(e[0]).max() / peak),
                "noiseless_rms_rel_peak": float(np.sqrt((e[0] ** 2).mean()) / peak),
                "noisy_rms_rel_peak": float(np.sqrt((e[1] ** 2).mean()) / peak),
                "noisy_pull_width": float(np.sqrt((((p.flux[1] - p.flux[0]) / sig) ** 2).mean())),
                "median_sigma_rel_peak": float(np.median(sig) / peak),
                "native_image_max_rel_peak": float(np.abs(e[2]).max() / peak),
                "native_image_rms_rel_peak": float(np.sqrt((e[2] ** 2).mean()) / peak),
                "flux_truth": float(tr.sum()), "flux_noiseless": float(p.flux[0].sum()),
                "diagnostics": {k: v for k, v in p.diagnostics.items() if k != "time_s"}}
            chart[f"{field}/{method}"] = {"noiseless": per_bin_rms(e[0], tr), "noisy": per_bin_rms(e[1], tr),
                                          "native": per_bin_rms(e[2], tr),
                                          "sigma": np.sqrt(p.variance.mean(axis=(1, 2)))
                                          / np.maximum(tr.mean(axis=(1, 2)), 1e-300)}
        p = runs["drizzle_native"][field]
        e = p.flux - native[field]
        metrics[f"{field}/drizzle_native_grid"] = {
            "time_s": p.diagnostics["time_s"], "max_rel_peak": float(np.abs(e).max() / native[field].max()),
            "rms_rel_peak": float(np.sqrt((e ** 2).mean()) / native[field].max())}
        chart[f"{field}/drizzle_native_grid"] = {"native": per_bin_rms(e, native[field])}
    result["metrics"] = metrics
    result["peak_rss_GiB"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    result["machine"]["loadavg_end"] = loadavg()
    for k, v in metrics.items():
        print(k, {a: (round(b, 4) if isinstance(b, float) and b > 1e-3 else b) for a, b in v.items()
                  if a != "diagnostics"})
    write_json(out_dir / "rectify_speed_accuracy.json", result)
    _plot(chart, g_lbda, lbda, out_dir / "rectify_speed_accuracy.png")


def _plot(chart, g_lbda, lbda, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5), sharey=True)
    f = "narrow"
    for method, colour in (("lsq", "C0"), ("drizzle", "C1")):
        c = chart[f"{f}/{method}"]
        ax[0].semilogy(g_lbda, np.maximum(c["noiseless"], 1e-17), colour, label=f"{method}: image = P·truth")
        ax[0].semilogy(g_lbda, c["native"], colour, ls="--", label=f"{method}: native image (grid model error)")
        ax[1].semilogy(g_lbda, c["noisy"], colour, label=f"{method}: noisy, measured")
        ax[1].semilogy(g_lbda, c["sigma"], colour, ls=":", label=f"{method}: predicted σ")
    ax[0].semilogy(lbda, chart[f"{f}/drizzle_native_grid"]["native"], "C2", lw=0.8,
                   label="drizzle, native grid 510×116")
    ax[0].set_title("narrow field, noiseless: rms error per λ bin / mean flux")
    ax[1].set_title(f"noisy (T = {EXPOSURE:.0f} s): rms error per λ bin / mean flux")
    for a in ax:
        a.set_xlabel("λ [Å]")
        a.legend(fontsize=7)
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
