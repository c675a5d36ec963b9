"""Run inside benchmarks/.refvenv (slicersim==1.0.0): time cube and Airy-spectrum calls.

Usage: python _reference_cube_runner.py INPUT.npz OUTPUT.json REPEAT
"""
import json
import sys
import time
import warnings

import numpy as np

warnings.filterwarnings("ignore")


def timed(func, repeat):
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        func()
        out.append(time.perf_counter() - t0)
    return out


def main():
    inp, outp, repeat = sys.argv[1], sys.argv[2], int(sys.argv[3])
    import slicersim
    data = np.load(inp)
    target = slicersim.LazuliTarget(data["lbda"], data["flux"], mag=None, band="bessellb")
    target.change_detector(nmd=(16, 8, 0), nramps=1)
    sim = target.simulation
    res = {"version": slicersim.__version__,
           "cube_gaussian_s": timed(lambda: sim.get_cube(psf_profile="default"), repeat),
           "cube_airy_s": timed(lambda: sim.get_cube(psf_profile="airy"), repeat),
           "spectrum_airy_s": timed(lambda: sim.get_spectrum(psf_profile="airy"), max(1, repeat - 1))}
    cube = sim.get_cube(psf_profile="airy")
    res["cube_airy_sum_adu"] = float(np.nansum(np.asarray(cube[0])))
    with open(outp, "w") as fh:
        json.dump(res, fh)


if __name__ == "__main__":
    main()
