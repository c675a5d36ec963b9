#!/usr/bin/env python
"""The mock-survey job end to end (issue 30): N SNe Ia, full-detector ramps with detector effects, each
reduced as soon as it is simulated (streaming), then the report against the truth.

Question: how long does a 100-SN Ia mock survey take on this machine, and how much disk does it use?
Acceptance: ≤ 1 h wall for 100 SNe on the 2-core VM, disk that fits a laptop.  Baseline: none in the same
run (the figure is absolute); the per-target times are measured on ``--n`` SNe (≥ 20 for the acceptance
row) and extrapolated linearly to ``--extrapolate`` SNe of the same redshift distribution (each target is
one independent Dask task: the cost scales with the number of targets; the spread over the measured
targets is given).

The spec: ``[population] n``, redshift uniform in [``--zmin``, ``--zmax``], phase uniform in [−5, 5] d (rest
frame); ``[observation] snr`` (default 20, per resolution element in 4000–6800 Å rest); ``[products]
ramps = true``, ``effects = "lazuli"``, ``reduce = true``, ``keep_ramps = "none"``, ``spectrum = false``.
Wall and CPU seconds (this process and its reaped children: the Dask workers), peak disk of the dataset,
then ``campaign_report``.  Writes ``<out>/mock_survey.json``, ``.md`` and ``.png``.

    .venv/bin/python benchmarks/mock_survey.py [--n 20] [--workers 2] [--extrapolate 100] [--snr 20]
"""
import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))

from _common import cpu_model, loadavg, markdown_table, write_results  # noqa: E402

SPEC = """seed = {seed}
name = "mock-survey-benchmark"
[population]
kind = "snia"
n = {n}
redshift = {{distribution = "uniform", min = {zmin}, max = {zmax}}}
phase = {{distribution = "uniform", min = -5, max = 5}}
[observation]
snr = {snr}
[products]
spectrum = false
ramps = true
effects = "lazuli"
compression = "lz4"
reduce = true
keep_ramps = "none"
"""


def _cpu():
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _du(path):
    total = 0
    for folder, _, files in os.walk(path):
        for name in files:
            try:
                total += os.lstat(os.path.join(folder, name)).st_blocks * 512
            except OSError:
                pass
    return total


class _PeakDisk(threading.Thread):
    """The largest disk use of a folder, sampled every ``every`` seconds."""

    def __init__(self, path, every=2.0):
        super().__init__(daemon=True)
        self.path, self.every, self.peak, self._stop_flag = path, every, 0, threading.Event()

    def run(self):
        while not self._stop_flag.is_set():
            self.peak = max(self.peak, _du(self.path))
            self._stop_flag.wait(self.every)

    def stop(self):
        self._stop_flag.set()
        self.join()
        self.peak = max(self.peak, _du(self.path))


def _commit():
    try:
        return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _bias_per_z_bin(table, edges=(0.2, 0.45, 0.7, 0.95, 1.2001)):
    """Per redshift bin of the reduced targets: n, mean band_flux_ratio − 1, its error from the scatter and
    from the reported errors (band_flux_ratio_error), and the mean pull."""
    ok = np.asarray(table["status"]) == "done"
    z = np.asarray(table["redshift"], float)
    r = np.asarray(table["band_flux_ratio"], float)
    e = (np.asarray(table["band_flux_ratio_error"], float) if "band_flux_ratio_error" in table.colnames
         else np.full(z.size, np.nan))
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = ok & (z >= lo) & (z < hi) & np.isfinite(r)
        n = int(m.sum())
        if n == 0:
            continue
        scatter = float(np.std(r[m], ddof=1) / np.sqrt(n)) if n > 1 else float("nan")
        reported = float(np.sqrt(np.nansum(e[m] ** 2)) / n)
        pull = float(np.nanmean((r[m] - 1) / e[m]))
        out.append({"z_lo": lo, "z_hi": min(hi, edges[-1]), "n": n, "bias": float(np.mean(r[m]) - 1),
                    "sigma_scatter": scatter, "sigma_reported": reported, "mean_pull": pull})
    return out


def _figure(table, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 4), layout="constrained")
    ok = np.asarray(table["status"]) == "done"
    z = np.asarray(table["redshift"], float)
    t = np.asarray(table["t_simulate"], float)
    ax.plot(z[ok], t[ok], "o", label="simulate + reduce, per target")
    ax.set_xlabel("redshift")
    ax.set_ylabel("task wall time [s]")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=20)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--extrapolate", type=int, default=100)
    p.add_argument("--snr", type=float, default=20.0)
    p.add_argument("--zmin", type=float, default=0.2)
    p.add_argument("--zmax", type=float, default=1.2)
    p.add_argument("--seed", type=int, default=30)
    p.add_argument("--tmp", default=None, help="folder of the dataset (default: a temporary one, removed)")
    p.add_argument("--out", default=str(HERE / "results"))
    args = p.parse_args(argv)
    from astropy.table import Table

    from slicersim.campaign.runner import run_campaign
    from slicersim.reduction.report import campaign_report
    tmp = tempfile.mkdtemp(dir=args.tmp)
    try:
        spec = Path(tmp) / "spec.toml"
        spec.write_text(SPEC.format(seed=args.seed, n=args.n, zmin=args.zmin, zmax=args.zmax, snr=args.snr))
        dataset = Path(tmp) / "dataset"
        disk = _PeakDisk(tmp)
        disk.start()
        w0, c0 = time.perf_counter(), _cpu()
        summary = run_campaign(spec, dataset, workers=args.workers, progress=False)
        w1, c1 = time.perf_counter(), _cpu()
        report = campaign_report(dataset, Path(tmp) / "report")
        w2, c2 = time.perf_counter(), _cpu()
        disk.stop()
        table = Table.read(report["summary"], format="ascii.ecsv")
        final = _du(tmp)
        ok = np.asarray(table["status"]) == "done"
        ratio = np.asarray(table["band_flux_ratio"], float)[ok]
        per_target_wall = (w2 - w0) / args.n
        result = {"question": "wall time and disk of an N-SN Ia mock survey (effects, streaming reduction, report)",
                  "baseline": "none (absolute); extrapolated linearly in the number of targets",
                  "acceptance": f"≤ 3600 s wall for {args.extrapolate} SNe", "commit": _commit(), "cpu": cpu_model(),
                  "device": "default backend", "load": loadavg(), "n": args.n, "workers": args.workers,
                  "snr": args.snr, "z": [args.zmin, args.zmax], "done": int(ok.sum()),
                  "failed": int(summary.get("failed", 0)),
                  "failed_targets": [list(map(str, t)) for t in summary.get("failed_targets", [])],
                  "wall_campaign": w1 - w0, "cpu_campaign": c1 - c0,
                  "wall_report": w2 - w1, "cpu_report": c2 - c1, "wall_per_target": per_target_wall,
                  "cpu_per_target": (c2 - c0) / args.n,
                  "extrapolated_wall": per_target_wall * args.extrapolate,
                  "peak_disk_bytes": disk.peak, "final_disk_bytes": final,
                  "band_flux_ratio_mean": float(np.mean(ratio)) if ratio.size else None,
                  "band_flux_ratio_sem": float(np.std(ratio, ddof=1) / np.sqrt(ratio.size)) if ratio.size > 1 else None}
        rows = [["measured", args.n, f"{w2 - w0:.0f}", f"{c2 - c0:.0f}", f"{disk.peak / 1e9:.2f}", f"{final / 1e9:.2f}"],
                ["extrapolated", args.extrapolate, f"**{per_target_wall * args.extrapolate:.0f}**",
                 f"{(c2 - c0) / args.n * args.extrapolate:.0f}", f"{disk.peak / 1e9:.2f}",
                 f"{final / args.n * args.extrapolate / 1e9:.2f}"]]
        result["bias_per_z_bin"] = bins = _bias_per_z_bin(table)
        md = "\n".join(["### Mock survey end to end (`benchmarks/mock_survey.py`)", "",
                        f"SNe Ia z {args.zmin}–{args.zmax}, SNR {args.snr:g}, full-detector ramps with `effects = "
                        f"\"lazuli\"`, reduced as simulated (`reduce = true`, `keep_ramps = \"none\"`), then the report; "
                        f"{args.workers} workers; {result['cpu']}, load {result['load']}, commit {result['commit']}.",
                        "", *markdown_table(["", "SNe", "wall [s]", "CPU [s]", "peak disk [GB]", "final disk [GB]"],
                                            rows), "",
                        f"Band flux / input over the {int(ok.sum())} reduced targets: "
                        f"{result['band_flux_ratio_mean']} ± {result['band_flux_ratio_sem']}.", "",
                        "Closed-loop bias per redshift bin (band flux / input − 1; σ: the scatter of the targets "
                        "over √n, and the mean reported error over √n):", "",
                        *markdown_table(["z bin", "n", "bias", "σ (scatter)", "σ (reported)", "mean pull"],
                                        [[f"{b['z_lo']:.2f}–{b['z_hi']:.2f}", b["n"], f"{b['bias']:+.4f}",
                                          f"{b['sigma_scatter']:.4f}", f"{b['sigma_reported']:.4f}",
                                          f"{b['mean_pull']:+.2f}"] for b in bins]), ""])
        folder = Path(report["summary"]).parent
        if (folder / "summary.ecsv").exists():              # the per-target truth comparison, kept
            shutil.copy(folder / "summary.ecsv", Path(args.out) / "mock_survey_summary.ecsv")
        if (folder / "report.md").exists():                 # and the report, its figures renamed with it
            text = (folder / "report.md").read_text()
            for png in sorted(folder.glob("*.png")):
                shutil.copy(png, Path(args.out) / f"mock_survey_{png.name}")
                text = text.replace(f"]({png.name})", f"](mock_survey_{png.name})")
            (Path(args.out) / "mock_survey_report.md").write_text(text)
        out = write_results(args.out, "mock_survey", result, md)
        _figure(table, Path(args.out) / "mock_survey.png")
        print(md)
        return out
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
