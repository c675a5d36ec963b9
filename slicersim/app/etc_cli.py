"""The survey jobs of ``slicersim etc`` and ``slicersim ramp`` (used by :mod:`slicersim.app.cli`).

* ``slicersim etc --catalog T.ecsv --snr 20 --out R.ecsv``: the batch ETC
  (:func:`slicersim.etc.solve_many`, through :func:`slicersim.campaign.plan.plan_survey_with`, the
  engine of survey plans and campaigns) over a target table read by the campaigns' catalogue
  reader (:class:`slicersim.campaign.population.CatalogPopulation`); one row per target out.
* ``slicersim ramp --redshift Z`` with the SN's ``--phase``, ``--peak-absmag`` and ``--source``,
  and ``--snr S``: the readout and ramps of the single-target ETC instead of the default readout.

Phases are rest-frame days from B-band maximum, passed through to the library unchanged.
"""
from __future__ import annotations

import os

__all__ = ["add_etc_arguments", "cmd_etc_catalog", "check_etc_flags", "etc_table", "add_ramp_target_arguments",
           "check_ramp_target_flags", "ramp_supernova", "ETC_TABLE_COLUMNS", "DEFAULT_SOURCE"]

#: the SN Ia model of ``--source`` when not given (offline, built into sncosmo)
DEFAULT_SOURCE = "hsiao-subsampled"
#: the output table's ETC columns: (name, unit, description), after the catalogue's own columns
ETC_TABLE_COLUMNS = (
    ("field", None, "field of view"),
    ("n", None, "MACC groups per ramp"),
    ("m", None, "frames per group"),
    ("d", None, "dropped frames between groups"),
    ("nramps", None, "ramps"),
    ("exposure_time", "s", "total exposure time of all ramps"),
    ("snr", None, "band SNR reached"),
    ("data_volume", "GB", "raw group-level data of all ramps, 16 bits per read, uncompressed (1 GB = 1e9 bytes)"),
    ("status", None, "ok, or failed: no readout reaches the SNR (see error)"),
    ("error", None, "why a failed target cannot reach its SNR"),
)
#: units and descriptions of the catalogue's SN Ia columns in the output
PARAMETER_COLUMNS = {"redshift": (None, "redshift"),
                     "phase": ("d", "rest-frame days from B-band maximum"),
                     "peak_absmag": ("mag", "peak absolute magnitude, rest-frame Bessell B (AB)"),
                     "x1": (None, "SALT stretch"), "c": (None, "SALT colour"),
                     "mwebv": ("mag", "Milky-Way E(B-V) (F99, R_V 3.1)"),
                     "hostebv": ("mag", "host E(B-V) (CCM89, R_V 3.1)")}
#: the output formats of ``--out``
OUT_FORMATS = (".ecsv", ".csv")


# ---------------------------------------------------------------------------- etc --catalog
def add_etc_arguments(parser, sources):
    """``--catalog`` (in the mutually exclusive group ``sources``), ``--source``, ``--out`` and
    ``--overwrite`` on the ``etc`` parser."""
    sources.add_argument("--catalog", metavar="TABLE",
                         help="ECSV or CSV (or Parquet) table of SNe Ia, one row per target: redshift (required), "
                              "target_id, phase [rest-frame days from B-band maximum; default 0], peak_absmag "
                              "[default -19.3], x1, c (SALT sources), mwebv, hostebv; other columns are copied. "
                              "Writes one row per target to --out")
    parser.add_argument("--source", metavar="NAME",
                        help=f"sncosmo SN Ia source of --redshift and --catalog (default: {DEFAULT_SOURCE}; "
                             "salt2/salt3 need sncosmo's data)")
    parser.add_argument("--out", metavar="FILE.ecsv",
                        help="with --catalog: per-target table (ECSV or CSV): readout, exposure time, SNR reached, "
                             "data volume, status")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")


def check_etc_flags(args):
    """The flags of ``etc`` that apply to one source only (ParameterError naming them)."""
    from slicersim.errors import ParameterError
    if args.catalog is None:
        given = [flag for flag, value in (("--out", args.out), ("--overwrite", args.overwrite or None))
                 if value is not None]
        if given:
            raise ParameterError(f"{' and '.join(given)} {'apply' if len(given) > 1 else 'applies'} only with "
                                 "--catalog (the single-target ETC prints its answer)")
    elif args.out is None:
        raise ParameterError("--catalog needs --out FILE.ecsv (or .csv): the per-target table")
    if args.spectrum is not None and args.source is not None:
        raise ParameterError("--source applies only with --redshift or --catalog (--spectrum is the spectrum)")


def _check_out(path, overwrite):
    """--out: .ecsv or .csv, not a directory, FIFO or device, not an existing file without --overwrite."""
    from slicersim.errors import ParameterError
    from slicersim.io.atomic import check_output_path
    if os.path.isdir(path) or path.endswith(os.sep):
        check_output_path(path, overwrite, ParameterError, "--out")        # refused: a directory
    if not path.lower().endswith(OUT_FORMATS):
        raise ParameterError(f"--out must end with {' or '.join(OUT_FORMATS)}, got {path}")
    check_output_path(path, overwrite, ParameterError, "--out")


def _read_catalog(path, source):
    """(population, table) of ``--catalog``: the campaigns' reader, SN parameters the table does
    not give at their fixed defaults (phase 0, peak_absmag −19.3, x1 = c = 0 for SALT, no dust)."""
    from slicersim import validation
    from slicersim.campaign.population import CatalogPopulation
    with validation.flag_names({"population.file": "--catalog"}):
        salt = isinstance(source, str) and "salt" in source.lower()
        pop = CatalogPopulation(path, source=source, **({"x1": 0.0, "c": 0.0} if salt else {}))
        table = pop.draw(0)                        # constants only: the seed draws nothing
    return pop, table


def _etc_options(args):
    """The :class:`~slicersim.campaign.plan.SurveyOptions` of ``etc --catalog``: one field for all."""
    from slicersim.campaign.plan import SurveyOptions
    config = (args.config[0] if len(args.config) == 1 else list(args.config)) if args.config else "cbe"
    field = args.field or "narrow"
    return SurveyOptions(snr=args.snr, lbda_range=tuple(args.lbda_range or (4000.0, 6800.0)),
                         frame=args.frame or "rest", z_switch=float("inf"), fields=(field, field), config=config,
                         search=args.search or "exact", conventions=args.conventions, progress=None,
                         allow_partial=bool(args.allow_partial))


def etc_table(catalog, plan, opts, source, path, digest=None):
    """The output table of ``etc --catalog``.

    Parameters
    ----------
    catalog : astropy Table (N rows)
        the targets as drawn by :meth:`CatalogPopulation.draw
        <slicersim.campaign.population.CatalogPopulation.draw>` (every SN parameter filled in)
    plan : :class:`~slicersim.campaign.plan.SurveyPlan`
        its batch ETC, one row per target in the same order
    opts : :class:`~slicersim.campaign.plan.SurveyOptions`
        the checked options it ran with (one field)
    source : str
        the sncosmo model;  ``path``, ``digest``: the catalogue file and its sha256, recorded

    Returns
    -------
    astropy Table (N rows): target_id, redshift, phase [d, rest frame], peak_absmag [mag], the
    catalogue's other columns, then :data:`ETC_TABLE_COLUMNS` (exposure_time [s], data_volume
    [GB]; a failed row has readout 0 and NaN time, SNR and volume); units and descriptions in the
    column metadata, the options and ``phase_frame = "rest"`` in ``meta``.
    """
    import numpy as np

    from slicersim.versioning import __version__
    ptab = plan.table
    first = [c for c in ("target_id", *PARAMETER_COLUMNS) if c in catalog.colnames]
    out = catalog[first + [c for c in catalog.colnames if c not in first]].copy(copy_data=True)
    out.meta = {}
    failed = np.asarray(ptab["status"]) == "failed"
    for name, unit, description in ETC_TABLE_COLUMNS:
        values = np.asarray(ptab[name])
        if name == "data_volume":
            values = values / 1e9
        if name in ("exposure_time", "snr", "data_volume"):
            values = np.where(failed, np.nan, values.astype(float))
        if name == "status":
            values = np.where(failed, "failed", "ok")
        out[name] = values
        out[name].unit, out[name].description = unit, description
    out["snr"].description = ("band SNR reached, per resolution element" if opts.per_resolution else
                              "band SNR reached, per bin")
    for name, (unit, description) in PARAMETER_COLUMNS.items():
        if name in out.colnames:
            if out[name].unit is None and unit is not None:
                out[name].unit = unit
            out[name].description = out[name].description or description
    out.meta.update({"catalog": path, "catalog_sha256": digest, "phase_frame": "rest", "source": source,
                     "snr_goal": opts.snr, "lbda_range": list(opts.lbda_range), "frame": opts.frame,
                     "field": opts.fields[0], "config": str(opts.config), "search": opts.search,
                     "conventions": opts.conventions, "precision": plan.totals.get("precision"),
                     "slicersim": __version__})
    return out


def _write(table, path, overwrite):
    import io

    from slicersim.errors import ParameterError
    from slicersim.io.atomic import atomic_bytes
    buf = io.StringIO()
    table.write(buf, format="ascii.ecsv" if path.lower().endswith(".ecsv") else "ascii.csv")
    atomic_bytes(path, buf.getvalue().encode(), overwrite=overwrite, error_class=ParameterError)


def cmd_etc_catalog(args) -> int:
    """``slicersim etc --catalog T --out R``: exit 0, or 1 when some targets cannot reach the SNR
    (their rows say why)."""
    import numpy as np

    from slicersim.campaign.plan import check_client_memory, plan_survey_with
    from slicersim.campaign.products import spectrum_grid
    _check_out(args.out, args.overwrite)
    opts = _etc_options(args).checked()                    # bad values and names: before reading
    source = args.source or DEFAULT_SOURCE
    pop, catalog = _read_catalog(args.catalog, source)
    lbda = spectrum_grid()
    check_client_memory(len(catalog), lbda.size)
    fluxes = np.asarray(pop.spectra(catalog, lbda), dtype=float)
    fluxes = np.where(np.isfinite(fluxes), fluxes, 0.0)     # outside the model: no flux (as campaigns)
    plan = plan_survey_with(np.asarray(catalog["redshift"], dtype=float), lbda, fluxes, opts,
                            target_ids=np.asarray(catalog["target_id"]))
    table = etc_table(catalog, plan, opts, source, args.catalog, pop.digest)
    _write(table, args.out, args.overwrite)
    ok = np.asarray(table["status"]) == "ok"
    hours = float(np.sum(np.asarray(table["exposure_time"])[ok])) / 3600
    volume = float(np.sum(np.asarray(table["data_volume"])[ok]))
    print(f"{len(table)} targets: {int(ok.sum())} reach SNR {opts.snr:g}, {int((~ok).sum())} failed; "
          f"exposure time {hours:,.2f} h, raw data {volume:,.1f} GB in all")
    print(f"wrote {args.out}")
    if not ok.all():
        first = table[~ok][0]
        print(f"{int((~ok).sum())} target(s) cannot reach SNR {opts.snr:g}, e.g. target {first['target_id']}: "
              f"{first['error']}")
        return 1
    return 0


# ---------------------------------------------------------------------------- ramp of a SN Ia
def add_ramp_target_arguments(parser):
    """``--phase``, ``--peak-absmag``, ``--source`` and ``--snr`` on the ``ramp`` parser."""
    parser.add_argument("--phase", type=float, metavar="DAYS",
                        help="with --redshift: rest-frame days from B-band maximum (default: 0, the peak)")
    parser.add_argument("--peak-absmag", type=float, metavar="MAG",
                        help="with --redshift: peak absolute magnitude, rest-frame Bessell B (AB) (default: -19.3)")
    parser.add_argument("--source", metavar="NAME",
                        help=f"with --redshift: sncosmo SN Ia source (default: {DEFAULT_SOURCE})")
    parser.add_argument("--snr", type=float, metavar="S",
                        help="with --redshift: choose the readout (--nmd) and --nramps with the ETC to reach SNR S "
                             "per resolution element in 4000-6800 Angstrom rest frame (printed), instead of the "
                             "default readout")


#: the SN flags of ``ramp`` (dest: flag), each only with --redshift
RAMP_TARGET_FLAGS = {"phase": "--phase", "peak_absmag": "--peak-absmag", "source": "--source", "snr": "--snr"}
#: detector flags of ``ramp`` the ETC of ``--snr`` would not see
RAMP_DETECTOR_FLAGS = {"tframe": "--tframe", "ron": "--ron", "dark": "--dark", "roic_glow": "--roic-glow",
                       "gain": "--gain"}


def check_ramp_target_flags(args):
    """Check the SN flags of ``ramp`` before anything runs: --snr not with an explicit readout
    (--nmd, --nramps) nor detector flags, and > 0; --phase and --peak-absmag in the catalogues'
    bounds (ParameterError naming the flag).  Returns the SN flags given without --redshift (for
    the caller's "apply only with --redshift" message), else []."""
    from slicersim import validation
    from slicersim.campaign.population import CatalogPopulation
    from slicersim.errors import ParameterError
    given = [flag for dest, flag in RAMP_TARGET_FLAGS.items() if getattr(args, dest) is not None]
    if args.redshift is None:
        return given
    if args.snr is not None:
        explicit = [flag for dest, flag in (("nmd", "--nmd"), ("nramps", "--nramps"))
                    if getattr(args, dest) is not None]
        if explicit:
            raise ParameterError(f"--snr chooses the readout and ramps with the ETC: drop {' and '.join(explicit)} "
                                 "(or drop --snr to give the readout yourself)")
        detector = [flag for dest, flag in RAMP_DETECTOR_FLAGS.items() if getattr(args, dest) is not None]
        if detector:
            raise ParameterError(f"--snr: the ETC uses the configuration's detector, not {'/'.join(detector)}: "
                                 "give them in a --config file, or give --nmd and --nramps instead of --snr")
        from slicersim.snr.search import check_snr_target
        with validation.flag_names({"snr": "--snr"}):
            check_snr_target(args.snr)
    for dest, flag in (("phase", "--phase"), ("peak_absmag", "--peak-absmag")):
        if getattr(args, dest) is not None:
            lo, hi = CatalogPopulation.BOUNDS[dest]
            validation.number(flag, getattr(args, dest), low=lo, high=hi)
    return []


def ramp_supernova(args, config, field, conventions):
    """The SN Ia of ``ramp --redshift``, with ``--snr`` its readout chosen by the ETC (printed).

    Parameters
    ----------
    args : argparse.Namespace
        redshift, phase [rest-frame days from B-band maximum], peak_absmag [mag], source, snr
        (None: the library's defaults, and no ETC)
    config, field, conventions : of :class:`~slicersim.targets.LazuliSupernova`

    Returns
    -------
    (target, nmd, nramps) : the :class:`~slicersim.targets.LazuliSupernova`, and the readout
    (n, m, d) and number of ramps the ETC chose for SNR ``args.snr`` per resolution element in
    4000–6800 Å rest frame (None, None without ``--snr``).
    """
    from slicersim.targets import LazuliSupernova
    sn = {"phase": args.phase, "peak_absmag": args.peak_absmag, "source": args.source}
    target = LazuliSupernova(args.redshift, config=config, field=field, conventions=conventions,
                             **{k: v for k, v in sn.items() if v is not None})
    if args.snr is None:
        return target, None, None
    res = target.setup_to_snr(args.snr)
    lo, hi = res["lbda_range_obs"]
    n, m, d = (int(v) for v in res["nmd"])
    print(f"ETC: SNR {args.snr:g} per resolution element in 4000-6800 Angstrom rest frame ({lo:.0f}-{hi:.0f} "
          f"observed): readout --nmd {n} {m} {d} --nramps {int(res['nramps'])}, exposure time "
          f"{res['exposure_time']:.2f} s, SNR reached {res['snr_per_resolution']:.2f}, "
          f"{target.get_data_volume():.2f} GB")
    return target, (n, m, d), int(res["nramps"])
