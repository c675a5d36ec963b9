"""Command-line interface: ``slicersim {info,demo,etc}`` (also ``python -m slicersim``)."""

from __future__ import annotations

import argparse
import os
import platform
import sys
from importlib import metadata


def _version(dist: str) -> str:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        if dist == "slicersim":
            import slicersim
            return getattr(slicersim, "__version__", "unknown (not installed)")
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

    run_demo(args.outdir)
    return 0


def _read_spectrum(path):
    """Two-column text/CSV file: wavelength [Angstrom], flux [erg/s/cm2/Angstrom]."""
    import numpy as np

    lbda, flux = [], []
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            line = line.split("#", 1)[0].replace(",", " ").replace(";", " ").strip()
            if not line:
                continue
            fields = line.split()
            try:
                x, y = float(fields[0]), float(fields[1])
            except (ValueError, IndexError):
                continue  # header or malformed line
            lbda.append(x)
            flux.append(y)
    if len(lbda) < 2:
        raise SystemExit(f"slicersim etc: {path}: need at least two numeric 'wavelength flux' rows")
    lbda, flux = np.asarray(lbda), np.asarray(flux)
    order = np.argsort(lbda, kind="stable")
    return lbda[order], flux[order]


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


def _print_result(result, indent=0) -> None:
    if not isinstance(result, dict):
        print(" " * indent + _fmt_value(result))
        return
    width = max((len(str(k)) for k in result), default=0)
    for key, value in result.items():
        if isinstance(value, dict):
            print(" " * indent + f"{key}:")
            _print_result(value, indent + 2)
        else:
            print(" " * indent + f"{str(key):<{width}} : {_fmt_value(value)}")


def cmd_etc(args) -> int:
    from slicersim import targets

    kwargs = {"snr": args.snr}
    if args.lbda_range is not None:
        kwargs["lbda_range"] = tuple(args.lbda_range)
    if args.config:
        kwargs["config"] = args.config[0] if len(args.config) == 1 else list(args.config)
    if args.field is not None:
        kwargs["field"] = args.field
    if args.search is not None:
        kwargs["search"] = args.search
    if args.redshift is not None:
        kwargs["frame"] = args.frame or "rest"
        result = targets.lazuli_sn_etc(args.redshift, **kwargs)
    else:
        if args.frame is not None:
            kwargs["frame"] = args.frame
        lbda, flux = _read_spectrum(args.spectrum)
        result = targets.lazuli_etc(lbda, flux, **kwargs)
    _print_result(result)
    return 0


def cmd_ramp(args) -> int:
    import numpy as np

    from slicersim.products import ramps
    nmd = tuple(args.nmd)
    common = dict(seed=args.seed, out=args.out, compression=args.compression, progress=True,
                  backend=args.backend)
    if args.rate is not None:
        rate = np.load(args.rate) if args.rate.endswith(".npy") else np.loadtxt(args.rate, ndmin=2)
        path = ramps.simulate(rate, nmd, args.nramps, tframe=args.tframe, ron=args.ron, dark=args.dark,
                              roic_glow=args.roic_glow, gain=args.gain, **common)
    else:
        from slicersim.targets import LazuliSupernova
        target = LazuliSupernova(args.redshift, config=args.config or "cbe", field=args.field)
        path = target.get_ramps(nmd=nmd, nramps=args.nramps, **common)
    print(f"wrote {path}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="slicersim", description="Image-slicer IFS simulator.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version('slicersim')}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser("info", help="versions and OpenCL platforms/devices")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("demo", help="run the demonstration simulation")
    p.add_argument("--outdir", default="demo_output", metavar="DIR", help="output directory (default: %(default)s)")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("etc", help="exposure-time calculator")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--redshift", type=float, metavar="Z", help="SN Ia at redshift Z")
    src.add_argument("--spectrum", metavar="FILE",
                     help="two-column text/CSV: wavelength [Angstrom], flux [erg/s/cm^2/Angstrom]")
    p.add_argument("--snr", type=float, default=20.0, help="target signal-to-noise ratio (default: %(default)s)")
    p.add_argument("--lbda-range", type=float, nargs=2, metavar=("LO", "HI"), help="wavelength range [Angstrom]")
    p.add_argument("--frame", choices=("obs", "rest"), help="frame of --lbda-range (default: rest for --redshift)")
    p.add_argument("--config", action="append", metavar="cbe|eol|PATH",
                   help="instrument configuration; repeat to apply several in order")
    p.add_argument("--field", choices=("narrow", "wide"), help="field of view")
    p.add_argument("--search", choices=("exact", "reference"), help="readout search strategy")
    p.set_defaults(func=cmd_etc)

    p = sub.add_parser("ramp", help="raw up-the-ramp H4RG reads to a group-level HDF5 file")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--redshift", type=float, metavar="Z", help="full detector image of a SN Ia at Z")
    src.add_argument("--rate", metavar="FILE", help="rate image [e-/s] (.npy or text)")
    p.add_argument("--nmd", type=int, nargs=3, default=(16, 8, 0), metavar=("N", "M", "D"),
                   help="MACC readout (default: %(default)s)")
    p.add_argument("--nramps", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, metavar="FILE.h5")
    p.add_argument("--compression", choices=("gzip", "lz4", "zstd", "bitshuffle-lz4"))
    p.add_argument("--config", metavar="cbe|eol|PATH")
    p.add_argument("--field", choices=("narrow", "wide"), default="narrow")
    p.add_argument("--tframe", type=float, default=2.83)
    p.add_argument("--ron", type=float, default=12.0)
    p.add_argument("--dark", type=float, default=2.8e-3)
    p.add_argument("--roic-glow", type=float, default=3e-3)
    p.add_argument("--gain", type=float, default=1.0)
    p.add_argument("--backend", choices=("auto", "opencl", "numpy"), default="auto")
    p.set_defaults(func=cmd_ramp)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except BrokenPipeError:  # e.g. `slicersim info | head`
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
