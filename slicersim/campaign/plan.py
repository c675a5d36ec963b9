"""Survey plans: the batch ETC of a whole population, its on-sky time and raw data volume.

For each field the population's targets go through one :func:`slicersim.etc.solve_many`
call (narrow field below ``z_switch``, wide at and above it, as in the paper).  Per target:
the readout (n, m, d, nramps), the exposure time, the SNR reached (per resolution element
in the band, as the ETC defines it) and the raw group-level data volume

    data_volume = nramps · n · N_y · N_x · 2 bytes     (16-bit H4RG groups, all reads kept)

uncompressed and divided by ``compression_ratio``.  Totals::

    on_sky_time   = Σ exposure_time + N_planned · overhead          [s]
    duration      = on_sky_time / efficiency                        [s, and years of 365.25 d]

A target the ETC cannot serve (no flux in its band, a readout beyond the limits) is
reported with ``status = "failed"`` and its error; the others are planned.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from slicersim.errors import ETCError, ParameterError, SpectrumError

__all__ = ["SurveyPlan", "plan_survey", "plot_time_and_volume", "check_client_memory", "survey_totals", "YEAR_S", "PLAN_COLUMNS"]

YEAR_S = 365.25 * 86400.0
BYTES_PER_READ = 2
#: columns of a plan table, in order
PLAN_COLUMNS = ("target_id", "redshift", "field", "n", "m", "d", "nramps", "exposure_time", "snr",
                "data_volume", "data_volume_compressed", "status", "error")


@dataclass
class SurveyPlan:
    """Per-target table (:data:`PLAN_COLUMNS`) and totals (dict, SI units and bytes)."""

    table: object
    totals: dict

    def summary(self):
        """Totals as text with units."""
        t = self.totals
        per_field = ", ".join(f"{k} {v}" for k, v in t["targets_per_field"].items())
        lines = [f"targets            : {t['targets']} ({per_field}); failed {t['failed']}",
                 f"exposure time      : {t['exposure_time'] / 3600:,.1f} h ({t['exposure_time'] / YEAR_S:.3f} yr)",
                 f"overheads          : {t['overhead_time'] / 3600:,.1f} h ({t['overhead']:g} s per target)",
                 f"survey duration    : {t['duration'] / YEAR_S:.3f} yr at {100 * t['efficiency']:g} % "
                 "observing efficiency",
                 f"raw data volume    : {t['data_volume'] / 1e12:,.3f} TB uncompressed, "
                 f"{t['data_volume_compressed'] / 1e12:,.3f} TB at compression ratio {t['compression_ratio']:g}",
                 f"per target         : median {t['median_exposure_time'] / 3600:.2f} h, "
                 f"{t['median_data_volume'] / 1e9:.2f} GB"]
        if "precision" in t:
            lines.append(f"batch ETC precision: {t['precision']}")
        return "\n".join(lines)


def _check(snr, lbda_range, z_switch, overhead, efficiency, compression_ratio, redshift, fluxes, lbda):
    def finite(v, name, lo=None, lo_open=False, hi=None):
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not np.isfinite(v):
            raise ParameterError(f"{name} must be a finite number, got {v!r}")
        if lo is not None and (v < lo or (lo_open and v == lo)) or hi is not None and v > hi:
            raise ParameterError(f"{name} must be {'>' if lo_open else '≥'} {lo}"
                                 + (f" and ≤ {hi}" if hi is not None else "") + f", got {v!r}")
    finite(snr, "snr", 0, True)
    rng_ = np.asarray(lbda_range, dtype=float) if np.size(lbda_range) == 2 else None
    if rng_ is None or not np.all(np.isfinite(rng_)) or not 0 < rng_[0] < rng_[1]:
        raise ParameterError(f"lbda_range must be (lo, hi) in Å with 0 < lo < hi, got {lbda_range!r}")
    finite(overhead, "overhead", 0)
    finite(efficiency, "efficiency", 0, True, 1)
    finite(compression_ratio, "compression_ratio", 1)
    if not (np.isinf(z_switch) and z_switch > 0):
        finite(z_switch, "z_switch", 0)
    z = np.asarray(redshift, dtype=float)
    if z.ndim != 1 or z.size == 0:
        raise ParameterError("the population is empty: nothing to plan")
    if np.any(~np.isfinite(z)) or np.any(z < 0):
        raise ParameterError("redshifts must be finite and not negative")
    if np.shape(fluxes) != (z.size, np.size(lbda)):
        raise ParameterError(f"fluxes must have shape ({z.size}, {np.size(lbda)}), got {np.shape(fluxes)}")
    return z


def _target_error(exc, target_id):
    """The ETC's error for a batch of one, naming the target by its id (not its batch index)."""
    import re
    msg = " ".join(str(exc).split())
    msg = re.sub(r"^target(\(s\))? \[?0\]?:? ", "", msg)
    return f"{type(exc).__name__}: target {target_id}: {msg}"


def check_client_memory(ntarget, nlbda, copies=4):
    """Refuse (ParameterError) a population whose spectra would not fit in this machine's
    available memory (``copies`` float64 arrays of (N, nλ) during planning)."""
    import psutil
    need = int(ntarget) * int(nlbda) * 8 * copies
    avail = psutil.virtual_memory().available
    if need > 0.8 * avail:
        raise ParameterError(f"{ntarget} targets need ~{need / 2**30:.1f} GiB to plan on this machine "
                             f"({avail / 2**30:.1f} GiB available): split the population")


def _solve(lbda, fluxes, idx, errors, out, kwargs):
    """Solve targets ``idx``; a failing batch is bisected so each failing target gets its error."""
    from slicersim.etc.solve import solve_many
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")          # partial bands: reported once by the caller
            tab = solve_many(lbda, fluxes[idx], redshifts=kwargs["z"][idx], **kwargs["etc"])
    except (ETCError, SpectrumError) as exc:
        if idx.size == 1:
            errors[int(idx[0])] = _target_error(exc, kwargs["ids"][int(idx[0])])
            return
        half = idx.size // 2
        _solve(lbda, fluxes, idx[:half], errors, out, kwargs)
        _solve(lbda, fluxes, idx[half:], errors, out, kwargs)
        return
    for key in ("n", "m", "d", "nramps", "exposure_time", "snr"):
        out[key][idx] = np.asarray(tab[key])


def plan_survey(redshift, lbda, fluxes, snr=20.0, lbda_range=(4000.0, 6800.0), frame="rest", z_switch=0.8,
                fields=("narrow", "wide"), config="cbe", search="exact", conventions="physical", overhead=0.0,
                efficiency=1.0, compression_ratio=1.0, target_ids=None, per_resolution=True, progress=False,
                detector_shape=None, precision="auto"):
    """Plan a survey of targets with spectra ``fluxes`` (N, k) [erg/s/cm²/Å] on ``lbda`` [Å].

    snr : SNR per resolution element (``per_resolution``) in ``lbda_range`` [Å] of ``frame``
    z_switch : ``fields[0]`` below it, ``fields[1]`` at and above it (``inf``: one field)
    overhead [s per target], efficiency (0, 1], compression_ratio ≥ 1 : see the module docstring
    precision : of the batch ETC's band-variance kernel (:func:`slicersim.etc.solve.solve_many`)
    Returns a :class:`SurveyPlan`.
    """
    from astropy.table import Table

    from slicersim.assembly import build_simulation
    from slicersim.backends.precision import resolve_precision
    precision = resolve_precision(precision, "auto", "batch_etc")[1]        # bad names: before any work
    z = _check(snr, lbda_range, z_switch, overhead, efficiency, compression_ratio, redshift, fluxes, lbda)
    fluxes = np.asarray(fluxes, dtype=float)
    ntarget = z.size
    ids = np.arange(ntarget) if target_ids is None else np.asarray(target_ids)
    field = np.where(z < z_switch, fields[0], fields[1])
    out = {k: np.zeros(ntarget, dtype=np.int64) for k in ("n", "m", "d", "nramps")}
    out.update(exposure_time=np.zeros(ntarget), snr=np.zeros(ntarget))
    errors = {}
    etc = dict(snr=snr, lbda_ranges=lbda_range, frame=frame, config=config, search=search,
               conventions=conventions, per_resolution=per_resolution, progress=progress, precision=precision)
    shapes = {}
    for f in dict.fromkeys(field):
        sel = np.nonzero(field == f)[0]
        # chunks of neighbouring redshifts share their bands: the ETC's per-chunk LSF and
        # transfers then cover ~1 band instead of the union of all (same numbers per target)
        sel = sel[np.argsort(z[sel], kind="stable")]
        shapes[f] = tuple(build_simulation(config, f, pointsource=None, conventions=conventions).detector.shape)
        _solve(lbda, fluxes, sel, errors, out, {"z": z, "ids": ids, "etc": {**etc, "field": f}})
    shape = detector_shape or next(iter(shapes.values()))
    failed = np.zeros(ntarget, dtype=bool)
    failed[list(errors)] = True
    volume = out["nramps"] * out["n"] * int(shape[0]) * int(shape[1]) * BYTES_PER_READ       # bytes
    table = Table()
    table["target_id"], table["redshift"], table["field"] = ids, z, field
    for key in ("n", "m", "d", "nramps"):
        table[key] = out[key]
    table["exposure_time"] = out["exposure_time"]
    table["exposure_time"].unit = "s"
    table["snr"] = out["snr"]
    table["snr"].description = "band SNR per resolution element" if per_resolution else "band SNR per bin"
    table["data_volume"] = volume.astype(np.int64)
    table["data_volume"].unit = "byte"
    table["data_volume_compressed"] = np.round(volume / compression_ratio).astype(np.int64)
    table["data_volume_compressed"].unit = "byte"
    table["status"] = np.where(failed, "failed", "planned")
    table["error"] = [errors.get(i, "") for i in range(ntarget)]
    totals = {"targets": ntarget, "overhead": float(overhead), "efficiency": float(efficiency),
              "compression_ratio": float(compression_ratio), "snr": float(snr),
              "lbda_range": [float(v) for v in lbda_range], "frame": frame, "z_switch": float(z_switch),
              "config": str(config), "search": search, "conventions": conventions, "precision": precision}
    totals.update(survey_totals(table, overhead, efficiency, compression_ratio))
    table.meta["totals"] = totals
    return SurveyPlan(table, totals)


def survey_totals(table, overhead, efficiency, compression_ratio):
    """Totals of a plan table (module docstring): planned / failed counts, per field,
    exposure, overheads, duration [s, yr], raw volume [bytes], medians."""
    ok = np.asarray(table["status"]) != "failed"
    field = np.asarray(table["field"])
    exposure_s = np.asarray(table["exposure_time"], dtype=float)[ok]
    volume = np.asarray(table["data_volume"], dtype=np.int64)[ok]
    nplanned = int(ok.sum())
    exposure = float(exposure_s.sum())
    overhead_time = nplanned * float(overhead)
    duration = (exposure + overhead_time) / float(efficiency)
    return {"planned": nplanned, "failed": int((~ok).sum()),
            "targets_per_field": {f: int(np.count_nonzero(field[ok] == f)) for f in dict.fromkeys(field)},
            "exposure_time": exposure, "overhead_time": overhead_time, "duration": duration,
            "duration_years": duration / YEAR_S, "data_volume": int(volume.sum()),
            "data_volume_compressed": int(np.round(volume.sum() / compression_ratio)),
            "median_exposure_time": float(np.median(exposure_s)) if nplanned else 0.0,
            "median_data_volume": float(np.median(volume)) if nplanned else 0.0}


def plot_time_and_volume(plans, path, zbins=None, paper=None):
    """The paper's figure: redshift upwards, raw data volume [GB] leftwards, exposure time [h]
    rightwards, one curve per plan (``plans``: {label: SurveyPlan}); ``paper``: optional
    {label: (z, hours, GB)} points to overlay."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (axv, axt) = plt.subplots(1, 2, sharey=True, figsize=(8, 5), gridspec_kw={"wspace": 0.03})
    for k, (label, plan) in enumerate(plans.items()):
        tab = plan.table
        ok = np.asarray(tab["status"]) == "planned"
        z = np.asarray(tab["redshift"])[ok]
        hours = np.asarray(tab["exposure_time"])[ok] / 3600
        gb = np.asarray(tab["data_volume"])[ok] / 1e9
        edges = np.linspace(z.min(), z.max(), 16) if zbins is None else np.asarray(zbins)
        mid = 0.5 * (edges[1:] + edges[:-1])
        which = np.clip(np.digitize(z, edges) - 1, 0, mid.size - 1)
        med_h = np.array([np.median(hours[which == i]) if np.any(which == i) else np.nan for i in range(mid.size)])
        med_v = np.array([np.median(gb[which == i]) if np.any(which == i) else np.nan for i in range(mid.size)])
        color = f"C{k}"
        axt.scatter(hours, z, s=2, alpha=0.15, color=color, rasterized=True)
        axv.scatter(gb, z, s=2, alpha=0.15, color=color, rasterized=True)
        axt.plot(med_h, mid, color=color, lw=2, label=f"{label}: {plan.totals['duration_years']:.2f} yr")
        axv.plot(med_v, mid, color=color, lw=2, label=f"{label}: {plan.totals['data_volume'] / 1e12:.1f} TB")
    for label, (pz, ph, pv) in (paper or {}).items():
        if ph is not None:
            axt.plot(ph, pz, "k*", ms=9, label=f"paper {label}")
        if pv is not None:
            axv.plot(pv, pz, "k*", ms=9, label=f"paper {label}")
    axv.invert_xaxis()
    axv.set_xlabel("raw data volume per target [GB]")
    axt.set_xlabel("exposure time per target [h]")
    axv.set_ylabel("redshift")
    zs = [p.totals["z_switch"] for p in plans.values()]
    for ax in (axv, axt):
        if zs and np.isfinite(zs[0]):
            ax.axhline(zs[0], color="0.5", ls=":", lw=1)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="lower right" if ax is axt else "lower left")
    fig.suptitle("Time and raw data volume vs redshift (narrow field below the dotted line, wide above)",
                 fontsize=10)
    fig.savefig(path, dpi=130, bbox_inches="tight")
    plt.close(fig)
    return path
