"""Scores of a ramp pipeline against the truth of a simulated exposure (NumPy only, no I/O).

:mod:`slicersim.reduction.stress` runs pipelines on every exposure of a campaign dataset and calls
these functions with arrays; they never read a file.  Every score is a count or a statistic with
its Monte Carlo error, and a score whose truth (or pipeline output) is absent is NaN with a note
(:class:`Score` collects both), never a silent number.

Conventions
-----------
* A *truth jump* is the charge of the cosmic-ray (and persistence) deposits of one pixel that
  first show in group ``g`` of an integration (frame ``f`` from the reset: ``g = f // (m + d)``),
  summed over the deposits of that pixel-group.  It is *recovered* when the pipeline flags
  JUMP_DET in group ``g`` or ``g + 1`` (a deposit inside the ``m`` reads of group ``g`` splits its
  step between two differences).  Jumps in group 0 (no difference before them), in saturated
  groups or on pixels that are not scored are left out.
* Its size in σ is the charge over the noise of the difference of two consecutive group means,
  :func:`group_difference_sigma` (read noise, rounding and the Poisson noise of the pixel's
  expected charge).
* A *false flag* is a JUMP_DET pixel-group of a scored pixel with no deposit in that group or
  the one before (with IPC, nor in a 4-neighbour's), counted per scored pixel-group (groups ≥ 1).
* Slopes are compared with the expected rate [e-/s] per pixel: bias = mean(rate − expected),
  pull = (rate − expected) / err; per flux bin of the expected rate.
* Saturation: the pipeline's SATURATED group flags against the truth's (the simulator's flags from
  the true charge).
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["SIGMA_BINS", "CHARGE_BINS", "FLUX_BINS", "Score", "bin_labels", "group_difference_sigma",
           "truth_jumps", "score_jumps", "score_slopes", "score_saturation", "score_lost", "aggregate",
           "biased_bins"]

#: jump size bins [σ of a group difference]
SIGMA_BINS = (5.0, 10.0, 30.0, math.inf)
#: jump charge bins [electrons]
CHARGE_BINS = (0.0, 1e3, 1e4, math.inf)
#: expected-rate bins of the slope scores [e-/s]
FLUX_BINS = (0.0, 1.0, 10.0, 100.0, 1000.0, math.inf)
#: JWST group flags
_SATURATED, _JUMP = 2, 4


def bin_labels(edges, unit=""):
    """Column-name labels of the bins between ``edges``.

    Parameters
    ----------
    edges : sequence of float
        Increasing bin edges (the last may be ``inf``).
    unit : str
        Appended to each label (e.g. ``"sigma"``).

    Returns
    -------
    list of str
        ``"5to10sigma"``, ..., ``"gt30sigma"`` for the last, open bin.
    """
    def num(v):
        return f"{v:g}".replace("+", "")
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        out.append((f"gt{num(lo)}" if math.isinf(hi) else f"{num(lo)}to{num(hi)}") + unit)
    return out


class Score:
    """Scores of one exposure and pipeline: ``values`` {column: number} and ``notes`` [text] saying
    why a score is NaN."""

    def __init__(self):
        self.values, self.notes = {}, []

    def nan(self, columns, note):
        """Set ``columns`` to NaN (counts to 0) with ``note``."""
        for col in columns:
            self.values[col] = 0 if col.startswith("n_") else math.nan
        if note not in self.notes:
            self.notes.append(note)

    def update(self, other):
        """Take the values and notes of ``other`` (a Score)."""
        self.values.update(other.values)
        self.notes += [n for n in other.notes if n not in self.notes]
        return self


def group_difference_sigma(expected_rate, ron, gain, nmd, tframe):
    """Noise of the difference of two consecutive group means [electrons].

    Parameters
    ----------
    expected_rate : numpy.ndarray of shape (ny, nx)
        Expected charge rate [e-/s] (dark included).
    ron : float
        White read noise per frame [electron].
    gain : float
        Gain [ADU/e-] (the ±½ ADU rounding of each group mean adds 1/12 ADU²).
    nmd : (int, int, int)
        Groups, frames per group, dropped frames between groups.
    tframe : float
        Frame time [s].

    Returns
    -------
    numpy.ndarray of shape (ny, nx)
        σ [electrons]: √(2 (σ²/m + 1/(12 g²)) + rate · (m + d) · t_frame).
    """
    _, m, d = nmd
    read = 2.0 * (ron ** 2 / m + 1.0 / (12.0 * gain ** 2))
    return np.sqrt(read + np.clip(expected_rate, 0.0, None) * (m + d) * tframe)


def truth_jumps(deposits, nmd, nints, shape):
    """The truth jumps of the deposits: one per pixel-group, charges summed.

    Parameters
    ----------
    deposits : numpy structured array
        Rows with fields ``ramp``, ``frame`` (from the reset), ``y``, ``x``, ``electrons``
        (``slicersim.products.effects.CR_DTYPE``).
    nmd : (int, int, int)
        Groups n, frames per group m, dropped frames d.
    nints : int
        Integrations.
    shape : (ny, nx)
        Detector size [px].

    Returns
    -------
    dict
        ``ramp``, ``group``, ``y``, ``x`` (int64 arrays, one entry per pixel-group with a deposit
        seen by the ramp) and ``electrons`` (float64, summed), and ``touched``: bool array
        (nints, n, ny, nx) of the pixel-groups with a deposit in that group.
    """
    n, m, d = nmd
    ny, nx = shape
    dep = np.asarray(deposits)
    frame = dep["frame"].astype(np.int64)
    seen = (frame < n * (m + d) - d) & (dep["ramp"].astype(np.int64) < nints)
    dep, frame = dep[seen], frame[seen]
    group = np.minimum(frame // (m + d), n - 1)
    key = ((dep["ramp"].astype(np.int64) * n + group) * ny + dep["y"].astype(np.int64)) * nx + dep["x"].astype(np.int64)
    uniq, inverse = np.unique(key, return_inverse=True)
    charge = np.bincount(inverse, weights=dep["electrons"].astype(np.float64), minlength=uniq.size)
    touched = np.zeros((nints, n, ny, nx), bool)
    touched.reshape(-1)[uniq] = True
    x = uniq % nx
    y = (uniq // nx) % ny
    g = (uniq // (nx * ny)) % n
    r = uniq // (nx * ny * n)
    return {"ramp": r, "group": g, "y": y, "x": x, "electrons": charge, "touched": touched}


def _binomial(found, total):
    """(fraction, binomial error) of ``found`` of ``total`` (NaN, NaN when total is 0)."""
    if total == 0:
        return math.nan, math.nan
    p = found / total
    return p, math.sqrt(max(p * (1 - p), 1.0 / total) / total)    # never 0: one event's worth at p = 0 or 1


def score_jumps(jumps, sigma, flagged, good, saturated=None, ipc=False, sigma_bins=SIGMA_BINS,
                charge_bins=CHARGE_BINS):
    """Jump recall by size and charge, and false jump flags.

    Parameters
    ----------
    jumps : dict
        :func:`truth_jumps` of the exposure.
    sigma : numpy.ndarray of shape (ny, nx)
        :func:`group_difference_sigma` [electrons].
    flagged : numpy.ndarray of shape (nints, ngroups, ny, nx), bool
        The pipeline's JUMP_DET group flags.
    good : numpy.ndarray of shape (ny, nx), bool
        The pixels scored.
    saturated : numpy.ndarray of shape (nints, ngroups, ny, nx), bool, optional
        The truth's saturated groups (left out of the scores).
    ipc : bool
        The exposure has inter-pixel capacitance: a flag beside a deposit (4-neighbours) is not false.
    sigma_bins, charge_bins : sequence of float
        Bin edges [σ] and [electrons].

    Returns
    -------
    Score
        ``jump_recall_<bin>`` (fraction), ``jump_recall_err_<bin>`` (binomial error), ``n_jump_<bin>``
        (truth jumps), ``n_jump_found_<bin>`` for each σ bin and charge bin; ``false_jump_rate``
        (per pixel-group), ``n_false_jump``, ``n_pixel_groups``.
    """
    sc = Score()
    nints, n = flagged.shape[:2]
    g, y, x, r = jumps["group"], jumps["y"], jumps["x"], jumps["ramp"]
    usable = (g >= 1) & good[y, x]
    after = np.minimum(g + 1, n - 1)
    if saturated is not None:
        usable &= ~saturated[r, g, y, x]
    found = flagged[r, g, y, x] | flagged[r, after, y, x]
    size = jumps["electrons"] / sigma[y, x]
    for name, edges, value in (("sigma", sigma_bins, size), ("e", charge_bins, jumps["electrons"])):
        for label, lo, hi in zip(bin_labels(edges, name), edges[:-1], edges[1:]):
            sel = usable & (value >= lo) & (value < hi)
            total, hit = int(sel.sum()), int((found & sel).sum())
            frac, err = _binomial(hit, total)
            sc.values.update({f"jump_recall_{label}": frac, f"jump_recall_err_{label}": err,
                              f"n_jump_{label}": total, f"n_jump_found_{label}": hit})
    touched = jumps["touched"].copy()
    touched[:, 1:] |= jumps["touched"][:, :-1]
    if ipc:
        near = touched.copy()
        near[..., 1:, :] |= touched[..., :-1, :]
        near[..., :-1, :] |= touched[..., 1:, :]
        near[..., :, 1:] |= touched[..., :, :-1]
        near[..., :, :-1] |= touched[..., :, 1:]
        touched = near
    scored = np.broadcast_to(good, flagged.shape).copy()
    scored[:, 0] = False
    if saturated is not None:
        scored &= ~saturated
    false = flagged & ~touched & scored
    npg = int(scored.sum())
    sc.values.update({"false_jump_rate": false.sum() / npg if npg else math.nan,
                      "n_false_jump": int(false.sum()), "n_pixel_groups": npg})
    return sc


def score_slopes(rate, err, expected, good, flux_bins=FLUX_BINS):
    """Slope bias and pulls per flux bin of the expected rate.

    Parameters
    ----------
    rate : numpy.ndarray of shape (ny, nx)
        The pipeline's rate [e-/s] (NaN where it has none).
    err : numpy.ndarray of shape (ny, nx) or None
        Its reported error [e-/s] (None: no pulls).
    expected : numpy.ndarray of shape (ny, nx)
        The expected rate [e-/s].
    good : numpy.ndarray of shape (ny, nx), bool
        The pixels scored.
    flux_bins : sequence of float
        Edges of the expected-rate bins [e-/s].

    Returns
    -------
    Score
        Per bin label ``<lo>to<hi>``: ``n_slope_<bin>`` pixels, ``slope_bias_<bin>`` mean(rate −
        expected) [e-/s], ``slope_bias_err_<bin>`` its standard error, ``slope_resid_std_<bin>``
        [e-/s], ``slope_rel_bias_<bin>`` bias / mean expected, ``pull_mean_<bin>``,
        ``pull_width_<bin>`` (standard deviation; |pull| > 10 left out and counted in
        ``pull_outlier_frac_<bin>``).
    """
    sc = Score()
    ok = good & np.isfinite(rate)
    if err is not None:
        ok &= np.isfinite(err) & (err > 0)
    resid = rate - expected
    for label, lo, hi in zip(bin_labels(flux_bins), flux_bins[:-1], flux_bins[1:]):
        sel = ok & (expected >= lo) & (expected < hi)
        nsel = int(sel.sum())
        v = {f"n_slope_{label}": nsel}
        if nsel >= 2:
            res = resid[sel]
            v[f"slope_bias_{label}"] = float(res.mean())
            v[f"slope_resid_std_{label}"] = float(res.std(ddof=1))
            v[f"slope_bias_err_{label}"] = float(res.std(ddof=1) / math.sqrt(nsel))
            v[f"slope_rel_bias_{label}"] = float(res.mean() / expected[sel].mean()) if expected[sel].mean() > 0 \
                else math.nan
        else:
            for k in ("slope_bias", "slope_resid_std", "slope_bias_err", "slope_rel_bias"):
                v[f"{k}_{label}"] = math.nan
        if err is not None and nsel >= 2:
            pull = resid[sel] / err[sel]
            inner = np.abs(pull) <= 10.0
            v[f"pull_mean_{label}"] = float(pull[inner].mean()) if inner.sum() else math.nan
            v[f"pull_width_{label}"] = float(pull[inner].std(ddof=1)) if inner.sum() > 1 else math.nan
            v[f"pull_outlier_frac_{label}"] = float(1.0 - inner.mean())
        else:
            for k in ("pull_mean", "pull_width", "pull_outlier_frac"):
                v[f"{k}_{label}"] = math.nan
        sc.values.update(v)
    if err is None:
        sc.notes.append("no reported errors: pulls are NaN")
    return sc


def score_saturation(flagged, truth, good):
    """The pipeline's SATURATED groups against the truth's.

    Parameters
    ----------
    flagged, truth : numpy.ndarray of shape (nints, ngroups, ny, nx), bool
        Saturated groups according to the pipeline and to the truth.
    good : numpy.ndarray of shape (ny, nx), bool
        The pixels scored.

    Returns
    -------
    Score
        ``sat_recall`` (truth saturated groups flagged), ``sat_false_rate`` (flagged groups the
        truth has unsaturated, per unsaturated group), ``sat_agreement`` (groups where both agree),
        ``n_sat_truth``, ``n_sat_flagged``.
    """
    sc = Score()
    g = np.broadcast_to(good, truth.shape)
    t, f = truth & g, flagged & g
    nt, ngood = int(t.sum()), int(g.sum())
    sc.values.update({"n_sat_truth": nt, "n_sat_flagged": int(f.sum()),
                      "sat_recall": (t & f).sum() / nt if nt else math.nan,
                      "sat_false_rate": (f & ~t).sum() / (ngood - nt) if ngood > nt else math.nan,
                      "sat_agreement": float((t == f)[g].mean()) if ngood else math.nan})
    if nt == 0:
        sc.notes.append("no saturated group in the truth: sat_recall is NaN")
    return sc


def score_lost(rate, dq, good):
    """Fraction of the scored pixels without a rate.

    Parameters
    ----------
    rate : numpy.ndarray of shape (ny, nx)
        The pipeline's rate [e-/s].
    dq : numpy.ndarray of shape (ny, nx) or None
        Its pixel flags (DO_NOT_USE, bit 1, counts as lost).
    good : numpy.ndarray of shape (ny, nx), bool
        The pixels scored.

    Returns
    -------
    Score
        ``lost_frac`` and ``n_pixels`` (scored).
    """
    sc = Score()
    lost = ~np.isfinite(rate)
    if dq is not None:
        lost |= (np.asarray(dq).astype(np.int64) & 1) != 0
    npix = int(good.sum())
    sc.values.update({"lost_frac": float(lost[good].mean()) if npix else math.nan, "n_pixels": npix})
    return sc


def _pool_mean_std(n, mean, std):
    """Pooled (n, mean, std) of groups given by their sizes, means and standard deviations (ddof 1)."""
    n, mean, std = (np.asarray(a, float) for a in (n, mean, std))
    ok = (n > 0) & np.isfinite(mean)
    tot = n[ok].sum()
    if tot < 2:
        return tot, math.nan, math.nan
    m = (n[ok] * mean[ok]).sum() / tot
    s2 = np.where(n[ok] > 1, np.nan_to_num(std[ok]) ** 2 * (n[ok] - 1), 0.0)
    ss = s2.sum() + (n[ok] * (mean[ok] - m) ** 2).sum()
    return tot, m, math.sqrt(ss / (tot - 1))


def aggregate(rows, flux_bins=FLUX_BINS, sigma_bins=SIGMA_BINS, charge_bins=CHARGE_BINS):
    """Scores of several exposures of one pipeline pooled: counts summed, fractions from the sums,
    means and widths pooled (each pixel weighs the same).

    Parameters
    ----------
    rows : list of dict
        :class:`Score` values of the exposures (those that failed left out).
    flux_bins, sigma_bins, charge_bins : sequence of float
        The bins the rows were scored with.

    Returns
    -------
    dict
        The columns of one row (NaN where no exposure had the score).
    """
    out = {}
    get = lambda k: np.array([r.get(k, math.nan) for r in rows], float)   # noqa: E731
    for label in bin_labels(sigma_bins, "sigma") + bin_labels(charge_bins, "e"):
        tot, hit = np.nansum(get(f"n_jump_{label}")), np.nansum(get(f"n_jump_found_{label}"))
        anyv = np.isfinite(get(f"jump_recall_{label}")).any() or tot > 0
        frac, err = _binomial(int(hit), int(tot)) if anyv else (math.nan, math.nan)
        out.update({f"jump_recall_{label}": frac, f"jump_recall_err_{label}": err, f"n_jump_{label}": int(tot),
                    f"n_jump_found_{label}": int(hit)})
    npg, nfalse = np.nansum(get("n_pixel_groups")), np.nansum(get("n_false_jump"))
    out.update({"false_jump_rate": nfalse / npg if npg else math.nan, "n_false_jump": int(nfalse),
                "n_pixel_groups": int(npg)})
    for label in bin_labels(flux_bins):
        n = get(f"n_slope_{label}")
        tot, bias, std = _pool_mean_std(n, get(f"slope_bias_{label}"), get(f"slope_resid_std_{label}"))
        _, pmean, pwidth = _pool_mean_std(n, get(f"pull_mean_{label}"), get(f"pull_width_{label}"))
        rel = get(f"slope_rel_bias_{label}")
        okr = np.isfinite(rel) & (n > 0)
        out.update({f"n_slope_{label}": int(np.nansum(n)), f"slope_bias_{label}": bias,
                    f"slope_resid_std_{label}": std,
                    f"slope_bias_err_{label}": std / math.sqrt(tot) if tot >= 2 else math.nan,
                    f"slope_rel_bias_{label}": float((rel[okr] * n[okr]).sum() / n[okr].sum()) if okr.any()
                    else math.nan,
                    f"pull_mean_{label}": pmean, f"pull_width_{label}": pwidth,
                    f"pull_outlier_frac_{label}": float(np.nansum(get(f"pull_outlier_frac_{label}") * n)
                                                        / np.nansum(n)) if np.nansum(n) else math.nan})
    nt, nf = get("n_sat_truth"), get("n_sat_flagged")
    rec = get("sat_recall")
    okt = np.isfinite(rec) & (nt > 0)
    out.update({"n_sat_truth": int(np.nansum(nt)), "n_sat_flagged": int(np.nansum(nf)),
                "sat_recall": float((rec[okt] * nt[okt]).sum() / nt[okt].sum()) if okt.any() else math.nan})
    for key in ("sat_false_rate", "sat_agreement"):
        v = get(key)
        out[key] = float(np.nanmean(v)) if np.isfinite(v).any() else math.nan
    npix, lost = get("n_pixels"), get("lost_frac")
    okl = np.isfinite(lost) & (npix > 0)
    out.update({"n_pixels": int(np.nansum(npix)),
                "lost_frac": float((lost[okl] * npix[okl]).sum() / npix[okl].sum()) if okl.any() else math.nan})
    return out


def biased_bins(values, flux_bins=FLUX_BINS, nsigma=2.0, width_tolerance=0.1):
    """The flux bins where a pipeline is biased: |bias| > ``nsigma`` standard errors of the mean,
    or a pull width outside 1 ± ``width_tolerance``.

    Parameters
    ----------
    values : dict
        Score columns of one row (:func:`score_slopes` or :func:`aggregate`).
    flux_bins : sequence of float
        The bins they were scored with.
    nsigma, width_tolerance : float
        The thresholds.

    Returns
    -------
    list of dict
        One per offending bin: ``bin`` label, ``reason`` ("bias", "pull width" or both), ``bias``
        [e-/s], ``bias_err``, ``rel_bias``, ``pull_mean``, ``pull_width``, ``n``.
    """
    out = []
    for label in bin_labels(flux_bins):
        bias, err = values.get(f"slope_bias_{label}", math.nan), values.get(f"slope_bias_err_{label}", math.nan)
        width = values.get(f"pull_width_{label}", math.nan)
        why = []
        if np.isfinite(bias) and np.isfinite(err) and err > 0 and abs(bias) > nsigma * err:
            why.append("bias")
        if np.isfinite(width) and abs(width - 1.0) > width_tolerance:
            why.append("pull width")
        if why:
            out.append({"bin": label, "reason": " and ".join(why), "bias": bias, "bias_err": err,
                        "rel_bias": values.get(f"slope_rel_bias_{label}", math.nan),
                        "pull_mean": values.get(f"pull_mean_{label}", math.nan), "pull_width": width,
                        "n": values.get(f"n_slope_{label}", 0)})
    return out
