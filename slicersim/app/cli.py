"""Command-line interface: ``slicersim {info,demo,etc,ramp,survey,campaign,footprints,plot}`` (also
``python -m slicersim``).

User errors (a :class:`~slicersim.errors.SlicersimError`: bad values, impossible requests,
unreadable input files, unwritable or existing outputs; an ``OSError``; out of memory, of the host
or of the OpenCL device, with what was being allocated and the option that bounds memory; Ctrl-C)
are reported as one line ``slicersim: error: ...`` on stderr with exit status 2.  Set
``SLICERSIM_DEBUG=1`` to get the full traceback instead.  Anything else is a defect of slicersim:
its traceback is printed with a "please report" line, exit status 3.
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import sys
from importlib import metadata

from slicersim import validation
from slicersim.app import etc_cli
from slicersim.physics.conventions import CONVENTIONS, DEFAULT_CONVENTIONS


def _version(dist: str) -> str:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        if dist == "slicersim":
            from slicersim.versioning import __version__
            return __version__
        return "not installed"


def _fmt_bytes(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024


def cmd_info(args) -> int:
    from slicersim.backends import opencl

    print(f"slicersim {_version('slicersim')}")
    print(f"python    {platform.python_version()} ({sys.executable})")
    print(f"numpy     {_version('numpy')}")
    print(f"pyopencl  {_version('pyopencl')}")
    spec = os.environ.get(opencl.ENV_VAR)
    print(f"{opencl.ENV_VAR}={spec!r}" if spec is not None else f"{opencl.ENV_VAR} not set (default: first GPU, else first CPU)")
    try:
        devices = opencl.device_info()
    except (opencl.OpenCLUnavailableError, opencl.OpenCLForkError) as exc:
        print(f"OpenCL: unavailable -- {exc}")
        print("Computations will use the NumPy fallbacks.")
        return 0
    print("OpenCL devices (* = selected):")
    for d in devices:
        mark = "*" if d["selected"] else " "
        print(f" {mark} [{d['index']}] {d['name']}  ({d['type']}, {d['vendor']})")
        print(f"       platform: {d['platform']} / {d['platform_version']}")
        print(f"       version: {d['version']}, driver {d['driver_version']}")
        print(f"       compute units: {d['compute_units']}, global memory: {_fmt_bytes(d['global_mem'])}, "
              f"max work-group size: {d['max_work_group_size']}, fp64: {'yes' if d['fp64'] else 'NO'}")
    if not any(d["selected"] for d in devices):
        try:
            opencl.select_device()
        except opencl.OpenCLUnavailableError as exc:
            print(f"No device selected: {exc}")
            print("Computations will use the NumPy fallbacks.")
    return 0


def cmd_demo(args) -> int:
    from slicersim.app.demo import run_demo

    run_demo(args.outdir, **({"overwrite": True} if args.overwrite else {}))
    return 0


def _read_spectrum(path):
    """Two-column text/CSV file: wavelength [Angstrom], flux [erg/s/cm2/Angstrom].

    Lines before the first numeric row are a header; after it, a row that is not two numbers (or
    has more fields, as decimal commas give) is an error naming the file and the line
    (SpectrumError), as are a wavelength not above the previous row's (rows out of order, a
    duplicate: never sorted or dropped) and a file that is not UTF-8 text
    (e.g. a binary or .npy file given by mistake)."""
    import numpy as np

    from slicersim.errors import SpectrumError
    path = validation.regular_file("--spectrum", path, error=SpectrumError)
    with open(path, "rb") as fh:
        raw = fh.read()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SpectrumError(f"--spectrum: {path} is not a text file (byte {exc.start} is not UTF-8); "
                            "give a two-column text/CSV file: wavelength [Angstrom], flux") from None
    lbda, flux, lines, skipped = [], [], [], []
    for number, line in enumerate(text.splitlines(), start=1):
        fields = [f.strip("\"'") for f in line.split("#", 1)[0].replace(",", " ").replace(";", " ").split()]
        if not fields:                  # quoted CSV numbers ("4000","1e-17") are numbers
            continue
        if len(fields) > 2 and _two_numbers(fields) is not None:
            raise SpectrumError(f"--spectrum: {path}, line {number}: {len(fields)} fields "
                                f"{validation.short_repr(line.strip())}, expected two numbers 'wavelength flux' "
                                "(decimal commas? write numbers with a decimal point)")
        row = _two_numbers(fields)
        if row is None:
            if not lbda:
                skipped.append((number, line.strip()))
                continue                # header
            raise SpectrumError(f"--spectrum: {path}, line {number}: expected two numbers 'wavelength flux', "
                                f"got {validation.short_repr(line.strip())}")
        lbda.append(row[0])
        flux.append(row[1])
        lines.append(number)
    if len(lbda) < 2:
        where = f"; line {skipped[-1][0]} {validation.short_repr(skipped[-1][1])} is not two numbers" if skipped else ""
        raise SpectrumError(f"--spectrum: {path}: need at least two rows of two numbers 'wavelength flux', found "
                            f"{len(lbda)}{where}")
    from slicersim.io.tables import check_increasing
    check_increasing(lbda, f"--spectrum: {path}", error=SpectrumError, lines=lines)
    from slicersim.sources.spectra import validate_spectrum
    return validate_spectrum(np.asarray(lbda), np.asarray(flux), name=f"--spectrum {path}")


def _two_numbers(fields):
    """(x, y) from the first two fields of a row, or None when they are not two numbers."""
    try:
        return float(fields[0]), float(fields[1])
    except (ValueError, IndexError):
        return None


def _fmt_value(v) -> str:
    try:
        import numpy as np
        if isinstance(v, np.ndarray):
            if v.size <= 8:
                return np.array2string(v, precision=4, separator=", ")
            return f"array(shape={v.shape}, min={np.nanmin(v):.4g}, max={np.nanmax(v):.4g})"
        if isinstance(v, np.generic):
            v = v.item()
    except ImportError:  # pragma: no cover
        pass
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, (list, tuple)) and len(v) <= 8:
        return "[" + ", ".join(_fmt_value(x) for x in v) + "]"
    return str(v)


#: units (or meaning) printed after the keys of the ETC result
ETC_UNITS = {"nmd": "(groups, frames/group, dropped)", "nramps": "(ramps)", "exposure_time": "[s]",
             "snr": "(per resolution element)", "snr_per_bin": "(per bin)",
             "snr_target_per_bin": "(per bin)", "lbda_range_obs": "[Angstrom]", "data_volume": "[GB]"}


def _print_result(result, indent=0, units=None) -> None:
    if not isinstance(result, dict):
        print(" " * indent + _fmt_value(result))
        return
    units = units or {}
    result = {(f"{k} {units[k]}" if k in units else k): v for k, v in result.items()}
    width = max((len(str(k)) for k in result), default=0)
    for key, value in result.items():
        if isinstance(value, dict):
            print(" " * indent + f"{key}:")
            _print_result(value, indent + 2)
        else:
            print(" " * indent + f"{str(key):<{width}} : {_fmt_value(value)}")


def cmd_etc(args) -> int:
    from slicersim import targets

    etc_cli.check_etc_flags(args)
    if args.catalog is not None:
        return etc_cli.cmd_etc_catalog(args)
    kwargs = {"snr": args.snr}
    if args.lbda_range is not None:
        kwargs["lbda_range"] = tuple(args.lbda_range)
    if args.config:
        kwargs["config"] = args.config[0] if len(args.config) == 1 else list(args.config)
    if args.field is not None:
        kwargs["field"] = args.field
    if args.search is not None:
        kwargs["search"] = args.search
    if args.allow_partial:
        kwargs["allow_partial"] = True
    kwargs["conventions"] = args.conventions
    if args.redshift is not None:
        validation.redshift("--redshift", args.redshift)
        kwargs["frame"] = args.frame or "rest"
        if args.source is not None:
            kwargs["source"] = args.source
        result = targets.lazuli_sn_etc(args.redshift, **kwargs)
    else:
        if args.frame is not None:
            kwargs["frame"] = args.frame
        lbda, flux = _read_spectrum(args.spectrum)
        result = targets.lazuli_etc(lbda, flux, **kwargs)
    result.pop("target", None)           # the Python object: nothing a user can read
    _print_result(result, units=ETC_UNITS)
    return 0


#: detector flags of ``ramp`` and their defaults with ``--rate`` (with ``--redshift`` the
#: configuration supplies them; given flags override it)
RAMP_DETECTOR_DEFAULTS = {"tframe": 2.83, "ron": 12.0, "dark": 2.8e-3, "roic_glow": 3e-3, "gain": 1.0}
#: readout of ``ramp`` when neither --nmd nor --snr gives one
RAMP_DEFAULT_NMD = (16, 8, 0)


def _check_output(path, overwrite):
    """Refuse a bad output before any (slow) simulation (:func:`slicersim.io.atomic.check_output_path`):
    a directory (or a path ending with '/'), a FIFO, device or socket (never replaced, even with
    --overwrite), an existing file without --overwrite, a missing or read-only directory."""
    from slicersim.errors import RampFileError
    from slicersim.io.atomic import check_output_path
    check_output_path(path, overwrite, RampFileError, "--out")


def _load_rate(path, flag):
    """An image from a .npy file (NumPy's format) or a text file of numbers, as a float64 array;
    ParameterError naming the flag and the file when it is neither (a text file named .npy, a binary file
    given as text, a non-numeric entry) or when its .npy header declares more data than it holds."""
    import numpy as np

    from slicersim.errors import ParameterError
    from slicersim.io.npy import load_npy
    path = validation.regular_file(flag, path)
    if path.endswith(".npy"):
        try:
            rate = load_npy(flag, path)
        except ParameterError:
            raise
        except ValueError:       # NumPy's "pickled data" message: not an .npy file (text, or object array)
            raise ParameterError(f"{flag}: {path}: not a NumPy .npy file of numbers (a text image must not be named "
                                 ".npy)") from None
        if not isinstance(rate, np.ndarray):
            raise ParameterError(f"{flag}: {path}: an .npz archive, not a single .npy image")
    else:
        try:
            rate = np.loadtxt(path, ndmin=2)
        except UnicodeDecodeError:
            raise ParameterError(f"{flag}: {path}: not a text file of numbers (save a binary image with numpy.save "
                                 "and name it .npy)") from None
        except ValueError as exc:
            raise ParameterError(f"{flag}: {path}: cannot read a text image of numbers: {_one_line(exc)}") from None
    return validation.array(f"{flag}: {path}", rate, finite=False)


def _ramp_effects(args):
    """DetectorEffects from --effects, --effects-config and --cr-rate (None: no effect)."""
    if args.effects is None and args.effects_config is None and args.cr_rate is None:
        return None
    from slicersim.errors import EffectsError
    from slicersim.physics.effects import DetectorEffects
    effects = None
    prev = args.previous_charge is not None          # "all" and the presets then include persistence
    if args.effects_config is not None:
        effects = DetectorEffects.from_file(args.effects_config, has_previous_charge=prev, name="--effects-config")
    if args.effects is not None:
        named = DetectorEffects.from_text(args.effects, prev)
        effects = named if effects is None else effects.restricted_to(named.enabled)
    if args.cr_rate is not None:
        if effects is None or "cosmic_rays" not in effects.enabled:
            raise EffectsError("--cr-rate needs cosmic_rays in --effects (or in --effects-config)")
        with validation.flag_names({"cosmic_rays.rate [cm⁻² s⁻¹]": "--cr-rate [cm⁻² s⁻¹]"}):
            effects = effects.with_overrides(cr_rate=args.cr_rate)
    return effects


#: physical range of the ramp command's detector options: (low, high, unit) (the same bounds as a
#: raw file's keywords, :data:`slicersim.reduction.checks.ATTR_RANGES`)
RAMP_DETECTOR_RANGES = {"tframe": (1e-6, 1e4, "s"), "ron": (0.0, 1e4, "electron"), "dark": (0.0, 1e6, "e-/s"),
                        "roic_glow": (0.0, 1e6, "e-/frame"), "gain": (1e-3, 1e3, "ADU/e-")}
#: the 16-bit ADC's range [ADU]: a read noise above 1/8 of it would fill the file with 0 and 65535
ADC_MAX = 65535


def _check_ramp_detector(args):
    """The readout (--nmd, :func:`~slicersim.validation.readout`'s bounds) and the detector options
    in their physical range (ParameterError naming the flag); a read noise that alone would
    saturate the ADC (--ron × --gain > ADC_MAX / 8) is refused."""
    from slicersim.errors import ParameterError
    nmd = validation.readout(tuple(args.nmd if args.nmd is not None else RAMP_DEFAULT_NMD), name="--nmd",
                             error=ParameterError)
    for key, (low, high, unit) in RAMP_DETECTOR_RANGES.items():
        value = getattr(args, key, None)
        if value is not None:
            validation.number(f"--{key.replace('_', '-')} [{unit}]", value, low=low, high=high)
    if args.ron is not None:
        gain = args.gain if args.gain is not None else RAMP_DETECTOR_DEFAULTS["gain"]
        if args.ron * gain > ADC_MAX / 8:
            raise ParameterError(f"--ron {args.ron:g} electron × gain {gain:g} ADU/e- = {args.ron * gain:.3g} ADU of read "
                                 f"noise per frame: more than 1/8 of the 16-bit ADC range ({ADC_MAX} ADU), the "
                                 "ramps would be 0 and 65535 only")
    return nmd


#: what bounds the memory of each command, named in an out-of-memory error
MEMORY_HINTS = {
    "ramp": "lower --max-bytes (the row blocks in flight) or give a smaller --rate image",
    "reduce": "lower --max-bytes (the row blocks in flight); the rate images of the whole detector are held in "
              "memory",
    "campaign": "lower --memory-per-task (the chunks of one task) or use fewer --workers",
    "survey": "plan fewer targets at once (--n)",
}


def cmd_ramp(args) -> int:
    from slicersim.products import ramps
    if args.redshift is not None:
        validation.redshift("--redshift", args.redshift)
    sn_flags = etc_cli.check_ramp_target_flags(args)        # --snr with --nmd, --phase out of range, ...
    nmd = _check_ramp_detector(args)
    nramps = 1 if args.nramps is None else args.nramps
    if args.max_bytes is not None:
        validation.integer("--max-bytes", args.max_bytes, low=1)
    effects = _ramp_effects(args)              # bad names or values: one line, before anything runs
    _check_output(args.out, args.overwrite)
    seed = validation.new_seed() if args.seed is None else args.seed       # printed and recorded (SEED)
    common = dict(seed=seed, out=args.out, compression=args.compression, progress=None,
                  backend=args.backend, overwrite=args.overwrite, effects=effects, file_format=args.format,
                  precision=args.precision)
    if args.max_bytes is not None:
        common["max_bytes"] = args.max_bytes
    for key in ("groupdq", "window"):
        if getattr(args, key) is not None:
            common[key] = getattr(args, key)
    if args.previous_charge is not None:
        common["previous_charge"] = _load_rate(args.previous_charge, "--previous-charge")
    detector = {k: getattr(args, k) for k in RAMP_DETECTOR_DEFAULTS if getattr(args, k) is not None}
    if args.rate is not None:
        given = [f"--{k}" for k in ("config", "field", "conventions") if getattr(args, k) is not None] + sn_flags
        if given:
            from slicersim.errors import ParameterError
            raise ParameterError(f"{' and '.join(given)} {'apply' if len(given) > 1 else 'applies'} only with --redshift "
                                 "(with --rate the detector is set by --tframe/--ron/--dark/--roic-glow/--gain)")
        rate = _load_rate(args.rate, "--rate")
        from slicersim.physics.ramp import RampParameters, check_frame_charge
        check_frame_charge(rate, RampParameters(nmd=nmd, **(RAMP_DETECTOR_DEFAULTS | detector)),
                           {"rate": "--rate image", "dark": "--dark", "roic_glow": "--roic-glow"})
        path = ramps.simulate(rate, nmd, nramps, **(RAMP_DETECTOR_DEFAULTS | detector), **common)
    else:
        config = (args.config[0] if len(args.config) == 1 else list(args.config)) if args.config else "cbe"
        target, etc_nmd, etc_nramps = etc_cli.ramp_supernova(args, config, args.field or "narrow",
                                                             args.conventions or DEFAULT_CONVENTIONS)
        if etc_nmd is not None:
            nmd, nramps = etc_nmd, etc_nramps
        path = target.get_ramps(nmd=nmd, nramps=nramps, **detector, **common)
    print(f"wrote {path} (seed {seed})")            # --seed SEED repeats the run
    return 0


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows ``(default: ...)`` for every option that has a default (not for None)."""

    def _get_help_string(self, action):
        if action.default is None or action.default is False:
            return action.help
        return super()._get_help_string(action)


class _Parser(argparse.ArgumentParser):
    """Usage errors as one line ``slicersim: error: ...`` (exit 2), like every other user error.
    ``-1e300``, ``-.5``, ``-inf`` and ``-29.4,0`` are values, not options (argparse took ``--lbda-range -1e300
    1e300`` or ``--position -29.4,0`` for a flag and said "expected 2 arguments" / "expected one argument")."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        number = r"(?:(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|inf|infinity|nan)"
        # also a pair such as --position -29.4,0 (X,Y) or -1,-2
        self._negative_number_matcher = re.compile(rf"^-{number}(?:,\s*[-+]?{number})*$", re.IGNORECASE)

    def error(self, message):
        hint = f" (see '{self.prog} --help')"
        self.exit(2, f"slicersim: error: {_one_line(message)}{hint}\n")


def _one_line(text) -> str:
    return " ".join(str(text).split())


def build_parser() -> argparse.ArgumentParser:
    fmt = dict(formatter_class=_HelpFormatter)
    parser = _Parser(prog="slicersim", description="Image-slicer IFS simulator.", **fmt)
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version('slicersim')}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True, parser_class=_Parser)

    p = sub.add_parser("info", help="versions and OpenCL platforms/devices",
                       description="Versions and OpenCL platforms/devices.", **fmt)
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("demo", help="run the demonstration simulation",
                       description="Demonstration: ETC of a z = 1 SN Ia, figures, a raw ramp of the ETC's readout around the source.", **fmt)
    p.add_argument("--outdir", default="demo_output", metavar="DIR", help="output directory")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("etc", help="exposure-time calculator",
                       description="Exposure time to reach a SNR with the Lazuli IFS.", **fmt)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--redshift", type=float, metavar="Z", help="SN Ia at redshift Z")
    src.add_argument("--spectrum", metavar="FILE",
                     help="two-column text/CSV: wavelength [Angstrom], flux [erg/s/cm^2/Angstrom]")
    etc_cli.add_etc_arguments(p, src)
    p.add_argument("--snr", type=float, default=20.0, help="target signal-to-noise ratio per resolution element")
    p.add_argument("--lbda-range", type=float, nargs=2, metavar=("LO", "HI"),
                   help="wavelength range [Angstrom] (default: 4000 6800)")
    p.add_argument("--frame", choices=("obs", "rest"),
                   help="frame of --lbda-range (default: rest with --redshift and --catalog, obs with --spectrum)")
    p.add_argument("--config", action="append", metavar="cbe|eol|PATH",
                   help="instrument configuration; repeat to apply several in order (default: cbe)")
    p.add_argument("--field", choices=("narrow", "wide"), help="field of view (default: narrow)")
    p.add_argument("--search", choices=("exact", "reference"), help="readout search strategy (default: exact)")
    p.add_argument("--conventions", choices=CONVENTIONS, default=DEFAULT_CONVENTIONS,
                   help="physical model, or every slicersim 1.0 behaviour (gain in the variance, blur)")
    p.add_argument("--allow-partial", action="store_true",
                   help="accept a band partly outside the instrument grid or the spectrum (warns; the SNR "
                        "is that of the covered part; at least half the band must lie in the grid; default: refuse)")
    p.set_defaults(func=cmd_etc)

    d = RAMP_DETECTOR_DEFAULTS
    from_config = "with --redshift: the configuration's"
    p = sub.add_parser("ramp", help="raw up-the-ramp H4RG reads to a group-level HDF5 file",
                       description="Raw up-the-ramp H4RG reads to a group-level HDF5 file.", **fmt)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--redshift", type=float, metavar="Z", help="full detector image of a SN Ia at Z")
    src.add_argument("--rate", metavar="FILE", help="rate image [e-/s] (.npy or text)")
    p.add_argument("--nmd", type=int, nargs=3, metavar=("N", "M", "D"),
                   help=f"MACC readout: groups, frames per group, dropped frames (default: {RAMP_DEFAULT_NMD}); "
                        "with --snr: the ETC's")
    p.add_argument("--nramps", type=int, help="ramps between resets (default: 1); with --snr: the ETC's")
    etc_cli.add_ramp_target_arguments(p)
    p.add_argument("--seed", type=int, default=None,
                   help="noise seed, an integer in [0, 2**64) (default: a fresh seed, printed and recorded in the "
                        "file's SEED attribute: pass it again to repeat the run)")
    p.add_argument("--out", required=True, metavar="FILE", help="output file (HDF5, or JWST uncal FITS with "
                   "--format jwst-uncal)")
    p.add_argument("--format", choices=("hdf5", "jwst-uncal"),
                   help="output format (default: jwst-uncal for a .fits name, else hdf5)")
    p.add_argument("--groupdq", choices=("none", "observed", "truth"),
                   help="GROUPDQ of a jwst-uncal file: none (as flight level-1b files), observed (SATURATED "
                        "where the observed DN reaches the saturation level) or truth (the simulator's flags "
                        "from the true charge) (default: none; HDF5 files keep the simulator's flags)")
    p.add_argument("--window", type=int, nargs=4, metavar=("X0", "Y0", "NX", "NY"),
                   help="simulate and write only this window of the detector (first pixel X0 Y0, 0-based; "
                        "SUBSTRT1/2 = X0+1, Y0+1), read on the full detector's outputs and pixel clock: "
                        "the same pixels as a full-detector ramp of the same seed")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.add_argument("--compression", choices=("gzip", "lz4", "zstd", "bitshuffle-lz4"),
                   help="HDF5 compression (default: none)")
    p.add_argument("--config", action="append", metavar="cbe|eol|PATH", help="instrument configuration, only with "
                   "--redshift; repeat to apply several in order (default: cbe)")
    p.add_argument("--field", choices=("narrow", "wide"), help="field of view, only with --redshift "
                   "(default: narrow)")
    p.add_argument("--tframe", type=float, help=f"frame time [s] (default: {d['tframe']}; {from_config})")
    p.add_argument("--ron", type=float, help=f"read noise per frame [electron] (default: {d['ron']}; {from_config})")
    p.add_argument("--dark", type=float, help=f"dark current [e-/s] (default: {d['dark']}; {from_config})")
    p.add_argument("--roic-glow", type=float,
                   help=f"ROIC glow [e-/frame] (default: {d['roic_glow']}; {from_config})")
    p.add_argument("--gain", type=float, help=f"gain [ADU/e-] (default: {d['gain']}; {from_config})")
    p.add_argument("--conventions", choices=CONVENTIONS,
                   help=f"model conventions of the scene, only with --redshift (default: {DEFAULT_CONVENTIONS})")
    p.add_argument("--backend", choices=("auto", "opencl", "numpy"), default="auto", help="compute backend")
    p.add_argument("--max-bytes", type=int, metavar="BYTES", help="memory budget of the row blocks of ramps in "
                   "flight [bytes] (default: 536870912 = 512 MiB; lower it when memory runs out)")
    p.add_argument("--precision", choices=("auto", "double", "single"), default="auto",
                   help="floating type of the ramp samplers (auto: single only on a device without fast fp64; "
                        "single is not bit-identical to double: ~1e-3 of the values differ by 1 ADU, same "
                        "statistics)")
    p.add_argument("--effects", metavar="NAME[,NAME...]",
                   help="detector systematics (off by default): cosmic_rays, ipc, nonlinearity, correlated_noise, "
                        "reference_pixels, bad_pixels, persistence, all, or the preset 'lazuli'; parameters from "
                        "--effects-config.  'all' (and 'lazuli') = cosmic_rays, ipc, nonlinearity, correlated_noise, "
                        "reference_pixels, bad_pixels, plus persistence only when --previous-charge is given "
                        "(persistence needs the previous exposure's charge)")
    p.add_argument("--effects-config", metavar="FILE", help="TOML or JSON file with an [effects] section: "
                   "enabled = [...] and one table per effect (every parameter; see the README)")
    p.add_argument("--previous-charge", metavar="FILE",
                   help="charge image [e-] of the previous exposure (.npy or text), for the persistence effect")
    p.add_argument("--cr-rate", type=float, metavar="RATE",
                   help="cosmic-ray rate [cm^-2 s^-1] (default 5, the L2 value used for JWST)")
    p.set_defaults(func=cmd_ramp)

    from slicersim.app.campaign_cli import add_parsers
    add_parsers(sub, fmt)
    from slicersim.app import pictures_cli
    pictures_cli.add_parsers(sub, fmt)
    from slicersim.app import reduce_cli
    reduce_cli.add_parsers(sub, fmt)
    from slicersim.app import stress_cli
    stress_cli.add_parsers(sub, fmt)
    from slicersim.app import reffiles_cli
    reffiles_cli.add_parsers(sub, fmt, RAMP_DETECTOR_DEFAULTS, _ramp_effects)
    return parser


def _user_errors():
    """What the user can cause and act on: slicersim's own errors, the file system's, memory, ^C.
    Anything else is a defect of slicersim and is printed as an internal error (traceback kept)."""
    from slicersim.errors import SlicersimError
    return (SlicersimError, OSError, MemoryError, KeyboardInterrupt)


#: where internal errors are reported
ISSUE_TRACKER = "the slicersim issue tracker"


_PYTHON_FORMATWARNING = __import__("warnings").formatwarning


def _format_warning(message, category, filename, lineno, line=None):
    """Warnings as one line ``slicersim: warning: ...`` (no source file and code line)."""
    return f"slicersim: warning: {_one_line(message)}\n"


def _command_flags(parser, args):
    """{dest: --flag} of the (sub)command of ``parser`` that ``args`` runs, so that a message about a
    parameter names the flag the user typed (:func:`slicersim.validation.flag_names`)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction) and getattr(args, action.dest, None) in action.choices:
            return _command_flags(action.choices[getattr(args, action.dest)], args)
    return {a.dest: next((o for o in a.option_strings if o.startswith("--")), a.option_strings[0])
            for a in parser._actions if a.option_strings and a.dest not in ("help", "version")}


#: OpenCL status codes of a device or host out of memory (MEM_OBJECT_ALLOCATION_FAILURE,
#: OUT_OF_RESOURCES, OUT_OF_HOST_MEMORY, INVALID_BUFFER_SIZE)
_CL_MEMORY_CODES = (-4, -5, -6, -61)


def _out_of_memory(exc) -> str | None:
    """"host" or "OpenCL device" when ``exc`` says memory ran out (Python's MemoryError, NumPy's,
    pyopencl's MemoryError or a memory status code), else None."""
    if isinstance(exc, MemoryError):
        return "host"
    cl = sys.modules.get("pyopencl")
    if cl is not None and isinstance(exc, getattr(cl, "Error", ())):
        try:
            code = exc.code
        except Exception:                 # an Error without a routine/code: not ours to read
            code = None
        if isinstance(exc, getattr(cl, "MemoryError", ())) or code in _CL_MEMORY_CODES:
            return "OpenCL device"
    return None


def _memory_message(exc, where, command) -> str:
    """One line for running out of memory: where, what was being allocated, what bounds memory."""
    from slicersim.errors import SlicersimError
    hint = MEMORY_HINTS.get(command, "free memory or use a smaller input")
    text = _one_line(exc)
    if isinstance(exc, SlicersimError):           # a ResourceError: says what already, with the API's names
        return text.replace("max_bytes", "--max-bytes") if command in ("ramp", "reduce") else text
    return f"out of memory ({where}){': ' + text if text else ''}; {hint}"


def _tolerant_streams():
    """stdout / stderr that cannot fail on a character their encoding lacks: under ``LC_ALL=C`` without
    Python's UTF-8 mode they are ASCII, and "≥", "σ" or "…" in a result line raised UnicodeEncodeError
    after the work was done.  Such characters are written as backslash escapes instead."""
    for stream in (sys.stdout, sys.stderr):
        encoding = (getattr(stream, "encoding", None) or "").lower().replace("-", "")
        if encoding != "utf8" and hasattr(stream, "reconfigure"):
            try:
                stream.reconfigure(errors="backslashreplace")
            except (ValueError, OSError):   # a closed or foreign stream: leave it as it is
                pass


def main(argv=None) -> int:
    import warnings
    if argv is None:                      # the command itself (not a caller's main([...])): a short-lived process
        from slicersim.app.allocator import keep_freed_memory, no_huge_page_stalls
        keep_freed_memory()
        no_huge_page_stalls()
    _tolerant_streams()
    parser = build_parser()
    args = parser.parse_args(argv)
    # one line per warning where Python would print it (recorders such as catch_warnings(record=True)
    # still get the warning objects), unless an application already formats them its own way
    ours = warnings.formatwarning is _PYTHON_FORMATWARNING
    if ours:
        warnings.formatwarning = _format_warning
    try:
        with validation.flag_names(_command_flags(parser, args)):
            return int(args.func(args) or 0)
    except BrokenPipeError:  # e.g. `slicersim info | head`
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except _user_errors() as exc:
        if os.environ.get("SLICERSIM_DEBUG", "") not in ("", "0"):
            raise
        if isinstance(exc, KeyboardInterrupt):
            message = "interrupted"
        elif isinstance(exc, MemoryError):
            message = _memory_message(exc, "host", getattr(args, "command", None))
        elif isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
            message = f"{exc.filename}: {exc.strerror}"
        else:
            message = str(exc) or type(exc).__name__
        sys.stdout.flush()
        print(f"slicersim: error: {_one_line(message)}", file=sys.stderr)
        return 2
    except Exception as exc:  # a defect, not a user error: keep the traceback
        where = _out_of_memory(exc)
        if where is not None and os.environ.get("SLICERSIM_DEBUG", "") in ("", "0"):
            sys.stdout.flush()
            print(f"slicersim: error: {_memory_message(exc, where, getattr(args, 'command', None))}",
                  file=sys.stderr)
            return 2
        import traceback
        sys.stdout.flush()
        traceback.print_exc()
        print(f"slicersim: internal error ({type(exc).__name__}): {_one_line(str(exc))} -- this is a bug in "
              f"slicersim, please report it with the command and the traceback above to {ISSUE_TRACKER}",
              file=sys.stderr)
        return 3
    finally:
        if ours:
            warnings.formatwarning = _PYTHON_FORMATWARNING


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
