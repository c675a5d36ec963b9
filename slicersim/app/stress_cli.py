"""``slicersim stress DATASET --out DIR``: ramp pipelines (stcal, slicersim's fit_ramps, any executable)
run on every exposure of a campaign dataset on Dask and scored against the truth of the ramp files
(:func:`slicersim.reduction.stress.stress_dataset`); this module maps the flags onto it and prints a
few lines."""
from __future__ import annotations

__all__ = ["add_parsers", "cmd_stress"]


def cmd_stress(args) -> int:
    """Run the harness from the parsed flags; 0 when every pipeline ran on every exposure."""
    from slicersim import validation
    from slicersim.app.campaign_cli import dask_keywords
    from slicersim.reduction.stress import stress_dataset
    if args.workers is not None:
        validation.integer("--workers", args.workers, low=1)
    if args.exec_timeout is not None:
        validation.number("--exec-timeout [s]", args.exec_timeout, low=0.0, low_open=True)
    res = stress_dataset(args.dataset, args.out, pipelines=args.pipeline or ["stcal", "slicersim"],
                         workers=args.workers, exec_timeout=args.exec_timeout, overwrite=args.overwrite, progress=False if args.quiet else None,
                         **dask_keywords(args))
    print(f"{res['out']}: {res['exposures']} exposure(s), {len(res['failed'])} failed pipeline run(s) "
          f"in {res['seconds']:.1f} s; report {res['report']}")
    if res["without_ramps"]:
        print(f"  {len(res['without_ramps'])} target(s) of the dataset have no ramps (not simulated, failed or made "
              f"without): not stressed")
    for name, bins in res["biased"].items():
        for b in bins:
            print(f"  {name} biased in flux bin {b['bin']} e-/s ({b['reason']}): bias {b['bias']:+.4g} ± "
                  f"{b['bias_err']:.2g} e-/s, pull width {b['pull_width']:.3f}")
    for tid, name, error in res["failed"][:5]:
        print(f"  failed target {tid}, {name}: {error}")
    return 0 if not res["failed"] else 1


def add_parsers(sub, fmt):
    """Add ``stress`` to the ``slicersim`` subcommands."""
    p = sub.add_parser("stress", help="score ramp pipelines (stcal, fit_ramps, exec:CMD) on a campaign's ramps "
                                      "against their truth",
                       description="Run ramp pipelines on every exposure of a campaign dataset (products.ramps = "
                                   "true) on Dask and score them against the truth the ramp files carry: jump "
                                   "recall by size and charge, false jump flags, slope bias and pulls per flux "
                                   "bin, saturation flags, pixels lost.  Writes DIR/stress.ecsv, DIR/report.md "
                                   "and figures.  Pipelines get SCI and PIXELDQ (no GROUPDQ), calibrated with the "
                                   "JWST reference files of the simulated detector.", **fmt)
    p.add_argument("dataset", metavar="DATASET", help="campaign dataset directory with ramps")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (written complete, then renamed)")
    p.add_argument("--pipeline", action="append", metavar="stcal|slicersim|exec:COMMAND",
                   help="pipeline to score (repeat; default: stcal and slicersim).  exec:COMMAND runs COMMAND "
                        "INPUT.fits OUTPUT.fits (no shell): INPUT a level-1b file, OUTPUT a FITS file with SCI "
                        "(rate [DN/s], or [e-/s] when its BUNIT says electron), optional ERR and DQ")
    p.add_argument("--exec-timeout", type=float, metavar="SECONDS", help="seconds an exec: pipeline may run on "
                   "one exposure before it (and what it started) is killed and the exposure failed (default 3600)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing DIR")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    g = p.add_argument_group("Dask")
    from slicersim.app.campaign_cli import add_cluster_arguments
    add_cluster_arguments(g, "existing Dask scheduler (every worker must see the dataset)")
    p.set_defaults(func=cmd_stress)
