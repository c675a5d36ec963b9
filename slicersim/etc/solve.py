"""Batch exposure-time calculator: thousands of point sources in one call.

The instrument (PSF, throughput, QE, background, thermal terms) is computed
once; each target only changes the point-source spectrum.  For every target the
single-ramp band SNR of every candidate readout is evaluated at once (OpenCL
kernel ``band_variance.cl`` or its NumPy twin), then the readout is chosen with
:func:`slicersim.snr.search.exact_choice` (or the reference walk).
"""
from __future__ import annotations

import math

import numpy as np

from slicersim.backends.dispatch import DEFAULT_MAX_BYTES
from slicersim.errors import ETCError, SpectrumError
from slicersim.physics.conventions import DEFAULT_CONVENTIONS
from slicersim.snr.bands import check_band_in_grid, warn_partial_spectrum
from slicersim.snr.search import (candidate_readouts, check_reference_result,
                                  check_snr_target, exact_choice, limit_error, max_frames_for,
                                  reference_walk)
from slicersim.snr.snr_table import band_snr_table_for_models, template_psf

__all__ = ["solve_many"]


def _interp_matrix(lbda_in, lbda_out):
    """Indices and weights of the linear interpolation λ_in → λ_out (NaN outside)."""
    idx = np.clip(np.searchsorted(lbda_in, lbda_out) - 1, 0, lbda_in.size - 2)
    w = (lbda_out - lbda_in[idx]) / (lbda_in[idx + 1] - lbda_in[idx])
    outside = (lbda_out < lbda_in[0]) | (lbda_out > lbda_in[-1])
    return idx, w, outside


def _validate_batch(lbda, fluxes, lbda_ranges):
    lbda = np.asarray(lbda, dtype=float)
    fluxes = np.atleast_2d(np.asarray(fluxes, dtype=float))
    if lbda.ndim != 1 or lbda.size < 2:
        raise SpectrumError("lbda must be a 1-D array with at least 2 wavelengths")
    if not np.all(np.isfinite(lbda)) or np.any(np.diff(lbda) <= 0):
        raise SpectrumError("lbda must be finite and strictly increasing")
    if fluxes.ndim != 2 or fluxes.shape[1] != lbda.size or fluxes.shape[0] == 0:
        raise SpectrumError(f"fluxes must have shape (N, {lbda.size}), got {fluxes.shape}")
    bad = ~np.all(np.isfinite(fluxes), axis=1)
    if bad.any():
        raise SpectrumError(f"fluxes of target(s) {np.nonzero(bad)[0][:10].tolist()} contain NaN/inf")
    neg = np.any(fluxes < 0, axis=1)
    if neg.any():
        raise SpectrumError(f"fluxes of target(s) {np.nonzero(neg)[0][:10].tolist()} contain negative values")
    ranges = np.asarray(lbda_ranges, dtype=float)
    if ranges.shape == (2,):
        ranges = np.broadcast_to(ranges, (fluxes.shape[0], 2))
    if ranges.shape != (fluxes.shape[0], 2) or np.any(~(ranges[:, 1] > ranges[:, 0])):
        raise ETCError(f"lbda_ranges must have shape (N, 2) with lo < hi, got {np.shape(lbda_ranges)}")
    return lbda, fluxes, ranges


def solve_many(lbda, fluxes, snr, lbda_ranges, frame="obs", config="cbe", field="narrow",
               search="exact", redshifts=None, per_resolution=True, backend="auto",
               max_bytes=DEFAULT_MAX_BYTES, progress=False, conventions=DEFAULT_CONVENTIONS,
               allow_partial=True, precision="auto"):
    """Solve the ETC for many point sources at once.

    Parameters
    ----------
    lbda : (k,) [Å];  fluxes : (N, k) [erg/s/cm²/Å]
    snr : float or (N,)  target SNR (per resolution element when ``per_resolution``)
    lbda_ranges : (N, 2) or (2,) band [Å] in ``frame``
    frame : "obs" or "rest" (needs ``redshifts``)
    config, field : instrument (see :func:`slicersim.targets.build_simulation`)
    search : "exact" or "reference"
    conventions : "physical" (default) or "slicersim-1.0" (:mod:`slicersim.physics.conventions`)
    allow_partial : bands partly outside the grid (≥ 50 % inside) or partly outside the input
        spectrum are answered on the covered part with one BandCoverageWarning naming the
        targets (default, batch); False raises SpectrumError as the single-target calls do
        (:mod:`slicersim.snr.bands`)
    precision : "auto" (default), "double" or "single" for the band-variance kernel
        (:mod:`slicersim.backends.precision`, product ``"batch_etc"``; "auto" is double on CPUs and
        fast-fp64 GPUs); the single-target ETC is always float64

    Returns
    -------
    astropy Table, one row per target: n, m, d, nramps, exposure_time [s], snr
    (band SNR per resolution element reached), snr_per_bin, data_volume [GB].
    """
    from astropy.table import Table

    from slicersim.assembly import build_simulation
    from slicersim.backends.precision import resolve_precision
    backend, precision = resolve_precision(precision, backend, "batch_etc")     # bad names: before any work
    lbda, fluxes, ranges = _validate_batch(lbda, fluxes, lbda_ranges)
    ntarget = fluxes.shape[0]
    snr = np.broadcast_to(np.asarray(snr, dtype=float), (ntarget,))
    for s in np.unique(snr):
        check_snr_target(s)
    if frame == "rest":
        if redshifts is None:
            raise ETCError("frame='rest' needs the redshifts of the targets")
        z = np.broadcast_to(np.asarray(redshifts, dtype=float), (ntarget,))
        ranges = ranges * (1 + z)[:, None]
    elif frame != "obs":
        raise ETCError(f"frame must be 'obs' or 'rest', got {frame!r}")
    if search not in ("exact", "reference"):
        raise ETCError(f"unknown search {search!r}: 'exact' or 'reference'")

    sim = build_simulation(config, field, pointsource=None, conventions=conventions)
    spec, det = sim.spectrograph, sim.detector
    grid = sim.lbda
    if lbda[0] >= grid[-1] or lbda[-1] <= grid[0]:
        raise SpectrumError(f"input wavelengths {lbda[0]:.0f}–{lbda[-1]:.0f} Å do not overlap the "
                            f"instrument range {grid[0]:.0f}–{grid[-1]:.0f} Å")
    band = np.stack([np.searchsorted(grid, ranges[:, 0], side="left"),
                     np.searchsorted(grid, ranges[:, 1], side="right")], axis=1)
    empty = band[:, 1] <= band[:, 0]
    if empty.any():
        raise ETCError(f"band of target(s) {np.nonzero(empty)[0][:10].tolist()} contains no "
                       f"instrument bin ({grid[0]:.0f}–{grid[-1]:.0f} Å)")
    check_band_in_grid(ranges, spec.lbda_edges, who="batch", allow_partial=allow_partial)
    warn_partial_spectrum(ranges, lbda[0], lbda[-1], who="batch", allow_partial=allow_partial)
    target = snr / math.sqrt(spec.dispersion_resolution) if per_resolution else snr.copy()

    psf = template_psf(sim)
    psf2 = psf**2
    half = int(4.0 * spec.lsf_sigma + 0.5)
    f2p, qe, gain = sim.flambda_to_photon, sim.qe, det.gain
    uniform = sum(spec.apply_lsf(arr) for arr in (sim.background_photons, sim._thermal_photons("telescope"),
                                                  sim._thermal_photons("optics")))
    idx, w, outside = _interp_matrix(lbda, grid)
    cand = candidate_readouts(det.min_group, det.max_group or 64, det.nmd[2])
    per_target_bytes = grid.size * psf.shape[1] * 8 * 3
    step = max(1, int(max_bytes // per_target_bytes))
    rows = {k: np.zeros(ntarget, dtype=int) for k in ("n", "m", "d", "nramps")}
    reached = np.full(ntarget, np.nan)
    chunks = range(0, ntarget, step)
    if progress:
        from tqdm.auto import tqdm
        chunks = tqdm(chunks, total=len(chunks), desc="ETC", unit="chunk")
    for t0 in chunks:
        t1 = min(ntarget, t0 + step)
        # only the bins of this chunk's bands (plus the LSF half-width) are needed
        lo, hi = int(band[t0:t1, 0].min()), int(band[t0:t1, 1].max())
        s0, s1 = max(0, lo - half), min(grid.size, hi + half)
        flux_grid = fluxes[t0:t1, idx[s0:s1]] * (1 - w[s0:s1]) + fluxes[t0:t1, idx[s0:s1] + 1] * w[s0:s1]
        flux_grid[:, outside[s0:s1]] = np.nan                                      # erg/s/cm²/Å
        photons = flux_grid * f2p[s0:s1]                                           # ph/s
        # LSF with reflect ends: at a window edge inside the grid only the discarded
        # margin bins are affected (the margin is the LSF half-width)
        def lsf(a, ax):
            return spec.apply_lsf(a, axis=ax)
        keep = slice(lo - s0, hi - s0)
        point = lsf(photons[:, :, None] * psf[None, s0:s1], 1)[:, keep]            # ph/s/cell
        Q = qe[None, lo:hi, None] * (point + uniform[None, lo:hi, None])           # e-/s/cell
        signal_rate = lsf(photons * qe[s0:s1], 1)[:, keep] * gain                  # ADU/s
        sub_band = band[t0:t1] - lo
        snr1 = band_snr_table_for_models(sim, (Q, signal_rate), sub_band, cand, backend=backend,
                                         psf2=psf2[lo:hi], precision=precision)
        if search == "exact":
            choice = exact_choice(snr1, *cand, target[t0:t1], max_frames=max_frames_for(det.tframe))
            if choice["limited"].any():
                t = t0 + int(np.nonzero(choice["limited"])[0][0])
                err = limit_error(snr[t], ranges[t], det.tframe)
                raise ETCError(f"target {t}: {err}")
            for key in rows:
                rows[key][t0:t1] = choice[key]
            reached[t0:t1] = choice["snr"]
            continue
        # reference walk: look the single-ramp SNR up in the table, evaluate off-table readouts
        lookup = {(int(a), int(b), int(c)): k for k, (a, b, c) in enumerate(zip(*cand))}
        for t in range(t0, t1):
            local = t - t0
            extra = {}

            def snr_of(n, m, d, r, local=local, extra=extra):
                key = (n, m, d)
                if key in lookup:
                    return snr1[local, lookup[key]] * math.sqrt(r)
                if key not in extra:
                    one = (np.array([n]), np.array([m]), np.array([d]))
                    extra[key] = band_snr_table_for_models(
                        sim, (Q[local:local + 1], signal_rate[local:local + 1]), sub_band[local:local + 1],
                        one, backend="numpy", psf2=psf2[lo:hi])[0, 0]
                return extra[key] * math.sqrt(r)
            nmd, r, s, _ = reference_walk(snr_of, target[t], det.max_group or 64, det.nmd[2])
            try:
                check_reference_result(snr[t], ranges[t], target[t], s,
                                       r * (nmd[0] * (nmd[1] + nmd[2]) - nmd[2]) * det.tframe, det.tframe,
                                       nmd=nmd, max_group=det.max_group)
            except ETCError as exc:
                raise ETCError(f"target {t}: {exc}") from None
            rows["n"][t], rows["m"][t], rows["d"][t] = nmd
            rows["nramps"][t], reached[t] = r, s
    failed = rows["n"] == 0
    if failed.any():
        raise ETCError(f"target(s) {np.nonzero(failed)[0][:10].tolist()} cannot reach their SNR "
                       "(no signal in the band)")
    frames = rows["n"] * (rows["m"] + rows["d"]) - rows["d"]
    table = Table(rows)
    table["exposure_time"] = rows["nramps"] * frames * det.tframe
    table["exposure_time"].unit = "s"
    table["snr"] = reached * (math.sqrt(spec.dispersion_resolution) if per_resolution else 1.0)
    table["snr_per_bin"] = reached
    table["data_volume"] = rows["nramps"] * rows["n"] * det.shape[0] * det.shape[1] * 16 / 8e9
    table["data_volume"].unit = "GB"
    table.meta.update(config=str(config), field=field, search=search, frame=frame, conventions=conventions,
                      precision=precision)
    return table
