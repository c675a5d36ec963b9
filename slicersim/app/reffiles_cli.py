"""``slicersim reffiles``: the JWST calibration reference files of the simulated detector."""
from __future__ import annotations

from slicersim import validation

__all__ = ["add_parsers", "cmd_reffiles"]

#: the detector flags shared with ``slicersim ramp`` (dest → unit)
_DETECTOR_FLAGS = {"tframe": "s", "ron": "electron", "dark": "e-/s", "roic_glow": "e-/frame", "gain": "ADU/e-"}


def add_parsers(sub, fmt, detector_defaults, ramp_effects):
    """Add the ``reffiles`` sub-command to ``sub`` (argparse sub-parsers): ``detector_defaults`` the
    ``ramp --rate`` detector ({tframe, ron, dark, roic_glow, gain}), ``ramp_effects(args)`` the
    DetectorEffects of --effects / --effects-config (as ``ramp`` reads them)."""
    d = dict(detector_defaults)
    p = sub.add_parser("reffiles", help="JWST reference files (gain, read noise, saturation, ...) of the detector",
                       description="The JWST calibration reference files of the simulated detector, as stcal and the "
                                   "jwst pipeline read them (stdatamodels formats): gain [e-/DN], readnoise [CDS DN], "
                                   "saturation [DN], superbias [DN], linearity, dark [DN per frame], mask, ipc; "
                                   "named slicersim_<detector>_<type>.fits.  They match ramps of the same detector "
                                   "parameters, effects, seed and size (--ramps FILE: those a ramp file records).",
                       **fmt)
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (made if missing)")
    p.add_argument("--ramps", metavar="FILE", help="a slicersim ramp file (HDF5 or level-1b FITS): the reference "
                   "files of its recorded parameters, effects, seed and size (no other detector flag then)")
    p.add_argument("--config", action="append", metavar="cbe|eol|PATH",
                   help="instrument configuration whose detector is described (as ramp --redshift uses it); "
                        "repeat to apply several in order (default: the ramp command's --rate detector)")
    p.add_argument("--field", choices=("narrow", "wide"), help="field of view, with --config (default: narrow)")
    p.add_argument("--shape", type=int, nargs=2, metavar=("NY", "NX"),
                   help="image size [px] of the ramps (default: the configuration's detector, 4096 4096)")
    p.add_argument("--seed", type=int, help="the ramps' seed: their per-pixel maps (bad pixels, nonlinearity, "
                   "bias) are drawn from it (required unless --ramps)")
    words = {"tframe": "frame time", "ron": "read noise per frame", "dark": "dark current", "roic_glow": "ROIC glow",
             "gain": "gain"}
    for key, unit in _DETECTOR_FLAGS.items():
        p.add_argument(f"--{key.replace('_', '-')}", type=float,
                       help=f"{words[key]} [{unit}] of the ramps (default: {d[key]}; with --config: the "
                            "configuration's)")
    p.add_argument("--effects", metavar="NAME[,NAME...]", help="the ramps' detector effects, as ramp --effects "
                   "(e.g. the preset 'lazuli'); ipc, nonlinearity, reference_pixels and bad_pixels enter the files")
    p.add_argument("--effects-config", metavar="FILE", help="TOML or JSON file with an [effects] section, as ramp "
                   "--effects-config")
    p.add_argument("--detector", default="lazuli", metavar="LABEL", help="detector label in the file names")
    p.add_argument("--dark-frames", type=int, default=4, metavar="N",
                   help="frames of the dark reference ramp (stcal extends it linearly to longer ramps)")
    p.add_argument("--overwrite", action="store_true", help="replace existing reference files")
    p.set_defaults(func=cmd_reffiles, previous_charge=None, cr_rate=None, detector_defaults=d,
                   ramp_effects=ramp_effects)


def _parameters(args):
    """(RampParameters, shape) of the detector the flags describe."""
    from slicersim.errors import ParameterError
    from slicersim.physics.ramp import RampParameters
    given = {k: getattr(args, k) for k in _DETECTOR_FLAGS if getattr(args, k) is not None}
    for key, value in given.items():
        validation.number(f"--{key.replace('_', '-')} [{_DETECTOR_FLAGS[key]}]", value, low=0.0,
                          low_open=key in ("tframe", "gain"))
    if args.config:
        from slicersim.assembly import build_simulation
        config = args.config[0] if len(args.config) == 1 else list(args.config)
        sim = build_simulation(config, args.field or "narrow")
        det = sim.detector
        values = dict(tframe=det.tframe, ron=det.ron, dark=det.dark, roic_glow=det.roic_glow, gain=det.gain,
                      thermal_dark=sim.thermal_dark, saturation=min(det.saturation, 65535.0))
        shape = det.shape
    else:
        if args.field is not None:
            raise ParameterError("--field applies only with --config")
        values, shape = dict(args.detector_defaults), None
    values.update(given)
    if args.shape is not None:
        shape = validation.shape("--shape", tuple(args.shape))
    if shape is None:
        raise ParameterError("--shape NY NX is needed without --config (the image size of the ramps)")
    return RampParameters(nmd=(2, 1, 0), **values), shape


def cmd_reffiles(args) -> int:
    """Write the reference files (one line per error, exit 2)."""
    from slicersim.errors import ParameterError
    from slicersim.products import reference
    validation.integer("--dark-frames", args.dark_frames, low=2, high=1 << 16)
    if args.ramps is not None:
        others = [f"--{k.replace('_', '-')}" for k in ("config", "field", "shape", "seed", "effects", "effects_config",
                                                      *_DETECTOR_FLAGS) if getattr(args, k) is not None]
        if others:
            raise ParameterError(f"--ramps takes the detector from the ramp file: drop {', '.join(others)}")
        paths = reference.write_reference_files_for_ramps(args.ramps, args.out, detector=args.detector,
                                                          overwrite=args.overwrite, dark_frames=args.dark_frames)
    else:
        if args.seed is None:
            raise ParameterError("--seed is needed: the seed of the ramps, whose per-pixel maps are drawn from it "
                                 "(or --ramps FILE)")
        seed = validation.seed(args.seed, name="--seed")
        effects = args.ramp_effects(args)
        p, shape = _parameters(args)
        paths = reference.write_reference_files(args.out, p, effects, seed, shape, detector=args.detector,
                                                overwrite=args.overwrite, dark_frames=args.dark_frames)
    for kind, path in paths.items():
        print(f"wrote {path} ({kind})")
    return 0

