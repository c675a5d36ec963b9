"""Run the public reference ETC (``slicersim==1.0.0``) on a batch of targets.

This helper is executed by ``benchmarks/etc_vs_reference.py`` with the
interpreter of the isolated reference virtual environment
(``benchmarks/.refvenv/bin/python``), so that the reference package never
clashes with our own ``slicersim`` package.

Usage::

    benchmarks/.refvenv/bin/python benchmarks/_reference_runner.py INPUT.npz OUTPUT.json

``INPUT.npz`` holds

* ``lbda``        (nλ,)    input wavelength grid [Å]
* ``fluxes``      (N, nλ)  input f_λ spectra [erg/s/cm²/Å]
* ``lbda_ranges`` (N, 2)   band over which the SNR is evaluated [Å]
* ``snr``         ()       target SNR (per resolution element)
* ``frame``       ()       frame of ``lbda_ranges`` ("obs" or "rest")
* ``band``        ()       band name given to ``LazuliTarget`` (unused, mag=None)
* ``field``       ()       spectrograph field ("narrow" or "wide")
* ``z``           (N,)     redshifts (only copied to the output)

For each target we time, with ``time.perf_counter`` (wall) and ``time.process_time``
(CPU of this process: what other jobs on a shared machine do not inflate), the reference's own ETC
path (the one of its ``lazuli_etc``)::

    target = slicersim.LazuliTarget(lbda, flux, mag=None, band="bessellb")
    target.setup_to_snr(snr, per_resolution=True, lbda_range=(lo, hi), frame="obs")

and record the readout mode (n, m, d), the number of ramps, the total exposure
time and the band SNR reached.  Per-target exceptions are caught and recorded.
Everything the reference prints goes to stderr so that it cannot corrupt our
output, which is written only to ``OUTPUT.json``.
"""

import argparse
import contextlib
import hashlib
import io
import json
import math
import os
import platform
import sys
import time
import traceback
import warnings
from pathlib import Path


def _sha256(path):
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return None


def _versions():
    out = {"python": platform.python_version()}
    for name in ("slicersim", "numpy", "scipy", "astropy", "sncosmo", "pandas"):
        try:
            mod = __import__(name)
            out[name] = getattr(mod, "__version__", "unknown")
        except Exception as exc:  # pragma: no cover - informative only
            out[name] = f"unavailable ({exc.__class__.__name__})"
    return out


def _to_builtin(value):
    """Convert numpy scalars / arrays / tuples into JSON-friendly objects."""
    try:
        import numpy as np
    except ImportError:  # pragma: no cover
        np = None
    if np is not None:
        if isinstance(value, np.ndarray):
            return [_to_builtin(v) for v in value.tolist()]
        if isinstance(value, np.generic):
            return _to_builtin(value.item())
    if isinstance(value, (list, tuple)):
        return [_to_builtin(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _to_builtin(v) for k, v in value.items()}
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _config_info(fallback_config):
    """Locate the configuration the reference uses by default.

    ``LazuliTarget`` -> ``Simulation.from_source(instrument="lazuli_cbe.toml")``
    -> ``iotools.read_config`` which resolves bare file names inside the package
    data folder ``slicersim/config`` (``iotools.PACKAGE_PATH``).
    """
    from slicersim import iotools

    # PACKAGE_PATH is an importlib.resources Traversable (MultiplexedPath).
    packaged = Path(str(iotools.PACKAGE_PATH.joinpath("lazuli_cbe.toml")))
    info = {
        "default_instrument": "lazuli_cbe.toml",
        "package_config_dir": str(packaged.parent),
        "packaged_cbe_exists": packaged.is_file(),
        "instrument_kwarg": None,
    }
    if packaged.is_file():
        info["packaged_cbe_sha256"] = _sha256(packaged)
    if fallback_config:
        fb = Path(fallback_config)
        info["shared_cbe"] = str(fb)
        info["shared_cbe_sha256"] = _sha256(fb) if fb.exists() else None
        if packaged.is_file() and fb.exists():
            info["packaged_equals_shared"] = info["packaged_cbe_sha256"] == info["shared_cbe_sha256"]
        if not packaged.is_file() and fb.exists():
            # Only needed for a broken wheel: point the reference at the shared copy.
            info["instrument_kwarg"] = str(fb)
    return info


def run(input_path, output_path, fallback_config=None, warmup=1):
    import numpy as np

    data = np.load(input_path, allow_pickle=False)
    lbda = np.asarray(data["lbda"], dtype=float)
    fluxes = np.asarray(data["fluxes"], dtype=float)
    ranges = np.asarray(data["lbda_ranges"], dtype=float)
    snr = float(data["snr"])
    frame = str(data["frame"]) if "frame" in data else "obs"
    band = str(data["band"]) if "band" in data else "bessellb"
    field = str(data["field"]) if "field" in data else "narrow"
    zs = np.asarray(data["z"], dtype=float) if "z" in data else np.full(len(fluxes), np.nan)

    t_import0 = time.perf_counter()
    # the reference prints ("Reading configuration from ...") on some paths
    with contextlib.redirect_stdout(sys.stderr):
        import slicersim
    t_import = time.perf_counter() - t_import0

    cfg = _config_info(fallback_config)
    target_kwargs = {}
    if cfg["instrument_kwarg"]:
        target_kwargs["instrument"] = cfg["instrument_kwarg"]

    def solve(flux, lo, hi):
        timings = {}
        c0 = time.process_time()
        t0 = time.perf_counter()
        target = slicersim.LazuliTarget(lbda, flux, mag=None, band=band, **target_kwargs)
        if field != "narrow":  # LazuliTarget already selects the narrow field
            target.change_spectrograph(field)
        t1 = time.perf_counter()
        _, reached = target.setup_to_snr(snr, per_resolution=True,
                                         lbda_range=[float(lo), float(hi)],
                                         frame=frame)
        t2 = time.perf_counter()
        timings["cpu_seconds"] = time.process_time() - c0
        timings["construct_s"] = t1 - t0
        timings["setup_to_snr_s"] = t2 - t1
        timings["seconds"] = t2 - t0
        return target, reached, timings

    # Untimed warm-up (first call pays lazy imports / file reads / caches).
    warm = []
    for i in range(min(warmup, len(fluxes))):
        w0 = time.perf_counter()
        try:
            with contextlib.redirect_stdout(sys.stderr), warnings.catch_warnings():
                warnings.simplefilter("ignore")
                solve(fluxes[i], *ranges[i])
            warm.append(time.perf_counter() - w0)
        except Exception:
            warm.append(None)

    rows = []
    for i, (flux, (lo, hi)) in enumerate(zip(fluxes, ranges)):
        row = {"index": i, "z": float(zs[i]), "lbda_range": [float(lo), float(hi)]}
        captured = io.StringIO()
        try:
            with contextlib.redirect_stdout(captured), \
                    warnings.catch_warnings(record=True) as wlist:
                warnings.simplefilter("always")
                warnings.simplefilter("ignore", ResourceWarning)  # unclosed toml files
                target, reached, timings = solve(flux, lo, hi)
            readout = target.get_readout_config()
            nmd = [int(v) for v in readout["nmd"]]
            nramps = int(readout["nramps"])
            times = target.simulation.get_times()
            dr = float(target.simulation.spectrograph.dispersion_resolution)
            reached = float(reached) if reached is not None else None
            row.update({
                "ok": True,
                "nmd": nmd,
                "nramps": nramps,
                "exposure_time": float(target.get_exposure_time()),
                "exposure_time_per_ramp": _to_builtin(times.get("exposure_time")),
                "integration_time_per_ramp": _to_builtin(times.get("integration_time")),
                "snr_per_bin": reached,
                "snr": reached * math.sqrt(dr) if reached is not None else None,
                **timings,
                "n_warnings": len(wlist),
                "warnings": sorted({f"{w.category.__name__}: {w.message}"[:200] for w in wlist}),
            })
        except Exception as exc:
            row.update({
                "ok": False,
                "error": f"{exc.__class__.__name__}: {exc}",
                "traceback": traceback.format_exc(limit=6),
            })
        text = captured.getvalue()
        if text:
            row["stdout_tail"] = text[-500:]
        rows.append(_to_builtin(row))
        status = (f"{tuple(row['nmd'])}x{row['nramps']} T={row['exposure_time']:.2f}s "
                  f"[{row['seconds']:.3f}s]" if row.get("ok") else row["error"])
        print(f"[reference] {i + 1:3d}/{len(fluxes)} z={zs[i]:.4f} {status}",
              file=sys.stderr, flush=True)

    ok_times = [r["seconds"] for r in rows if r.get("ok")]
    ok_cpu = [r["cpu_seconds"] for r in rows if r.get("ok")]
    summary = {
        "mean_cpu_seconds_per_target": float(np.mean(ok_cpu)) if ok_cpu else None,
        "n_targets": len(rows),
        "n_ok": len(ok_times),
        "total_seconds": float(sum(ok_times)),
        "mean_seconds_per_target": float(np.mean(ok_times)) if ok_times else None,
        "median_seconds_per_target": float(np.median(ok_times)) if ok_times else None,
        "min_seconds_per_target": float(np.min(ok_times)) if ok_times else None,
        "import_seconds": t_import,
        "warmup_seconds": warm,
    }
    out = {
        "reference_package": "slicersim==1.0.0",
        "module_file": str(Path(slicersim.__file__).resolve()),
        "api": ("slicersim.LazuliTarget(lbda, flux, mag=None, band='bessellb') ; "
                "target.setup_to_snr(snr, per_resolution=True, lbda_range=[lo, hi], frame='obs')"),
        "snr": snr,
        "frame": frame,
        "field": field,
        "config": cfg,
        "versions": _versions(),
        "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(),
                    "processor": platform.processor()},
        "summary": summary,
        "rows": rows,
    }
    Path(output_path).write_text(json.dumps(_to_builtin(out), indent=1))
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("input", help="input .npz")
    parser.add_argument("output", help="output .json")
    parser.add_argument("--fallback-config", default=None,
                        help="lazuli_cbe.toml to use if the wheel lacks its own config")
    parser.add_argument("--warmup", type=int, default=1,
                        help="number of untimed warm-up solves (default 1)")
    args = parser.parse_args(argv)
    run(args.input, args.output, fallback_config=args.fallback_config, warmup=args.warmup)
    return 0


if __name__ == "__main__":
    sys.exit(main())
