#!/usr/bin/env python
"""PSF cube benchmark: accuracy against time for the Lazuli narrow-field cube.

The cube is the fraction of a point source's flux in each of the 58 × 116
cells (0.04″) at each of the 525 wavelengths of the reference configuration
(510 with the built-in CBE curves when ../shared/reference is absent), source
at (0, 0), D = 3 m, ε = 0, jitter 0.010″ (0.25 cells), instrumental blur
√(2.3² − 4) = 1.136 cells along x.

Points (method, setting):
* ``airy-opencl`` / ``airy-numpy``, ``o=N``: ``psf_cube(profile="airy",
  oversampling=N)`` on the exact sub-cell grid, N = 1, 2, 3, 4, 5, 9, 15,
  and the default ``oversampling="auto"`` (per axis: (o_y, o_x) = (4, 3) here);
* ``gaussian-opencl`` / ``gaussian-numpy``: the Airy-equivalent Gaussian
  (σ = 0.8 R_Airy / 2.35 with jitter and blur in quadrature, slicersim 1.0's
  default profile);
* ``airy-reference-numpy``, ``o=3``: slicersim 1.0's Airy sub-sample grid;
* whatever :func:`extra_points` returns (hook for other methods).

Errors are measured against an oracle: the same Airy cube at o = 31 (OpenCL),
itself cross-checked against 31-point Gauss–Legendre sub-cell nodes.
``max_err_rel_peak`` = max over λ of max |P − P_oracle| / max P_oracle(λ);
``flux_err`` = max over λ of |Σ P − Σ P_oracle| (fraction of the source flux).
Times are warm (kernels built), best of ``--repeat`` runs: wall clock
(``seconds``) and process CPU time of all threads (``cpu_seconds``).
A wide-field (0.08″) convergence check on 25 wavelengths is added to the JSON.

Writes ``<out>/psf_speed_accuracy.json`` and ``.png``.

Usage::

    .venv/bin/python benchmarks/psf_speed_accuracy.py [--repeat 5] [--out benchmarks/results]
        [--no-numpy-above 15] [--oracle 31]
"""
import argparse
import importlib.util
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from _common import timed as common_timed, write_json  # noqa: E402  (benchmarks/ is on sys.path)

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
OVERSAMPLINGS = (1, 2, 3, 4, 5, 9, 15, "auto")


def lazuli_narrow():
    """(lbda [Å], shape, psf keyword arguments, description) of the Lazuli narrow field."""
    from slicersim.targets import LazuliTarget
    env = os.environ.get("SLICERSIM_REFERENCE_DIR")
    refdir = Path(env) if env else REPO.parent / "shared" / "reference"
    cfg_file = refdir / "config" / "lazuli_cbe.toml"
    config = [str(cfg_file)] if cfg_file.is_file() else "cbe"
    lbda_in = np.arange(3000.0, 20000.0, 10.0)
    sim = LazuliTarget(lbda_in, np.ones_like(lbda_in), mag=None, config=config, field="narrow").simulation
    tel, spec = sim.telescope, sim.spectrograph
    kw = dict(spatial_scale=spec.spatial_scale, guiding_sigma=tel.guiding_sigma,
              instrumental_sigma=sim.instrumental_sigma, diameter=tel.diameter_ext,
              obscuration=tel.obscuration, sigma_ref_arcsec=tel.psf_sigma_ref)
    source = "reference lazuli_cbe.toml" if cfg_file.is_file() else "built-in cbe"
    return sim.lbda.copy(), tuple(spec.shape), kw, source


def timed(func, repeat):
    """(result, best wall time [s], all wall times, best process CPU time [s]) after
    one untimed warm-up call.  CPU time sums all threads of this process (the
    OpenCL runtime's too): a load-independent measure of the work on a shared machine."""
    t = common_timed(func, repeat, warmup=True)
    return t.result, t.best_wall, t.walls, t.best_cpu


def errors(cube, oracle):
    peak = oracle.max(axis=(1, 2))
    err = np.abs(cube - oracle).max(axis=(1, 2)) / peak
    flux = np.abs(cube.sum(axis=(1, 2)) - oracle.sum(axis=(1, 2)))
    return float(err.max()), float(flux.max()), err


def extra_points(ctx):
    """Hook for more methods: a list of point dicts {method, setting, seconds,
    max_err_rel_peak, flux_err}.  By default the ``points(ctx)`` of
    ``benchmarks/_psf_extra_points.py`` when that file exists.  ``ctx`` holds
    lbda, shape, kwargs (psf_cube keywords), oracle (cube), repeat, and the
    helpers ``timed`` and ``errors``."""
    path = HERE / "_psf_extra_points.py"
    if not path.is_file():
        return []
    spec = importlib.util.spec_from_file_location("psf_extra_points", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return list(mod.points(ctx))


def wide_field_check(oracle_o, backend):
    """Convergence with o in the wide field (0.08″, jitter 0.125 cells) on 25 wavelengths."""
    from slicersim.backends.psf import psf_cube
    lbda, shape, kw, _ = lazuli_narrow()
    lbda = lbda[np.linspace(0, lbda.size - 1, 25).astype(int)]
    kw = dict(kw, spatial_scale=0.08)
    kw.pop("sigma_ref_arcsec")
    oracle = psf_cube(lbda, shape, (0.0, 0.0), "airy", oversampling=oracle_o, backend=backend, **kw)
    rows = []
    for o in OVERSAMPLINGS:
        cube = psf_cube(lbda, shape, (0.0, 0.0), "airy", oversampling=o, backend=backend, **kw)
        e, f, _ = errors(cube, oracle)
        rows.append({"oversampling": label(o, lbda, kw), "max_err_rel_peak": e, "flux_err": f})
    return rows


def label(o, lbda, kw):
    """"o=N", or "auto=(o_y,o_x)" with the factors "auto" picks."""
    if o != "auto":
        return f"o={o}"
    from slicersim.physics.psf import airy_wavenumber, midpoint_oversampling
    kmax = float(airy_wavenumber(np.min(lbda), kw["diameter"], kw["spatial_scale"]))
    gam = kw["guiding_sigma"] / kw["spatial_scale"]
    oy = midpoint_oversampling(gam, kmax)
    ox = midpoint_oversampling(float(np.hypot(gam, kw["instrumental_sigma"])), kmax)
    return f"auto=({oy},{ox})"


def run(args):
    from slicersim.backends import opencl
    from slicersim.backends.dispatch import resolve_backend
    from slicersim.backends.psf import psf_cube

    lbda, shape, kw, source = lazuli_narrow()
    airy_kw = {k: v for k, v in kw.items() if k != "sigma_ref_arcsec"}
    have_cl = resolve_backend("auto") == "opencl"
    fast = "opencl" if have_cl else "numpy"
    pos = (0.0, 0.0)
    load0 = os.getloadavg()
    print(f"Lazuli narrow field {len(lbda)} x {shape[0]} x {shape[1]} ({source}); backend {fast}", flush=True)

    t0 = time.perf_counter()
    oracle = psf_cube(lbda, shape, pos, "airy", oversampling=args.oracle, backend=fast, **airy_kw)
    t_oracle = time.perf_counter() - t0
    check = psf_cube(lbda, shape, pos, "airy", oversampling=args.oracle, grid="gauss", backend=fast, **airy_kw)
    oracle_check, _, _ = errors(check, oracle)
    print(f"oracle o={args.oracle}: {t_oracle:.1f} s; vs Gauss-Legendre o={args.oracle}: {oracle_check:.1e}",
          flush=True)

    points = []

    def add(method, setting, func, repeat):
        cube, best, times, cpu = timed(func, repeat)
        e, f, per_lbda = errors(cube, oracle)
        points.append({"method": method, "setting": setting, "seconds": best, "max_err_rel_peak": e,
                       "flux_err": f, "all_seconds": times, "cpu_seconds": cpu,
                       "err_at_lbda": {f"{lbda[i]:.0f}": float(per_lbda[i])
                                       for i in (0, len(lbda) // 4, len(lbda) // 2, len(lbda) - 1)}})
        print(f"  {method:22s} {setting:12s} {best:8.3f} s (cpu {cpu:7.3f} s)  err/peak {e:.2e}  "
              f"flux {f:.2e}", flush=True)

    backends = (["opencl"] if have_cl else []) + ["numpy"]
    for backend in backends:
        for o in OVERSAMPLINGS:
            if backend == "numpy" and o != "auto" and o > args.no_numpy_above:
                continue
            rep = args.repeat if o == "auto" or o <= 5 else 1
            add(f"airy-{backend}", label(o, lbda, kw), lambda o=o, b=backend: psf_cube(
                lbda, shape, pos, "airy", oversampling=o, backend=b, **airy_kw), rep)
        add(f"gaussian-{backend}", "erf", lambda b=backend: psf_cube(
            lbda, shape, pos, "gaussian", backend=b, **kw), args.repeat)
    add("airy-reference-numpy", "o=3", lambda: psf_cube(
        lbda, shape, pos, "airy", oversampling=3, grid="reference", backend="numpy", **airy_kw), 1)

    ctx = {"lbda": lbda, "shape": shape, "position": pos, "kwargs": kw, "oracle": oracle,
           "repeat": args.repeat, "timed": timed, "errors": errors}
    for p in ([] if args.skip_extra else extra_points(ctx)):
        points.append(p)

    wide = wide_field_check(args.oracle, fast)
    for row in wide:
        print(f"  wide field {row['oversampling']:12s}: err/peak {row['max_err_rel_peak']:.2e}")

    dev = None
    if have_cl:
        d = opencl.get_device()
        dev = f"{d.name.strip()} [{d.platform.name.strip()}]"
    result = {
        "benchmark": "psf_speed_accuracy",
        "cube": {"nlbda": int(lbda.size), "shape": list(shape), "lbda_range": [float(lbda[0]), float(lbda[-1])],
                 "configuration": source, "position": list(pos),
                 "parameters": {k: float(v) for k, v in kw.items()}},
        "oracle": {"oversampling": args.oracle, "grid": "exact", "seconds": t_oracle, "backend": fast,
                   "max_diff_vs_gauss_legendre_rel_peak": oracle_check},
        "points": [{k: v for k, v in p.items()} for p in points],
        "wide_field_check": wide,
        "default_oversampling": "auto",
        "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
                    "opencl_device": dev, "python": sys.version.split()[0], "numpy": np.__version__,
                    "loadavg_before": load0, "loadavg_after": os.getloadavg()},
        "reference_timing_note": "slicersim 1.0.0 get_cube(Airy) 1.7-3.7 s (median 2.7 s) on a 2-core "
                                 "AMD EPYC VM (shared/reference README 3.4)",
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "psf_speed_accuracy.json", result)
    plot(result, out / "psf_speed_accuracy.png")
    print(f"wrote {out / 'psf_speed_accuracy.json'} and .png")


def plot(result, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    floor = 1e-17
    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    methods = []
    for p in result["points"]:
        if p["method"] not in methods:
            methods.append(p["method"])
    markers = dict(zip(methods, "os^vD<>ph"))
    colors = dict(zip(methods, plt.rcParams["axes.prop_cycle"].by_key()["color"]))
    for ax, key, label in ((axes[0], "max_err_rel_peak", "max |P − P_oracle| / peak (worst λ)"),
                           (axes[1], "flux_err", "|Σ P − Σ P_oracle| (fraction of the source flux)")):
        for m in methods:
            pts = [p for p in result["points"] if p["method"] == m]
            line = [p for p in pts if p["setting"].startswith("o=")] if m.startswith("airy-") else []
            other = [p for p in pts if p not in line]
            if line and "reference" not in m:
                ax.plot([p["seconds"] for p in line], [max(p[key], floor) for p in line], marker=markers[m],
                        color=colors[m], label=m)
            else:
                other = pts
            for p in other:
                auto = p["setting"].startswith("auto")
                ax.plot(p["seconds"], max(p[key], floor), ls="none", color=colors[m],
                        marker="*" if auto else markers[m], ms=13 if auto else 7,
                        label=f"{m} (default)" if auto else (m if not line or "reference" in m else None))
            for p in pts:
                below = p["setting"].startswith("auto")
                ax.annotate(p["setting"], (p["seconds"], max(p[key], floor)), textcoords="offset points",
                            xytext=(5, -11 if below else 3), fontsize=7)
        ax.axvline(2.7, color="grey", lw=0.8, ls="--")
        ax.text(2.7, 0.97, " slicersim 1.0\n get_cube(Airy)\n 2.7 s", transform=ax.get_xaxis_transform(),
                fontsize=7, color="grey", va="top")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("wall time per cube [s] (warm, best of runs)")
        ax.set_ylabel(label)
        ax.grid(True, which="major", alpha=0.3)
    axes[0].axhline(1e-3, color="grey", lw=0.8, ls=":")
    c, mach = result["cube"], result["machine"]
    fig.suptitle(f"Airy PSF cube {c['nlbda']}×{c['shape'][0]}×{c['shape'][1]} (Lazuli narrow field, jitter + blur) "
                 f"vs o={result['oracle']['oversampling']} oracle; {mach['cores']} cores, "
                 f"{mach['opencl_device'] or 'NumPy only'}; load average {mach['loadavg_before'][0]:.1f}",
                 fontsize=9)
    axes[0].legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def replot(json_path):
    """Redraw the PNG next to an existing JSON."""
    json_path = Path(json_path)
    plot(json.loads(json_path.read_text()), json_path.with_suffix(".png"))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5, help="timed runs per point (best kept)")
    ap.add_argument("--oracle", type=int, default=31, help="oversampling of the oracle")
    ap.add_argument("--no-numpy-above", type=int, default=15, help="skip NumPy points above this o")
    ap.add_argument("--out", default=str(HERE / "results"))
    ap.add_argument("--replot", metavar="JSON", help="only redraw the PNG of an existing JSON")
    ap.add_argument("--skip-extra", action="store_true",
                    help="skip the extra points of _psf_extra_points.py (host convolution, the slow part)")
    args = ap.parse_args(argv)
    if args.replot:
        replot(args.replot)
    else:
        run(args)


if __name__ == "__main__":
    main()
