"""``slicersim footprints`` and ``slicersim plot {slice-map,fields,psf}`` (registered by :mod:`slicersim.app.cli`)."""
from __future__ import annotations

import os

from slicersim import validation
from slicersim.errors import ConfigError, ParameterError

__all__ = ["add_parsers"]

FIGURE_SUFFIXES = (".png", ".pdf", ".svg")


def _config(args):
    config = getattr(args, "config", None) or ["cbe"]
    return config[0] if len(config) == 1 else list(config)


def _fields(choice):
    return ("narrow", "wide") if choice == "both" else (choice,)


def _check_figure(path, overwrite, flag="--out", created=None):
    """Refuse a bad figure path before anything is computed; its directory may be ``created``
    (the footprints' --out, made when missing)."""
    from slicersim.io.atomic import check_output_path, output_path
    if not path.lower().endswith(FIGURE_SUFFIXES):
        raise ParameterError(f"{flag} must end with {', '.join(FIGURE_SUFFIXES)}, got {path}")
    parent = os.path.dirname(output_path(path, ParameterError, flag))
    if parent == created and not os.path.exists(parent):
        return
    check_output_path(path, overwrite, ParameterError, flag)    # a directory, FIFO, device, existing file


def _mapper(args):
    from slicersim.assembly import default_mapper
    if args.spot_table is None:
        return default_mapper()
    from slicersim.instrument.mapper import SlicerMapper
    validation.regular_file("--spot-table", args.spot_table)   # missing, a directory, FIFO or device
    import warnings
    try:
        with warnings.catch_warnings():           # NumPy's "input contained no data": said below, in one line
            warnings.filterwarnings("ignore", message="loadtxt: input contained no data", category=UserWarning)
            return SlicerMapper.from_table(args.spot_table)
    except ConfigError as exc:                            # the table reader's own: it names the file (and line)
        raise ConfigError(f"--spot-table: {exc}") from None
    except (ValueError, KeyError, IndexError) as exc:     # a parse error
        raise ConfigError(f"--spot-table: {args.spot_table}: not a spot table: {' '.join(str(exc).split())}") \
            from None


def _footprints(args, mapper):
    from slicersim.assembly import build_simulation
    from slicersim.instrument.footprints import field_footprints
    config = _config(args)
    return [field_footprints(mapper, f, spectrograph=build_simulation(config, f).spectrograph,
                             truncate=args.truncate) for f in _fields(args.field)]


def _check_truncate(args):
    """--truncate: finite, in [0, MAX_TRUNCATE] [spot rms]."""
    validation.number("--truncate [spot rms]", args.truncate, low=0.0, high=validation.MAX_TRUNCATE)


def cmd_footprints(args) -> int:
    from slicersim.instrument.footprints import save_footprints
    from slicersim.io.footprint_files import check_outputs, footprint_paths
    _check_truncate(args)
    out = os.path.abspath(args.out)
    if os.path.exists(out) and not os.path.isdir(out):
        raise ParameterError(f"--out must be a directory: {args.out}")
    if not os.path.isdir(os.path.dirname(out)):
        raise ParameterError(f"--out: parent directory {os.path.dirname(out)} does not exist")
    paths = footprint_paths(out, args.name)
    if os.path.isdir(out):
        check_outputs(paths, args.overwrite)
    if args.figure:
        _check_figure(args.figure, args.overwrite, "--figure", created=out)
        if os.path.abspath(args.figure) in map(os.path.abspath, paths):
            raise ParameterError(f"--figure must not be one of the footprint files: {args.figure}")
    mapper = _mapper(args)
    fields = _footprints(args, mapper)
    also, fig = {}, None
    if args.figure:                    # drawn into a temporary, published together with the pair
        from slicersim.app.pictures import figure_writer, show_slice_map
        fig = show_slice_map(footprints=fields)
        path, writer = figure_writer(fig, args.figure, dpi=120, bbox_inches="tight")
        also[path] = writer
    made = not os.path.isdir(out)
    os.makedirs(out, exist_ok=True)
    try:
        written = save_footprints(out, *fields, name=args.name, overwrite=args.overwrite, also=also)
    except BaseException:
        if made:                       # nothing written: leave no empty directory behind
            try:
                os.rmdir(out)
            except OSError:
                pass
        raise
    finally:
        if fig is not None:
            import matplotlib.pyplot as plt
            plt.close(fig)
    for f in fields:
        shared = f.overlaps()
        npix = sum(s.npix for s in f)
        print(f"{f.field}: {len(f)} slices, {npix} px lit, {sum(n for *_, n in shared)} px shared by "
              f"{len(shared)} neighbour pairs (label: nearest slice), "
              f"{f.lbda_edges[0]:.0f}-{f.lbda_edges[-1]:.0f} Angstrom")
    for path in written:
        print(f"wrote {path}")
    return 0


def _target(args, field=None):
    from slicersim.targets import LazuliSupernova
    validation.redshift("--redshift", args.redshift)
    return LazuliSupernova(args.redshift, config=_config(args), field=field or args.field)


def cmd_plot(args) -> int:
    from slicersim.app import pictures
    _check_figure(args.out, args.overwrite)
    if args.figure == "slice-map":
        _check_truncate(args)
        if args.region is not None:
            r0, r1, c0, c1 = args.region
            if not (r0 < r1 and c0 < c1):
                raise ParameterError(f"--region needs ROW0 < ROW1 and COL0 < COL1, got {args.region}")
        mapper = _mapper(args)
        if args.region is not None:
            try:
                pictures.check_region(args.region, mapper.detector_shape)
            except ParameterError as exc:
                raise ParameterError(f"--region: {exc}") from None
        fields = _footprints(args, mapper)
        image = None
        if args.redshift is not None:
            image = _target(args, "narrow" if args.field == "both" else args.field).get_detector_image(mapper)
        pictures.show_slice_map(footprints=fields, image=image, region=args.region, labels=not args.no_labels,
                                savefile=args.out)
    elif args.figure == "fields":
        if args.lbda_range is not None and not args.lbda_range[0] < args.lbda_range[1]:
            raise ParameterError(f"--lbda-range needs LO < HI, got {args.lbda_range}")
        target = _target(args)
        if args.lbda_range is not None:
            pictures.check_wavelengths(target.simulation, args.lbda_range, "--lbda-range")
        validation.seed(args.seed, name="--seed")
        pictures.show_fields(target, lbda_range=args.lbda_range, seed=args.seed, savefile=args.out)
    else:
        target = _target(args)
        pictures.check_wavelengths(target.simulation, args.lbda, "--lbda")
        pictures.show_psf_profiles(target, lbda=args.lbda, savefile=args.out)
    print(f"wrote {args.out}")
    return 0


def add_parsers(sub, fmt):
    """Add ``footprints`` and ``plot`` to the ``slicersim`` subcommands."""
    p = sub.add_parser("footprints", help="slice footprints on the detector for pipelines",
                       description="Slice footprints on the detector, from the optical model (no projection): "
                                   "a FITS label image (slice id per pixel, -1 = no light) and a JSON file of "
                                   "outlines [px], wavelength ranges and traces.", **fmt)
    p.add_argument("--field", choices=("narrow", "wide", "both"), default="both", help="field(s)")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (created if missing)")
    p.add_argument("--name", default="footprints", help="file stem: NAME_labels.fits, NAME_outlines.json")
    p.add_argument("--config", action="append", metavar="cbe|eol|PATH",
                   help="configuration giving the wavelength grid; repeat to layer (default: cbe)")
    p.add_argument("--spot-table", metavar="FILE", help="optical model, spot-table format (default: the built-in "
                   "Lazuli layout)")
    p.add_argument("--truncate", type=float, default=4.0, help="window half-width beyond a cell [spot rms], as "
                   "the projection")
    p.add_argument("--figure", metavar="FILE", help="also draw the slice map (.png, .pdf or .svg)")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")
    p.set_defaults(func=cmd_footprints)

    p = sub.add_parser("plot", help="figures: slice map, both fields, PSF profiles",
                       description="Figures of the instrument (matplotlib, written to a file).", **fmt)
    kinds = p.add_subparsers(dest="figure", metavar="FIGURE", required=True, parser_class=type(p))
    q = kinds.add_parser("slice-map", help="detector with the slice footprints outlined",
                         description="The detector with every slice's footprint outlined and labelled; "
                                     "background: the label image, or with --redshift a SN Ia's detector image.",
                         **fmt)
    q.add_argument("--field", choices=("narrow", "wide", "both"), default="both", help="field(s)")
    q.add_argument("--redshift", type=float, metavar="Z", help="background: detector image [e-/s] of a SN Ia at Z "
                   "in --field (narrow with both)")
    q.add_argument("--region", type=int, nargs=4, metavar=("ROW0", "ROW1", "COL0", "COL1"), help="zoom [px]")
    q.add_argument("--no-labels", action="store_true", help="do not write the slice ids")
    q.add_argument("--spot-table", metavar="FILE", help="optical model (default: the built-in Lazuli layout)")
    q.add_argument("--truncate", type=float, default=4.0, help="window half-width beyond a cell [spot rms]")
    q = [q, kinds.add_parser("fields", help="scene and cube of both fields side by side",
                             description="Projected scene, cube and spectra of a SN Ia in both fields.", **fmt),
         kinds.add_parser("psf", help="PSF radial profiles and encircled energy",
                          description="Airy and Gaussian PSF profiles and encircled energies.", **fmt)]
    q[1].add_argument("--redshift", type=float, default=0.5, metavar="Z", help="SN Ia redshift")
    q[1].add_argument("--field", choices=("narrow", "wide"), default="narrow", help="field of the target")
    q[1].add_argument("--lbda-range", type=float, nargs=2, metavar=("LO", "HI"),
                      help="wavelength range of the images [Angstrom] (default: all)")
    q[1].add_argument("--seed", type=int, help="draw a noisy cube with this seed (default: signal)")
    q[2].add_argument("--lbda", type=float, nargs="+", default=[5000.0, 10000.0, 15000.0], metavar="L",
                      help="wavelengths [Angstrom]")
    q[2].add_argument("--field", choices=("narrow", "wide"), default="narrow", help="field")
    q[2].set_defaults(redshift=0.5)
    for k in q:
        k.add_argument("--config", action="append", metavar="cbe|eol|PATH",
                       help="instrument configuration; repeat to layer (default: cbe)")
        k.add_argument("--out", required=True, metavar="FILE", help="figure file (.png, .pdf or .svg)")
        k.add_argument("--overwrite", action="store_true", help="replace an existing figure")
        k.set_defaults(func=cmd_plot)
