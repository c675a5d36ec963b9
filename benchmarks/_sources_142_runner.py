"""Run inside benchmarks/.refvenv142 (slicersim==1.4.2): the power-law cases of sources_vs_142.py.

Usage: python _sources_142_runner.py INPUT.json OUTPUT.json OUTPUT.npz
INPUT: {"cases": [[alpha, mag], ...], "band": "bessellr", "waves": [...], "band_obs": [lo, hi],
        "snr": 20, "nmd": [n, m, d], "blur_modes": ["native", "physical"]}

Each case: ``LazuliPowerLaw(alpha=, mag=, band=)`` in the narrow field (``change_spectrograph``,
as ``_blur_reference_runner.py`` does), its input F_λ at ``waves``, the band SNR per resolution
element at the readout ``nmd`` × 1, then ``setup_to_snr(snr, lbda_range=band_obs, frame="obs")``.
Blur modes are those of ``_blur_reference_runner.py`` ("physical": σ_x = √(dr²−4)/2 cells, ours).
"""
import json
import sys
import time
import warnings

import numpy as np

warnings.filterwarnings("ignore")


def main():
    inp, out_json, out_npz = sys.argv[1:4]
    with open(inp) as fh:
        spec = json.load(fh)
    import slicersim
    from _blur_reference_runner import _blur_sigma, _override_blur     # same folder (sys.path[0])
    waves = np.asarray(spec["waves"], dtype=float)
    band = spec["band_obs"]
    results, arrays = [], {}
    for (alpha, mag), mode in ((case, mode) for mode in spec["blur_modes"] for case in spec["cases"]):
        target = slicersim.LazuliPowerLaw(alpha=alpha, mag=mag, band=spec["band"])
        target.change_spectrograph("narrow")
        sim = target.simulation
        sigma = _blur_sigma(mode, float(sim.spectrograph.dispersion_resolution))
        if sigma is not None:
            _override_blur(sim.spectrograph, sigma)
        lbda = np.asarray(sim.spectrograph.lbda, dtype=float)
        _, flux = sim.scene.pointsource.get_spectrum(lbda)
        target.simulation.update(nmd=tuple(spec["nmd"]), nramps=1)
        _, signal, variance = target.get_spectrum(incl_error=False)
        row = {"alpha": alpha, "mag": mag, "blur_mode": mode, "nbins": int(lbda.size),
               "flux_at_waves": np.interp(waves, lbda, flux).tolist(),
               "snr_at_nmd": float(target.get_band_snr(band, frame="obs", per_resolution=True)),
               "exposure_time_at_nmd": float(target.get_exposure_time())}
        t0 = time.perf_counter()
        config, reached = target.setup_to_snr(spec["snr"], lbda_range=band, frame="obs")
        row.update(etc_s=time.perf_counter() - t0, nmd=[int(v) for v in config["nmd"]],
                   nramps=int(config["nramps"]), snr=float(reached),
                   exposure_time=float(target.get_exposure_time()))
        results.append(row)
        key = f"{mode}_a{alpha}_m{mag}"
        arrays[key + "_lbda"], arrays[key + "_signal"], arrays[key + "_variance"] = lbda, signal, variance
    with open(out_json, "w") as fh:
        json.dump({"version": slicersim.__version__, "cases": results}, fh)
    np.savez(out_npz, **arrays)


if __name__ == "__main__":
    main()
