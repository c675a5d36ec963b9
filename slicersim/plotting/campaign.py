"""Figures of a campaign's summary: band-flux bias and pulls against redshift, SNR against the ETC.

Arrays in, Figure out (:mod:`slicersim.plotting`); the per-redshift-bin means come from the caller
(:func:`slicersim.reduction.summary.redshift_bins`).
"""
from __future__ import annotations

import numpy as np

from slicersim.plotting.figures import finish

__all__ = ["plot_bias_vs_redshift", "plot_snr_vs_etc"]


def _binned(ax, bins, color="k", label="mean ± error per z bin"):
    if bins is None or not len(bins.get("z_mid", [])):
        return
    ok = np.isfinite(bins["mean"])
    ax.errorbar(bins["z_mid"][ok], bins["mean"][ok], yerr=np.nan_to_num(bins["error"][ok]),
                xerr=0.5 * (bins["z_hi"] - bins["z_lo"])[ok], fmt="s", color=color, ms=6, capsize=3, label=label,
                zorder=3)


def plot_bias_vs_redshift(z, ratio, ratio_error, pull, ratio_bins=None, pull_bins=None, title=None,
                          savefile=None):
    """Two panels against redshift: band flux / input (±1σ) and the pulls, with per-bin means.

    Parameters
    ----------
    z, ratio, ratio_error, pull : (N,) arrays (NaN: left out)
    ratio_bins, pull_bins : dicts of :func:`~slicersim.reduction.summary.redshift_bins` or None
    title : figure title;  savefile : path (written atomically) or None

    Returns
    -------
    matplotlib Figure.
    """
    import matplotlib.pyplot as plt
    z, ratio, err, pull = (np.asarray(a, float) for a in (z, ratio, ratio_error, pull))
    fig, (a1, a2) = plt.subplots(2, 1, sharex=True, figsize=(7, 6.5), layout="constrained")
    ok = np.isfinite(z) & np.isfinite(ratio)
    a1.errorbar(z[ok], ratio[ok], yerr=np.nan_to_num(err[ok]), fmt="o", color="C0", alpha=0.6, ms=4,
                label="targets")
    _binned(a1, ratio_bins)
    a1.axhline(1.0, color="0.4", lw=1, ls="--")
    a1.set_ylabel("band flux / input")
    a1.legend(loc="best", fontsize="small")
    ok = np.isfinite(z) & np.isfinite(pull)
    a2.plot(z[ok], pull[ok], "o", color="C1", alpha=0.6, ms=4, label="targets")
    _binned(a2, pull_bins)
    a2.axhline(0.0, color="0.4", lw=1, ls="--")
    for s in (-1, 1):
        a2.axhline(s, color="0.7", lw=0.8, ls=":")
    a2.set_ylabel("pull (ratio − 1) / σ")
    a2.set_xlabel("redshift z")
    if title:
        a1.set_title(title)
    return finish(fig, savefile)


def plot_snr_vs_etc(snr_etc, snr_measured, snr_reported=None, title=None, savefile=None):
    """Band SNR measured (and reported) against the ETC's prediction, with the 1:1 line.

    Parameters
    ----------
    snr_etc, snr_measured : (N,) arrays;  snr_reported : (N,) array or None
    title : figure title;  savefile : path or None

    Returns
    -------
    matplotlib Figure.
    """
    from slicersim.plotting.figures import new_axes
    fig, ax = new_axes(figsize=(6, 5.5))
    etc, meas = np.asarray(snr_etc, float), np.asarray(snr_measured, float)
    ok = np.isfinite(etc) & np.isfinite(meas)
    ax.plot(etc[ok], meas[ok], "o", color="C0", label="measured (residuals vs input)")
    vals = [etc[ok], meas[ok]]
    if snr_reported is not None:
        rep = np.asarray(snr_reported, float)
        okr = np.isfinite(etc) & np.isfinite(rep)
        ax.plot(etc[okr], rep[okr], "x", color="C3", label="reported (pipeline errors)")
        vals.append(rep[okr])
    vals = np.concatenate(vals)
    if vals.size:
        lo, hi = float(vals.min()), float(vals.max())
        pad = 0.05 * (hi - lo or max(hi, 1.0))
        ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], color="0.4", lw=1, ls="--", label="1:1")
    ax.set_xlabel("ETC band SNR (readout used)")
    ax.set_ylabel("band SNR")
    ax.legend(loc="best", fontsize="small")
    if title:
        ax.set_title(title)
    return finish(fig, savefile)
