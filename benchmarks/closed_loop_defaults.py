#!/usr/bin/env python
"""Closed-loop bias with the documented CLI and its defaults, as a new user would run it.

For each redshift z and seed K (``--seeds`` realisations from ``--seed-offset``), in subprocesses::

    slicersim ramp --redshift Z --seed K --field FIELD --out RAW.h5 [--effects NAME]
    slicersim reduce RAW.h5 --out RED.h5 --spectra --field FIELD --quiet

FIELD is the one the survey plan assigns (``slicersim.campaign.plan.plan_survey``, the default of
``slicersim survey plan --z-switch``): narrow below ``z_switch`` (0.8), wide at and above it.
Both commands are timed (wall seconds).  Every other option is the CLI's default: MACC(16,8,0),
one ramp, CBE configuration, white noise (no detector effect unless ``--effects``; the
reduction's corrections are on by default), the reduction's default grid, rectification,
extraction and weights.

Truth: ``LazuliSupernova(z, field=FIELD).get_spectrum()`` (the noiseless point source's
LSF-convolved spectrum in ADU summed over the ramps, with the ETC's variance), converted to
e-/s per native bin (÷ gain · integration time) and aggregated into the reduced spectrum's bins by
the overlap fraction of every native bin in every output bin.  Band: rest frame 4000–6800 Å
(output bins whose centre lies inside; bins with non-finite flux skipped).

Per realisation: band flux / truth (Σ F̂ / Σ T), its σ (√band-sum variance / Σ T: the file's
``COVARIANCE`` when it has one, else Σ VAR), pull = (ratio − 1) / σ, χ²/dof per bin
(mean (F̂ − T)² / VAR), reported band SNR (Σ T / √band variance), the ETC's band SNR
(Σ signal / √Σ variance of the native bins in the band) and their ratio.  Per redshift: means with
their standard error (scatter / √n), the measured SNR (Σ T / rms over realisations of Σ F̂ − Σ T,
n ≥ 3) over the ETC's, mean wall times.  Acceptance: |ratio − 1| ≤ max(1 %, 3 σ_mean);
χ²/dof within 1 ± 0.15; reported SNR within 10 % of the ETC's.

Writes ``<out>/closed_loop_defaults[_<NAME>].{json,md,png}``; the JSON is rewritten after every
realisation.  Ramp files are ~1 GB: each RAW and RED is deleted once analysed (``--keep`` keeps them).

    .venv/bin/python benchmarks/closed_loop_defaults.py [--redshifts 0.2 0.5 0.8 1.0 1.5] [--seeds 4]
        [--seed-offset 0] [--effects NAME] [--workdir DIR] [--keep] [--out benchmarks/results]
    .venv/bin/python benchmarks/closed_loop_defaults.py --from-json A.json B.json [--out DIR]
"""
import argparse
import datetime
import inspect
import json
import math
import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))

from _common import cpu_model, fmt, loadavg, markdown_table, write_json  # noqa: E402

BENCHMARK = "closed_loop_defaults"
BAND_REST = (4000.0, 6800.0)            # Å, rest frame
FIELDS = ("narrow", "wide")             # plan_survey's fields=(below z_switch, at and above)
CLI_NMD = (16, 8, 0)                    # `slicersim ramp` defaults: --nmd, --nramps
CLI_NRAMPS = 1
TOL_BIAS = 0.01                         # |ratio − 1| ≤ max(TOL_BIAS, 3 σ_mean)
TOL_CHI2 = 0.15                         # |χ²/dof − 1| ≤ TOL_CHI2
TOL_SNR = 0.10                          # |reported / ETC − 1| ≤ TOL_SNR


def default_z_switch():
    """plan_survey's default z_switch (the CLI's ``--z-switch`` default is the same 0.8)."""
    try:
        from slicersim.campaign.plan import plan_survey
        return float(inspect.signature(plan_survey).parameters["z_switch"].default)
    except Exception:                                 # noqa: BLE001 - being edited: the documented value
        return 0.8


def planned_field(z, z_switch):
    """plan_survey's rule: ``fields[0]`` below z_switch, ``fields[1]`` at and above it."""
    return FIELDS[0] if z < z_switch else FIELDS[1]


def overlap_matrix(native_edges, out_edges):
    """M[b, j]: fraction of native bin j (edges ``native_edges``) inside output bin b."""
    native_edges, out_edges = np.asarray(native_edges, float), np.asarray(out_edges, float)
    lo = np.maximum(out_edges[:-1, None], native_edges[None, :-1])
    hi = np.minimum(out_edges[1:, None], native_edges[None, 1:])
    return np.clip(hi - lo, 0.0, None) / np.diff(native_edges)[None, :]


def git(*args):
    try:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def slicersim_exe():
    """The ``slicersim`` entry point beside this Python (the venv's), else the one on PATH."""
    exe = Path(sys.executable).parent / "slicersim"
    return str(exe) if exe.exists() else (shutil.which("slicersim") or "slicersim")


def stem_for(effects):
    return BENCHMARK if not effects else f"{BENCHMARK}_{re.sub(r'[^A-Za-z0-9_.-]+', '+', effects)}"


# --------------------------------------------------------------------------- truth
class Truth:
    """The noiseless point source of ``LazuliSupernova(z, field)`` with the CLI's readout."""

    def __init__(self, z, field):
        from slicersim.targets import LazuliSupernova
        self.z, self.field = z, field
        sn = LazuliSupernova(z, field=field)
        if sn.get_readout_config() != {"nmd": CLI_NMD, "nramps": CLI_NRAMPS}:
            sn.change_detector(nmd=CLI_NMD, nramps=CLI_NRAMPS)       # the ramp CLI's defaults
        sim = sn.simulation
        lb, sig, var = sn.get_spectrum()
        self.times = sim.get_times()
        self.gain = float(sim.detector.gain)
        self.native_lbda = np.asarray(lb, float)
        self.native_edges = np.asarray(sim.spectrograph.lbda_edges, float)
        if self.native_edges.size != self.native_lbda.size + 1:
            raise RuntimeError(f"{self.native_lbda.size} native bins but {self.native_edges.size} edges")
        self.rate = np.nan_to_num(np.asarray(sig, float) / (self.gain * self.times["integration_time"]))  # e-/s
        lo, hi = (b * (1 + z) for b in BAND_REST)
        inband = (self.native_lbda >= lo) & (self.native_lbda <= hi) & np.isfinite(sig) & np.isfinite(var)
        self.etc_snr = float(np.sum(sig[inband]) / np.sqrt(np.sum(var[inband])))
        self.native_band_bins = int(inband.sum())
        self.band_obs = (lo, hi)


def read_spectrum(path, field):
    import h5py
    with h5py.File(path, "r") as fh:
        g = fh[f"spectra/{field}"]
        out = {k: g[k][()] for k in ("FLUX", "VAR", "LBDA_EDGES")}
        out["COVARIANCE"] = g["COVARIANCE"][()] if "COVARIANCE" in g else None
        out["datasets"] = sorted(g.keys())
        out["attrs"] = {k: v for k, v in g.attrs.items() if np.ndim(v) == 0}
        out["file_attrs"] = {k: v for k, v in fh.attrs.items() if np.ndim(v) == 0 and len(str(v)) < 2000}
    return out


def analyse(spec, truth):
    """Band metrics of one reduced spectrum against the truth."""
    flux, var, edges = (np.asarray(spec[k], float) for k in ("FLUX", "VAR", "LBDA_EDGES"))
    centre = 0.5 * (edges[1:] + edges[:-1])
    T = overlap_matrix(truth.native_edges, edges) @ truth.rate
    rest = centre / (1 + truth.z)
    inside = (rest >= BAND_REST[0]) & (rest <= BAND_REST[1])
    band = inside & np.isfinite(flux)
    cov = spec["COVARIANCE"]
    sum_f, sum_t = float(flux[band].sum()), float(T[band].sum())
    var_diag = float(var[band].sum())
    band_var = float(np.asarray(cov, float)[np.ix_(band, band)].sum()) if cov is not None else var_diag
    ratio = sum_f / sum_t
    sigma = math.sqrt(band_var) / sum_t if band_var >= 0 else float("nan")
    snr_rep = sum_t / math.sqrt(band_var) if band_var > 0 else float("nan")
    return {"ratio": ratio, "sigma": sigma, "pull": (ratio - 1) / sigma,
            "chi2_dof": float(np.mean((flux[band] - T[band]) ** 2 / var[band])),
            "sum_flux": sum_f, "sum_truth": sum_t, "band_var": band_var, "band_var_diag": var_diag,
            "variance_source": "COVARIANCE" if cov is not None else "VAR",
            "snr_reported": snr_rep, "snr_etc": truth.etc_snr, "snr_reported_over_etc": snr_rep / truth.etc_snr,
            "nbins_band": int(band.sum()), "nbins_skipped_nonfinite": int((inside & ~band).sum()),
            "nbins_nonfinite_var": int((band & ~np.isfinite(var)).sum()),
            "nbins_total": int(flux.size), "bin_edges_range": [float(edges[0]), float(edges[-1])],
            "residual_rel": ((flux[band] - T[band]) / T[band]).tolist(),
            "spectrum_datasets": spec["datasets"], "spectrum_attrs": spec["attrs"],
            "reduced_file_attrs": spec.get("file_attrs", {})}


# --------------------------------------------------------------------------- running
def run_timed(cmd, log):
    """Run ``cmd`` (output to ``log``); wall seconds.  RuntimeError with the log's tail on failure."""
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        rc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL).returncode
    dt = time.perf_counter() - t0
    if rc != 0:
        tail = "\n".join(Path(log).read_text(errors="replace").splitlines()[-15:])
        raise RuntimeError(f"{shlex.join(cmd)} failed (exit {rc}) after {dt:.0f} s:\n{tail}")
    return dt


def realisation(z, seed, field, effects, truth, work, keep, exe):
    tag = f"z{z:g}_s{seed}" + (f"_{re.sub(r'[^A-Za-z0-9_.-]+', '+', effects)}" if effects else "")
    raw, red = work / f"raw_{tag}.h5", work / f"red_{tag}.h5"
    for p in (raw, red):                                  # our own names, from an earlier --keep run
        if p.exists():
            p.unlink()
    ramp = [exe, "ramp", "--redshift", f"{z:g}", "--seed", str(seed), "--field", field, "--out", str(raw)]
    if effects:
        ramp += ["--effects", effects]
    reduce = [exe, "reduce", str(raw), "--out", str(red), "--spectra", "--field", field, "--quiet"]
    row = {"z": z, "seed": seed, "field": field, "effects": effects, "load_start": loadavg(),
           "commands": [shlex.join(ramp), shlex.join(reduce)]}
    try:
        row["t_ramp"] = run_timed(ramp, work / f"ramp_{tag}.log")
        row["raw_bytes"] = raw.stat().st_size
        row["t_reduce"] = run_timed(reduce, work / f"reduce_{tag}.log")
        row["reduce_output_tail"] = Path(work / f"reduce_{tag}.log").read_text(errors="replace").splitlines()[-6:]
        row.update(analyse(read_spectrum(red, field), truth))
    except Exception as exc:                              # noqa: BLE001 - recorded, the run goes on
        row["error"] = f"{type(exc).__name__}: {exc}"
    finally:
        if not keep:
            for p in (raw, red):
                if p.exists():
                    p.unlink()
    return row


# --------------------------------------------------------------------------- summary
def summarise(rows):
    """Per-z summary of the successful realisations (sorted by z)."""
    out = []
    for z in sorted({r["z"] for r in rows}):
        ok = [r for r in rows if r["z"] == z and "error" not in r]
        failed = sum(1 for r in rows if r["z"] == z and "error" in r)
        n = len(ok)
        s = {"z": z, "n": n, "failed": failed, "field": (ok or [r for r in rows if r["z"] == z])[0]["field"]}
        if n == 0:
            out.append(s)
            continue
        ratio = np.array([r["ratio"] for r in ok])
        chi2 = np.array([r["chi2_dof"] for r in ok])
        rep = np.array([r["snr_reported_over_etc"] for r in ok])
        pull = np.array([r["pull"] for r in ok])
        sem = (lambda v: float(v.std(ddof=1) / math.sqrt(n)) if n > 1 else float("nan"))
        s["ratio"], s["ratio_sem"] = float(ratio.mean()), sem(ratio)
        # n = 1: no scatter; the reported σ of the one realisation stands in for σ_mean
        s["ratio_err_source"] = "scatter" if n > 1 else "reported"
        s["ratio_err"] = s["ratio_sem"] if n > 1 else float(ok[0]["sigma"])
        s["ratio_reported_sigma_mean"] = float(np.mean([r["sigma"] for r in ok]) / math.sqrt(n))
        s["pull_mean"], s["pull_std"] = float(pull.mean()), float(pull.std(ddof=1)) if n > 1 else float("nan")
        s["chi2_dof"], s["chi2_dof_err"] = float(chi2.mean()), sem(chi2)
        s["snr_etc"] = float(np.mean([r["snr_etc"] for r in ok]))
        s["snr_reported_over_etc"] = float(rep.mean())
        if n >= 3:
            resid = np.array([r["sum_flux"] - r["sum_truth"] for r in ok])
            sum_t = float(np.mean([r["sum_truth"] for r in ok]))
            s["snr_measured"] = sum_t / float(np.sqrt(np.mean(resid ** 2)))
            s["snr_measured_over_etc"] = s["snr_measured"] / s["snr_etc"]
        else:
            s["snr_measured"] = s["snr_measured_over_etc"] = None
        s["t_ramp"] = float(np.mean([r["t_ramp"] for r in ok]))
        s["t_reduce"] = float(np.mean([r["t_reduce"] for r in ok]))
        s["t_reduce_over_ramp"] = s["t_reduce"] / s["t_ramp"]
        s["variance_source"] = sorted({r["variance_source"] for r in ok})
        s["accept_bias"] = bool(abs(s["ratio"] - 1) <= max(TOL_BIAS, 3 * s["ratio_err"]))
        s["accept_chi2"] = bool(abs(s["chi2_dof"] - 1) <= TOL_CHI2)
        s["accept_snr"] = bool(abs(s["snr_reported_over_etc"] - 1) <= TOL_SNR)
        out.append(s)
    return out


def yes_no(v):
    return "–" if v is None else ("yes" if v else "**no**")


def render_markdown(result):
    runs = result["runs"]
    effects = result.get("effects")
    lines = [f"# Closed loop with the CLI's defaults (`benchmarks/{BENCHMARK}.py`)"
             + (f", effects `{effects}`" if effects else ""), ""]
    ramp = "slicersim ramp --redshift Z --seed K --field FIELD --out RAW.h5" + (f" --effects {effects}" if effects else "")
    lines += [f"`{ramp}` then `slicersim reduce RAW.h5 --out RED.h5 --spectra --field FIELD --quiet` "
              f"(every other option the default: MACC{CLI_NMD} × {CLI_NRAMPS} ramp, CBE); FIELD: narrow for "
              f"z < {result['z_switch']:g}, wide from it (the survey plan's default z-switch).  Truth: "
              "`LazuliSupernova(z, field).get_spectrum()` in e-/s, aggregated into the output bins.  Band: rest "
              f"{BAND_REST[0]:.0f}–{BAND_REST[1]:.0f} Å.  Ratio = Σ F̂ / Σ T ± standard error of the mean over the "
              "seeds (n = 1: the reported σ); measured SNR needs n ≥ 3; times: mean wall seconds per command.", ""]
    header = ["z", "field", "n", "band flux / truth", "mean pull", "χ²/dof", "reported SNR / ETC",
              "measured SNR / ETC", "ETC band SNR", "ramp [s]", "reduce [s]", "reduce / ramp",
              f"bias ok (≤ max({TOL_BIAS:.0%}, 3σ))", f"χ² ok (1 ± {TOL_CHI2:g})", f"SNR ok (±{TOL_SNR:.0%})"]
    rows = []
    for s in result["summary"]:
        if s["n"] == 0:
            rows.append([f"{s['z']:g}", s["field"], f"0 ({s['failed']} failed)"] + ["–"] * (len(header) - 3))
            continue
        n = f"{s['n']}" + (f" ({s['failed']} failed)" if s["failed"] else "")
        rows.append([f"{s['z']:g}", s["field"], n,
                     f"{s['ratio']:.4f} ± {s['ratio_err']:.4f}" + ("" if s["n"] > 1 else " (σ)"),
                     fmt(s["pull_mean"], "{:+.2f}"),
                     f"{s['chi2_dof']:.3f}" + ("" if s["n"] < 2 else f" ± {s['chi2_dof_err']:.3f}"),
                     f"{s['snr_reported_over_etc']:.3f}", fmt(s["snr_measured_over_etc"], "{:.3f}"),
                     f"{s['snr_etc']:.1f}", f"{s['t_ramp']:.1f}", f"{s['t_reduce']:.1f}",
                     f"{s['t_reduce_over_ramp']:.2f}",
                     yes_no(s["accept_bias"]), yes_no(s["accept_chi2"]), yes_no(s["accept_snr"])])
    lines += markdown_table(header, rows)
    lines += [""]
    for run in runs:
        lines.append(f"Produced by `{run['argv']}` at commit {run['commit']}"
                     + (" (tracked files modified)" if run.get("git_dirty") else "")
                     + f", {run['started']}; {run['cpu']}, load {run['load_before']} → {run.get('load_after')}.")
    if result.get("merged_from"):
        lines.append(f"Merged from {', '.join(result['merged_from'])}.")
    errors = [r for r in result["realisations"] if "error" in r]
    if errors:
        lines += ["", "Failed realisations:", ""]
        lines += [f"* z = {r['z']:g}, seed {r['seed']}: {r['error'].splitlines()[0]}" for r in errors]
    return "\n".join(lines) + "\n"


def render_plot(result, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    summ = [s for s in result["summary"] if s["n"] > 0]
    fig, ax = plt.subplots(3, 1, figsize=(6.5, 8.5), sharex=True)
    if summ:
        z = np.array([s["z"] for s in summ])
        ax[0].axhspan(1 - TOL_BIAS, 1 + TOL_BIAS, color="0.85", label="±1 %")
        ax[0].errorbar(z, [s["ratio"] for s in summ], yerr=[s["ratio_err"] for s in summ], fmt="o", capsize=3)
        reals = [r for r in result["realisations"] if "error" not in r]
        ax[0].plot([r["z"] for r in reals], [r["ratio"] for r in reals], ".", color="0.5", ms=3,
                   label="realisations")
        ax[0].axhline(1, color="k", lw=0.8)
        ax[0].set_ylabel("band flux / truth")
        ax[0].legend(fontsize=8)
        ax[1].axhspan(1 - TOL_CHI2, 1 + TOL_CHI2, color="0.85")
        ax[1].errorbar(z, [s["chi2_dof"] for s in summ],
                       yerr=[0 if not np.isfinite(s["chi2_dof_err"] or np.nan) else s["chi2_dof_err"] for s in summ],
                       fmt="o", capsize=3)
        ax[1].axhline(1, color="k", lw=0.8)
        ax[1].set_ylabel("χ²/dof per bin")
        ax[2].axhspan(1 - TOL_SNR, 1 + TOL_SNR, color="0.85")
        ax[2].plot(z, [s["snr_reported_over_etc"] for s in summ], "o", label="reported / ETC")
        meas = [(s["z"], s["snr_measured_over_etc"]) for s in summ if s.get("snr_measured_over_etc") is not None]
        if meas:
            ax[2].plot(*zip(*meas), "s", mfc="none", label="measured / ETC")
        ax[2].axhline(1, color="k", lw=0.8)
        ax[2].set_ylabel("band SNR / ETC")
        ax[2].legend(fontsize=8)
    ax[2].set_xlabel("redshift")
    eff = result.get("effects")
    ax[0].set_title("closed loop, CLI defaults" + (f", effects {eff}" if eff else ""), fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_all(result, out_dir):
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stem = stem_for(result.get("effects"))
    result["summary"] = summarise(result["realisations"])
    write_json(out / f"{stem}.json", result)
    (out / f"{stem}.md").write_text(render_markdown(result))
    render_plot(result, out / f"{stem}.png")
    return [out / f"{stem}.{ext}" for ext in ("json", "md", "png")]


def merge(files, effects):
    """Realisations of earlier runs, the latest per (z, seed) (a success beats a failure)."""
    runs, rows, eff, zsw = [], {}, set(), set()
    for f in files:
        res = json.loads(Path(f).read_text())
        runs += [r for r in res.get("runs", []) if r not in runs]
        eff.add(res.get("effects"))
        zsw.add(res.get("z_switch"))
        for r in res.get("realisations", []):
            key = (r["z"], r["seed"])
            if key not in rows or "error" in rows[key] or "error" not in r:
                rows[key] = r
    if effects is None:
        if len(eff) > 1:
            raise SystemExit(f"the files mix effects {sorted(map(str, eff))}: give --effects to pick one")
        effects = next(iter(eff))
    rows = {k: r for k, r in rows.items() if r.get("effects") == effects}
    if len(zsw) > 1:
        print(f"warning: the files used different z-switches {sorted(zsw)}", file=sys.stderr)
    return {"benchmark": BENCHMARK, "effects": effects, "z_switch": next(iter(zsw)), "runs": runs,
            "merged_from": [str(f) for f in files], "realisations": [rows[k] for k in sorted(rows)]}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--redshifts", type=float, nargs="+", default=[0.2, 0.5, 0.8, 1.0, 1.5])
    ap.add_argument("--seeds", type=int, default=4, help="realisations per redshift")
    ap.add_argument("--seed-offset", type=int, default=0, help="seeds are offset, ..., offset + seeds − 1")
    ap.add_argument("--effects", default=None, metavar="NAME", help="`slicersim ramp --effects NAME`")
    ap.add_argument("--z-switch", type=float, default=None,
                    help="narrow below, wide from this z (default: plan_survey's, 0.8)")
    ap.add_argument("--workdir", default=None, help="folder for the ramp and reduced files (default: a temporary one)")
    ap.add_argument("--keep", action="store_true", help="keep the ramp and reduced files (and logs)")
    ap.add_argument("--from-json", nargs="+", default=None, metavar="FILE",
                    help="merge earlier results and only re-render")
    ap.add_argument("--out", default=str(HERE / "results"))
    args = ap.parse_args()

    if args.from_json:
        result = merge(args.from_json, args.effects)
        for p in write_all(result, args.out):
            print(f"wrote {p}")
        print(render_markdown(result))
        return 0

    z_switch = default_z_switch() if args.z_switch is None else args.z_switch
    exe = slicersim_exe()
    run = {"argv": shlex.join([os.path.relpath(sys.executable, ROOT) if sys.executable.startswith(str(ROOT))
                               else sys.executable, os.path.relpath(__file__, ROOT)] + sys.argv[1:]),
           "started": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
           "cpu": cpu_model(), "ncpu": os.cpu_count(), "load_before": loadavg(), "commit": git("rev-parse", "--short", "HEAD"),
           "git_dirty": bool(git("status", "--porcelain", "--untracked-files=no")), "slicersim": exe,
           "python": sys.version.split()[0], "redshifts": args.redshifts, "seeds": args.seeds,
           "seed_offset": args.seed_offset, "commands": []}
    result = {"benchmark": BENCHMARK, "effects": args.effects, "z_switch": z_switch, "runs": [run],
              "band_rest": BAND_REST, "readout": {"nmd": CLI_NMD, "nramps": CLI_NRAMPS},
              "tolerances": {"bias": TOL_BIAS, "chi2": TOL_CHI2, "snr": TOL_SNR}, "realisations": []}
    if args.workdir:
        Path(args.workdir).mkdir(parents=True, exist_ok=True)
        tmp, work = None, Path(args.workdir)
    elif args.keep:
        tmp, work = None, Path(tempfile.mkdtemp(prefix="cld_"))
    else:
        tmp = tempfile.TemporaryDirectory(prefix="cld_")
        work = Path(tmp.name)
    print(f"work folder {work}; fields: narrow for z < {z_switch:g}, wide from it; {exe}", flush=True)
    try:
        for z in args.redshifts:
            field = planned_field(z, z_switch)
            truth = Truth(z, field)
            print(f"z = {z:g} ({field}): ETC band SNR {truth.etc_snr:.1f} over {truth.native_band_bins} native bins",
                  flush=True)
            for k in range(args.seeds):
                seed = args.seed_offset + k
                row = realisation(z, seed, field, args.effects, truth, work, args.keep, exe)
                run["commands"] += row["commands"]
                result["realisations"].append(row)
                if "error" in row:
                    print(f"  z {z:g} seed {seed}: FAILED {row['error']}", flush=True)
                else:
                    print(f"  z {z:g} seed {seed}: ratio {row['ratio']:.4f} ± {row['sigma']:.4f} "
                          f"(pull {row['pull']:+.2f}), χ²/dof {row['chi2_dof']:.3f}, SNR reported/ETC "
                          f"{row['snr_reported_over_etc']:.3f}, ramp {row['t_ramp']:.1f} s, reduce "
                          f"{row['t_reduce']:.1f} s", flush=True)
                run["load_after"] = loadavg()
                write_all(result, args.out)               # partial results survive an interruption
    finally:
        if tmp is not None:
            tmp.cleanup()
        elif args.keep:
            print(f"kept the files in {work}")
    run["load_after"] = loadavg()
    run["finished"] = datetime.datetime.now().astimezone().isoformat(timespec="seconds")
    for p in write_all(result, args.out):
        print(f"wrote {p}")
    print(render_markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
