"""Spectra and curves versus wavelength: extracted spectrum and SNR, variance budget,
instrument curves (throughput, QE, resolving power, thermal radiance).

The functions take duck-typed models (a Target: anything with a ``.simulation``; a
Simulation: ``get_spectrum``, ``spectrograph``, ...) or plain arrays, import pyplot lazily,
return the matplotlib Figure and, with ``savefile``, write it atomically and release it.
"""
from __future__ import annotations

import numpy as np

from slicersim.errors import ParameterError
from slicersim.plotting.figures import check_axes, check_savefile, finish, new_axes

__all__ = ["SOURCE_STYLES", "plot_spectrum", "plot_variance_budget", "plot_instrument", "plot_curves",
           "readout_title"]


#: label and colour of each variance source (fixed so that figures are comparable)
SOURCE_STYLES = {
    "dark": ("dark current", "tab:blue"),
    "roic_glow": ("ROIC glow", "tab:purple"),
    "thermal_dark": ("thermal dark (undispersed optics)", "tab:brown"),
    "ron": ("read noise", "tab:gray"),
    "pointsource": ("point source (photon noise)", "tab:red"),
    "background": ("zodiacal background", "tab:green"),
    "host": ("host galaxy", "tab:olive"),
    "thermal": ("thermal (telescope + optics)", "tab:orange"),
}


# --------------------------------------------------------------------------- #
#  helpers                                                                     #
# --------------------------------------------------------------------------- #
def _split(target_or_sim):
    """(target or None, simulation)."""
    sim = getattr(target_or_sim, "simulation", None)
    if sim is not None:
        return target_or_sim, sim
    if hasattr(target_or_sim, "get_spectrum") and hasattr(target_or_sim, "spectrograph"):
        return None, target_or_sim
    raise ParameterError(f"target_or_sim must be a Target or a Simulation, got {type(target_or_sim).__name__}")


def _last_etc(target):
    etc = getattr(target, "last_etc", None) if target is not None else None
    return etc if isinstance(etc, dict) and "lbda_range_obs" in etc else None


def readout_title(sim, target=None):
    """Title of a figure: the readout (n, m, d) × ramps and exposure time [s], then the target's
    redshift, configuration and field.

    Parameters
    ----------
    sim : Simulation
        The simulation (its readout and exposure time).
    target : Target, optional
        The target (its redshift, configuration and field).

    Returns
    -------
    str
        The title, on one or two lines.
    """
    t = sim.get_times()
    n, m, d = (int(v) for v in t["nmd"])
    texp = float(t["exposure_time"])
    title = (f"readout (n, m, d) = ({n}, {m}, {d}) × {int(t['nramps'])} ramp"
             f"{'s' if int(t['nramps']) != 1 else ''} — total exposure {texp:.0f} s ({texp / 60:.1f} min)")
    bits = []
    if target is not None and getattr(target, "redshift", None) is not None:
        bits.append(f"z = {target.redshift:g}")
    config = getattr(target, "config", None) or getattr(sim, "config", None)
    field = getattr(target, "field", None) or getattr(sim, "field", None)
    if isinstance(config, (str, list, tuple)) and config:
        bits.append(f"config {config if isinstance(config, str) else '+'.join(map(str, config))}")
    if field:
        bits.append(f"{field} field")
    return title + ("\n" + ", ".join(bits) if bits else "")


def _as_curve(values, lbda):
    return np.broadcast_to(np.asarray(values, dtype=float), np.shape(lbda))


def _shade_band(ax, etc, label=None):
    lo, hi = etc["lbda_range_obs"]
    ax.axvspan(lo, hi, color="gold", alpha=0.25, lw=0, label=label, zorder=0)


def _add_rest_axis(ax, target):
    z = getattr(target, "redshift", None) if target is not None else None
    if z is None or not np.isfinite(z) or z <= -1:
        return
    sec = ax.secondary_xaxis("top", functions=(lambda x: x / (1 + z), lambda x: x * (1 + z)))
    sec.set_xlabel(f"rest-frame wavelength [Å] (z = {z:g})")


# --------------------------------------------------------------------------- #
#  spectrum                                                                    #
# --------------------------------------------------------------------------- #
def plot_spectrum(target_or_sim, ax=None, seed=None, savefile=None):
    """Extracted spectrum with its ±1σ band (top) and SNR per bin (bottom).

    The ETC band of ``target.last_etc`` (if any) is shaded and its target SNR
    per bin drawn as a horizontal line.

    Parameters
    ----------
    target_or_sim : Target or Simulation
        What is drawn.
    ax : matplotlib.axes.Axes or sequence of matplotlib.axes.Axes, optional
        None (new figure), a pair of Axes (spectrum, SNR) or a single Axes (spectrum panel
        only).
    seed : int or numpy.random.Generator, optional
        If given, a noisy realisation is drawn as points.
    savefile : str, os.PathLike or file object, optional
        If given the figure is saved there.

    Returns
    -------
    matplotlib.figure.Figure
        The figure.
    """
    check_savefile(savefile)
    target, sim = _split(target_or_sim)
    lbda, signal, variance = sim.get_spectrum()
    finite = np.isfinite(variance) & (variance >= 0)
    sigma = np.where(finite, np.sqrt(np.where(finite, variance, 0.0)), np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        snr = np.where(finite & (sigma > 0), signal / sigma, np.nan)
    etc = _last_etc(target)

    if ax is None:
        import matplotlib.pyplot as plt
        fig, (ax_spec, ax_snr) = plt.subplots(2, 1, sharex=True, figsize=(9, 7),
                                              gridspec_kw={"height_ratios": [3, 2]},
                                              layout="constrained")
    else:
        axes = check_axes(ax)
        if len(axes) not in (1, 2):
            raise ParameterError(f"ax must be one Axes (spectrum) or two (spectrum, SNR), got {len(axes)}")
        ax_spec, ax_snr = axes[0], (axes[1] if len(axes) == 2 else None)
        fig = ax_spec.figure

    # top: signal ± 1σ (+ a noisy draw)
    if etc is not None:
        _shade_band(ax_spec, etc, label="ETC band")
    ax_spec.fill_between(lbda, signal - sigma, signal + sigma, color="tab:blue", alpha=0.3, lw=0,
                         label="±1σ")
    ax_spec.plot(lbda, signal, color="tab:blue", lw=1.3, label="noiseless signal")
    if seed is not None:
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        noisy = np.where(finite, signal + rng.standard_normal(signal.shape) * np.nan_to_num(sigma), np.nan)
        ax_spec.plot(lbda, noisy, ".", color="k", ms=2.5, alpha=0.7,
                     label=f"noisy realisation (seed {seed})" if not isinstance(seed, np.random.Generator)
                     else "noisy realisation")
    ax_spec.set_ylabel("extracted signal [ADU]\n(all ramps)")
    ax_spec.legend(loc="best", fontsize="small")
    ax_spec.grid(alpha=0.3)
    _add_rest_axis(ax_spec, target)
    if ax is None:
        fig.suptitle(readout_title(sim, target), fontsize="medium")
    if ax_snr is None:
        ax_spec.set_xlabel("observed wavelength [Å]")
        return finish(fig, savefile)

    # bottom: SNR per bin, ETC band and target
    ax_snr.plot(lbda, snr, color="tab:red", lw=1.3, label="SNR per bin")
    if etc is not None:
        lo, hi = etc["lbda_range_obs"]
        _shade_band(ax_snr, etc, label=f"ETC band {lo:.0f}–{hi:.0f} Å")
        if "snr_target" in etc:
            ax_snr.hlines(float(etc["snr_target"]), lbda[0], lbda[-1], colors="k", linestyles="--", lw=1,
                          label=f"target band SNR per bin = {float(etc['snr_target']):.1f}")
        if "snr" in etc:
            ax_snr.hlines(float(etc["snr"]), lo, hi, colors="tab:green", lw=2,
                          label=f"reached band SNR per bin = {float(etc['snr']):.1f}")
    ax_snr.set_xlabel("observed wavelength [Å]")
    ax_snr.set_ylabel("SNR per bin")
    top = np.nanmax(snr) if np.isfinite(snr).any() else 1.0
    if etc is not None and "snr_target" in etc:
        top = max(top, float(etc["snr_target"]))
    ax_snr.set_ylim(0, 1.6 * top)   # head room for the legend
    ax_snr.legend(loc="upper right", fontsize="small", ncol=2)
    ax_snr.grid(alpha=0.3)
    ax_snr.set_xlim(lbda[0], lbda[-1])
    return finish(fig, savefile)


# --------------------------------------------------------------------------- #
#  variance budget                                                             #
# --------------------------------------------------------------------------- #
def plot_variance_budget(target_or_sim, ax=None, savefile=None):
    """Variance per source versus wavelength.

    Top: total variance and each source's contribution [ADU²] (log scale);
    bottom: each contribution as a fraction of the total.  A contribution is
    Var(all) − Var(source off) (see ``Simulation.get_variance_contribution``),
    so the fractions need not add up to exactly 1; their sum is drawn too.
    Sources that are zero everywhere are listed in the legend as such.

    Parameters
    ----------
    target_or_sim : Target or Simulation
        What is drawn.
    ax : sequence of matplotlib.axes.Axes, optional
        None (new figure) or a pair of Axes (variance, fraction).
    savefile : str, os.PathLike or file object, optional
        If given the figure is saved there.

    Returns
    -------
    matplotlib.figure.Figure
        The figure.
    """
    check_savefile(savefile)
    target, sim = _split(target_or_sim)
    contrib = sim.get_variance_contribution()
    lbda = sim.lbda
    total = np.asarray(contrib["variance"], dtype=float)
    good = np.isfinite(total) & (total > 0)
    etc = _last_etc(target)

    if ax is None:
        fig, (ax_var, ax_frac) = new_axes(nrows=2, sharex=True, figsize=(9, 7.5))
    else:
        ax_var, ax_frac = check_axes(ax, 2, "Axes (variance, fraction)")
        fig = ax_var.figure
    if etc is not None:
        _shade_band(ax_var, etc, label="ETC band")
        _shade_band(ax_frac, etc)
    ax_var.plot(lbda, np.where(good, total, np.nan), color="k", lw=2, label="total variance")
    frac_sum = np.zeros_like(total)
    zero = []
    for src, arr in contrib.items():
        if src == "variance":
            continue
        label, color = SOURCE_STYLES.get(src, (src, None))
        arr = np.asarray(arr, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            frac = np.where(good, arr / total, np.nan)
        frac_sum = frac_sum + np.nan_to_num(frac)
        if not np.any(np.abs(arr[np.isfinite(arr)]) > 0):
            zero.append(label)
            continue
        ax_var.plot(lbda, np.where(good & (arr > 0), arr, np.nan), color=color, lw=1.2, label=label)
        ax_frac.plot(lbda, frac, color=color, lw=1.2, label=label)
    ax_frac.plot(lbda, np.where(good, frac_sum, np.nan), color="k", ls=":", lw=1, label="sum of fractions")

    if zero:
        ax_var.plot([], [], " ", label="zero: " + ", ".join(zero))
    ax_var.set_yscale("log")
    positive = total[good]
    if positive.size:
        ax_var.set_ylim(bottom=max(positive.min() * 1e-4, 1e-12 * positive.max()))
    ax_var.set_ylabel("variance [ADU²]\n(extracted, all ramps)")
    ax_var.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize="small")
    ax_var.grid(alpha=0.3, which="both")
    ax_var.set_title("variance contribution per source (Var(all) − Var(source off))", fontsize="medium")
    _add_rest_axis(ax_var, target)

    ax_frac.set_xlabel("observed wavelength [Å]")
    ax_frac.set_ylabel("fraction of total variance")
    top = np.nanmax(np.where(good, frac_sum, np.nan)) if good.any() else 1.0
    ax_frac.set_ylim(min(0.0, np.nanmin(ax_frac.get_ylim())), max(1.05, top + 0.05))
    ax_frac.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize="small")
    ax_frac.grid(alpha=0.3)
    ax_frac.set_xlim(lbda[0], lbda[-1])
    if ax is None:
        fig.suptitle(readout_title(sim, target), fontsize="medium")
    return finish(fig, savefile)


# --------------------------------------------------------------------------- #
#  instrument                                                                  #
# --------------------------------------------------------------------------- #
def plot_instrument(sim, savefile=None):
    """Throughput, QE, throughput × QE (top) and resolving power (bottom) versus λ [Å].

    Parameters
    ----------
    sim : Simulation or Target
        The instrument drawn (a target's simulation).
    savefile : str, os.PathLike or file object, optional
        If given the figure is saved there.

    Returns
    -------
    matplotlib.figure.Figure
        The figure.
    """
    check_savefile(savefile)
    import matplotlib.pyplot as plt

    _, sim = _split(sim)
    lbda = sim.lbda
    thr = _as_curve(sim.spectrograph.throughput, lbda)
    qe = _as_curve(sim.qe, lbda)
    rpow = _as_curve(sim.spectrograph.resolving_power, lbda)

    fig, (ax_t, ax_r) = plt.subplots(2, 1, sharex=True, figsize=(9, 6.5),
                                     gridspec_kw={"height_ratios": [3, 2]}, layout="constrained")
    ax_t.plot(lbda, thr, color="tab:blue", lw=1.3, label="telescope + IFS throughput")
    ax_t.plot(lbda, qe, color="tab:orange", lw=1.3, label="detector QE")
    ax_t.plot(lbda, thr * qe, color="k", lw=2, label="throughput × QE")
    ax_t.set_ylabel("efficiency")
    ax_t.set_ylim(0, max(1.0, float(np.nanmax(np.concatenate([thr, qe])))) * 1.02)
    ax_t.legend(loc="best", fontsize="small")
    ax_t.grid(alpha=0.3)

    ax_r.plot(lbda, rpow, color="tab:purple", lw=1.5)
    ax_r.set_ylabel("resolving power R\n(per resolution element)")
    ax_r.set_xlabel("wavelength [Å]")
    ax_r.grid(alpha=0.3)
    ax_r.set_xlim(lbda[0], lbda[-1])

    spec = sim.spectrograph
    bits = [type(spec).__name__]
    if getattr(sim, "config", None):
        bits.append(f"config {sim.config}")
    if getattr(sim, "field", None):
        bits.append(f"{sim.field} field")
    try:
        bits.append(f"{spec.nlbda} bins, {spec.dispersion_resolution:g} bins per resolution element")
    except AttributeError:
        pass
    fig.suptitle("instrument: " + ", ".join(bits), fontsize="medium")
    return finish(fig, savefile)


def plot_curves(lbda, curves, ylabel, title=None, ax=None, savefile=None, ylim=None, xlabel="wavelength [Å]",
                yscale="linear"):
    """Curves versus wavelength on one Axes.

    Parameters
    ----------
    lbda : array_like of shape (nλ,)
        Wavelengths [Å].
    curves : dict
        {label: values}, each a scalar or of shape (nλ,).
    ylabel : str
        y label, with its unit (e.g. "throughput [fraction of photons]").
    title : str, optional
        Title of the axes.
    ax : matplotlib.axes.Axes, optional
        None (new figure) or an Axes.
    savefile : str, os.PathLike or file object, optional
        If given the figure is saved there.
    ylim : tuple of float, optional
        y limits.
    xlabel : str, optional
        x label, with its unit.
    yscale : {"linear", "log"}, optional
        Scale of the y axis.

    Returns
    -------
    matplotlib.figure.Figure
        The figure.
    """
    check_savefile(savefile)
    fig, ax = new_axes(ax, figsize=(8, 4.5))
    lbda = np.asarray(lbda, dtype=float)
    for label, values in curves.items():
        ax.plot(lbda, _as_curve(values, lbda), lw=1.4, label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_yscale(yscale)
    if ylim is not None:
        ax.set_ylim(*ylim)
    if lbda.size:
        ax.set_xlim(lbda[0], lbda[-1])
    if len(curves) > 1:
        ax.legend(loc="best", fontsize="small")
    ax.grid(alpha=0.3)
    if title:
        ax.set_title(title, fontsize="medium")
    return finish(fig, savefile)
