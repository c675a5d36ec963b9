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
from dataclasses import dataclass, replace

import numpy as np

from slicersim.errors import ETCError, ParameterError, SpectrumError
from slicersim.validation import MAX_REDSHIFT, array as validation_array, checked_fields, choice, flag, number, \
    redshift as check_redshift, short_repr, shown

__all__ = ["SurveyPlan", "SurveyOptions", "plan_survey", "plan_survey_with", "plot_time_and_volume", "check_client_memory", "survey_totals", "YEAR_S", "PLAN_COLUMNS"]

YEAR_S = 365.25 * 86400.0
BYTES_PER_READ = 2
#: columns of a plan table, in order
PLAN_COLUMNS = ("target_id", "redshift", "field", "n", "m", "d", "nramps", "exposure_time", "snr",
                "data_volume", "data_volume_compressed", "status", "error")


@dataclass
class SurveyPlan:
    """Per-target table and totals of a survey plan (made by :func:`plan_survey`).

    Parameters
    ----------
    table : astropy.table.Table
        One row per target, columns ``PLAN_COLUMNS``: target_id, redshift, field, n, m, d,
        nramps, exposure_time [s], snr, data_volume [bytes], data_volume_compressed [bytes],
        status, error.
    totals : dict
        The totals, in SI units and bytes (see :meth:`summary`).
    """

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


#: values of ``frame`` (None: "rest", a survey's targets having redshifts)
FRAMES = ("rest", "obs")
#: the fields a survey can use
FIELDS = ("narrow", "wide")


@checked_fields
@dataclass(frozen=True)
class SurveyOptions:
    """How a survey is observed and planned (:func:`plan_survey`).

    Parameters
    ----------
    snr : float, optional
        SNR per resolution element (``per_resolution``, else per bin) in ``lbda_range``.
    lbda_range : tuple of float, optional
        (min, max) of the band [Å] in ``frame``.
    frame : {"rest", "obs"} or None, optional
        "rest", "obs" or None = "rest" (a survey's targets always have redshifts).
    z_switch : float, optional
        ``fields[0]`` below it, ``fields[1]`` at and above it (``inf``: one field).
    fields : tuple of str, optional
        The two fields.
    config, search, conventions : optional
        Of the batch ETC (:func:`slicersim.etc.solve_many`).
    overhead : float, optional
        Overhead [s per target], for the totals (module docstring).
    efficiency : float, optional
        Observing efficiency, in (0, 1], for the totals.
    compression_ratio : float, optional
        ≥ 1, for the totals.
    per_resolution : bool, optional
        SNR per resolution element (else per bin).
    progress : bool or None, optional
        The batch ETC's bar (None: when stderr is a terminal).
    detector_shape : tuple of int, optional
        (ny, nx) of the volume (default: the field's).
    precision : {"auto", "double", "single"}, optional
        Of the batch ETC's band-variance kernel.
    allow_partial : bool, optional
        A band partly outside the grid or the spectrum is answered on its covered part
        (default); False: such a target fails with the coverage error (as the single-target
        ETC).
    """
    snr: float = 20.0
    lbda_range: tuple = (4000.0, 6800.0)
    frame: str | None = None
    z_switch: float = 0.8
    fields: tuple = ("narrow", "wide")
    config: object = "cbe"
    search: str = "exact"
    conventions: str = "physical"
    overhead: float = 0.0
    efficiency: float = 1.0
    compression_ratio: float = 1.0
    per_resolution: bool = True
    progress: bool | None = None
    detector_shape: tuple | None = None
    precision: object = "auto"
    allow_partial: bool = True

    def checked(self):
        """A copy with every value checked and converted (ParameterError naming the keyword); the
        precision's names first, before any work."""
        from slicersim.backends.precision import resolve_precision
        precision = resolve_precision(self.precision, "auto", "batch_etc")[1]
        lo, hi = _wavelength_range(self.lbda_range)
        z_switch = self.z_switch if _is_inf(self.z_switch) else check_redshift("z_switch", self.z_switch,
                                                                                allow_zero=True)
        if isinstance(self.fields, (str, bytes)) or np.size(self.fields) != 2:
            raise ParameterError(f"fields must be two field names (below, at and above z_switch), got "
                                 f"{short_repr(self.fields)}")
        fields = tuple(choice(f"fields[{i}]", f, FIELDS) for i, f in enumerate(self.fields))
        return replace(self, fields=fields, snr=number("snr", self.snr, low=0, low_open=True), lbda_range=(lo, hi),
                       frame=choice("frame", self.frame, FRAMES + (None,)) or "rest", z_switch=float(z_switch),
                       overhead=number("overhead", self.overhead, low=0, unit="s"),
                       efficiency=number("efficiency", self.efficiency, low=0, low_open=True, high=1),
                       compression_ratio=number("compression_ratio", self.compression_ratio, low=1),
                       precision=precision, allow_partial=flag("allow_partial", self.allow_partial))


def _is_inf(value):
    """True for +inf (one field for every redshift)."""
    return isinstance(value, (int, float, np.floating)) and not isinstance(value, bool) and value == np.inf


def _wavelength_range(lbda_range):
    """(lo, hi) [Å] with 0 < lo < hi."""
    name = shown("lbda_range")
    if isinstance(lbda_range, (str, bytes)) or np.size(lbda_range) != 2:
        raise ParameterError(f"{name} must be (lo, hi) in Å with 0 < lo < hi, got {short_repr(lbda_range)}")
    lo, hi = (number(f"{name}[{i}]", v, low=0, low_open=True, unit="Angstrom") for i, v in enumerate(lbda_range))
    if not lo < hi:
        raise ParameterError(f"{name} must be (lo, hi) in Å with 0 < lo < hi, got {short_repr(lbda_range)}")
    return lo, hi


def _check_population(redshift, lbda, fluxes, target_ids):
    """(z (N,), fluxes (N, k) float64, ids (N,)): redshifts finite and ≥ 0, one spectrum per target
    on ``lbda``, target ids unique (default 0 … N − 1)."""
    z = validation_array("redshift", redshift, ndim=1, low=0, high=MAX_REDSHIFT)
    if z.size == 0:
        raise ParameterError("redshift: the population is empty: nothing to plan")
    if np.shape(fluxes) != (z.size, np.size(lbda)):
        raise ParameterError(f"fluxes must have shape ({z.size}, {np.size(lbda)}), got {np.shape(fluxes)}")
    ids = np.arange(z.size) if target_ids is None else np.asarray(target_ids)
    if ids.shape != z.shape:
        raise ParameterError(f"target_ids must have one id per redshift ({z.size}), got shape {ids.shape}")
    values, counts = np.unique(ids, return_counts=True)
    if np.any(counts > 1):
        dups = values[counts > 1]
        listed = ", ".join(str(v) for v in dups[:10]) + (", …" if dups.size > 10 else "")
        raise ParameterError(f"target_ids must be unique: {dups.size} id(s) repeated ({listed})")
    return z, np.asarray(fluxes, dtype=float), ids


def _solve_fields(lbda, fluxes, z, ids, opts):
    """Batch ETC per field: (out: readout, exposure time and SNR per target, errors: {index:
    message} of the targets it cannot serve, field per target, detector shape per field)."""
    from slicersim.assembly import build_simulation
    ntarget = z.size
    field = np.where(z < opts.z_switch, opts.fields[0], opts.fields[1])
    out = {k: np.zeros(ntarget, dtype=np.int64) for k in ("n", "m", "d", "nramps")}
    out.update(exposure_time=np.zeros(ntarget), snr=np.zeros(ntarget))
    errors, shapes = {}, {}
    etc = dict(snr=opts.snr, lbda_ranges=opts.lbda_range, frame=opts.frame, config=opts.config, search=opts.search,
               conventions=opts.conventions, per_resolution=opts.per_resolution, progress=opts.progress,
               precision=opts.precision, allow_partial=opts.allow_partial)
    for f in dict.fromkeys(field):
        sel = np.nonzero(field == f)[0]
        # chunks of neighbouring redshifts share their bands: the ETC's per-chunk LSF and
        # transfers then cover ~1 band instead of the union of all (same numbers per target)
        sel = sel[np.argsort(z[sel], kind="stable")]
        shapes[f] = tuple(build_simulation(opts.config, f, pointsource=None,
                                           conventions=opts.conventions).detector.shape)
        _solve(lbda, fluxes, sel, errors, out, {"z": z, "ids": ids, "etc": {**etc, "field": f}})
    return out, errors, field, shapes


def _plan_table(ids, z, field, out, errors, volume, opts):
    """The plan's per-target table (:data:`PLAN_COLUMNS`); ``volume`` raw bytes per target."""
    from astropy.table import Table
    failed = np.zeros(z.size, dtype=bool)
    failed[list(errors)] = True
    table = Table()
    table["target_id"], table["redshift"], table["field"] = ids, z, field
    for key in ("n", "m", "d", "nramps"):
        table[key] = out[key]
    table["exposure_time"] = out["exposure_time"]
    table["exposure_time"].unit = "s"
    table["snr"] = out["snr"]
    table["snr"].description = "band SNR per resolution element" if opts.per_resolution else "band SNR per bin"
    table["data_volume"] = volume.astype(np.int64)
    table["data_volume"].unit = "byte"
    table["data_volume_compressed"] = np.round(volume / opts.compression_ratio).astype(np.int64)
    table["data_volume_compressed"].unit = "byte"
    table["status"] = np.where(failed, "failed", "planned")
    table["error"] = [errors.get(i, "") for i in range(z.size)]
    return table


def plan_survey_with(redshift, lbda, fluxes, options, target_ids=None):
    """:func:`plan_survey` with its options as one :class:`SurveyOptions`; returns a :class:`SurveyPlan`."""
    opts = options.checked()
    z, fluxes, ids = _check_population(redshift, lbda, fluxes, target_ids)
    out, errors, field, shapes = _solve_fields(lbda, fluxes, z, ids, opts)
    shape = opts.detector_shape or next(iter(shapes.values()))
    volume = out["nramps"] * out["n"] * int(shape[0]) * int(shape[1]) * BYTES_PER_READ       # bytes
    table = _plan_table(ids, z, field, out, errors, volume, opts)
    totals = {"targets": z.size, "overhead": opts.overhead, "efficiency": opts.efficiency,
              "compression_ratio": opts.compression_ratio, "snr": opts.snr,
              "lbda_range": list(opts.lbda_range), "frame": opts.frame, "z_switch": opts.z_switch,
              "config": str(opts.config), "search": opts.search, "conventions": opts.conventions,
              "precision": opts.precision}
    totals.update(survey_totals(table, opts.overhead, opts.efficiency, opts.compression_ratio))
    table.meta["totals"] = totals
    return SurveyPlan(table, totals)


def plan_survey(redshift, lbda, fluxes, snr=20.0, lbda_range=(4000.0, 6800.0), frame=None, z_switch=0.8, *,
                target_ids=None, options=None, **keywords):
    """Plan a survey of targets: the batch ETC of each target and the survey totals.

    Parameters
    ----------
    redshift : array_like of shape (N,)
        Redshift of each target.
    lbda : array_like of shape (k,)
        Wavelengths of the spectra [Å].
    fluxes : array_like of shape (N, k)
        F_λ of each target [erg/s/cm²/Å].
    snr : float, optional
        SNR per resolution element (``per_resolution``) in ``lbda_range``.
    lbda_range : tuple of float, optional
        (min, max) of the band [Å] in ``frame``.
    frame : {"rest", "obs"} or None, optional
        Frame of ``lbda_range`` (None = "rest").
    z_switch : float, optional
        ``fields[0]`` below it, ``fields[1]`` at and above it (``inf``: one field).
    target_ids : array_like of shape (N,), optional
        Unique target ids (default 0 … N − 1).
    options : SurveyOptions, optional
        A whole ``SurveyOptions`` (then no other option keyword).
    **keywords
        The other fields of ``SurveyOptions``: fields, config, search, conventions,
        overhead [s per target], efficiency (0, 1], compression_ratio ≥ 1, per_resolution,
        progress, detector_shape, precision.

    Returns
    -------
    SurveyPlan
        The per-target table and the totals.
    """
    if options is None:
        unknown = sorted(set(keywords) - set(SurveyOptions.__dataclass_fields__))
        if unknown:
            raise ParameterError(f"plan_survey: unknown keyword(s) {', '.join(map(repr, unknown))}; valid: "
                                 f"{', '.join(SurveyOptions.__dataclass_fields__)}")
        options = SurveyOptions(snr=snr, lbda_range=lbda_range, frame=frame, z_switch=z_switch, **keywords)
    elif keywords or (snr, tuple(np.ravel(lbda_range)), frame, z_switch) != (20.0, (4000.0, 6800.0), None, 0.8):
        raise ParameterError("plan_survey: give options= or option keywords, not both")
    return plan_survey_with(redshift, lbda, fluxes, options, target_ids)


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
    rightwards, one curve per plan.

    Parameters
    ----------
    plans : dict
        {label: SurveyPlan}, one curve (median per redshift bin) each.
    path : str or path-like
        Where the figure is saved.
    zbins : array_like, optional
        Edges of the redshift bins of the medians (default: 15 bins over the planned range).
    paper : dict, optional
        {label: (z, hours, GB)} points to overlay.

    Returns
    -------
    str or path-like
        ``path``, the figure written.
    """
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
