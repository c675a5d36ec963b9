"""``slicersim survey plan`` and ``slicersim campaign {run,status,report}`` (registered by :mod:`slicersim.app.cli`)."""
from __future__ import annotations

import os

import numpy as np

__all__ = ["add_parsers", "add_dask_arguments", "dask_keywords"]

YEAR_S = 365.25 * 86400.0


def _gb(nbytes):
    return f"{nbytes / 1e9:,.1f} GB"


def cmd_survey_plan(args) -> int:
    from slicersim.campaign.plan import plan_survey
    from slicersim.campaign.population import SNIaPopulation
    from slicersim.campaign.products import spectrum_grid
    from slicersim.campaign.plan import check_client_memory
    from slicersim.errors import ParameterError
    from slicersim.io.atomic import check_output_path
    for path, exts, flag in ((args.out, (".ecsv", ".csv"), "--out"), (args.figure, (".png", ".pdf", ".svg"),
                                                                       "--figure")):
        if not path:
            continue
        if os.path.isdir(path) or path.endswith(os.sep):
            check_output_path(path, args.overwrite, ParameterError, flag)    # refused: a directory
        if not path.endswith(exts):
            raise ParameterError(f"{flag} must end with {' or '.join(exts)}, got {path}")
        check_output_path(path, args.overwrite, ParameterError, flag)        # a FIFO, device, existing file
    if args.n < 1:
        raise ParameterError(f"--n must be ≥ 1 (an empty population has nothing to plan), got {args.n}")
    from slicersim import validation
    if args.z_switch != float("inf"):
        validation.redshift("--z-switch", args.z_switch, allow_zero=True)
    from slicersim.backends.precision import resolve_precision
    resolve_precision(args.precision, "auto", "batch_etc")         # e.g. double without fp64: before the draws
    seed = validation.seed(args.seed, name="--seed")
    seed = validation.new_seed() if seed is None else seed      # recorded in the table and printed
    lbda = spectrum_grid()
    check_client_memory(args.n, lbda.size)
    config = (args.config[0] if len(args.config) == 1 else list(args.config)) if args.config else "cbe"
    with validation.flag_names({"population.redshift.min": "--zmin", "population.redshift.max": "--zmax"}):
        pop = SNIaPopulation(args.n, redshift={"distribution": args.distribution, "min": args.zmin, "max": args.zmax})
    table = pop.draw(seed)
    fluxes = pop.spectra(table, lbda)
    fluxes = np.where(np.isfinite(fluxes), fluxes, 0.0)
    plan = plan_survey(np.asarray(table["redshift"]), lbda, fluxes, snr=args.snr, lbda_range=tuple(args.lbda_range),
                       frame="rest", z_switch=args.z_switch, config=config, search=args.search,
                       conventions=args.conventions, overhead=args.overhead, efficiency=args.efficiency,
                       compression_ratio=args.compression_ratio, target_ids=np.asarray(table["target_id"]),
                       progress=None, precision=args.precision)
    plan.table.meta["population_seed"] = seed
    if args.out:
        _write_table(plan.table, args.out, args.overwrite)
    print(plan.summary())
    print(f"population seed    : {seed}{'' if args.seed is not None else ' (drawn: --seed repeats it)'}")
    if args.figure:
        _write_figure({f"SNR {args.snr:g}": plan}, args.figure, args.overwrite)
        print(f"wrote {args.figure}")
    if args.out:
        print(f"wrote {args.out}")
    failed = plan.totals["failed"]
    if failed:
        first = plan.table[np.asarray(plan.table["status"]) == "failed"][0]
        print(f"{failed} target(s) could not be planned, e.g. target {first['target_id']}: {first['error']}")
    return 1 if failed else 0


def _write_table(table, path, overwrite):
    import io

    from slicersim.errors import ParameterError
    from slicersim.io.atomic import atomic_bytes
    buf = io.StringIO()
    fmt = "ascii.ecsv" if path.endswith(".ecsv") else "ascii.csv"
    if not path.endswith((".ecsv", ".csv")):
        raise ParameterError(f"--out must end with .ecsv or .csv, got {path}")
    table.write(buf, format=fmt)
    atomic_bytes(path, buf.getvalue().encode(), overwrite=overwrite)


def _write_figure(plans, path, overwrite):
    """The time and volume figure, written atomically (a temporary renamed in when complete)."""
    import matplotlib

    from slicersim.campaign.plan import plot_time_and_volume
    from slicersim.errors import ParameterError
    from slicersim.io.file_set import write_files

    def draw(fh):
        with matplotlib.rc_context({"savefig.format": os.path.splitext(path)[1][1:].lower()}):
            plot_time_and_volume(plans, fh)
    write_files({path: draw}, overwrite=overwrite, error_class=ParameterError)


def _check_dataset_argument(path, command="status", what="DIR"):
    """``campaign status DIR`` (``report``): a file or FIFO is refused naming what the command takes (a
    campaign spec given by mistake: the command that runs it)."""
    from slicersim.errors import ParameterError
    if os.path.isdir(path) or not os.path.lexists(path):
        return                          # a directory, or missing: campaign_status says
    kind = "a file" if os.path.isfile(path) else "not a directory (a FIFO, device or socket)"
    hint = (f"; {path} looks like a campaign spec: run it with 'slicersim campaign run {path} --out DIR', then "
            f"'slicersim campaign {command} DIR'") if path.lower().endswith(".toml") else ""
    takes = f"'slicersim campaign {command}' takes a dataset directory (the --out DIR of 'slicersim campaign run')" \
        if what == "DIR" else f"{what} takes a reduction directory (the --out DIR of 'slicersim reduce DATASET --spectra')"
    raise ParameterError(f"{path} is {kind}: {takes}{hint}")


def _check_spec_argument(path):
    """``campaign run SPEC.toml``: a directory (a dataset given where its spec goes) is refused naming
    what the command takes."""
    from slicersim.errors import ParameterError
    if not os.path.isdir(path):
        return                          # a file, or missing: load_spec says
    from slicersim.io.dataset import SPEC_JSON
    if os.path.isfile(os.path.join(path, SPEC_JSON)):
        what = (f"{path} is a dataset directory, not a campaign spec: 'slicersim campaign run' takes SPEC.toml "
                f"and --out DIR (to resume this dataset: 'slicersim campaign run SPEC.toml --out {path}' with "
                f"the spec it was made from; its state: 'slicersim campaign status {path}')")
    else:
        what = f"{path} is a directory, not a campaign spec: 'slicersim campaign run' takes SPEC.toml --out DIR"
    raise ParameterError(what)


def cmd_campaign_run(args) -> int:
    import math

    from slicersim.campaign.runner import run_campaign
    from slicersim.errors import ParameterError
    _check_spec_argument(args.spec)
    if not (math.isfinite(args.memory_per_task) and 1 <= args.memory_per_task <= 2**20):
        raise ParameterError(f"--memory-per-task must be in [1, 1048576] MiB, got {args.memory_per_task}")
    spec = args.spec
    if args.precision is not None:             # overrides products.precision, written into the stored spec
        from slicersim.campaign.spec import load_spec, with_products
        spec = with_products(load_spec(args.spec), precision=args.precision)
    res = run_campaign(spec, args.out, workers=args.workers, force=args.force,
                       retry_failed=args.retry_failed, progress=False if args.no_progress else None,
                       threads_per_worker=args.threads_per_worker,
                       max_bytes=int(args.memory_per_task * 2**20), **dask_keywords(args))
    print(f"{res['dataset']}: {res['targets']} targets, {res['done']} done, {res['failed']} failed, "
          f"{res['missing']} missing ({res['computed']} computed in {res['seconds']:.1f} s)")
    if res["failed"] and not args.retry_failed:    # a rerun does not recompute them: say how (disk full, ...)
        print(f"{res['failed']} failed target(s) are kept as failed on a rerun: `slicersim campaign status "
              f"{args.out}` lists why; --retry-failed runs them again")
    return 0 if res["failed"] == 0 and res["missing"] == 0 else 1


def cmd_campaign_status(args) -> int:
    from slicersim.campaign.runner import campaign_status
    _check_dataset_argument(args.dataset)
    st = campaign_status(args.dataset, verify=not args.no_verify)
    print(f"{st['dataset']}: {st['targets']} targets, {st['done']} done, {st['missing']} missing, "
          f"{st['failed']} failed")
    for tid, why in st["failed_targets"][:args.show]:
        print(f"  failed  {tid}: {why}")
    for tid, why in st["missing_targets"][:args.show]:
        print(f"  missing {tid}: {why}")
    return 0 if st["missing"] == 0 and st["failed"] == 0 else 1


def cmd_campaign_report(args) -> int:
    from slicersim.reduction.report import campaign_report
    _check_dataset_argument(args.dataset, "report")
    if args.reduced is not None:
        _check_dataset_argument(args.reduced, "report", "--reduced")
    res = campaign_report(args.dataset, args.out, reduced=args.reduced)
    table = res["table"]
    ratio = np.asarray(table["band_flux_ratio"], float)
    ok = np.isfinite(ratio)
    mean = f", band flux / input {ratio[ok].mean():.4f} (mean of {int(ok.sum())})" if ok.any() else ""
    print(f"{res['summary']}: {len(table)} targets{mean}")
    print(f"wrote {res['report']} and {', '.join(os.path.basename(f) for f in res['figures'])}")
    return 0


def add_dask_arguments(parser, scheduler=True):
    """``--dashboard``, ``--tls-ca-file``, ``--tls-cert``, ``--tls-key`` (and, with ``scheduler``,
    ``--scheduler``) on ``parser`` (a parser or an argument group); :func:`dask_keywords` reads them."""
    parser.add_argument("--dashboard", action="store_true",
                        help="serve the embedded cluster's Dask dashboard on 127.0.0.1:8787 (this machine only; "
                             "default: off)")
    if scheduler:
        parser.add_argument("--scheduler", metavar="ADDRESS",
                            help="existing Dask scheduler, e.g. tls://host:8786 (with --tls-* files) or "
                                 "tcp://host:8786 (unencrypted: anyone who reaches it runs code as its workers; "
                                 "trusted networks only)")
    parser.add_argument("--tls-ca-file", metavar="CA.pem", help="CA certificate of the --scheduler's TLS (or Dask's "
                                                                "distributed.comm.tls configuration)")
    parser.add_argument("--tls-cert", metavar="CERT.pem", help="this client's TLS certificate for --scheduler")
    parser.add_argument("--tls-key", metavar="KEY.pem", help="this client's TLS private key for --scheduler")


def add_cluster_arguments(group, scheduler_help):
    """``--workers N`` or ``--scheduler ADDRESS`` (mutually exclusive) and the other Dask flags
    (:func:`add_dask_arguments`) on an argument ``group`` of a dataset command (reduce, stress)."""
    w = group.add_mutually_exclusive_group()
    w.add_argument("--workers", type=int, metavar="N", help="workers of the embedded Dask LocalCluster "
                   "(default: CPU count)")
    w.add_argument("--scheduler", metavar="ADDRESS", help=scheduler_help)
    add_dask_arguments(group, scheduler=False)


def dask_keywords(args):
    """{"scheduler", "security", "dashboard"} keywords of run_campaign / reduce_dataset from the flags
    of :func:`add_dask_arguments`; the --tls-* files apply only with --scheduler."""
    from slicersim.campaign.runner import tls_security
    from slicersim.errors import ParameterError
    files = [getattr(args, name, None) for name in ("tls_ca_file", "tls_cert", "tls_key")]
    scheduler = getattr(args, "scheduler", None)
    if any(f is not None for f in files) and not scheduler:
        raise ParameterError("--tls-ca-file/--tls-cert/--tls-key apply to --scheduler only (the embedded cluster "
                             "makes its own temporary TLS credentials)")
    if scheduler and getattr(args, "dashboard", False):
        raise ParameterError("--dashboard applies to the embedded cluster only (an existing --scheduler serves "
                             "its own dashboard)")
    return {"scheduler": scheduler, "security": tls_security(*files) if scheduler else None,
            "dashboard": bool(getattr(args, "dashboard", False))}


def add_parsers(sub, fmt):
    """Add the ``survey`` and ``campaign`` commands to the CLI's subparsers."""
    from slicersim.physics.conventions import CONVENTIONS, DEFAULT_CONVENTIONS

    survey = sub.add_parser("survey", help="survey planning (time and raw data volume of a population)",
                            description="Survey planning.", **fmt)
    ssub = survey.add_subparsers(dest="survey_command", metavar="SUBCOMMAND", required=True,
                                 parser_class=type(survey))
    p = ssub.add_parser("plan", help="batch ETC of a SN Ia population: per-target readout, time, volume; totals",
                        description="Plan a SN Ia survey: one batch ETC per field, per-target readout, "
                                    "exposure time, SNR and raw data volume, and the totals.", **fmt)
    p.add_argument("--n", type=int, default=8000, help="number of SNe Ia")
    p.add_argument("--zmin", type=float, default=0.05, help="lowest redshift")
    p.add_argument("--zmax", type=float, default=1.5, help="highest redshift")
    p.add_argument("--distribution", choices=("uniform", "volumetric"), default="uniform",
                   help="redshift distribution")
    p.add_argument("--snr", type=float, default=20.0, help="SNR per resolution element in the band")
    p.add_argument("--lbda-range", type=float, nargs=2, default=(4000.0, 6800.0), metavar=("LO", "HI"),
                   help="rest-frame band [Angstrom]")
    p.add_argument("--z-switch", type=float, default=0.8, help="narrow field below, wide field from this redshift")
    p.add_argument("--config", action="append", metavar="cbe|eol|PATH",
                   help="instrument configuration; repeat to apply several in order (default: cbe)")
    p.add_argument("--search", choices=("exact", "reference"), default="exact", help="readout search")
    p.add_argument("--conventions", choices=CONVENTIONS, default=DEFAULT_CONVENTIONS, help="model conventions")
    p.add_argument("--overhead", type=float, default=0.0, help="per-target overhead (slew, settle) [s]")
    p.add_argument("--efficiency", type=float, default=1.0, help="observing efficiency (fraction of time on sky)")
    p.add_argument("--compression-ratio", type=float, default=1.0, help="raw data compression ratio")
    p.add_argument("--seed", type=int, default=None,
                   help="population seed, an integer in [0, 2**64) (default: drawn, printed and recorded in the "
                        "table's metadata)")
    p.add_argument("--out", metavar="FILE.ecsv", help="per-target table (ECSV or CSV)")
    p.add_argument("--figure", metavar="FILE.png", help="time and volume vs redshift figure")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    p.add_argument("--precision", choices=("auto", "double", "single"), default="auto",
                   help="precision of the batch ETC's band-variance kernel (auto: single only on a device "
                        "without fast fp64)")
    p.set_defaults(func=cmd_survey_plan)

    camp = sub.add_parser("campaign", help="mock datasets on Dask: run a campaign spec, report its status",
                          description="Campaigns: per-target products of a population on Dask.", **fmt)
    csub = camp.add_subparsers(dest="campaign_command", metavar="SUBCOMMAND", required=True,
                               parser_class=type(camp))
    p = csub.add_parser("run", help="run or resume a campaign",
                        description="Run (or resume: only what is missing is computed) a campaign spec "
                                    "into a dataset directory.", **fmt)
    p.add_argument("spec", metavar="SPEC.toml", help="campaign spec")
    p.add_argument("--out", required=True, metavar="DIR", help="dataset directory")
    p.add_argument("--workers", type=int, help="workers of the embedded LocalCluster (default: CPU count)")
    add_dask_arguments(p)
    p.add_argument("--threads-per-worker", type=int, help="OpenCL CPU threads per worker (default: CPUs/workers)")
    p.add_argument("--memory-per-task", type=float, default=1024.0,
                   help="memory budget of a task's chunks and ramp blocks [MiB]")
    p.add_argument("--precision", choices=("auto", "double", "single"),
                   help="precision of the cube kernels (overrides the spec's products.precision; default auto: "
                        "single only on devices without fast fp64)")
    p.add_argument("--force", action="store_true", help="start again in a dataset made from another spec")
    p.add_argument("--retry-failed", action="store_true", help="run failed targets again")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_campaign_run)
    p = csub.add_parser("status", help="done / missing / failed targets of a dataset",
                        description="Report a dataset's done, missing and failed targets.", **fmt)
    p.add_argument("dataset", metavar="DIR", help="dataset directory")
    p.add_argument("--no-verify", action="store_true", help="skip the product checksums (sizes only)")
    p.add_argument("--show", type=int, default=20, help="list at most this many failed/missing targets")
    p.set_defaults(func=cmd_campaign_status)
    p = csub.add_parser("report", help="summary and report of a campaign against its truth (bias, pulls, SNR)",
                        description="Per-target summary of a campaign against each target's truth (summary.ecsv: "
                                    "band flux / input, its error and pull, chi2, SNR reported, measured and "
                                    "predicted by the ETC, position error, flags, times) and a report (report.md) "
                                    "with figures: band flux / input and pulls against redshift, SNR against the "
                                    "ETC.  From the reduced spectra with --reduced, else from the campaign's "
                                    "simulated spectra.", **fmt)
    p.add_argument("dataset", metavar="DATASET", help="campaign dataset directory")
    p.add_argument("--reduced", metavar="RED", help="its reduction directory (slicersim reduce DATASET --out RED "
                                                    "--spectra)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder of the report (made when missing)")
    p.set_defaults(func=cmd_campaign_report)
