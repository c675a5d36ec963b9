"""How much correlated-noise variance the reference-pixel correction removes from group means
and from the OLS slopes of a ramp (the rate image), full H4RG-10 geometry (4096², 32 outputs),
NGHXRG default amplitudes, MACC(n, 8, 0), light-sensitive pixels only.

E[before] is the model (``group_combination_variance`` with ``ols_slope_weights``; w = (1,) for
group means), E[after] the mean over ramps of the generator (``CorrelatedNoise``, seed 21) after
``refpix_correct``, each group corrected on its own full frame.  With ``--check-ramps N`` the
model's slope variance is also checked against N ramps of the generator (rows 2000:2016, no
correction: the uncorrected slope variance needs many ramps, the slow drift is one draw per ramp).

    .venv/bin/python benchmarks/refpix_slopes.py --groups 16 --ramps 10           # ≈ 13 s per ramp
    .venv/bin/python benchmarks/refpix_slopes.py --groups 64 --ramps 4            # ≈ 60 s per ramp, 4 GB
    .venv/bin/python benchmarks/refpix_slopes.py --groups 16 --ramps 0 --check-ramps 240
    .venv/bin/python benchmarks/refpix_slopes.py --groups 16 --ramps 2 --own-only       # u_pink + ACN only

Prints one JSON line per ramp and a summary line (removed fractions ± the standard error of the
ramp mean).  ``--first`` starts at another ramp index (to split a run).
"""
import argparse
import json
import time

import numpy as np

from slicersim.backends.correlated_noise import CorrelatedNoise
from slicersim.physics.correlated_noise import (CorrelatedNoiseParameters, ReadoutGeometry,
                                                group_combination_variance, ols_slope_weights,
                                                picture_frame_template)
from slicersim.physics.reference_pixels import reference_pixel_mask
from slicersim.reduction.refpix import refpix_correct

SHAPE, M, TFRAME, SEED = (4096, 4096), 8, 2.83, 21


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--groups", type=int, default=16)
    ap.add_argument("--ramps", type=int, default=10)
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--check-ramps", type=int, default=0)
    ap.add_argument("--own-only", action="store_true",
                    help="each output's own noise only (c_pink, pedestal, picture frame 0)")
    a = ap.parse_args(argv)
    nmd = (a.groups, M, 0)
    p = CorrelatedNoiseParameters(**(dict(c_pink=0.0, pedestal=0.0, picture_frame=0.0) if a.own_only else {}))
    g = ReadoutGeometry.from_params(p, SHAPE, TFRAME)
    inner = ~reference_pixel_mask(SHAPE)
    ey, ex = picture_frame_template(SHAPE)
    pf_ms = float(np.mean((ey[4:-4, None] + ex[None, 4:-4]) ** 2))
    w = ols_slope_weights(nmd, TFRAME)
    slope_model = group_combination_variance(w, nmd, p, g, picture_frame_ms=pf_ms)
    mean_model = group_combination_variance([1.0], (1, M, 0), p, g, picture_frame_ms=pf_ms)
    print(json.dumps({"nmd": nmd, "slope_before_model": slope_model, "mean_before_model": mean_model}), flush=True)
    gen = CorrelatedNoise(p, SHAPE, nmd, TFRAME, SEED)
    summary = {"nmd": nmd, "own_only": a.own_only, "slope_before_model": slope_model, "mean_before_model": mean_model}
    if a.check_ramps:
        v = []
        for ramp in range(a.check_ramps):
            b = gen.block(ramp, 2000, 2016).astype(np.float64)
            v.append(float(np.mean(np.tensordot(w, b, 1)[:, 4:-4] ** 2)))
        summary["slope_before_generator"] = (float(np.mean(v)), float(np.std(v, ddof=1) / np.sqrt(len(v))))
    slope_after, mean_after = [], []
    for ramp in range(a.first, a.first + a.ramps):
        t0 = time.perf_counter()
        b = gen.block(ramp, 0, SHAPE[0])
        sb, sa, mb, ma = np.zeros(SHAPE), np.zeros(SHAPE), [], []
        for k in range(a.groups):
            c = refpix_correct(b[None, k:k + 1])[0, 0]
            sb += w[k] * b[k]
            sa += w[k] * c
            mb.append(float(np.mean(b[k][inner].astype(np.float64) ** 2)))
            ma.append(float(np.mean(c[inner] ** 2)))
        del b
        row = {"ramp": ramp, "mean_before": float(np.mean(mb)), "mean_after": float(np.mean(ma)),
               "slope_before": float(np.mean(sb[inner] ** 2)), "slope_after": float(np.mean(sa[inner] ** 2)),
               "seconds": time.perf_counter() - t0}
        print(json.dumps(row), flush=True)
        slope_after.append(row["slope_after"])
        mean_after.append(row["mean_after"])
    for key, after, model in (("slope", slope_after, slope_model), ("mean", mean_after, mean_model)):
        if len(after) > 1:
            m, e = float(np.mean(after)), float(np.std(after, ddof=1) / np.sqrt(len(after)))
            summary[f"{key}_after"] = (m, e)
            summary[f"{key}_removed"] = (1 - m / model, e / model)
    print(json.dumps(summary), flush=True)


if __name__ == "__main__":
    main()
