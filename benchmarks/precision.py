#!/usr/bin/env python
"""Single vs double precision kernels, per kernel family: time and max error, in one run.

For each family with single-precision kernels (:data:`slicersim.backends.precision.SINGLE_PRECISION_ERRORS`)
the same call is timed in both precisions (best of ``--repeat``, alternating, PSF cache bypassed)
and the single result compared with the double one: max |Δ| over the peak (and, for the cube,
over the noise σ of the brightest voxel's neighbourhood: max |Δ| / √variance); for the raw ramps
(integers) the fraction of values that differ and the slope shift in units of the slope σ.  Families still
double-only are listed as such.  Writes ``results/precision[_<device>].{json,md,png}`` (the
speed–accuracy chart) with the device, CPU model and load.

    .venv/bin/python benchmarks/precision.py [--repeat 5]
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

from _common import cpu_model, loadavg, write_json  # noqa: E402

from slicersim import LazuliSupernova  # noqa: E402
from slicersim.backends import opencl  # noqa: E402
from slicersim.backends.convolution import apply_lsf, convolve_cube  # noqa: E402
from slicersim.backends.precision import SINGLE_PRECISION_ERRORS, _measure_ratio, fp64_throughput_ratio  # noqa: E402
from slicersim.backends.psf import psf_cube  # noqa: E402
from slicersim.backends.psf_cache import bypass  # noqa: E402

#: kernel families of the issue still computed in double only
DOUBLE_ONLY = ("ramp fit (reduction)", "the single-target ETC (float64 by design)")


def _timed(fn, repeat):
    """Best time of each precision, alternating (drifts of a shared machine hit both alike)."""
    out, best = {}, {"double": float("inf"), "single": float("inf")}
    for p in ("double", "single"):
        out[p] = fn(p)                                  # warm: kernels built, buffers allocated
    for _ in range(repeat):
        for p in ("double", "single"):
            t0 = time.perf_counter()
            out[p] = fn(p)
            best[p] = min(best[p], time.perf_counter() - t0)
    return out, best


def _row(name, what, out, best, noise=None):
    d, s = out["double"], out["single"]
    err = float(np.nanmax(np.abs(s - d)) / np.nanmax(np.abs(d)))
    row = {"family": name, "case": what, "t_double_s": best["double"], "t_single_s": best["single"],
           "speedup": best["double"] / best["single"], "max_err_of_peak": err}
    if noise is not None:
        with np.errstate(invalid="ignore", divide="ignore"):
            row["max_err_in_sigma"] = float(np.nanmax(np.abs(s - d) / np.sqrt(noise)))
    print(f"{name:14s} {what:52s} ×{row['speedup']:.2f}  {err:.2e} of peak"
          + (f", {row['max_err_in_sigma']:.1e} σ" if noise is not None else ""), flush=True)
    return row


def ramp_rows(repeat, side=1024, nmd=(16, 8, 0)):
    """Raw ramps (integers): time of ``simulate`` in each precision on the Lazuli-like rate image of
    ``ramp_throughput.py`` (``side``², MACC ``nmd``), plain and with every effect; error as the
    fraction of SCI values that differ, the largest difference [ADU], and the rms slope shift in
    units of each pixel's Rauscher07 slope σ."""
    import math

    from ramp_throughput import DETECTOR, lazuli_rate_image

    from slicersim.physics.readout import variance_rauscher07
    from slicersim.products.ramps import fit_slopes, simulate
    rate = lazuli_rate_image(side, side)
    n, m, d = nmd
    tf = DETECTOR["tframe"]
    sigma = np.sqrt(variance_rauscher07(rate + DETECTOR["dark"], nmd, tf, math.hypot(DETECTOR["ron"], math.sqrt(m / 12)),
                                        0.0)) / ((n - 1) * (m + d) * tf)
    rows = []
    for effects, label in ((None, "plain"), ("all", "every effect (lazuli set)")):
        what = f"ramp {side}² Lazuli-like, MACC{nmd}, {label}"
        out, best = _timed(lambda p: simulate(rate, nmd, seed=4, precision=p, effects=effects, progress=False,
                                              **DETECTOR)[0], max(1, repeat // 2))
        ds, ss = (out[p].astype(np.int64) for p in ("double", "single"))
        diff = ss - ds
        shift = (fit_slopes(ss, nmd, tf) - fit_slopes(ds, nmd, tf)) / sigma
        row = {"family": "ramp", "case": what, "t_double_s": best["double"], "t_single_s": best["single"],
               "speedup": best["double"] / best["single"], "frac_values_differing": float(np.mean(diff != 0)),
               "max_abs_diff_adu": int(np.abs(diff).max()),
               "rms_slope_shift_in_sigma": float(np.sqrt(np.nanmean(shift ** 2)))}
        print(f"ramp           {what:52s} ×{row['speedup']:.2f}  {row['frac_values_differing']:.1e} of values "
              f"differ (max {row['max_abs_diff_adu']} ADU), slope shift rms {row['rms_slope_shift_in_sigma']:.1e} σ",
              flush=True)
        rows.append(row)
    return rows


def noise_rows(repeat):
    """Noise draws (:mod:`slicersim.backends.noise`) on the Lazuli narrow-field Airy cube's double signal
    and variance: the Gaussian realisation ``noisy_cube`` with float64 arrays in and out (the API's
    default) and with float32 ones (as ``build_cube(dtype=float32)``: double draws into a float64
    temporary, single straight into the float32 cube), error per voxel in units of its σ; Poisson
    counts ``poisson_draw`` of 1e6 means log-uniform in [1e-3, 1e5], error in units of √mean, and the
    fraction of counts that differ (``frac_counts_differing``)."""
    from slicersim.backends.noise import noisy_cube, poisson_draw
    signal, variance = LazuliSupernova(0.5).simulation.get_cube(psf_profile="airy", precision="double")
    shape = "×".join(map(str, signal.shape))
    rows = []
    o64 = {p: np.empty(signal.shape) for p in ("double", "single")}
    out, best = _timed(lambda p: noisy_cube(signal, variance, 12345, precision=p, out=o64[p]), repeat)
    rows.append(_row("noise", f"Gaussian noisy cube {shape}, float64 in/out", out, best, noise=variance))
    s32, v32 = signal.astype(np.float32), variance.astype(np.float32)
    o32 = {p: np.empty(signal.shape, np.float32) for p in ("double", "single")}

    def draw32(p):
        if p == "single":
            return noisy_cube(s32, v32, 12345, precision=p, out=o32[p])
        o32[p][...] = noisy_cube(s32, v32, 12345, precision=p)
        return o32[p]
    out, best = _timed(draw32, repeat)
    rows.append(_row("noise", f"Gaussian noisy cube {shape}, float32 in/out", out, best,
                     noise=v32.astype(np.float64)))
    mean = 10 ** np.random.default_rng(4).uniform(-3, 5, 1_000_000)
    out, best = _timed(lambda p: poisson_draw(mean, 21, precision=p), repeat)
    row = _row("noise", "Poisson counts, 1e6 means log-uniform in [1e-3, 1e5]", out, best, noise=mean)
    row["frac_counts_differing"] = float(np.mean(out["single"] != out["double"]))
    print(f"{'':14s} {'':52s}  {row['frac_counts_differing']:.1e} of the counts differ", flush=True)
    rows.append(row)
    return rows


def projection_rows(repeat):
    """Detector projection (``kernels/project.cl``): the deposit of both Lazuli fields' photo-electron
    rate cubes (SN z = 0.5; tables built once and held, as for a series of cubes) and the whole
    ``get_detector_image`` call (rate cubes, cached tables read back, deposit), in each precision;
    the single deposit's flux (image sum / cube sum − 1) is added to its row."""
    from slicersim.assembly import default_mapper
    from slicersim.backends.projection import deposit
    from slicersim.instrument.mapper import NARROW_SLICES, WIDE_SLICES
    target, mapper = LazuliSupernova(0.5), default_mapper()
    jobs = []
    for field, (cube, sim) in target.get_field_rate_cubes().items():
        tables = mapper.projection_tables(NARROW_SLICES if field == "narrow" else WIDE_SLICES, cube.shape[2],
                                          sim.spectrograph.lbda_edges)
        jobs.append((cube[:, ::-1, :].transpose(1, 0, 2), tables))

    def deposit_both(p):
        image = np.zeros(mapper.detector_shape)
        for value, tables in jobs:
            deposit(value, tables, out=image, precision=p)
        return image
    ncell = sum(t.ncell for _, t in jobs)
    out, best = _timed(deposit_both, repeat)
    row = _row("projection", f"deposit, both Lazuli fields (SN z=0.5, {ncell:.2e} cells)", out, best)
    total = sum(float(v.sum()) for v, _ in jobs)
    row["flux_single_rel"] = float(out["single"].sum() / total - 1)
    row["flux_double_rel"] = float(out["double"].sum() / total - 1)
    print(f"{'':14s} flux: image sum / cube sum − 1 = {row['flux_single_rel']:.1e} (single), "
          f"{row['flux_double_rel']:.1e} (double)", flush=True)
    out, best = _timed(lambda p: target.get_detector_image(mapper, precision=p), repeat)
    return [row, _row("projection", "get_detector_image, SN z=0.5 (cubes, cached tables, deposit)", out, best)]


def batch_etc_rows(repeat):
    """Batch ETC (``band_variance.cl``): a 300-SN Ia survey plan (z = 0.05–1.5, both fields) in each
    precision; error: max relative SNR difference (as "of peak"), and whether the readouts agree."""
    import warnings

    from slicersim.campaign.plan import plan_survey
    from slicersim.campaign.population import SNIaPopulation
    from slicersim.campaign.products import spectrum_grid
    lbda = spectrum_grid()
    pop = SNIaPopulation(300, redshift={"distribution": "uniform", "min": 0.05, "max": 1.5})
    table = pop.draw(3)
    fluxes = np.nan_to_num(pop.spectra(table, lbda))
    plans = {}

    def plan(p):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            plans[p] = plan_survey(np.asarray(table["redshift"]), lbda, fluxes, precision=p)
        return np.asarray(plans[p].table["snr"])
    out, best = _timed(plan, max(1, repeat // 2))
    row = _row("batch_etc", "survey plan, 300 SNe Ia z = 0.05–1.5: band SNR", out, best)
    a, b = plans["double"].table, plans["single"].table
    row["same_readouts"] = bool(all(np.array_equal(a[k], b[k]) for k in ("n", "m", "d", "nramps")))
    print(f"{'':14s} same readouts: {row['same_readouts']}", flush=True)
    return [row]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out", default=str(HERE / "results"))
    ap.add_argument("--ramp-side", type=int, default=1024, help="side of the ramp rows' rate image [px]")
    args = ap.parse_args()
    dev = opencl.get_device()
    device = f"{dev.name.strip()} ({opencl.device_type()}, {dev.platform.name.strip()})"
    res = {"benchmark": "precision", "device": device, "cpu": cpu_model(), "load_before": loadavg(),
           "fp64_throughput_ratio": fp64_throughput_ratio(), "fp64_throughput_ratio_measured": _measure_ratio(),
           "rows": [], "double_only": list(DOUBLE_ONLY)}
    print(f"{device}; fp32/fp64 FMA throughput ratio {res['fp64_throughput_ratio']:.2f} (the dial's), "
          f"{res['fp64_throughput_ratio_measured']:.2f} measured")
    sim = LazuliSupernova(0.5).simulation
    lbda = sim.lbda
    tel, spec = sim.telescope, sim.spectrograph
    common = dict(spatial_scale=spec.spatial_scale, guiding_sigma=tel.guiding_sigma,
                  instrumental_sigma=sim.instrumental_sigma, diameter=tel.diameter_ext, backend="opencl")
    with bypass():
        for name, kw, what in (
                ("psf", dict(profile="airy", obscuration=tel.obscuration, oversampling="auto"),
                 f"Airy, Lazuli narrow field, {lbda.size} λ, source off-centre"),
                ("psf", dict(profile="gaussian", sigma_ref_arcsec=tel.psf_sigma_ref),
                 f"Gaussian (erf), Lazuli narrow field, {lbda.size} λ")):
            out, best = _timed(lambda p: psf_cube(lbda, spec.shape, (0.3, -0.2), precision=p, **kw, **common),
                               args.repeat)
            res["rows"].append(_row(name, what, out, best))
        photons = np.nan_to_num(sim.get_scene_cubes(unit="photon")["pointsource"])
        out, best = _timed(lambda p: apply_lsf(photons, spec.lsf_sigma, backend="opencl", precision=p), args.repeat)
        res["rows"].append(_row("lsf", f"LSF on the point-source photon cube {photons.shape}", out, best))
        yy, xx = np.mgrid[:spec.shape[0], :spec.shape[1]]
        host = np.exp(-np.hypot((yy - spec.shape[0] / 2) / 6.0, (xx - spec.shape[1] / 2) / 11.0)) * 1e-17
        plane_stack = np.stack([host * (1 + 0.01 * k) for k in range(64)])
        for k in (11, 31):
            a = np.linspace(-3, 3, k)
            kern = np.exp(-(a[:, None] ** 2 + a[None, :] ** 2))
            kern /= kern.sum()
            for method in ("direct", "fft"):
                out, best = _timed(lambda p: convolve_cube(plane_stack, kern, method=method, backend="opencl",
                                                           precision=p), args.repeat)
                res["rows"].append(_row("convolution", f"host plane ⊛ {k}×{k} kernel, {method}, 64 planes", out,
                                        best))
        cubes = {}

        def cube(p):
            cubes[p] = sim.get_cube(psf_profile="airy", precision=p)
            return cubes[p][0]
        out, best = _timed(cube, args.repeat)
        res["rows"].append(_row("cube", "Airy cube, Lazuli narrow field (jitter, blur, LSF): signal", out, best,
                                noise=cubes["double"][1]))
        res["rows"].append(_row("cube", "the same: variance", {p: cubes[p][1] for p in cubes}, best))
    res["rows"] += noise_rows(args.repeat)
    res["rows"] += projection_rows(args.repeat)
    res["rows"] += batch_etc_rows(args.repeat)
    res["rows"] += ramp_rows(args.repeat, side=args.ramp_side)
    res["load_after"] = loadavg()
    for key, e in SINGLE_PRECISION_ERRORS.items():
        res.setdefault("documented", {})[key] = {"measured": e.measured, "tolerance": e.tolerance, "unit": e.unit}
    tag = "" if opencl.device_type() == "CPU" else "_" + "".join(c if c.isalnum() else "_" for c in dev.name.strip())
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / f"precision{tag}.json", res)
    lines = [f"# Single vs double precision kernels (`benchmarks/precision.py`)", "",
             f"{device}; CPU {res['cpu']}; load {res['load_before']} → {res['load_after']}; "
             f"fp32/fp64 FMA throughput {res['fp64_throughput_ratio']:.2f} for the dial (CPUs: 2, not timed), "
             f"{res['fp64_throughput_ratio_measured']:.2f} measured (auto picks single above 4).", "",
             "| family | case | double [s] | single [s] | speed-up | max error / peak | max error / σ |",
             "|---|---|---:|---:|---:|---:|---:|"]
    for r in res["rows"]:
        if "max_err_of_peak" not in r:
            continue
        sig = f"{r['max_err_in_sigma']:.1e}" if "max_err_in_sigma" in r else "—"
        lines.append(f"| {r['family']} | {r['case']} | {r['t_double_s']:.3f} | {r['t_single_s']:.3f} | "
                     f"{r['speedup']:.2f} | {r['max_err_of_peak']:.1e} | {sig} |")
    lines += ["", "Integer outputs (same Philox words in both precisions; not bit-identical):", "",
              "| family | case | double [s] | single [s] | speed-up | values differing | max |Δ| [ADU] | "
              "rms slope shift / σ |", "|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in res["rows"]:
        if "frac_values_differing" in r:
            lines.append(f"| {r['family']} | {r['case']} | {r['t_double_s']:.3f} | {r['t_single_s']:.3f} | "
                         f"{r['speedup']:.2f} | {r['frac_values_differing']:.1e} | {r['max_abs_diff_adu']} | "
                         f"{r['rms_slope_shift_in_sigma']:.1e} |")
    lines += ["", "Double only so far (no single-precision kernels): " + ", ".join(DOUBLE_ONLY) + "."]
    (out / f"precision{tag}.md").write_text("\n".join(lines) + "\n")
    _plot(res, out / f"precision{tag}.png")
    print("\n".join(lines))


def _plot(res, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(12, 7), gridspec_kw={"width_ratios": [1.6, 1]})
    markers = {"psf": "o", "lsf": "s", "convolution": "^", "cube": "D", "noise": "v", "projection": "P",
               "batch_etc": "X"}
    for r in res["rows"]:
        if "frac_values_differing" in r:
            ax2.scatter(r["speedup"], r["frac_values_differing"], s=45, label=r["case"][:48])
            continue
        short = ", ".join(r["case"].split(", ")[:2])[:48]
        ax.scatter(r["speedup"], r["max_err_of_peak"], s=45, marker=markers.get(r["family"], "o"),
                   label=f"{r['family']}: {short}")
    ax.axhline(1e-5, color="k", ls="--", lw=0.8, label="tolerance: 1e-5 of the peak")
    ax.axvline(1.5, color="grey", ls=":", lw=0.8)
    ax.set_yscale("log")
    ax.set_ylim(1e-9, 1e-4)
    ax.set_xlabel("speed-up of single over double (same run)")
    ax.set_ylabel("max |single − double| / peak")
    ax.set_title(f"Precision: speed vs accuracy\n{res['device'][:80]}", fontsize=8)
    ax.legend(fontsize=6.5, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2)
    ax2.set_yscale("log")
    ax2.set_xlabel("speed-up of single over double (same run)")
    ax2.set_ylabel("fraction of integer values differing")
    ax2.set_title("raw ramps (same Philox words)", fontsize=8)
    ax2.set_xlim(0.5, 2.5)
    ax2.set_ylim(1e-6, 1e-1)
    ax2.axhline(1e-2, color="k", ls="--", lw=0.8, label="tolerance: 1e-2 of the values")
    ax2.legend(fontsize=6.5, loc="upper center", bbox_to_anchor=(0.5, -0.14))
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()
