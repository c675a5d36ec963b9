#!/usr/bin/env python
"""Raw-ramp generator throughput: OpenCL kernels vs NumPy twin on a Lazuli-like detector image.

Image (:func:`lazuli_rate_image`, synthetic, seeded): every pixel collects the
CBE dark current 2.8e-3 e-/s + 1.2e-3 e-/s thermal dark (≈ 0.004 e-/s) and
3e-3 e-/frame of ROIC glow (passed to ``simulate`` as detector terms); 40
spectra traces along y (dispersion), 3 px wide (profile 0.3 / 1 / 0.3), rows
200–3895 of 4096, whose peak rate wanders smoothly in log between 0.01 and
50 e-/s (≈ 2.7 % of the pixels); 32 bright pixels at 1e3–3e4 e-/s (they
saturate).  Readout: t_f = 2.83 s, read noise 12 e-, gain 1, default
sampler settings.

Measured, in one run:

1. pixel-frames per second [pixels × n(m+d)−d frames / s] of ``simulate``
   (in memory, GROUPDQ not requested) for (16, 8, 0) and (64, 8, 0): OpenCL
   on a 512-row strip (2.1 M pixels; median of ``--repeat`` warm runs) and the
   NumPy twin on a 64-row strip (median of 2); both strips cross every trace,
   so they have the image's pixel mix.  The twin's strip is also simulated by
   the kernel and compared bit for bit.  Wall clock and process CPU time (all
   threads) are recorded: the 2-core VM is shared with other jobs, so the CPU
   time is the load-independent figure and ``loadavg`` is stored.
2. dark pixels (rate 0: dark + thermal + glow = 0.0143 e-/frame), 1024²,
   (16, 8, 0): dense sampler (``sparse_max_group=0``) vs default (sparse):
   speed, and the mean / variance of every group's collected charge (a run
   without read noise) with their Monte Carlo errors, against each other and
   against the analytic Poisson-process values (:func:`dark_paths`).
3. a full 4096² (64, 8, 0) ramp written to HDF5 (uncompressed), time split
   into simulation and writing; ``--extrapolate`` (or a run over 60 s) adds a
   2048² run scaled by 4.

Writes ``<out>/ramp_throughput.json``, ``.png`` and ``.md``.

    .venv/bin/python benchmarks/ramp_throughput.py [--repeat 5] [--skip-full] [--extrapolate]
        [--out benchmarks/results] [--tmp DIR]
"""
import argparse
import json
import math
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from slicersim.backends import opencl
from slicersim.products import ramps  # noqa: E402
from slicersim.instrument.detector import Detector  # noqa: E402

DETECTOR = dict(dark=2.8e-3, thermal_dark=1.2e-3, roic_glow=3e-3, tframe=2.83, ron=12.0, gain=1.0)


def lazuli_rate_image(ny=4096, nx=4096, seed=2026, ntraces=40, nbright=32):
    """Photo-electron rate [e-/s] (ny, nx) of a Lazuli-like exposure (see the module docstring)."""
    gen = np.random.default_rng(seed)
    rate = np.zeros((ny, nx))
    y = np.arange(ny)
    y0, y1 = int(200 * ny / 4096), int(3896 * ny / 4096)
    cols = gen.choice(np.arange(2, nx - 2, 4), size=min(ntraces, (nx - 4) // 4), replace=False)
    lo, hi = math.log10(0.01), math.log10(50.0)
    for x in cols:
        phase = gen.uniform(0, 2 * np.pi, 4)
        freq = gen.uniform(0.5, 6.0, 4) * 2 * np.pi / ny
        walk = sum(np.sin(f * y + p) for f, p in zip(freq, phase)) / 4.0        # in [-1, 1]
        level = lo + (hi - lo) * (0.5 + 0.5 * np.clip(walk * 1.6, -1, 1))
        peak = np.where((y >= y0) & (y < y1), 10.0 ** level, 0.0)
        rate[:, x - 1] += 0.3 * peak
        rate[:, x] += peak
        rate[:, x + 1] += 0.3 * peak
    iy, ix = gen.integers(0, ny, nbright), gen.integers(0, nx, nbright)
    rate[iy, ix] = 10 ** gen.uniform(3, math.log10(3e4), nbright)
    return rate


def nframes(nmd):
    n, m, d = nmd
    return n * (m + d) - d


def timed(fn, repeat):
    """(median wall [s], median CPU [s], last result) of ``repeat`` calls."""
    walls, cpus, out = [], [], None
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        walls.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
    return float(np.median(walls)), float(np.median(cpus)), out


def throughput(rate, nmd, repeat, twin_rows):
    kw = dict(DETECTOR, progress=False, seed=1)     # the same seed for kernel and twin
    strip = rate[1024:1024 + 512]
    ramps.simulate(strip[:8], nmd, backend="opencl", **kw)                    # build the kernels
    w_cl, c_cl, _ = timed(lambda: ramps.simulate(strip, nmd, backend="opencl", **kw), repeat)
    small = rate[1024:1024 + twin_rows]
    w_np, c_np, ref = timed(lambda: ramps.simulate(small, nmd, backend="numpy", **kw), 2)
    same = bool(np.array_equal(ref, ramps.simulate(small, nmd, backend="opencl", **kw)))
    pf_cl, pf_np = strip.size * nframes(nmd), small.size * nframes(nmd)
    row = {"nmd": list(nmd), "frames": nframes(nmd),
           "opencl": {"pixels": strip.size, "wall_s": w_cl, "cpu_s": c_cl, "Mpf_per_s": pf_cl / w_cl / 1e6,
                      "Mpf_per_cpu_s": pf_cl / c_cl / 1e6},
           "numpy": {"pixels": small.size, "wall_s": w_np, "cpu_s": c_np, "Mpf_per_s": pf_np / w_np / 1e6,
                     "Mpf_per_cpu_s": pf_np / c_np / 1e6},
           "bit_identical_on_twin_strip": same}
    row["ratio_wall"] = row["opencl"]["Mpf_per_s"] / row["numpy"]["Mpf_per_s"]
    row["ratio_cpu"] = row["opencl"]["Mpf_per_cpu_s"] / row["numpy"]["Mpf_per_cpu_s"]
    return row


def dark_paths(repeat, size=1024, nmd=(16, 8, 0)):
    """Dense vs sparse sampler on dark pixels: speed (Lazuli detector, read noise 12 e-) and the
    statistics of the collected charge (same pixels without read noise, bias 0, gain = m, so
    that SCI = the sum of the m reads in e-, exactly), against each other (independent seeds) and
    against the Poisson process: E = mμ(s + (m+1)/2), Var = m²μ(s + (m+1)(2m+1)/(6m)), s = g(m+d).
    Standard errors from the sample moments (Var of the sample variance = (μ₄ − σ⁴)/N)."""
    n, m, d = nmd
    rate = np.zeros((size, size))
    mu = (DETECTOR["dark"] + DETECTOR["thermal_dark"]) * DETECTOR["tframe"] + DETECTOR["roic_glow"]
    out = {"nmd": list(nmd), "pixels": rate.size, "mu_e_per_frame": mu}
    stats_kw = dict(DETECTOR, ron=0.0, bias=0.0, gain=float(m), progress=False)
    npx = rate.size
    s = np.arange(n) * (m + d)
    mean_a = m * mu * (s + (m + 1) / 2)
    var_a = m * m * mu * (s + (m + 1) * (2 * m + 1) / (6 * m))
    out["analytic_mean_e"], out["analytic_var_e2"] = mean_a.tolist(), var_a.tolist()
    for name, smg, seed in (("dense", 0.0, 41), ("sparse", None, 42)):
        ramps.simulate(rate[:8], nmd, sparse_max_group=smg, progress=False, **DETECTOR)
        w, c, _ = timed(lambda: ramps.simulate(rate, nmd, sparse_max_group=smg, seed=31, progress=False,
                                               **DETECTOR), repeat)
        x = ramps.simulate(rate, nmd, sparse_max_group=smg, seed=seed, **stats_kw)[0].reshape(n, -1)
        x = x.astype(float)
        mean, var = x.mean(1), x.var(1)
        se_mean = np.sqrt(var / npx)
        se_var = np.sqrt((((x - mean[:, None]) ** 4).mean(1) - var**2) / npx)
        out[name] = {"wall_s": w, "cpu_s": c, "Mpf_per_s": npx * nframes(nmd) / w / 1e6,
                     "mean_e": mean.tolist(), "var_e2": var.tolist(), "se_mean": se_mean.tolist(),
                     "se_var": se_var.tolist(),
                     "mean_vs_analytic_sigma": ((mean - mean_a) / se_mean).tolist(),
                     "var_vs_analytic_sigma": ((var - var_a) / se_var).tolist()}
    dn, sp = out["dense"], out["sparse"]
    out["mean_diff_sigma"] = ((np.array(sp["mean_e"]) - dn["mean_e"])
                              / np.hypot(sp["se_mean"], dn["se_mean"])).tolist()
    out["var_diff_sigma"] = ((np.array(sp["var_e2"]) - dn["var_e2"]) / np.hypot(sp["se_var"], dn["se_var"])).tolist()
    out["note"] = ("speed with read noise 12 e- (seed 31 for both); statistics without read noise, seeds 41 "
                   "(dense) and 42 (sparse); groups are correlated (cumulative charge)")
    out["speedup_sparse_vs_dense"] = dn["wall_s"] / sp["wall_s"]
    out["speedup_cpu"] = dn["cpu_s"] / sp["cpu_s"]
    return out


class _TimedWriter(ramps.RampWriter):
    seconds = 0.0

    def write_block(self, *args, **kwargs):
        t = time.perf_counter()
        super().write_block(*args, **kwargs)
        _TimedWriter.seconds += time.perf_counter() - t


def full_frame(rate, nmd, tmp):
    """Full-frame ramp to HDF5: wall, CPU, writing time, file and SCI sizes."""
    import h5py
    ny, nx = rate.shape
    path = Path(tmp) / f"ramp_{ny}x{nx}.h5"
    real = ramps.RampWriter
    ramps.RampWriter, _TimedWriter.seconds = _TimedWriter, 0.0
    load0 = os.getloadavg()
    try:
        t, c = time.perf_counter(), time.process_time()
        ramps.simulate(rate, nmd, out=path, progress=False, **DETECTOR)
        wall, cpu = time.perf_counter() - t, time.process_time() - c
    finally:
        ramps.RampWriter = real
    with h5py.File(path, "r") as fh:
        sci_bytes = fh["SCI"].id.get_storage_size()
    size = path.stat().st_size
    path.unlink()
    return {"shape": [ny, nx], "nmd": list(nmd), "wall_s": wall, "cpu_s": cpu, "write_s": _TimedWriter.seconds,
            "simulate_s": wall - _TimedWriter.seconds, "file_GB": size / 1e9, "sci_GB": sci_bytes / 1e9,
            "data_volume_GB": Detector(shape=(ny, nx)).data_volume(nmd, 1),
            "Mpf_per_s": ny * nx * nframes(nmd) / wall / 1e6, "loadavg_before": load0,
            "loadavg_after": os.getloadavg()}


def plot(result, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.6))
    rows = result["throughput"]
    xs = np.arange(len(rows))
    for k, (key, lab, col) in enumerate((("opencl", "OpenCL (PoCL)", "C0"), ("numpy", "NumPy twin", "C1"))):
        ax[0].bar(xs + (k - 0.5) * 0.38, [r[key]["Mpf_per_s"] for r in rows], 0.36, color=col, label=lab + ", wall")
        ax[0].scatter(xs + (k - 0.5) * 0.38, [r[key]["Mpf_per_cpu_s"] for r in rows], color="k", marker="_",
                      s=300, zorder=3, label="per CPU-second" if k == 0 else None)
    for i, r in enumerate(rows):
        ax[0].text(i, r["opencl"]["Mpf_per_s"] * 1.15, f"OpenCL / twin ×{r['ratio_wall']:.0f}", ha="center",
                   fontsize=9)
    ax[0].axhline(150, color="C3", ls="--", lw=1, label="goal 150 M/s")
    ax[0].set_yscale("log")
    ax[0].set_ylim(min(r["numpy"]["Mpf_per_cpu_s"] for r in rows) / 3,
                   max(r["opencl"]["Mpf_per_s"] for r in rows) * 4)
    ax[0].set_xticks(xs, [f"MACC{tuple(r['nmd'])}" for r in rows])
    ax[0].set_ylabel("pixel-frames / s [M]")
    ax[0].set_title("Lazuli-like image, simulate() in memory")
    ax[0].legend(fontsize=8, loc="upper right", ncol=2)

    dk = result["dark_pixels"]
    g = np.arange(len(dk["dense"]["mean_e"]))
    a2 = ax[1]
    a2.plot(g, dk["mean_diff_sigma"], "o-", label="mean charge: (sparse − dense) / σ")
    a2.plot(g, dk["var_diff_sigma"], "s-", label="charge variance: (sparse − dense) / σ")
    a2.plot(g, dk["sparse"]["mean_vs_analytic_sigma"], ":", color="C0", label="sparse mean − analytic")
    a2.plot(g, dk["sparse"]["var_vs_analytic_sigma"], ":", color="C1", label="sparse variance − analytic")
    a2.axhspan(-2, 2, color="0.9")
    a2.set_xlabel("group")
    a2.set_ylabel("difference [MC σ]")
    a2.set_ylim(-5, 5)
    a2.set_title(f"dark pixels {tuple(dk['nmd'])}: sparse {dk['sparse']['Mpf_per_s']:.0f} vs dense "
                 f"{dk['dense']['Mpf_per_s']:.0f} M/s (×{dk['speedup_sparse_vs_dense']:.1f})", fontsize=9)
    a2.legend(fontsize=8)

    a3 = ax[2]
    runs = result["full_frame"]
    labels, sim, wri = [], [], []
    for r in runs:
        scale = r.get("scale", 1.0)
        labels.append(f"{r['shape'][0]}² ×{scale:g}" if scale != 1 else f"{r['shape'][0]}²")
        sim.append(r["simulate_s"] * scale)
        wri.append(r["write_s"] * scale)
    a3.bar(labels, sim, label="simulate")
    a3.bar(labels, wri, bottom=sim, label="HDF5 write")
    a3.axhline(60, color="C3", ls="--", lw=1, label="goal 60 s")
    a3.set_ylabel("seconds")
    a3.set_title("full (64, 8, 0) ramp to HDF5")
    a3.legend(fontsize=8)
    fig.suptitle(f"ramp generator, {result['machine']['opencl_device']}; load average "
                 f"{result['machine']['loadavg_before'][0]:.1f}–{result['machine']['loadavg_after'][0]:.1f} "
                 f"on {result['machine']['cores']} cores", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def markdown(result):
    lines = ["### Raw-ramp generator throughput (`benchmarks/ramp_throughput.py`)", "",
             f"Lazuli-like 4096² image (dark + thermal 0.004 e-/s and glow everywhere, 40 traces "
             f"0.01–50 e-/s, {result['image']['trace_fraction']:.1%} of pixels above dark, 32 bright pixels); "
             f"{result['machine']['opencl_device']}, {result['machine']['cores']} cores shared with other jobs "
             f"(load average {result['machine']['loadavg_before'][0]:.1f} → "
             f"{result['machine']['loadavg_after'][0]:.1f}). Medians; pixel-frames per second of wall time "
             "and per CPU-second (all threads).", "",
             "| readout | OpenCL [M/s] | OpenCL [M/CPU-s] | NumPy twin [M/s] | twin [M/CPU-s] | ratio wall / CPU | bit-identical |",
             "|---|---:|---:|---:|---:|---:|---|"]
    for r in result["throughput"]:
        lines.append(f"| MACC{tuple(r['nmd'])} | {r['opencl']['Mpf_per_s']:.0f} | {r['opencl']['Mpf_per_cpu_s']:.0f} | "
                     f"{r['numpy']['Mpf_per_s']:.1f} | {r['numpy']['Mpf_per_cpu_s']:.1f} | "
                     f"{r['ratio_wall']:.0f}× / {r['ratio_cpu']:.0f}× | {r['bit_identical_on_twin_strip']} |")
    dk = result["dark_pixels"]
    worst = lambda key: max(max(map(abs, dk[k][key])) for k in ("dense", "sparse"))  # noqa: E731
    lines += ["", f"Dark pixels (μ = {dk['mu_e_per_frame']:.4f} e-/frame, {dk['pixels']} px, MACC{tuple(dk['nmd'])}): "
              f"sparse {dk['sparse']['Mpf_per_s']:.0f} M/s vs dense {dk['dense']['Mpf_per_s']:.0f} M/s "
              f"(×{dk['speedup_sparse_vs_dense']:.1f} wall, ×{dk['speedup_cpu']:.1f} CPU).  Collected charge "
              "(same pixels, no read noise, SCI = Σ of the m reads): sparse − dense within "
              f"{max(map(abs, dk['mean_diff_sigma'])):.1f} σ (group means) and {max(map(abs, dk['var_diff_sigma'])):.1f} σ "
              f"(variances) over the {len(dk['mean_diff_sigma'])} groups; both within {worst('mean_vs_analytic_sigma'):.1f} σ "
              f"and {worst('var_vs_analytic_sigma'):.1f} σ of the analytic Poisson-process mean and variance "
              f"(last group: {dk['analytic_mean_e'][-1]:.2f} e-, {dk['analytic_var_e2'][-1]:.1f} e-²).", ""]
    for r in result["full_frame"]:
        sc = r.get("scale", 1.0)
        lines.append(f"Full {r['shape'][0]}² MACC{tuple(r['nmd'])} ramp to HDF5: {r['wall_s']:.1f} s "
                     f"(simulate {r['simulate_s']:.1f} s, write {r['write_s']:.1f} s, {r['file_GB']:.2f} GB)"
                     + (f", ×{sc:g} → {r['wall_s'] * sc:.0f} s for 4096²" if sc != 1 else "")
                     + f"; SCI {r['sci_GB']:.3f} GB = data_volume {r['data_volume_GB']:.3f} GB.")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--twin-rows", type=int, default=64)
    ap.add_argument("--skip-full", action="store_true")
    ap.add_argument("--extrapolate", action="store_true", help="also run 2048² and scale by 4")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    ap.add_argument("--tmp", default=None, help="folder for the temporary HDF5 files")
    args = ap.parse_args()
    if not (opencl.is_available() and opencl.device_supports_fp64()):
        sys.exit("no OpenCL device with fp64: nothing to compare")
    dev = opencl.get_device()
    load0 = os.getloadavg()
    rate = lazuli_rate_image()
    above = float(np.mean(rate > 0))
    print(f"image 4096²: {above:.2%} of pixels above dark; load average {load0}", flush=True)
    rows = []
    for nmd in ((16, 8, 0), (64, 8, 0)):
        r = throughput(rate, nmd, args.repeat, args.twin_rows)
        rows.append(r)
        print(f"MACC{nmd}: OpenCL {r['opencl']['Mpf_per_s']:.0f} M pf/s ({r['opencl']['Mpf_per_cpu_s']:.0f} per CPU-s), "
              f"NumPy {r['numpy']['Mpf_per_s']:.1f} M pf/s ({r['numpy']['Mpf_per_cpu_s']:.1f}); ratio "
              f"{r['ratio_wall']:.0f}x wall, {r['ratio_cpu']:.0f}x CPU; identical {r['bit_identical_on_twin_strip']}",
              flush=True)
    dk = dark_paths(args.repeat)
    print(f"dark pixels: dense {dk['dense']['Mpf_per_s']:.0f}, sparse {dk['sparse']['Mpf_per_s']:.0f} M pf/s "
          f"(x{dk['speedup_sparse_vs_dense']:.1f})", flush=True)
    print(" group | mean e-: dense  sparse  analytic | var e-²: dense  sparse  analytic | (sp−dn)/σ mean var")
    for g in range(len(dk["dense"]["mean_e"])):
        print(f" {g:5d} | {dk['dense']['mean_e'][g]:13.4f} {dk['sparse']['mean_e'][g]:7.4f} "
              f"{dk['analytic_mean_e'][g]:9.4f} | {dk['dense']['var_e2'][g]:14.3f} {dk['sparse']['var_e2'][g]:7.3f} "
              f"{dk['analytic_var_e2'][g]:9.3f} | {dk['mean_diff_sigma'][g]:+5.2f} {dk['var_diff_sigma'][g]:+5.2f}")
    full = []
    if not args.skip_full:
        with tempfile.TemporaryDirectory(dir=args.tmp) as tmp:
            r = full_frame(rate, (64, 8, 0), tmp)
            full.append(r)
            print(f"full 4096² (64,8,0) to HDF5: {r['wall_s']:.1f} s (write {r['write_s']:.1f} s), "
                  f"{r['Mpf_per_s']:.0f} M pf/s, SCI {r['sci_GB']:.3f} GB", flush=True)
            if args.extrapolate or r["wall_s"] > 60:
                r2 = full_frame(lazuli_rate_image(2048, 2048), (64, 8, 0), tmp)
                r2["scale"] = 4.0
                full.append(r2)
                print(f"2048²: {r2['wall_s']:.1f} s → ×4 = {4 * r2['wall_s']:.0f} s", flush=True)
    result = {
        "benchmark": "ramp_throughput",
        "image": {"shape": [4096, 4096], "trace_fraction": above, "detector": DETECTOR,
                  "description": lazuli_rate_image.__doc__},
        "throughput": rows, "dark_pixels": dk, "full_frame": full,
        "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
                    "opencl_device": f"{dev.name.strip()} [{dev.platform.name.strip()}]",
                    "python": sys.version.split()[0], "numpy": np.__version__,
                    "loadavg_before": load0, "loadavg_after": os.getloadavg()},
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "ramp_throughput.json").write_text(json.dumps(result, indent=1))
    plot(result, out / "ramp_throughput.png")
    (out / "ramp_throughput.md").write_text(markdown(result))
    print(f"wrote {out / 'ramp_throughput.json'}, .png, .md")


if __name__ == "__main__":
    main()
