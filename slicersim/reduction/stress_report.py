"""The outputs of the stress harness (:mod:`slicersim.reduction.stress`): ``stress.ecsv``, the figures
and ``report.md``, from the records of the exposures."""
from __future__ import annotations

import io
import math
import os

import numpy as np

from slicersim.reduction import stress_score as score

__all__ = ["columns", "stress_table", "write_outputs"]

#: aggregate rows' target_id
AGGREGATE = -1


def columns(flux_bins=score.FLUX_BINS):
    """{column: (unit, description)} of the score columns of stress.ecsv, in order.

    Parameters
    ----------
    flux_bins : sequence of float
        Expected-rate bin edges [e-/s].

    Returns
    -------
    dict
    """
    cols = {}
    for kind, edges, unit in (("sigma", score.SIGMA_BINS, "σ of a group difference"),
                              ("e", score.CHARGE_BINS, "electrons")):
        for label, lo, hi in zip(score.bin_labels(edges, kind), edges[:-1], edges[1:]):
            span = f"{lo:g}–{hi:g} {unit}"
            cols[f"jump_recall_{label}"] = ("", f"fraction of the truth jumps of {span} flagged JUMP_DET in their "
                                                "group or the next")
            cols[f"jump_recall_err_{label}"] = ("", "binomial error of the recall")
            cols[f"n_jump_{label}"] = ("", f"truth jumps of {span} scored (group ≥ 1, unsaturated, good pixel)")
            cols[f"n_jump_found_{label}"] = ("", "of them flagged")
    cols["false_jump_rate"] = ("", "JUMP_DET pixel-groups with no deposit in that group or the one before "
                                   "(with IPC: nor in a 4-neighbour), per scored pixel-group")
    cols["n_false_jump"] = ("", "false jump flags")
    cols["n_pixel_groups"] = ("", "pixel-groups scored for false flags")
    for label, lo, hi in zip(score.bin_labels(flux_bins), flux_bins[:-1], flux_bins[1:]):
        span = f"expected rate {lo:g}–{hi:g} e-/s"
        cols[f"n_slope_{label}"] = ("", f"pixels with a rate, {span}")
        cols[f"slope_bias_{label}"] = ("electron / s", f"mean(rate − expected), {span}")
        cols[f"slope_bias_err_{label}"] = ("electron / s", "standard error of the bias")
        cols[f"slope_resid_std_{label}"] = ("electron / s", "standard deviation of rate − expected")
        cols[f"slope_rel_bias_{label}"] = ("", "bias / mean expected rate")
        cols[f"pull_mean_{label}"] = ("", "mean of (rate − expected) / err (|pull| ≤ 10)")
        cols[f"pull_width_{label}"] = ("", "standard deviation of the pulls (|pull| ≤ 10); 1 when the errors are right")
        cols[f"pull_outlier_frac_{label}"] = ("", "fraction of |pull| > 10")
    cols.update({"sat_recall": ("", "truth-saturated groups flagged SATURATED"),
                 "sat_false_rate": ("", "groups flagged SATURATED the truth has unsaturated, per unsaturated group"),
                 "sat_agreement": ("", "groups where the pipeline's and the truth's saturation agree"),
                 "n_sat_truth": ("", "truth-saturated groups of the scored pixels"),
                 "n_sat_flagged": ("", "groups flagged SATURATED by the pipeline"),
                 "lost_frac": ("", "scored pixels without a rate (NaN or DO_NOT_USE)"),
                 "n_pixels": ("", "pixels scored (no PIXELDQ flag)")})
    return cols


def stress_table(records, pipelines, dataset, flux_bins=score.FLUX_BINS):
    """The table of stress.ecsv: one row per exposure × pipeline, then one aggregate row per pipeline.

    Parameters
    ----------
    records : list of dict
        :func:`slicersim.reduction.stress.stress_exposure` results.
    pipelines : list of (str, list or None)
        The pipelines run.
    dataset : str
        The dataset's path (relative exposure paths, meta).
    flux_bins : sequence of float

    Returns
    -------
    astropy.table.Table
    """
    from astropy.table import Table
    cols = columns(flux_bins)
    rows = []
    for rec in records:
        for row in rec["rows"]:
            rows.append({"target_id": int(rec["target_id"]), "exposure": os.path.relpath(rec["path"], dataset),
                         "pipeline": row["pipeline"], "status": row["status"], "error": row["error"],
                         "seconds": float(row["seconds"]), "notes": "; ".join(row["notes"]), "values": row["values"]})
    for name, _ in pipelines:
        done = [r for r in rows if r["pipeline"] == name and r["status"] == "done"]
        nfail = sum(1 for r in rows if r["pipeline"] == name and r["status"] != "done")
        notes = sorted({n for r in done for n in r["notes"].split("; ") if n})
        rows.append({"target_id": AGGREGATE, "exposure": f"(all: {len(done)} done, {nfail} failed)", "pipeline": name,
                     "status": "aggregate", "error": "", "seconds": float(sum(r["seconds"] for r in done)),
                     "notes": "; ".join(notes),
                     "values": score.aggregate([r["values"] for r in done], flux_bins) if done else {}})
    table = Table()
    for key in ("target_id", "exposure", "pipeline", "status", "error", "seconds", "notes"):
        table[key] = [r[key] for r in rows] if rows else []
    for key, (unit, desc) in cols.items():
        integer = key.startswith("n_")
        vals = [r["values"].get(key, 0 if integer else math.nan) for r in rows]
        table[key] = np.asarray(vals, np.int64 if integer else np.float64)
        table[key].description = desc
        if unit:
            table[key].unit = unit
    desc = {"target_id": "campaign target (−1: aggregate of the pipeline's exposures)",
            "exposure": "ramp file, relative to the dataset", "pipeline": "stcal, slicersim or exec:COMMAND",
            "status": "done, failed or aggregate", "error": "one line, for a failed pipeline",
            "seconds": "wall time of the pipeline (sum for an aggregate)", "notes": "why a score is NaN, inputs used"}
    for key, text in desc.items():
        table[key].description = text
    table["seconds"].unit = "s"
    table.meta = {"dataset": dataset, "pipelines": [n for n, _ in pipelines],
                  "sigma_bins": [float(v) for v in score.SIGMA_BINS], "charge_bins_e": [float(v) for v in score.CHARGE_BINS],
                  "flux_bins_e_per_s": [float(v) for v in flux_bins],
                  "conventions": "see slicersim.reduction.stress_score: rates in e-/s (exec outputs converted from "
                                 "DN/s with the file's GAIN unless their BUNIT names electrons)"}
    return table


def _figures(table, pipelines, path, flux_bins):
    import matplotlib
    with matplotlib.rc_context({"backend": "Agg"}):
        import matplotlib.pyplot as plt
        agg = {str(r["pipeline"]): r for r in table if int(r["target_id"]) == AGGREGATE}
        labels = score.bin_labels(score.SIGMA_BINS, "sigma")
        fig, ax = plt.subplots(figsize=(6, 4))
        x = np.arange(len(labels))
        for k, (name, _) in enumerate(pipelines):
            if name in agg:
                r = agg[name]
                ax.errorbar(x + 0.05 * k, [r[f"jump_recall_{lb}"] for lb in labels],
                            yerr=[r[f"jump_recall_err_{lb}"] for lb in labels], marker="o", capsize=3, label=name)
        ax.set_xticks(x, [f"{a:g}–{b:g}" for a, b in zip(score.SIGMA_BINS[:-1], score.SIGMA_BINS[1:])])
        ax.set_xlabel("jump size [σ of a group difference]")
        ax.set_ylabel("recall")
        ax.set_ylim(None, 1.02)
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(os.path.join(path, "recall_vs_sigma.png"), dpi=100)
        plt.close(fig)
        flabels = score.bin_labels(flux_bins)
        mids = [math.sqrt(max(a, 1e-3) * b) if math.isfinite(b) else 2 * max(a, 1e-3) for a, b in
                zip(flux_bins[:-1], flux_bins[1:])]
        fig, axes = plt.subplots(2, 1, figsize=(6, 6), sharex=True)
        for k, (name, _) in enumerate(pipelines):
            if name in agg:
                r = agg[name]
                xs = np.asarray(mids) * (1 + 0.05 * k)
                n = np.asarray([r[f"n_slope_{lb}"] for lb in flabels], float)
                width = np.asarray([r[f"pull_width_{lb}"] for lb in flabels])
                axes[0].errorbar(xs, [r[f"pull_mean_{lb}"] for lb in flabels], yerr=width / np.sqrt(np.maximum(n, 1)),
                                 marker="o", capsize=3, label=name)
                axes[1].plot(xs, width, marker="o", label=name)
        axes[0].axhline(0, color="k", lw=0.5)
        axes[1].axhspan(0.9, 1.1, color="0.9")
        axes[0].set_ylabel("pull mean")
        axes[1].set_ylabel("pull width")
        axes[1].set_xscale("log")
        axes[1].set_xlim(min(mids) / 2, max(mids) * 2)     # positive limits: no NaN-only autoscale
        axes[1].set_xlabel("expected rate [e-/s]")
        axes[0].legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(os.path.join(path, "pull_vs_flux.png"), dpi=100)
        plt.close(fig)


def _fmt(v, spec=".3g"):
    try:
        v = float(v)
    except (TypeError, ValueError):
        return str(v)
    return "NaN" if not math.isfinite(v) else format(v, spec)


def _report(table, pipelines, dataset, flux_bins, biased):
    lines = [f"# Pipeline stress report: {dataset}", ""]
    agg = {str(r["pipeline"]): r for r in table if int(r["target_id"]) == AGGREGATE}
    per = [r for r in table if int(r["target_id"]) != AGGREGATE]
    nexp = len({int(r["target_id"]) for r in per})
    lines.append(f"{nexp} exposure(s), pipelines: {', '.join(n for n, _ in pipelines)}.  Rates in e-/s; units and "
                 "definitions in the column metadata of stress.ecsv.  Biased: |bias| > 2 standard errors or a pull "
                 "width outside 1 ± 0.1.")
    lines += ["", "## Biased bins", ""]
    any_biased = False
    for name, _ in pipelines:
        for b in biased.get(name, []):
            any_biased = True
            lines.append(f"- **{name}**, flux bin {b['bin']} e-/s ({b['reason']}): bias {_fmt(b['bias'], '+.4g')} ± "
                         f"{_fmt(b['bias_err'], '.2g')} e-/s (relative {_fmt(b['rel_bias'], '+.4f')}), pull mean "
                         f"{_fmt(b['pull_mean'], '+.3f')}, width {_fmt(b['pull_width'], '.3f')}, {int(b['n'])} pixels")
    if not any_biased:
        lines.append("- none")
    sig = score.bin_labels(score.SIGMA_BINS, "sigma")
    lines += ["", "## Summary per pipeline (all exposures)", "",
              "| pipeline | done/failed | " + " | ".join(f"recall {lb}" for lb in sig) +
              " | false jumps / pixel-group | saturation recall | saturation false rate | lost |",
              "|---|---|" + "---|" * (len(sig) + 4)]
    for name, _ in pipelines:
        r = agg.get(name)
        if r is None:
            continue
        lines.append(f"| {name} | {r['exposure'].split(': ', 1)[-1].rstrip(')')} | " +
                     " | ".join(f"{_fmt(r[f'jump_recall_{lb}'], '.4f')} ± {_fmt(r[f'jump_recall_err_{lb}'], '.2g')} "
                                f"(n={int(r[f'n_jump_{lb}'])})" for lb in sig) +
                     f" | {_fmt(r['false_jump_rate'], '.2e')} | {_fmt(r['sat_recall'], '.4f')} | "
                     f"{_fmt(r['sat_false_rate'], '.2e')} | {_fmt(r['lost_frac'], '.2e')} |")
    lines += ["", "![recall against jump size](recall_vs_sigma.png)", "", "## Slopes per flux bin", "",
              "| pipeline | expected rate [e-/s] | n | bias [e-/s] | relative bias | pull mean | pull width |",
              "|---|---|---|---|---|---|---|"]
    for name, _ in pipelines:
        r = agg.get(name)
        if r is None:
            continue
        for lb in score.bin_labels(flux_bins):
            lines.append(f"| {name} | {lb} | {int(r[f'n_slope_{lb}'])} | {_fmt(r[f'slope_bias_{lb}'], '+.3g')} ± "
                         f"{_fmt(r[f'slope_bias_err_{lb}'], '.2g')} | {_fmt(r[f'slope_rel_bias_{lb}'], '+.2e')} | "
                         f"{_fmt(r[f'pull_mean_{lb}'], '+.3f')} | {_fmt(r[f'pull_width_{lb}'], '.3f')} |")
    lines += ["", "![pulls against flux](pull_vs_flux.png)", ""]
    failed = [r for r in per if str(r["status"]) == "failed"]
    lines += ["## Failures", ""]
    lines += [f"- target {int(r['target_id'])}, {r['pipeline']}: {r['error']}" for r in failed[:20]] or ["- none"]
    if len(failed) > 20:
        lines.append(f"- … {len(failed) - 20} more in stress.ecsv")
    notes = {str(n) for r in agg.values() for n in str(r["notes"]).split("; ") if n}
    if notes:
        lines += ["", "## Notes", ""] + [f"- {n}" for n in sorted(notes)]
    return "\n".join(lines) + "\n"


def write_outputs(path, records, pipelines, dataset, flux_bins=score.FLUX_BINS):
    """Write stress.ecsv, the figures and report.md into the folder ``path``.

    Parameters
    ----------
    path : str
        An existing folder (the harness's temporary one).
    records : list of dict
        :func:`slicersim.reduction.stress.stress_exposure` results.
    pipelines : list of (str, list or None)
    dataset : str
    flux_bins : sequence of float

    Returns
    -------
    dict
        ``table`` (astropy Table) and ``biased`` {pipeline: :func:`~slicersim.reduction.stress_score.biased_bins`
        of its aggregate row}.
    """
    from slicersim.io.atomic import atomic_bytes
    table = stress_table(records, pipelines, dataset, flux_bins)
    buf = io.StringIO()
    table.write(buf, format="ascii.ecsv")
    atomic_bytes(os.path.join(path, "stress.ecsv"), buf.getvalue().encode())
    biased = {}
    for r in table:
        if int(r["target_id"]) == AGGREGATE:
            biased[str(r["pipeline"])] = score.biased_bins({c: r[c] for c in table.colnames}, flux_bins)
    _figures(table, pipelines, path, flux_bins)
    atomic_bytes(os.path.join(path, "report.md"), _report(table, pipelines, dataset, flux_bins, biased).encode())
    return {"table": table, "biased": biased}
