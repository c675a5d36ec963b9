"""The report of a campaign against its truth: ``summary.ecsv``, ``report.md`` and two figures.

``campaign_report(DATASET, OUT, reduced=RED)`` writes into the folder OUT (made when missing; every
file written atomically, replacing an earlier report's)::

    summary.ecsv                one row per target (:func:`slicersim.reduction.summary.summarize`)
    report.md                   counts, the band, per-redshift-bin bias and pulls, SNR against the ETC,
                                the per-target table, the figures
    bias_vs_redshift.png        band flux / input and pulls against z, per-bin mean ± error
    snr_vs_etc.png              band SNR measured (and reported) against the ETC's

``slicersim reduce DATASET --out RED --spectra`` writes it into RED; ``slicersim campaign report``
for any campaign.
"""
from __future__ import annotations

import io
import os

import numpy as np

from slicersim.errors import DatasetError

__all__ = ["campaign_report", "SUMMARY", "REPORT", "FIGURES"]

SUMMARY, REPORT = "summary.ecsv", "report.md"
FIGURES = ("bias_vs_redshift.png", "snr_vs_etc.png")


def _out_dir(out):
    path = os.path.abspath(os.fspath(out))
    if os.path.lexists(path) and not os.path.isdir(path):
        raise DatasetError(f"the report folder {path} is a file (or not a folder): give a folder")
    parent = os.path.dirname(path)
    if not os.path.isdir(parent):
        raise DatasetError(f"the report folder's parent {parent} does not exist")
    os.makedirs(path, exist_ok=True)
    return path


def campaign_report(dataset, out, reduced=None):
    """Write the summary, report and figures of campaign ``dataset`` (module docstring).

    Parameters
    ----------
    dataset : path of the campaign dataset
    out : folder of the report (made when missing; may be the reduction directory)
    reduced : its reduction directory (``slicersim reduce DATASET --out RED --spectra``), or None

    Returns
    -------
    dict: ``table`` (the summary, astropy Table), ``summary``, ``report``, ``figures`` (paths),
    ``bins`` (per-redshift-bin statistics of band_flux_ratio and pull).
    """
    import matplotlib
    from slicersim.io.atomic import atomic_bytes
    from slicersim.plotting.campaign import plot_bias_vs_redshift, plot_snr_vs_etc
    from slicersim.reduction.summary import redshift_bins, summarize
    table = summarize(dataset, reduced)
    path = _out_dir(out)
    buf = io.StringIO()
    table.meta = {"dataset": os.path.abspath(os.fspath(dataset)),
                  "reduced": None if reduced is None else os.path.abspath(os.fspath(reduced))}
    table.write(buf, format="ascii.ecsv")
    atomic_bytes(os.path.join(path, SUMMARY), buf.getvalue().encode(), overwrite=True)
    z = np.asarray(table["redshift"], float)
    bins = {"band_flux_ratio": redshift_bins(z, table["band_flux_ratio"], table["band_flux_ratio_error"]),
            "pull": redshift_bins(z, table["pull"])}
    figures = [os.path.join(path, name) for name in FIGURES]
    with matplotlib.rc_context({"backend": "Agg"}):
        plot_bias_vs_redshift(z, table["band_flux_ratio"], table["band_flux_ratio_error"], table["pull"],
                              bins["band_flux_ratio"], bins["pull"], title=_title(dataset, reduced),
                              savefile=figures[0])
        plot_snr_vs_etc(table["snr_etc"], table["snr_measured"], table["snr_reported"], savefile=figures[1])
    text = _markdown(table, bins, dataset, reduced)
    atomic_bytes(os.path.join(path, REPORT), text.encode(), overwrite=True)
    return {"table": table, "summary": os.path.join(path, SUMMARY), "report": os.path.join(path, REPORT),
            "figures": figures, "bins": bins}


def _title(dataset, reduced):
    what = "reduced spectra" if reduced is not None else "simulated spectra"
    return f"{os.path.basename(os.path.abspath(os.fspath(dataset)))}: {what} against the input"


def _fmt(v, spec=".4g"):
    try:
        v = float(v)
    except (TypeError, ValueError):
        return str(v)
    return "–" if not np.isfinite(v) else format(v, spec)


def _markdown(table, bins, dataset, reduced):
    n = len(table)
    status = [str(s) for s in table["status"]]
    ratio = np.asarray(table["band_flux_ratio"], float)
    ok = np.isfinite(ratio)
    lines = [f"# Campaign report: {os.path.abspath(os.fspath(dataset))}", ""]
    where = os.path.abspath(os.fspath(reduced)) if reduced is not None else "none (the campaign's simulated spectra)"
    lines.append(f"- reduction: {where}")
    lines.append(f"- targets: {n}; " + ", ".join(f"{s}: {status.count(s)}" for s in sorted(set(status))))
    lines.append(f"- compared with the input: {int(ok.sum())}")
    if ok.any():
        err = np.asarray(table["band_flux_ratio_error"], float)[ok]
        pull = np.asarray(table["pull"], float)
        pok = np.isfinite(pull)
        mean = float(ratio[ok].mean())
        lines.append(f"- band flux / input: mean {mean:.4f} ± {float(np.sqrt(np.sum(err**2)) / ok.sum()):.4f} "
                     f"(scatter {float(ratio[ok].std()):.4f})")
        if pok.any():
            lines.append(f"- pulls: mean {pull[pok].mean():+.2f}, standard deviation "
                         f"{pull[pok].std(ddof=1) if pok.sum() > 1 else float('nan'):.2f} (1 when the errors are right)")
        for name, label in (("snr_measured", "measured"), ("snr_reported", "reported")):
            q = np.asarray(table[name], float) / np.asarray(table["snr_etc"], float)
            q = q[np.isfinite(q)]
            if q.size:
                lines.append(f"- band SNR {label} / ETC: median {np.median(q):.3f}")
    lo, hi = np.asarray(table["band_lo"], float), np.asarray(table["band_hi"], float)
    ok = np.isfinite(lo) & np.isfinite(hi)
    if ok.any():
        first = int(np.argmin(np.where(ok, lo, np.inf)))
        last = int(np.argmax(np.where(ok, lo, -np.inf)))
        lines.append(f"- band (observer frame, per target: band_lo, band_hi): {lo[first]:.0f}–{hi[first]:.0f} Å "
                     f"to {lo[last]:.0f}–{hi[last]:.0f} Å")
    lines += ["", "## Against redshift", "", "![bias and pulls against redshift](bias_vs_redshift.png)", "",
              "| z bin | n | band flux / input | pull |", "|---|---|---|---|"]
    rb, pb = bins["band_flux_ratio"], bins["pull"]
    for i in range(len(rb["z_mid"])):
        pm = pb["mean"][i] if i < len(pb["mean"]) else np.nan
        pe = pb["error"][i] if i < len(pb["error"]) else np.nan
        lines.append(f"| {rb['z_lo'][i]:.3f}–{rb['z_hi'][i]:.3f} | {int(rb['n'][i])} | "
                     f"{_fmt(rb['mean'][i], '.4f')} ± {_fmt(rb['error'][i], '.4f')} | {_fmt(pm, '+.2f')} ± "
                     f"{_fmt(pe, '.2f')} |")
    lines += ["", "## SNR against the ETC", "", "![SNR against the ETC](snr_vs_etc.png)", "",
              "## Targets", "", "Units and definitions: the column metadata of summary.ecsv.", ""]
    cols = ("target_id", "status", "redshift", "phase", "band_flux_ratio", "band_flux_ratio_error", "pull", "chi2",
            "snr_reported", "snr_measured", "snr_etc", "position_error", "flags")
    lines.append("| " + " | ".join(cols) + " |")
    lines.append("|" + "---|" * len(cols))
    for row in table:
        lines.append("| " + " | ".join(str(row[c]) if c in ("target_id", "status", "flags") else _fmt(row[c])
                                       for c in cols) + " |")
    return "\n".join(lines) + "\n"
