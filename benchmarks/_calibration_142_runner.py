"""Run inside benchmarks/.refvenv142 (slicersim==1.4.2): QTH and Fabry–Perot flats, offline.

Usage: python _calibration_142_runner.py OUTPUT.npz OUTPUT.json [--image]

Writes the per-bin median spaxel spectra (narrow/wide QTH, narrow FP) to OUTPUT.npz and the
scalars (lamp surface brightness, cube sums, readout, etalon table path, optional detector
image) to OUTPUT.json.  band="bessellr": 1.4.2's default "sdssr" needs a download.
"""
import json
import sys
import time
import warnings

import numpy as np

warnings.filterwarnings("ignore")
WAVELENGTHS = [5000.0, 6000.0, 10000.0, 15000.0]


def main():
    out_npz, out_json = sys.argv[1], sys.argv[2]
    with_image = "--image" in sys.argv[3:]
    import slicersim
    from slicersim.iotools import expand_path
    from slicersim.lazuli import Lazuli3DFlat
    res = {"version": slicersim.__version__, "wavelengths": WAVELENGTHS}
    arrays = {}
    t0 = time.perf_counter()
    qth = Lazuli3DFlat.from_qth(band="bessellr")
    res["readout"] = {k: list(v) if isinstance(v, tuple) else v for k, v in qth.get_readout_config().items()}
    res["exposure_time"] = float(qth.get_exposure_time())
    bg = qth.simulation.scene.background
    res["lamp_surface_brightness"] = [float(v) for v in bg.get_spectrum(np.array(WAVELENGTHS))[1]]
    (cn, vn), (cw, vw) = qth.get_cube(which="both")
    arrays["lbda"] = np.asarray(qth.simulation.spectrograph.lbda, float)
    for name, cube, var in (("narrow", cn, vn), ("wide", cw, vw)):
        arrays[f"qth_{name}_median"] = np.nanmedian(cube, axis=(1, 2))
        arrays[f"qth_{name}_variance_median"] = np.nanmedian(var, axis=(1, 2))
        res[f"qth_{name}_shape"] = list(cube.shape)
        res[f"qth_{name}_sum"] = float(np.nansum(cube))
        res[f"qth_{name}_spatial_ptp_max"] = float(np.nanmax(np.nanmax(cube, axis=(1, 2))
                                                             - np.nanmin(cube, axis=(1, 2))))
    res["qth_max"] = float(max(np.nanmax(cn), np.nanmax(cw)))
    res["saturation"] = float(qth.simulation.detector.saturation)
    res["qth_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    fp = Lazuli3DFlat.from_febryperot(band="bessellr")
    c, _ = fp.get_cube(which="current")
    arrays["fp_narrow_median"] = np.nanmedian(c, axis=(1, 2))
    res["fp_s"] = time.perf_counter() - t0
    res["fp_table"] = str(expand_path("lazuli_fp_transmission.csv"))
    if with_image:
        from slicersim.mapper import SlicerMapper
        t0 = time.perf_counter()
        mapper = SlicerMapper.from_data(str(expand_path("mapping_spotdata.csv")))
        img = qth.to_image(mapper)
        res["image"] = {"sum": float(np.nansum(img)), "nonzero": int(np.count_nonzero(img)),
                        "max": float(np.nanmax(img)), "seconds": time.perf_counter() - t0}
    np.savez(out_npz, **arrays)
    with open(out_json, "w") as fh:
        json.dump(res, fh)


if __name__ == "__main__":
    main()
