"""Speed vs accuracy of the correlated-noise generators (exact, multirate, group, white).

Speed: seconds per full-detector (4096², 32 outputs) group of a MACC(n, 8, 0) ramp, excluding
and including the once-per-ramp low-frequency part, reported as ratios to multirate; "exact"
cannot run at full size (its streams are frames × 573 580 samples per output) and is timed on a
256 × 512 detector and scaled by pixel-groups.  Accuracy on a small detector (256 × 64, 2 or 4
outputs, NGHXRG amplitudes): PSD band ratios (simulated / model, m = 1, 0.1 Hz – 1 kHz) and
the group-mean variance ratio (m = 8) — the exact generator is the model's reference.

    .venv/bin/python benchmarks/correlated_noise.py [--ramps N] [--groups N]

Writes benchmarks/results/correlated_noise.{json,png,md}.  Default run ≈ 1–2 min.
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy import signal

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import cpu_model, loadavg, write_json  # noqa: E402

from slicersim.backends.correlated_noise import CorrelatedNoise  # noqa: E402
from slicersim.physics.correlated_noise import (METHODS, CorrelatedNoiseParameters, ReadoutGeometry,  # noqa: E402
                                                group_mean_variance, model_psd)

OUT = Path(__file__).resolve().parent / "results"


def speed(groups):
    res = {}
    p = CorrelatedNoiseParameters()
    for method in ("multirate", "group", "white"):
        gen = CorrelatedNoise(p, (4096, 4096), (groups, 8, 0), 2.83, 1, method=method)
        t0 = time.perf_counter()
        if method == "multirate":
            gen._ramp_state(0)
        t1 = time.perf_counter()
        gen.block(0, 0, 4096)
        t2 = time.perf_counter()
        res[method] = {"per_group_s": (t2 - t1) / groups, "per_ramp_setup_s": t1 - t0}
    small = CorrelatedNoiseParameters(n_outputs=4)
    gen = CorrelatedNoise(small, (256, 512), (4, 8, 0), 2.83 * 257 / 4097, 1, method="exact")
    t0 = time.perf_counter()
    gen.block(0, 0, 256)
    dt = time.perf_counter() - t0
    res["exact"] = {"per_group_s": dt / 4 * (4096 * 4096) / (256 * 512), "per_ramp_setup_s": 0.0,
                    "note": "timed on 256 x 512 (4 outputs), scaled by pixel-groups; memory would be "
                            "~(frames x 573580 x 33 x 8 B) at full size"}
    return res


def accuracy(ramps):
    res = {}
    p = CorrelatedNoiseParameters(n_outputs=2, nroh=0, nfoh=0, f_min=0.01, pedestal=0, picture_frame=0)
    edges = np.geomspace(0.1, 1000, 13)
    pv = CorrelatedNoiseParameters(n_outputs=4)
    for method in METHODS:
        ps = []
        for r in range(ramps):
            gen = CorrelatedNoise(p, (256, 64), (64, 1, 0), 2.83, 3, method=method)
            b = gen.block(r, 0, 256)
            g = gen.geometry
            x = np.arange(g.ncol, 2 * g.ncol)
            s = np.empty((b.shape[0], g.ny, g.row_len))
            s[:, :, g.scan_index(x)] = b[:, :, x]
            f, pxx = signal.welch(s.ravel(), fs=1 / g.dwell, nperseg=2**16)
            ps.append(pxx)
        ps = np.mean(ps, axis=0)
        model = model_psd(f, p, g)
        bands = [float(ps[(f >= lo) & (f < hi)].mean() / model[(f >= lo) & (f < hi)].mean())
                 for lo, hi in zip(edges[:-1], edges[1:])]
        v = [float((CorrelatedNoise(pv, (128, 64), (4, 8, 0), 2.83, 11, method=method).block(r, 0, 128)
                    .astype(float) ** 2).mean()) for r in range(2 * ramps)]
        pred = group_mean_variance(8, pv, ReadoutGeometry.from_params(pv, (128, 64), 2.83))
        res[method] = {"psd_band_ratio": bands, "psd_max_error": float(np.max(np.abs(np.array(bands) - 1))),
                       "group_variance_ratio": float(np.mean(v) / pred),
                       "group_variance_mc_error": float(np.std(v, ddof=1) / np.sqrt(len(v)) / pred)}
    return res, edges


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ramps", type=int, default=8)
    ap.add_argument("--groups", type=int, default=4)
    ap.add_argument("--out", default=str(OUT), help="results folder (default benchmarks/results)")
    a = ap.parse_args()
    out = Path(a.out)
    t0 = time.perf_counter()
    sp = speed(a.groups)
    acc, edges = accuracy(a.ramps)
    ref = sp["multirate"]["per_group_s"]
    result = {"cpu_model": cpu_model(), "loadavg": loadavg(), "ramps": a.ramps, "groups": a.groups,
              "speed_ratio_to_multirate": {m: sp[m]["per_group_s"] / ref for m in sp},
              "setup_ratio_to_multirate_group": {m: sp[m]["per_ramp_setup_s"] / ref for m in sp},
              "speed_seconds_this_run": sp, "accuracy": acc, "psd_band_edges_hz": edges,
              "wall_s": time.perf_counter() - t0}
    write_json(out / "correlated_noise.json", result)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    centres = np.sqrt(edges[:-1] * edges[1:])
    for m in METHODS:
        ax1.semilogx(centres, acc[m]["psd_band_ratio"], "o-", label=m)
        ax2.scatter(sp[m]["per_group_s"] / ref, abs(acc[m]["group_variance_ratio"] - 1) + 1e-3, label=m)
        ax2.annotate(m, (sp[m]["per_group_s"] / ref, abs(acc[m]["group_variance_ratio"] - 1) + 1e-3))
    ax1.axhspan(0.9, 1.1, color="0.9")
    ax1.set(xlabel="frequency [Hz]", ylabel="simulated / model PSD (m = 1)", title="PSD accuracy")
    ax1.legend()
    ax2.set(xscale="log", yscale="log", xlabel="time per full-detector group / multirate's",
            ylabel="|group-mean variance / model − 1| (m = 8)", title="speed vs accuracy")
    fig.tight_layout()
    fig.savefig(out / "correlated_noise.png", dpi=110)
    lines = ["# Correlated-noise generators: speed vs accuracy", "",
             f"CPU: {result['cpu_model']}, load {result['loadavg']}; command: "
             "`.venv/bin/python benchmarks/correlated_noise.py`", "",
             "| method | time/group ÷ multirate | PSD max band error (m=1) | group variance / model (m=8) |",
             "|---|---|---|---|"]
    for m in METHODS:
        lines.append(f"| {m} | {sp[m]['per_group_s'] / ref:.2f} | {acc[m]['psd_max_error']:.3f} | "
                     f"{acc[m]['group_variance_ratio']:.3f} ± {acc[m]['group_variance_mc_error']:.3f} |")
    lines += ["", f"multirate once-per-ramp low part = {sp['multirate']['per_ramp_setup_s'] / ref:.1f} groups' time.",
              "", "Where each breaks: *exact* is the reference but its memory and time grow with frames × "
              "frame_len (no full-detector ramp); *multirate* follows the model within a few % in every band and "
              "in the group variance; *group* keeps the PSD shape within a frame but drops the frame-to-frame 1/f "
              "correlation (group means too quiet at low frequency, variance ≈ half the model's at m = 8); "
              "*white* has the right one-pixel variance by construction but no PSD shape at all (flat)."]
    (out / "correlated_noise.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
