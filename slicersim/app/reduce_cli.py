"""``slicersim reduce``: raw ramps (our HDF5 or a JWST level-1b FITS) → rates, with variance and DQ;
with ``--spectra`` → rates, rectified cubes and point-source spectra; a campaign dataset
directory → one reduced product per target (a Dask task each, resumable).

The heavy parts are :func:`slicersim.reduction.ramp_fit.fit_ramps`,
:func:`slicersim.reduction.pipeline.reduce_exposure` and
:func:`slicersim.reduction.campaign.reduce_dataset`; this module only maps the command-line
flags onto them (validated before any data are read) and prints one line per product.
"""
from __future__ import annotations

import math
import os

from slicersim.validation import short_repr

__all__ = ["add_parsers", "cmd_reduce", "parse_lbda_edges"]

#: flags of --spectra (name on the command line, attribute)
_SPECTRA_FLAGS = (("--field", "field"), ("--lbda-edges", "lbda_edges"), ("--ncol", "ncol"),
                  ("--rectify", "rectify"), ("--extraction", "extraction"), ("--psf", "psf"),
                  ("--position", "position"), ("--aperture", "aperture"), ("--config", "config"),
                  ("--no-background", "no_background"), ("--no-ipc", "no_ipc"),
                  ("--no-propagate", "no_propagate"), ("--dark", "dark"), ("--weights", "weights"),
                  ("--cubes", "cubes"))
#: flags of a dataset directory
_DATASET_FLAGS = (("--workers", "workers"), ("--scheduler", "scheduler"), ("--retry-failed", "retry_failed"),
                  ("--force", "force"), ("--verify", "verify"), ("--dashboard", "dashboard"),
                  ("--tls-ca-file", "tls_ca_file"), ("--tls-cert", "tls_cert"), ("--tls-key", "tls_key"))
#: most λ bins accepted from START,STOP,STEP
MAX_BINS = 100_000
#: the command-line flag of each Python keyword a reduction error may name
FLAG_OF = {"field": "--field", "lbda_edges": "--lbda-edges", "ncol": "--ncol", "rectify_method": "--rectify",
           "extraction": "--extraction", "psf": "--psf", "position": "--position", "aperture": "--aperture",
           "config": "--config", "background": "--no-background", "ipc": "--no-ipc", "propagate": "--no-propagate",
           "dark": "--dark", "weights": "--weights", "cubes": "--cubes", "weighting": "--weighting", "jump_threshold": "--jump-threshold",
           "gain": "--gain", "read_noise": "--ron", "ron": "--ron", "with_truth": "--with-truth",
           "refpix": "--no-refpix", "linearity": "--no-linearity", "workers": "--workers",
           "scheduler": "--scheduler", "allow_partial": "--allow-partial", "max_bytes": "--max-bytes"}


def cli_message(text):
    """A reduction error's message with the Python keywords it names written as command-line flags:
    a leading ``name`` ("ncol must be ...", "unknown weights ..."), ``name=VALUE`` and ``name=``
    (a hint "give position= (CLI --position)" keeps only the flag)."""
    import re
    names = "|".join(sorted(FLAG_OF, key=len, reverse=True))
    text = re.sub(rf"\b({names})=\S* in Python, (--[\w-]+) on the command line", lambda m: m.group(2), text)
    text = re.sub(rf"\b({names})=\S*\s*\((?:CLI:?|on the command line:?)\s*(--[\w-]+)[^)]*\)",
                  lambda m: m.group(2), text)
    text = re.sub(rf"\b({names})=(?:True|False|None|'[^']*'|\S+\b)?", lambda m: FLAG_OF[m.group(1)], text)
    text = re.sub(rf"^(unknown )?({names})\b(?= \(| \[| must| has| applies| apply|:| [\'\"])",
                  lambda m: (m.group(1) or "") + FLAG_OF[m.group(2)], text)
    return text


class _FlagNames:
    """Context: a SlicersimError raised inside is raised again, same class, with :func:`cli_message`."""

    def __enter__(self):
        return self

    def __exit__(self, kind, exc, tb):
        from slicersim.errors import SlicersimError
        if exc is None or not isinstance(exc, SlicersimError) or not exc.args or not isinstance(exc.args[0], str):
            return False
        text = cli_message(exc.args[0])
        if text == exc.args[0]:
            return False
        try:
            new = type(exc)(text)
        except Exception:                       # a subclass with another constructor: leave it
            return False
        raise new.with_traceback(tb) from exc.__cause__


def _check_out(path, overwrite):
    """Refuse a bad --out file before any work (:func:`slicersim.io.atomic.check_output_path`); a
    single ramp file is reduced to one HDF5 file, so a directory is refused."""
    from slicersim.errors import ParameterError
    from slicersim.io.atomic import check_output_path
    check_output_path(path, overwrite, ParameterError, "--out")


def parse_lbda_edges(text):
    """λ edges [Å] of ``--lbda-edges``: ``START,STOP,STEP`` (START, START+STEP, ..., STOP; STOP − START a
    multiple of STEP) or the name of a file (.npy, or text: the edges, whitespace or comma separated)."""
    import numpy as np

    from slicersim import validation
    from slicersim.errors import ParameterError
    if os.path.lexists(text):
        validation.regular_file("--lbda-edges", text)            # a FIFO, device, directory: refused
        try:
            if text.endswith(".npy"):
                from slicersim.io.npy import load_npy
                edges = load_npy("--lbda-edges", text)
            else:
                import io
                with open(text, encoding="utf-8") as fh:
                    edges = np.loadtxt(io.StringIO(fh.read().replace(",", " ")), ndmin=1)
        except ParameterError:
            raise
        except (OSError, ValueError, UnicodeDecodeError) as exc:
            raise ParameterError(f"--lbda-edges: cannot read λ edges from {text}: {' '.join(str(exc).split())}") \
                from None
        edges = np.ravel(edges) if np.ndim(edges) == 2 and 1 in np.shape(edges) else edges
        if np.ndim(edges) != 1 or np.size(edges) < 2 or not np.issubdtype(np.asarray(edges).dtype, np.number):
            raise ParameterError(f"--lbda-edges: {text} must hold ≥ 2 numbers (λ edges [Å]), got shape "
                                 f"{np.shape(edges)}")
        return np.asarray(edges, np.float64)
    parts = text.split(",")
    try:
        start, stop, step = (float(p) for p in parts)
    except ValueError:
        raise ParameterError(f"--lbda-edges must be START,STOP,STEP [Å] or an existing file, got "
                             f"{short_repr(text)}") from None
    given = f"{start:g},{stop:g},{step:g}"
    if not all(math.isfinite(v) for v in (start, stop, step)) or step <= 0 or stop <= start:
        raise ParameterError(f"--lbda-edges START,STOP,STEP needs finite START < STOP and STEP > 0, got {given}")
    nbins = (stop - start) / step
    if nbins > MAX_BINS:
        raise ParameterError(f"--lbda-edges {given} makes {nbins:.3g} bins (at most {MAX_BINS})")
    if abs(nbins - round(nbins)) > 1e-6 * max(1.0, nbins):
        raise ParameterError(f"--lbda-edges {given}: STOP − START must be a multiple of STEP")
    return start + step * np.arange(int(round(nbins)) + 1)


def _parse_position(text):
    from slicersim.errors import ParameterError
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise ParameterError(f"--position must be X,Y [cells from the field centre], got {short_repr(text)}") \
            from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ParameterError(f"--position must be finite, got {x:g},{y:g}")
    return x, y


def _load_npy(text, flag, expected):
    """The .npy array of a file option (one-line ParameterError when missing or unreadable)."""
    from slicersim import validation
    from slicersim.errors import ParameterError
    from slicersim.io.npy import load_npy
    if not os.path.lexists(text):
        raise ParameterError(f"{flag} must be {expected}, got {short_repr(text)}")
    validation.regular_file(flag, text)                          # a FIFO, device, directory: refused
    try:
        return load_npy(flag, text)
    except ParameterError:
        raise
    except (OSError, ValueError) as exc:
        raise ParameterError(f"{flag}: cannot read {text} as a .npy array: {' '.join(str(exc).split())}") from None


def _load_psf(text):
    if text == "fit":
        return "fit"
    return _load_npy(text, "--psf", "'fit' or an existing .npy file (nλ, slices, columns)")


def _parse_dark(text):
    """--dark: 'auto', 'none', a rate [e-/s] or a .npy image [e-/s]."""
    if text in ("auto", "none"):
        return text
    try:
        return float(text)
    except ValueError:
        return _load_npy(text, "--dark", "'auto', 'none', a rate [e-/s] or an existing .npy image")


def _given(args, flags):
    return [flag for flag, attr in flags if getattr(args, attr) not in (None, False)]


def _apply(flags):
    return f"{', '.join(flags)} appl{'ies' if len(flags) == 1 else 'y'}"


def _check_flags(args, dataset):
    from slicersim import validation
    from slicersim.errors import ParameterError
    if not args.spectra and _given(args, _SPECTRA_FLAGS):
        raise ParameterError(f"{_apply(_given(args, _SPECTRA_FLAGS))} only with --spectra")
    if not dataset and _given(args, _DATASET_FLAGS):
        raise ParameterError(f"{_apply(_given(args, _DATASET_FLAGS))} only to a campaign dataset "
                             f"directory, and {args.raw} is not a directory")
    if dataset and args.overwrite:
        raise ParameterError("--overwrite applies to a single ramp file; a reduction directory is resumed "
                             "(--force starts it again when its options changed)")
    if args.workers is not None:
        validation.integer("--workers", args.workers, low=1)
    validation.integer("--show", args.show, low=0)
    if args.jump_threshold is not None:
        validation.number("--jump-threshold [σ] (0: no jump detection)", args.jump_threshold, low=0.0)
    if args.gain is not None:
        validation.number("--gain [DN/e-]", args.gain, low=0.0, low_open=True)
    if args.ron is not None:
        validation.number("--ron (read noise per frame)", args.ron, low=0.0, high=1e4, unit="electron")
    if args.max_bytes is not None:
        validation.integer("--max-bytes", args.max_bytes, low=1)


def _spectra_options(args):
    """reduce_exposure options of the flags given (None left to the pipeline's defaults)."""
    from slicersim.reduction.checks import check_spectra_options
    opts = {"field": args.field, "ncol": args.ncol, "rectify_method": args.rectify, "extraction": args.extraction,
            "aperture": args.aperture, "background": False if args.no_background else None,
            "propagate": False if args.no_propagate else None,
            "lbda_edges": parse_lbda_edges(args.lbda_edges) if args.lbda_edges is not None else None,
            "position": _parse_position(args.position) if args.position is not None else None,
            "psf": _load_psf(args.psf) if args.psf is not None else None,
            "dark": _parse_dark(args.dark) if args.dark is not None else None, "weights": args.weights,
            "config": (args.config[0] if len(args.config) == 1 else list(args.config)) if args.config else None,
            "ipc": False if args.no_ipc else None, "cubes": True if args.cubes else None}
    opts = {k: v for k, v in opts.items() if v is not None}       # --dark none: "none" (kept, not None)
    with _FlagNames():
        check_spectra_options(**opts)              # every value, before any data are read
    return opts


def cmd_reduce(args) -> int:
    from slicersim.errors import ParameterError
    dataset = os.path.isdir(args.raw)
    if os.path.isfile(args.raw) and args.raw.lower().endswith(".toml"):
        raise ParameterError(f"{args.raw} is a TOML file, not a ramp file: 'slicersim reduce' takes a ramp file or a "
                             f"campaign dataset directory (a campaign spec? run it first: 'slicersim campaign run "
                             f"{args.raw} --out DIR' with products.ramps = true, then 'slicersim reduce DIR --out RED')")
    _check_flags(args, dataset)
    if not dataset and not os.path.isfile(args.raw):
        if os.path.lexists(args.raw):       # a FIFO, device or socket: never opened
            raise ParameterError(f"{args.raw} is not a regular file (nor a dataset directory)")
        raise ParameterError(f"{args.raw}: no such ramp file or dataset directory")
    if not dataset and os.path.exists(args.out) and os.path.samefile(args.raw, args.out):
        raise ParameterError(f"--out is RAW itself ({args.raw}): the ramps would be lost")
    fit_options = {"refpix": False if args.no_refpix else None, "linearity": False if args.no_linearity else None,
                   "jump_threshold": args.jump_threshold, "weighting": args.weighting, "gain": args.gain,
                   "ron": args.ron, "with_truth": args.with_truth}
    if args.max_bytes is not None:
        fit_options["max_bytes"] = args.max_bytes
    options = _spectra_options(args) if args.spectra else {}
    if dataset:
        return _reduce_dataset(args, fit_options, options)
    _check_out(args.out, args.overwrite)
    from slicersim.reduction.campaign import reduce_file
    with _FlagNames():
        result = reduce_file(args.raw, args.out, spectra=args.spectra, overwrite=args.overwrite,
                             fit_options=fit_options, progress=not args.quiet and None, **options)
    rate = result["rates"].rate
    line = (f"{result['path']}: rates {rate.shape[-2]}×{rate.shape[-1]} of {rate.shape[0] if rate.ndim == 3 else 1} "
            f"integration(s), {int((result['rates'].njumps > 0).sum())} pixel(s) with jumps")
    if args.spectra:
        spectra, cubes = result["spectra"], result["cubes"]
        names = list(dict.fromkeys([*cubes, *spectra, *(("narrow", "wide") if args.field == "both" else ())]))
        line += "; " + ", ".join(name + (f" cube {'×'.join(map(str, cubes[name].flux.shape[-3:]))}," if name in cubes
                                         else "") + " "
                                 + (f"spectrum ({spectra[name].method})" if name in spectra else "no spectrum (no source)")
                                 for name in names)
    print(line)
    return 0


def _reduce_dataset(args, fit_options, options):
    from slicersim.app.campaign_cli import dask_keywords
    from slicersim.reduction.campaign import reduce_dataset
    with _FlagNames():
        res = reduce_dataset(args.raw, args.out, workers=args.workers, **dask_keywords(args),
                             spectra=args.spectra, retry_failed=args.retry_failed, force=args.force,
                             verify=args.verify, progress=False if args.quiet else None, fit_options=fit_options,
                             **options)
    print(f"{res['out']}: {res['targets']} targets, {res['done']} reduced, {res['failed']} failed, "
          f"{res['missing']} missing, {res['unavailable']} without ramps ({res['computed']} reduced now "
          f"in {res['seconds']:.1f} s)")
    for tid, error in res["failed_targets"][:args.show]:
        print(f"  failed {tid}: {error}")
    for tid, why in res.get("unavailable_targets", [])[:args.show]:
        print(f"  without ramps {tid}: {why}")
    if res.get("report"):
        print(f"summary against the input: {os.path.join(res['out'], 'summary.ecsv')}, report {res['report']}")
    elif res.get("report_error"):
        print(f"no summary against the input ({res['report_error']}); the reductions stand: `slicersim campaign "
              f"report {args.raw} --reduced {res['out']} --out DIR` makes it")
    return 0 if res["done"] == res["targets"] else 1


def add_parsers(sub, fmt):
    """Add ``reduce`` to the ``slicersim`` subcommands."""
    from slicersim.reduction.checks import MAX_NCOL
    from slicersim.reduction.ramp_fit import DEFAULT_JUMP_THRESHOLD, WEIGHTINGS
    from slicersim.reduction.rectify import METHODS as RECTIFY_METHODS
    from slicersim.reduction.spectra import METHODS as EXTRACTION_METHODS
    p = sub.add_parser("reduce", help="raw ramps → rates [e-/s] (--spectra: spectra, --cubes: cubes); campaign datasets",
                       description="Up-the-ramp fit of a raw ramp file (slicersim HDF5 or JWST level-1b FITS): "
                                   "bias, reference-pixel and nonlinearity corrections when the file carries "
                                   "those effects, saturation, jump detection, GLS or OLS slopes.  With "
                                   "--spectra, the point source's spectrum is extracted (and with --cubes the rates "
                                   "are rectified into (λ, slice, column) cubes; one HDF5: rates/, spectra/, "
                                   "cubes/).  "
                                   "RAW may be a campaign dataset directory (products.ramps = true): every "
                                   "target is reduced in a Dask task into the directory --out "
                                   "(products/tNNNNNNN/rates.h5 or reduced.h5, records/, catalog.ecsv); run "
                                   "again, it resumes.", **fmt)
    p.add_argument("raw", metavar="RAW", help="ramp file (.h5 from `slicersim ramp`, or a level-1b .fits), or a "
                   "campaign dataset directory")
    p.add_argument("--out", required=True, metavar="OUT.h5|DIR",
                   help="output HDF5 file (RATE, VAR, DQ, NJUMPS, ...), or directory for a dataset")
    p.add_argument("--weighting", choices=WEIGHTINGS, default="gls",
                   help="gls: exact MACC covariance (lowest variance); ols: unweighted (Rauscher07 variance)")
    p.add_argument("--jump-threshold", type=float, default=DEFAULT_JUMP_THRESHOLD, metavar="SIGMA",
                   help="two-point-difference jump test [σ]; 0: no detection")
    p.add_argument("--no-refpix", action="store_true", help="skip the reference-pixel correction")
    p.add_argument("--no-linearity", action="store_true", help="skip the nonlinearity correction")
    p.add_argument("--gain", type=float, metavar="DN/e-", help="override the file's GAIN")
    p.add_argument("--ron", "--read-noise", dest="ron", type=float, metavar="RON",
                   help="override the file's read noise per frame [electron] (--read-noise: its earlier name)")
    p.add_argument("--with-truth", action="store_true", help="copy truth/rate beside the fitted rates "
                   "(TRUTH_RATE; rates/TRUTH_RATE with --spectra)")
    p.add_argument("--max-bytes", type=int, metavar="BYTES", help="memory budget of the row blocks of the ramp fit "
                   "in flight [bytes] (default: 268435456 = 256 MiB; lower it when memory runs out)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    g = p.add_argument_group("rates → cubes → spectra (with --spectra)")
    g.add_argument("--spectra", action="store_true",
                   help="also rectify cubes and extract spectra (for a dataset: and write OUT/summary.ecsv, "
                        "OUT/report.md and figures, each target against its truth)")
    g.add_argument("--field", choices=("narrow", "wide", "both"),
                   help="field(s) to rectify (default: narrow; for a dataset, each target's own field)")
    g.add_argument("--lbda-edges", metavar="START,STOP,STEP|FILE",
                   help="λ bin edges [Å]: START, START+STEP, ..., STOP; or a file of edges (.npy or text) "
                        "(default: the prism's native grid, 2 native bins per bin)")
    g.add_argument("--ncol", type=int, metavar="N", help=f"columns per slice, 1 to {MAX_NCOL} (default: 58)")
    g.add_argument("--cubes", action="store_true",
                   help="also rectify the (λ, slice, column) cube(s) (default: only for a cube extraction or with "
                        "--rectify/--weights; the forward extraction's spectrum comes from the pixels)")
    g.add_argument("--rectify", choices=RECTIFY_METHODS, help="cube rectification (implies --cubes): lsq: exact "
                   "weighted least squares (default); drizzle: fast pixel-to-cell sharing, smooths the cube")
    g.add_argument("--extraction", choices=("forward", *EXTRACTION_METHODS),
                   help="spectrum extraction: 'forward' (default when the file records its instrument "
                        "configuration) fits the point source on the detector pixels with the configuration's "
                        "PSF, LSF and projection (unbiased for any --ncol/--rectify); 'gls', 'optimal', "
                        "'aperture' extract from the cube and need --psf FILE.npy when the instrument is known "
                        "(a PSF fitted on the coarse cells biases them)")
    g.add_argument("--no-ipc", action="store_true",
                   help="do not deconvolve the rates by the file's inter-pixel capacitance kernel (done by "
                        "default when the file records the IPC effect)")
    g.add_argument("--config", action="append", metavar="cbe|eol|PATH",
                   help="instrument configuration of the forward model; repeat to apply several in order "
                        "(default: the one the file records)")
    g.add_argument("--psf", metavar="fit|FILE.npy", help="cube extractions: 'fit' a Gaussian fitted on the cube; "
                   "or a .npy array (nλ, slices, columns) of PSF fractions or a forward-modelled template")
    g.add_argument("--position", metavar="X,Y", help="source position [cells from the field centre] "
                   "(default: fitted)")
    g.add_argument("--aperture", type=float, metavar="SIGMA", help="aperture radius [white-light PSF σ] "
                   "(default: 3)")
    g.add_argument("--no-background", action="store_true", help="no background subtraction")
    g.add_argument("--dark", metavar="auto|none|E/S|FILE.npy",
                   help="dark rate subtracted before rectification: 'auto' (default) the file's DARK_RATE "
                        "(dark + thermal dark + glow; nothing, with a warning, if the file has none) plus the "
                        "warm and hot pixels' extra dark where the file records its bad pixels, "
                        "'none', a rate [e-/s] or a .npy detector image [e-/s]")
    g.add_argument("--weights", choices=("model", "forward", "data"),
                   help="lsq weights of the cube: 'forward' (default) the variance of the fitted point source + "
                        "background model, 'model' that of the first cubes' image, 'data' the ramp fit's own "
                        "variance")
    g.add_argument("--no-propagate", action="store_true",
                   help="optimal/aperture on an lsq cube: cells-independent variance instead of the full "
                        "cube covariance")
    g = p.add_argument_group("campaign datasets (RAW is a dataset directory)")
    from slicersim.app.campaign_cli import add_cluster_arguments
    add_cluster_arguments(g, "existing Dask scheduler, e.g. tls://host:8786 with the --tls-* files (every worker "
                          "must see both directories; tcp:// only on a trusted network)")
    g.add_argument("--retry-failed", action="store_true", help="reduce the targets recorded as failed again")
    g.add_argument("--force", action="store_true", help="start again in a reduction directory made with other "
                   "options or from another dataset")
    g.add_argument("--verify", action="store_true", help="check the checksum of every reduced product when "
                   "resuming (default: sizes)")
    g.add_argument("--show", type=int, default=5, metavar="N", help="list at most N failed targets")
    p.set_defaults(func=cmd_reduce)
