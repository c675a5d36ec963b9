"""``slicersim reduce``: raw ramps (our HDF5 or a JWST level-1b FITS) → rates, with variance and DQ.

The heavy part is :func:`slicersim.reduction.ramp_fit.fit_ramps`; this module only maps the
command-line flags onto it (validated before any data are read) and writes the product atomically.
"""
from __future__ import annotations

import os

__all__ = ["add_parsers", "cmd_reduce"]


def _check_out(path, overwrite):
    from slicersim.errors import ParameterError
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise ParameterError(f"--out: directory {directory} does not exist")
    if os.path.lexists(path) and not overwrite:
        raise ParameterError(f"--out: {path} exists (pass --overwrite to replace it)")


def cmd_reduce(args) -> int:
    from slicersim.errors import ParameterError
    from slicersim.reduction.ramp_fit import fit_ramps
    if not os.path.isfile(args.raw):
        raise ParameterError(f"{args.raw}: no such ramp file")
    _check_out(args.out, args.overwrite)
    if args.jump_threshold is not None and not args.jump_threshold >= 0:
        raise ParameterError(f"--jump-threshold must be ≥ 0 (0: no jump detection), got {args.jump_threshold}")
    product = fit_ramps(args.raw, refpix=False if args.no_refpix else None,
                        linearity=False if args.no_linearity else None, jump_threshold=args.jump_threshold,
                        weighting=args.weighting, gain=args.gain, read_noise=args.read_noise,
                        with_truth=args.with_truth, progress=not args.quiet and None)
    path = product.write(args.out, overwrite=args.overwrite)
    rate = product.rate
    print(f"{path}: rates {rate.shape[-2]}×{rate.shape[-1]} of {rate.shape[0] if rate.ndim == 3 else 1} "
          f"integration(s), {int((product.njumps > 0).sum())} pixel(s) with jumps")
    return 0


def add_parsers(sub, fmt):
    """Add ``reduce`` to the ``slicersim`` subcommands."""
    from slicersim.reduction.ramp_fit import DEFAULT_JUMP_THRESHOLD, WEIGHTINGS
    p = sub.add_parser("reduce", help="raw ramps → rates [e-/s] with variance, DQ and jumps",
                       description="Up-the-ramp fit of a raw ramp file (slicersim HDF5 or JWST level-1b FITS): "
                                   "bias, reference-pixel and nonlinearity corrections when the file carries "
                                   "those effects, saturation, jump detection, GLS or OLS slopes.", **fmt)
    p.add_argument("raw", metavar="RAW", help="ramp file (.h5 from `slicersim ramp`, or a level-1b .fits)")
    p.add_argument("--out", required=True, metavar="RATES.h5", help="output HDF5 file (RATE, VAR, DQ, NJUMPS, ...)")
    p.add_argument("--weighting", choices=WEIGHTINGS, default="gls",
                   help="gls: exact MACC covariance (lowest variance); ols: unweighted (Rauscher07 variance)")
    p.add_argument("--jump-threshold", type=float, default=DEFAULT_JUMP_THRESHOLD, metavar="SIGMA",
                   help="two-point-difference jump test [σ]; 0: no detection")
    p.add_argument("--no-refpix", action="store_true", help="skip the reference-pixel correction")
    p.add_argument("--no-linearity", action="store_true", help="skip the nonlinearity correction")
    p.add_argument("--gain", type=float, metavar="DN/e-", help="override the file's GAIN")
    p.add_argument("--read-noise", type=float, metavar="e-", help="override the file's read noise per frame")
    p.add_argument("--with-truth", action="store_true", help="copy truth/rate beside the fitted rates")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    p.set_defaults(func=cmd_reduce)
