"""Exposure-time search: the readout (n, m, d) × nramps reaching a band SNR.

Two strategies:

* ``"exact"`` (default): the readout with the smallest total exposure time whose
  band SNR is ≥ the target, found directly on the allowed grid
  n ∈ [min_group, max_group], m ∈ {8, 4, 1}, d = the detector's d, r ≥ 1,
  using SNR(n, m, d, r) = √r · SNR(n, m, d, 1) (ramps are summed).
* ``"reference"``: the integer walk of slicersim 1.0 (``fetch_snr``), step for
  step, including its tolerance of 0.5 and its cycles.
"""
from __future__ import annotations

import math

import numpy as np

from slicersim import validation
from slicersim.errors import ETCError, ParameterError
from slicersim.snr.snr_table import band_snr_table_for_models, sim_band_indices
from slicersim.physics.readout import readout_times

__all__ = ["solve_readout", "reference_walk", "exact_choice", "FRAMES_PER_GROUP", "SEARCHES",
           "check_snr", "check_snr_target", "check_search",
           "MAX_TOTAL_EXPOSURE", "MAX_RAMPS"]

#: frames per group allowed by the exact search (MACC modes of the H4RG ROIC)
FRAMES_PER_GROUP = (8, 4, 1)
#: longest total exposure [s] the ETC returns (1 Julian year); longer requests raise ETCError
MAX_TOTAL_EXPOSURE = 365.25 * 86400.0
#: most ramps the ETC returns (keeps ramps × frames exact in int64); more raise ETCError
MAX_RAMPS = 10**9
#: the search strategies of :func:`solve_readout`
SEARCHES = ("exact", "reference")
#: relative shortfall (beyond the walk's absolute tolerance 0.5) accepted at the end of the
#: reference walk; a walk ending lower raises ETCError
REFERENCE_SHORTFALL = 0.10


def check_snr(snr, name="snr"):
    """A target SNR as a float: a finite number > 0.  ParameterError for what is not a number
    (strings, bools, lists), ETCError for an impossible value (NaN, inf, ≤ 0); both name ``name``."""
    name = validation.shown(name)
    is_number = isinstance(snr, (int, float, np.integer, np.floating)) and not isinstance(snr, (bool, np.bool_))
    error = ETCError if is_number else ParameterError
    try:
        return validation.number(name, snr, low=0.0, low_open=True, error=error)
    except error:
        raise error(f"{name}: the target SNR must be a finite number > 0, got "
                    f"{validation.short_repr(snr)}") from None


def check_snr_target(snr, name="snr"):
    """A target SNR: a finite number > 0 (:func:`check_snr`: ETCError for an
    impossible value, ParameterError for what is not a number)."""
    return check_snr(snr, name)


def check_search(search):
    """``search`` one of :data:`SEARCHES` (ETCError listing them otherwise)."""
    return validation.choice("search", search, SEARCHES, error=ETCError)


# --------------------------------------------------------------------------- #
#  reference walk (slicersim 1.0 fetch_snr)                                    #
# --------------------------------------------------------------------------- #
def _walk(value, snr_of, target, tol, vmin, vmax, maxiter, trace):
    """Integer walk on one free parameter; returns (value, snr)."""
    s = snr_of(value)
    history, step, stop, it = [], 1, False, 0
    while abs(s - target) > tol and it < maxiter:
        history.append(value)
        if value <= vmin:
            value = vmin
            s = snr_of(value)
        if stop or (value <= vmin and s >= target):
            break
        high = s >= target
        new = value - step if high else value + step
        if new <= 0:
            new = 1
        new = max(new, vmin)
        if vmax is not None:
            new = min(new, vmax)
        s_new = snr_of(new)
        step = 2 * step if (s_new >= target) == high else 1
        value, s = new, s_new
        if len(history) > 3 and history[-2] == value:
            if value > history[-1]:
                break
            stop = True
        it += 1
    return value, s


def reference_walk(snr, target, max_group=64, d0=0, tol=0.5, maxiter=30):
    """slicersim 1.0 readout walk.

    Parameters
    ----------
    snr : callable (n, m, d, r) -> band SNR per bin
    target : float  target band SNR per bin

    Returns
    -------
    (n, m, d), r, reached SNR, trace (list of ((n, m, d), r, snr))
    """
    trace = []

    def evaluate(n, m, d, r):
        val = float(snr(n, m, d, r))
        trace.append(((n, m, d), r, val))
        return val

    s1 = evaluate(max_group, 8, d0, 1)
    if s1 >= target - tol:  # bright: walk on n (no upper bound)
        if evaluate(32, 4, 0, 1) <= target - tol:
            n, m, d = 32, 8, 0
        elif evaluate(8, 4, 0, 1) >= target - tol:
            n, m, d = 32, 1, 0
        else:
            n, m, d = 20, 4, 0
        n, s = _walk(n, lambda v: evaluate(v, m, d, 1), target, tol, 2, None, maxiter, trace)
        return (n, m, d), 1, s, trace
    # faint: walk on the number of ramps, then fine-tune the groups
    n, m, d = max_group, 8, d0
    r, s = _walk(4, lambda v: evaluate(n, m, d, v), target, tol, 2, None, maxiter, trace)
    if abs(s - target) > 1:
        r = r if s - 1 > target else r + 1
        n, m = n - 10, 8
        n, s = _walk(n, lambda v: evaluate(v, m, d, r), target, tol, 2, max_group, maxiter, trace)
    return (n, m, d), r, s, trace


# --------------------------------------------------------------------------- #
#  exact search                                                                #
# --------------------------------------------------------------------------- #
def candidate_readouts(min_group, max_group, d=0, frames_per_group=FRAMES_PER_GROUP):
    """Arrays (n, m, d) of every candidate single-ramp readout, m-major."""
    ns = np.arange(min_group, max_group + 1)
    n = np.tile(ns, len(frames_per_group))
    m = np.repeat(np.asarray(frames_per_group), ns.size)
    return n, m, np.full_like(n, d)


def exact_choice(snr1, n, m, d, target, max_extra_ramps=None, max_frames=None):
    """Choose the minimal-exposure readout from single-ramp SNRs.

    Parameters
    ----------
    snr1 : (N, K) band SNR per bin of one ramp for each target and candidate
    n, m, d : (K,) candidate readouts (m-major blocks of increasing n)
    target : (N,) target SNR per bin
    max_extra_ramps : int, optional
        ramps r are searched in [rmin, 2 rmin + max_extra_ramps] (default 10), rmin the
        fewest ramps any candidate needs
    max_frames : float, optional
        largest total number of frames (nramps × frames per ramp) accepted; a target
        whose best readout needs more gets n = 0 and ``limited`` = True.  Default
        :data:`MAX_RAMPS` × the longest candidate ramp (keeps the integers exact).

    Returns
    -------
    dict of (N,) arrays: n, m, d, nramps, nframes (total frames), snr, limited
    (n = 0 where no readout reaches the target; ``limited`` where one would, but
    beyond ``max_frames`` / :data:`MAX_RAMPS`).

    The cost does not depend on the number of ramps: for each candidate k the fewest
    ramps r_k with snr1_k √r_k ≥ target is found in closed form (then corrected by
    ±1 with the exact float test of the former loop over r), and the candidate with
    the smallest (total frames, ramps, groups) is kept -- the same choice as the
    former loop over r (kept as :func:`exact_choice_loop` for reference).
    """
    snr1 = np.atleast_2d(np.asarray(snr1, dtype=float))
    target = np.broadcast_to(np.asarray(target, dtype=float), snr1.shape[:1])
    n, m, d = (np.asarray(a) for a in (n, m, d))
    ntarget, ncand = snr1.shape
    frames = (n * (m + d) - d).astype(np.int64)              # frames per ramp per candidate
    clean = np.where(np.isfinite(snr1), snr1, -np.inf)
    best_snr1 = clean.max(axis=1) if ncand else np.full(ntarget, -np.inf)
    out = {k: np.zeros(ntarget, dtype=int) for k in ("n", "m", "d", "nramps", "nframes")}
    out["snr"] = np.full(ntarget, np.nan)
    out["limited"] = np.zeros(ntarget, dtype=bool)
    if ntarget == 0 or ncand == 0:
        return out
    rmax_extra = 10 if max_extra_ramps is None else max_extra_ramps
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        rmin = np.ceil((target / best_snr1) ** 2 * (1 - 1e-12))
        rmin = np.where(best_snr1 > 0, np.maximum(rmin, 1), np.inf)
        # closed-form fewest ramps per candidate (float), then exact integer correction
        rk = np.ceil((target[:, None] / clean) ** 2 * (1 - 1e-12))
    rk = np.where(clean > 0, np.maximum(rk, rmin[:, None]), np.inf)
    rk = np.where(np.isfinite(rk), rk, np.inf)
    # beyond MAX_RAMPS the integers are not exact any more: such a candidate is "limited"
    reachable = np.isfinite(rk) & (rk <= MAX_RAMPS)
    r = np.where(reachable, rk, 1).astype(np.int64)
    t2 = target[:, None]

    def feasible(rr):
        with np.errstate(divide="ignore", invalid="ignore"):
            return clean >= t2 / np.sqrt(rr.astype(float))
    for _ in range(4):                                      # r_k too small: step up
        up = reachable & ~feasible(r)
        if not up.any():
            break
        r = np.where(up, r + 1, r)
    for _ in range(4):                                      # r_k - 1 still reaches: step down
        prev = np.maximum(r - 1, 1)
        down = reachable & (r - 1 >= rmin[:, None]) & feasible(prev)
        if not down.any():
            break
        r = np.where(down, prev, r)
    ok = reachable & feasible(r) & (r >= rmin[:, None])
    within = ok & (r <= 2 * rmin[:, None] + rmax_extra)
    big = np.iinfo(np.int64).max
    tot = np.where(within, r * frames[None, :], big)
    # lexicographic minimum of (total frames, ramps, groups) per target
    rr = np.where(within, r, big)
    nn = np.broadcast_to(n, tot.shape)
    first = np.lexsort((nn, rr, tot), axis=-1)[:, 0]
    best = np.where(within.any(axis=1), first, -1)
    limit = (MAX_RAMPS * int(frames.max())) if max_frames is None else max_frames
    found = best >= 0
    rows = np.nonzero(found)[0]
    kk = best[rows]
    over = np.zeros(ntarget, dtype=bool)
    over[rows] = tot[rows, kk] > limit
    # a target with signal whose best readout is off-limits (or needs more than MAX_RAMPS)
    out["limited"] = (best_snr1 > 0) & (over | ~found)
    keep = rows[~over[rows]]
    kk = best[keep]
    out["n"][keep], out["m"][keep], out["d"][keep] = n[kk], m[kk], d[kk]
    out["nramps"][keep], out["nframes"][keep] = r[keep, kk], tot[keep, kk]
    out["snr"][keep] = clean[keep, kk] * np.sqrt(r[keep, kk].astype(float))
    return out


def exact_choice_loop(snr1, n, m, d, target, max_extra_ramps=None):
    """The former loop over ramps r (cost ∝ r; kept to test :func:`exact_choice` against)."""
    snr1 = np.atleast_2d(np.asarray(snr1, dtype=float))
    target = np.broadcast_to(np.asarray(target, dtype=float), snr1.shape[:1])
    ntarget = snr1.shape[0]
    frames = n * (m + d) - d
    clean = np.where(np.isfinite(snr1), snr1, -np.inf)
    best_snr1 = clean.max(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        rmin = np.ceil((target / best_snr1) ** 2 * (1 - 1e-12))
    rmin = np.where(best_snr1 > 0, np.maximum(rmin, 1), np.inf)
    rmax_extra = 10 if max_extra_ramps is None else max_extra_ramps
    out = {k: np.zeros(ntarget, dtype=int) for k in ("n", "m", "d", "nramps", "nframes")}
    out["snr"] = np.full(ntarget, np.nan)
    best_key = np.full(ntarget, np.iinfo(np.int64).max, dtype=np.int64)
    finite_r = np.isfinite(rmin)
    if not finite_r.any():
        return out
    r_lo = int(rmin[finite_r].min())
    r_hi = int(np.max(2 * rmin[finite_r] + rmax_extra))
    blocks = [np.nonzero((m == mm) & (d == dd))[0] for mm, dd in dict.fromkeys(zip(m, d))]
    for r in range(r_lo, r_hi + 1):
        need = target / math.sqrt(r)
        active = finite_r & (r >= rmin) & (r <= 2 * rmin + rmax_extra)
        if not active.any():
            continue
        for blk in blocks:
            cm = np.maximum.accumulate(clean[:, blk], axis=1)
            idx = np.sum(cm < need[:, None], axis=1)
            ok = active & (idx < blk.size)
            kk = blk[np.minimum(idx, blk.size - 1)]
            tot = r * frames[kk]
            key = (tot.astype(np.int64) * 100000 + r) * 1000 + n[kk]
            better = ok & (key < best_key)
            if better.any():
                best_key[better] = key[better]
                out["n"][better], out["m"][better], out["d"][better] = n[kk][better], m[kk][better], d[kk][better]
                out["nramps"][better], out["nframes"][better] = r, tot[better]
                out["snr"][better] = clean[better, kk[better]] * math.sqrt(r)
    return out


def max_frames_for(tframe, max_exposure=None):
    """Largest total number of frames of an exposure of at most ``max_exposure`` s
    (default :data:`MAX_TOTAL_EXPOSURE`) with frames of ``tframe`` s."""
    max_exposure = MAX_TOTAL_EXPOSURE if max_exposure is None else max_exposure
    return math.floor(max_exposure / tframe)


def _no_signal(sim, snr, lbda_range, mask, snr1):
    """The message for a band no readout reaches: the best single-ramp SNR found and, for a point
    source, its F_λ in the band."""
    lo, hi = (float(v) for v in lbda_range)
    finite = np.asarray(snr1)[np.isfinite(snr1)]
    best = f"{float(finite.max()):g}" if finite.size else "NaN"
    ps = getattr(sim.scene, "pointsource", None)
    flux, why = "", "no signal there"
    if ps is not None:
        f = ps.flambda(sim.lbda[mask])
        f = f[np.isfinite(f)]
        flux = f"; the point source's F_λ there is at most {float(f.max()):g} erg/s/cm²/Å" if f.size else \
            "; the point-source spectrum has no sample there"
        if f.size and f.max() > 0 and finite.size and finite.max() == 0:   # a signal, but every cell saturated
            why = ("the band saturates the detector even in the shortest readout (the source is too bright, or its "
                   "F_λ is not in erg/s/cm²/Å)")
    return (f"target SNR {snr:g} cannot be reached in the band {lo:g}–{hi:g} Å: {why} (best SNR per "
            f"bin of one ramp over the readouts tried: {best}{flux})")


def limit_error(snr, lbda_range, tframe, what="exceeds", exposure=None):
    """ETCError for a target beyond :data:`MAX_TOTAL_EXPOSURE` / :data:`MAX_RAMPS`."""
    lo, hi = (float(v) for v in lbda_range)
    got = f" (the search ends at {exposure:.3g} s)" if exposure is not None else ""
    return ETCError(f"target SNR {snr:g} in the band {lo:g}–{hi:g} Å {what} the exposure limit: "
                    f"it needs more than MAX_TOTAL_EXPOSURE = {MAX_TOTAL_EXPOSURE:.4g} s (1 year; "
                    f"{max_frames_for(tframe)} frames of {tframe} s) or more than MAX_RAMPS = "
                    f"{MAX_RAMPS} ramps{got}")


def check_reference_result(snr, lbda_range, target, reached, exposure_time, tframe, tol=0.5,
                           nmd=None, max_group=None):
    """Refuse the end of a reference walk beyond :data:`MAX_TOTAL_EXPOSURE`, or below the
    target by more than its tolerance ``tol`` plus :data:`REFERENCE_SHORTFALL` × target
    (the slicersim 1.0 walk stops up to ~5 % short on the public reference cases, which
    must keep reproducing).  A walk ending at n > ``max_group`` raises too."""
    if nmd is not None and max_group and nmd[0] > max_group:
        lo, hi = (float(v) for v in lbda_range)
        raise ETCError(f"target SNR {snr:g} in the band {lo:g}–{hi:g} Å: the reference walk ends at "
                       f"readout {tuple(int(v) for v in nmd)}, beyond max_group = {max_group} "
                       "(use search='exact')")
    if not np.isfinite(reached) or reached < target * (1 - REFERENCE_SHORTFALL) - tol:
        lo, hi = (float(v) for v in lbda_range)
        if exposure_time > MAX_TOTAL_EXPOSURE or not np.isfinite(reached):
            raise limit_error(snr, lbda_range, tframe, "cannot be reached within", exposure_time)
        raise ETCError(f"target SNR {snr:g} in the band {lo:g}–{hi:g} Å: the reference walk ends "
                       f"at SNR {reached:.6g} per bin, below the target {target:.6g} by more than its "
                       f"tolerance {tol} (after {exposure_time:.3g} s; limit MAX_TOTAL_EXPOSURE = "
                       f"{MAX_TOTAL_EXPOSURE:.4g} s)")
    if exposure_time > MAX_TOTAL_EXPOSURE:
        raise limit_error(snr, lbda_range, tframe, "exceeds", exposure_time)


# --------------------------------------------------------------------------- #
#  single-target driver                                                        #
# --------------------------------------------------------------------------- #
def solve_readout(sim, snr, lbda_range, per_resolution=True, search="exact", backend="auto",
                  allow_partial=False, frame=None):
    """Solve the ETC for a :class:`~slicersim.simulation.Simulation`.

    ``lbda_range`` [Å] is read in ``frame``: "rest", "obs" or None (default: "rest" when the
    simulation knows a redshift, else "obs"; :meth:`Simulation.band_range
    <slicersim.simulation.Simulation.band_range>`).  ``allow_partial``: band coverage rule of
    :meth:`Simulation.band_mask <slicersim.simulation.Simulation.band_mask>` (:mod:`slicersim.snr.bands`).

    Returns a dict: nmd, nramps, snr (band SNR per bin reached), snr_target (per bin),
    exposure_time (total, s), trace (reference search only), lbda_range_obs (the band [Å]
    in the observer frame).
    """
    snr = check_snr_target(snr)
    search = check_search(search)
    lbda_range = sim.band_range(lbda_range, frame)          # observer frame from here on
    dr = sim.spectrograph.dispersion_resolution
    target = snr / math.sqrt(dr) if per_resolution else snr
    det = sim.detector
    mask = sim.band_mask(lbda_range, allow_partial=allow_partial)
    if search == "reference":
        memo = {}

        def snr_of(n, m, d, r):
            key = (n, m, d)
            if key not in memo:
                if det.max_group and n > det.max_group:   # the 1.0 walk on n has no upper bound
                    check_reference_result(snr, lbda_range, target, np.inf, 0.0, det.tframe,
                                           nmd=key, max_group=det.max_group)
                memo[key] = sim.get_band_snr(lbda_range, nmd=key, nramps=1, allow_partial=allow_partial,
                                             frame="obs")
            return memo[key] * math.sqrt(r)
        nmd, nramps, reached, trace = reference_walk(snr_of, target, det.max_group or 64, det.nmd[2])
        check_reference_result(snr, lbda_range, target, reached,
                               nramps * readout_times(nmd, det.tframe)["exposure_time_per_ramp"], det.tframe)
    else:
        n, m, d = candidate_readouts(det.min_group, det.max_group or 64, det.nmd[2])
        band = sim_band_indices(mask)[None, :]
        snr1 = band_snr_table_for_models(sim, [sim.extraction_model], band, (n, m, d), backend=backend)
        choice = exact_choice(snr1, n, m, d, np.array([target]), max_frames=max_frames_for(det.tframe))
        if choice["limited"][0]:
            raise limit_error(snr, lbda_range, det.tframe)
        if choice["n"][0] == 0:
            raise ETCError(_no_signal(sim, snr, lbda_range, mask, snr1))
        nmd = (int(choice["n"][0]), int(choice["m"][0]), int(choice["d"][0]))
        nramps, reached, trace = int(choice["nramps"][0]), float(choice["snr"][0]), None
    exptime = nramps * readout_times(nmd, det.tframe)["exposure_time_per_ramp"]
    return {"nmd": nmd, "nramps": nramps, "snr": reached, "snr_target": target,
            "snr_per_resolution": reached * math.sqrt(dr), "exposure_time": exptime, "trace": trace,
            "lbda_range_obs": lbda_range}
