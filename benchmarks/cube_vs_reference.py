"""Cube generator vs the reference slicersim 1.0.0 (PyPI, own venv), same run.

Lazuli narrow field, SN Ia z = 1 (sncosmo hsiao-subsampled, peak M_B = −19.3),
readout (16, 8, 0) × 1, cube 525 × 58 × 116 (reference configuration files):

* Airy PSF cube with jitter, slice blur and LSF   (goal ≥ 50× faster)
* Gaussian PSF cube                                 (goal ≥ 20× faster)
* Airy-weighted extracted spectrum                  (goal ≥ 100× faster)

The Airy timings compute the PSF each time (``psf_cache.bypass()``), as the reference does;
``cube_airy_psf_cached_s`` is the same cube with the PSF blocks cached across calls.

Writes benchmarks/results/cube_vs_reference.json (+ .png).  Usage:
    .venv/bin/python benchmarks/cube_vs_reference.py [--repeat 3] [--skip-reference]
"""
import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import timed as common_timed, write_json  # noqa: E402  (benchmarks/ is on sys.path)

HERE = Path(__file__).resolve().parent
REFVENV = HERE / ".refvenv"
RESULTS = HERE / "results"


def reference_config():
    env = os.environ.get("SLICERSIM_REFERENCE_DIR")
    root = Path(env) if env else HERE.parents[1] / "shared" / "reference"
    cfg = root / "config" / "lazuli_cbe.toml"
    return str(cfg) if cfg.is_file() else "cbe"


def ensure_refvenv():
    py = REFVENV / "bin" / "python"
    if py.exists():
        return py
    subprocess.run([sys.executable, "-m", "venv", str(REFVENV)], check=True)
    subprocess.run([str(py), "-m", "pip", "install", "-q", "slicersim==1.0.0"], check=True)
    return py


def sn_spectrum(z=1.0):
    import sncosmo
    from astropy.cosmology import Planck18
    lbda = np.arange(3000.0, 20000.0, 10.0)
    model = sncosmo.Model("hsiao-subsampled")
    model.set(z=z, t0=0)
    model.set_source_peakabsmag(-19.3, "bessellb", "ab", cosmo=Planck18)
    return lbda, model.flux(0.0, lbda)


def timed(func, repeat):
    """Wall times [s] of ``repeat`` calls (:func:`_common.timed`)."""
    return common_timed(func, repeat).walls


def run_reference(lbda, flux, repeat):
    py = ensure_refvenv()
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON")}
    with tempfile.TemporaryDirectory() as tmp:
        inp, outp = Path(tmp) / "in.npz", Path(tmp) / "out.json"
        np.savez(inp, lbda=lbda, flux=flux)
        subprocess.run([str(py), str(HERE / "_reference_cube_runner.py"), str(inp), str(outp), str(repeat)],
                       check=True, env=env, cwd=tmp)
        return json.loads(outp.read_text())


def run_ours(lbda, flux, repeat):
    from slicersim.backends import opencl, psf_cache
    from slicersim import LazuliTarget
    target = LazuliTarget(lbda, flux, config=reference_config(), field="narrow")
    target.change_detector(nmd=(16, 8, 0), nramps=1)
    sim = target.simulation
    first = {}
    t0 = time.perf_counter(); sim.get_cube(psf_profile="airy"); first["cube_airy_s"] = time.perf_counter() - t0
    t0 = time.perf_counter(); sim.get_spectrum(psf_profile="airy"); first["spectrum_airy_s"] = time.perf_counter() - t0

    def spectrum_airy():
        sim._cache.pop(("extraction", "airy"), None)      # recompute the Airy weights each time
        sim.get_spectrum(psf_profile="airy")
    def uncached(func):            # the PSF computed each time, as the reference does (no PSF cache)
        def run():
            with psf_cache.bypass():
                func()
        return run
    res = {"cube_gaussian_s": timed(lambda: sim.get_cube(psf_profile="gaussian"), repeat),
           "cube_airy_s": timed(uncached(lambda: sim.get_cube(psf_profile="airy")), repeat),
           "cube_airy_psf_cached_s": timed(lambda: sim.get_cube(psf_profile="airy"), repeat),
           "spectrum_airy_s": timed(uncached(spectrum_airy), repeat),
           "cube_gaussian_noisy_s": timed(lambda: sim.get_cube(psf_profile="gaussian", seed=1), repeat),
           "first_call_s": first,
           "device": opencl.device_info() if opencl.is_available() else []}
    signal, _ = sim.get_cube(psf_profile="airy")
    res["cube_airy_sum_adu"] = float(np.nansum(signal))
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--skip-reference", action="store_true")
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args(argv)
    lbda, flux = sn_spectrum()
    ours = run_ours(lbda, flux, args.repeat)
    ref = None
    if not args.skip_reference:
        try:
            ref = run_reference(lbda, flux, args.repeat)
        except Exception as exc:  # keep our numbers even if the reference cannot run
            print(f"reference unavailable: {exc}")
    goals = {"cube_airy_s": 50, "cube_gaussian_s": 20, "spectrum_airy_s": 100}
    rows = []
    for key, goal in goals.items():
        t_ours = statistics.median(ours[key])
        t_ref = statistics.median(ref[key]) if ref else None
        ratio = t_ref / t_ours if ref else None
        rows.append({"call": key, "ours_s": t_ours, "reference_s": t_ref, "ratio": ratio, "goal": goal,
                     "goal_met": None if ratio is None else ratio >= goal})
        print(f"{key:18s} ours {t_ours * 1e3:9.1f} ms   reference "
              f"{'n/a' if t_ref is None else f'{t_ref * 1e3:9.1f} ms'}   ratio "
              f"{'n/a' if ratio is None else f'{ratio:7.1f}x'} (goal >= {goal}x)")
    if ref:
        print(f"Airy cube sum: ours {ours['cube_airy_sum_adu']:.1f} ADU, reference {ref['cube_airy_sum_adu']:.1f} "
              f"ADU ({ours['cube_airy_sum_adu'] / ref['cube_airy_sum_adu'] - 1:+.2%}; the reference's Airy "
              "sub-sample grid is off and sums high)")
    os.makedirs(args.out, exist_ok=True)
    result = {"machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                          "load_average": os.getloadavg()},
              "case": "SN Ia z=1, Lazuli CBE narrow, (16,8,0) x 1, 525x58x116",
              "rows": rows, "ours": ours, "reference": ref}
    write_json(Path(args.out, "cube_vs_reference.json"), result)
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(figsize=(7, 4))
        x = np.arange(len(rows))
        ax.bar(x - 0.2, [r["ours_s"] for r in rows], 0.4, label="slicersim (OpenCL)")
        if ref:
            ax.bar(x + 0.2, [r["reference_s"] for r in rows], 0.4, label="slicersim 1.0.0")
        ax.set_xticks(x, [r["call"] for r in rows])
        ax.set_yscale("log")
        ax.set_ylabel("seconds (median)")
        ax.legend()
        fig.tight_layout()
        fig.savefig(Path(args.out, "cube_vs_reference.png"), dpi=110)
    except Exception as exc:  # pragma: no cover
        print(f"no plot: {exc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
