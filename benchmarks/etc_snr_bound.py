#!/usr/bin/env python
"""Why the closed loop's SNR is not the ETC's (issue 11): the ETC against the best any pipeline can do.

Targets: ``closed_loop.py``'s Lazuli SNe Ia (z = 0.3, 0.5, 0.8; 8 rectified bins of 2 native bins,
MACC(16,8,0), 1 ramp).  All variances are exact (no Monte Carlo): the ETC's own pixel-variance model
on the noiseless detector image (source + background + dark, read noise).  Per redshift:

* **ETC** — ``get_spectrum()``: optimal extraction over cells, each cell's detector noise (read
  noise, dark) counted on the pixels it owns: one row (physical conventions,
  :func:`slicersim.physics.conventions.detector_pixels_per_cell`) — a native bin is 1 px along the
  dispersion and the LSF already holds the 2-px slit image, so consecutive bins of one spaxel
  share their rows;
* **ETC, 2 px per cell** — slicersim 1.0's count: the slit image's 2 px per cell, cells
  independent (read noise and dark counted twice);
* **pixel matched filter** — √Σ_p s_p²/V_p over the detector pixels of the window's light: the
  Cramér–Rao bound for the band flux when the spectral shape is known (no pipeline does better);
* **oracle GLS** — rectification with the exact weights and the GLS extraction of
  ``closed_loop_bias.py`` (what our pipeline reaches with perfect weights): per bin (√diag of its
  covariance), long band (row sums of the covariance: a band much longer than the window), and
  the 8-bin window sum (its ends see the anticorrelation with bins outside).

Band SNRs are ratios to the ETC's band SNR (ΣS/√ΣV); per-bin ones to the ETC per bin (mean S /
√mean V, ``get_band_snr``).  Writes ``etc_snr_bound.{json,md,png}``.

    .venv/bin/python benchmarks/etc_snr_bound.py [--redshifts 0.3 0.5 0.8]
"""
import argparse
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

import closed_loop as cl  # noqa: E402
from _common import cpu_model, loadavg, markdown_table, write_results  # noqa: E402
from closed_loop_bias import OraclePath  # noqa: E402

from slicersim.instrument.mapper import SlicerMapper  # noqa: E402
from slicersim.reduction.rectify import rectify  # noqa: E402
from slicersim.reduction.spectra import extract_spectrum  # noqa: E402

DETECTOR_TERMS = ("ron", "dark", "roic_glow", "thermal_dark")


def one_redshift(z, mapper, ncols=(58, 116)):
    out = None
    for ncol in ncols:
        cl.NCOL = ncol
        r = _one_grid(z, mapper)
        if out is None:
            out = {k: v for k, v in r.items() if not k.startswith(("oracle", "neighbour"))}
            out["grids"] = {}
        out["grids"][str(ncol)] = {k: v for k, v in r.items() if k.startswith(("oracle", "neighbour"))}
    print(out, flush=True)
    return out


def _one_grid(z, mapper):
    t = cl.Target(z, 8)
    sim = t.sim
    image = t.sn.get_detector_image(mapper)                        # e-/s/px, no dark
    var = cl._etc_pixel_variance(t, image)                         # (e-/s)², the ETC's pixel model
    native_all = np.nan_to_num(sim.get_scene_cubes(unit="electron")["pointsource"])   # e-/s per cell
    native = native_all[t.i0:t.i1]
    edges_native = sim.spectrograph.lbda_edges
    # oracle GLS: exact weights, the closed loop's rectification grid and template
    oracle = OraclePath(t, mapper, native, edges_native[t.i0:t.i1 + 1], var)
    cube = rectify(np.zeros_like(image), var, mapper=mapper, field="narrow", lbda_edges=t.edges, ncol=cl.NCOL)
    nb = t.edges.size - 1
    C = extract_spectrum(cube, method="gls", psf=oracle.T).diagnostics["covariance"][:nb, :nb]
    per_bin_var, long_band_var = np.diag(C)[cl.K], C.sum(axis=1)[cl.K]
    # ETC: per native bin, summed in pairs (the rectified bins)
    _, s_adu, v_adu = t.sn.get_spectrum()
    contrib = sim.get_variance_contribution()
    def pair(a):
        return a[t.i0:t.i1].reshape(-1, 2).sum(1)[cl.K]
    S, V = pair(s_adu), pair(v_adu)
    V_det = sum(pair(contrib[k]) for k in DETECTOR_TERMS)
    V_paper = V + V_det                                           # slicersim 1.0: detector terms on 2 px
    to_rate2 = 1.0 / (sim.detector.gain * sim.get_times()["integration_time"]) ** 2   # ADU² → (e-/s)²
    etc_bin = t.truth.mean() / np.sqrt(to_rate2 * V.mean())
    etc_band = t.truth.sum() / np.sqrt(to_rate2 * V.sum())
    # pixel matched filter over the window's native bins (light of the window only)
    j0, j1 = t.i0 + 2 * cl.PAD, t.i1 - 2 * cl.PAD
    window = np.zeros_like(native_all[j0 - 4:j1 + 4])
    window[4:-4] = native_all[j0:j1]
    src = mapper.project_fields(sim.lbda[j0 - 4:j1 + 4], edges_native[j0 - 4:j1 + 5], narrow=window)
    ok = np.isfinite(var) & (var > 0)
    mf = np.sqrt(np.sum(src[ok] ** 2 / var[ok]))
    etc_band_native = native_all[j0:j1].sum() / np.sqrt(to_rate2 * v_adu[j0:j1].sum())
    n = C.shape[0]
    corr = np.mean([C[i, i + 1] / np.sqrt(C[i, i] * C[i + 1, i + 1]) for i in range(cl.PAD, n - cl.PAD - 1)])
    out = {"z": z, "etc_snr_per_bin": float(etc_bin), "etc_snr_band": float(etc_band),
           "detector_variance_fraction": float(V_det.sum() / V.sum()),
           "etc_2px_over_etc": float(np.sqrt(V.sum() / V_paper.sum())),
           "matched_filter_over_etc": float(mf / etc_band_native),
           "oracle_long_band_over_etc": float(t.truth.mean() / np.sqrt(long_band_var.mean()) / etc_bin),
           "oracle_window_sum_over_etc": float(t.truth.sum() / np.sqrt(C[cl.K, cl.K].sum()) / etc_band),
           "oracle_per_bin_over_etc": float(t.truth.mean() / np.sqrt(per_bin_var.mean()) / etc_bin),
           "neighbour_correlation": float(corr)}
    return out


def markdown(res):
    head = ["z", "columns per slice", "detector share of ETC variance", "ETC, 2 px per cell (1.0)",
            "pixel matched filter (bound)", "oracle GLS, long band", "oracle GLS, 8-bin sum", "oracle GLS, per bin",
            "neighbour corr."]
    rows = []
    for r in res["redshifts"]:
        for ncol, g in r["grids"].items():
            rows.append([f"{r['z']}", ncol, f"{r['detector_variance_fraction']:.2f}", f"{r['etc_2px_over_etc']:.3f}",
                         f"{r['matched_filter_over_etc']:.3f}", f"{g['oracle_long_band_over_etc']:.3f}",
                         f"{g['oracle_window_sum_over_etc']:.3f}", f"{g['oracle_per_bin_over_etc']:.3f}",
                         f"{g['neighbour_correlation']:+.3f}"])
    return "\n".join([
        "# ETC SNR against the pixel-level bound (`benchmarks/etc_snr_bound.py`)", "",
        f"{res['cpu']}; exact variances (no Monte Carlo).  Every column is SNR / the ETC's SNR "
        "(band columns: band sum; per bin: per rectified bin of 2 native bins).", ""] + markdown_table(head, rows) + [
        "",
        "The ETC counts each cell's read noise and dark on the one pixel row it owns (physical "
        "conventions): a native bin is 1 px along the dispersion and the LSF already spreads each line "
        "over the 2-px slit image, so consecutive bins of a spaxel share their rows.  It then meets the "
        "pixel-level bound; slicersim 1.0's 2 px per cell (cells independent) counts them twice and "
        "falls short wherever read noise matters.  The oracle (the pipeline's rectification and GLS with "
        "exact weights) reaches the ETC in a long band at the cells' own 116 columns per slice; 58 columns "
        "(2 cells each, the closed loop's faster grid) lose 5–7 %.  Per rectified bin it stays ~10 % below "
        "at either grid: the λ grid does not follow the pixel rows, so neighbouring bins share pixels and "
        "are anticorrelated (−0.11), which a band sum cancels."])


def plot(res, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    z = [r["z"] for r in res["redshifts"]]
    fig, ax = plt.subplots(figsize=(6, 4))
    for key, label in (("etc_2px_over_etc", "ETC, 2 px per cell (slicersim 1.0)"),
                       ("matched_filter_over_etc", "pixel matched filter (bound)")):
        ax.plot(z, [r[key] for r in res["redshifts"]], "o-", label=label)
    for ncol in res["redshifts"][0]["grids"]:
        for key, label in (("oracle_long_band_over_etc", "oracle GLS, long band"),
                           ("oracle_per_bin_over_etc", "oracle GLS, per bin")):
            ax.plot(z, [r["grids"][ncol][key] for r in res["redshifts"]], "s--", label=f"{label}, {ncol} columns")
    ax.axhline(1.0, color="k", lw=0.8)
    ax.axhspan(0.95, 1.05, color="0.9", zorder=0)
    ax.set_xlabel("redshift")
    ax.set_ylabel("SNR / ETC")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--redshifts", type=float, nargs="+", default=[0.3, 0.5, 0.8])
    ap.add_argument("--ncols", type=int, nargs="+", default=[58, 116], help="rectified columns per slice")
    ap.add_argument("--out", default=str(HERE / "results"))
    args = ap.parse_args()
    mapper = SlicerMapper.default()
    res = {"cpu": cpu_model(), "load_before": loadavg(),
           "redshifts": [one_redshift(z, mapper, args.ncols) for z in args.redshifts]}
    res["load_after"] = loadavg()
    write_results(args.out, "etc_snr_bound", res, markdown(res))
    plot(res, Path(args.out) / "etc_snr_bound.png")


if __name__ == "__main__":
    main()
