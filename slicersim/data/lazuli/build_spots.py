#!/usr/bin/env python
"""Build slicersim's own Lazuli detector layout ``lazuli_spots.csv``.

The file has the format of the reference's optical model table
(``slice fieldpos lbda x y rmsx_um rmsy_um``; λ in µm, x/y in mm from the
detector centre, spot rms in µm) and is read by
``slicersim.mapper.SlicerMapper.default()``.  It is a *synthetic* layout
built from the assumptions below, not a ray trace of the as-built
instrument:

* H4RG detector, 4096 × 4096 pixels of 10 µm; p = 100·X[mm] + 2048.
* 116 slices: narrow field (slices 1–58) on the top half (p_y > 2048), wide
  field (59–116) on the bottom half, each field in two horizontal tiers of
  29 slices (as in the reference layout): tier 1 = slices 1–29, tier 2 =
  30–58, tier 3 = 59–87, tier 4 = 88–116, centred at p_y = 3584, 2560, 1536,
  512.  Tiers 1 and 3 run towards −x with the slice id, tiers 2 and 4 towards
  +x (so slices 29/30 and 87/88, neighbours on the sky, are stacked).  Slice
  pitch 121 px, centred on p_x = 2048.
* Dispersion along −y (blue at the top of each tier), following the
  simulator's own dispersion law: ``dispersion_prism.ecsv`` through the same
  not-a-knot cubic spline as the wavelength grid, scaled by
  K = dispersion_scale × dispersion_resolution / 2 of ``lazuli_cbe.toml``
  (1.3 × 2.3 / 2 = 1.495), i.e. one CBE wavelength bin per pixel.  The
  0.4 µm point of every slice sits D_span/2 above the tier centre
  (D_span = D(1.70001 µm) = 509.4 px).
* Slice length along x: L = 116 px × (0.995 − 0.09 ρ²) × (1 + 0.005 (τ − ½))
  (0.90–1.0 × 116 px; ρ ∈ [−1, 1] is the slice's x position across the
  detector, τ = D(λ)/D_span), with a small cubic (barrel) term along the
  slice; fieldpos −1 → +1 runs towards −x.
* Distortions: the slice centre drifts towards the detector centre with λ
  (x_c = 2048 + (x_c0 − 2048)(1 − 0.008 (τ − ½)), ≤ 14 px over the trace at
  the edges), smile p_y += 1.5 px (1 + 0.3 ρ²) φ² and tilt p_y += 1.2 px ρ φ.
* Spot rms (µm): the optics' aberration, growing with λ and towards the slice ends / field
  edges: rmsx = 2.0 + 2.4 w + 0.4 φ² + 0.3 ρ², rmsy = 2.0 + 2.7 w + 0.3 φ² + 0.3 ρ²,
  w = (λ − 0.39)/(1.72 − 0.39): 2.0–5.3 µm (0.2–0.53 px), within the aberration budget of the
  CBE dispersion resolution dr = 2.3 px, σ_ab = √(dr² − 2²)/2 = 0.568 px (the monochromatic slice
  image is the 2-px slice width blurred by the aberration: the cube's LSF carries it, and the
  projection adds only a spot's excess over it, ``SlicerMapper.cube_blur_px``).  The reference's
  ray-traced narrow-field medians are 1.1–4.5 µm.
* Nodes: fieldpos −1, −0.5, 0, 0.5, 1; λ from 0.39 to 1.72 µm (beyond the
  4000–17000 Å grid and its bin edges), placed so that the piecewise-linear
  interpolation between nodes follows the dispersion spline to ≤ 0.05 px
  (56 nodes).  Written with 1e-5 mm (0.001 px) and 0.001 µm resolution.

Run ``python build_spots.py`` to rewrite the file (deterministic; needs
numpy, scipy and astropy).
"""
import os
import sys
import tomllib

import numpy as np
from astropy.table import Table
from scipy.interpolate import CubicSpline

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "lazuli_spots.csv")

NPIX, PIX_UM = 4096, 10.0
FIELDPOS = np.array([-1.0, -0.5, 0.0, 0.5, 1.0])
LBDA_MIN, LBDA_MAX = 0.39, 1.72        # micron
NODE_TOL_PX = 0.05
PITCH = 121.0
TIER_Y = (3584.0, 2560.0, 1536.0, 512.0)
LENGTH = 116.0
SMILE, TILT, DRIFT, BARREL = 1.5, 1.2, 0.008, 0.02


def dispersion_px():
    """D(λ [µm]) [px]: the simulator's dispersion spline, scaled by K of the CBE config."""
    with open(os.path.join(HERE, "lazuli_cbe.toml"), "rb") as fh:
        spec = tomllib.load(fh)["spectrograph"]
    law = Table.read(os.path.join(HERE, spec["dispersion_law"]), format="ascii.ecsv")
    k = spec["dispersion_scale"] * spec["dispersion_resolution"] / 2.0
    lam = np.asarray(law["wavelength"].to("micron").value, float)
    return CubicSpline(lam, k * np.asarray(law["offset"], float), bc_type="not-a-knot", extrapolate=True), k


def lbda_nodes(disp, tol=NODE_TOL_PX, step=1e-4):
    """Greedy nodes (multiples of 1e-4 µm) with linear-interpolation error ≤ tol px."""
    fine = np.round(np.arange(LBDA_MIN, LBDA_MAX + step / 2, step), 4)
    d = disp(fine)
    nodes = [0]
    while nodes[-1] < fine.size - 1:
        a = nodes[-1]
        lo, hi = a + 1, fine.size - 1
        while lo < hi:                      # largest b with chord error <= tol
            b = (lo + hi + 1) // 2
            chord = d[a] + (d[b] - d[a]) * (fine[a:b + 1] - fine[a]) / (fine[b] - fine[a])
            if np.abs(chord - d[a:b + 1]).max() <= tol:
                lo = b
            else:
                hi = b - 1
        nodes.append(lo)
    return fine[nodes]


def layout(disp, lam):
    """(slice, fieldpos, lbda, x_mm, y_mm, rmsx_um, rmsy_um) rows."""
    d_span = float(disp(1.70001))
    tau = disp(lam) / d_span                                  # 0 at 0.4 µm, 1 at 1.7 µm
    w = (lam - LBDA_MIN) / (LBDA_MAX - LBDA_MIN)
    rows = []
    for s in range(1, 117):
        tier, n = divmod(s - 1, 29)
        sign = -1.0 if tier in (0, 2) else 1.0                 # tiers 1, 3 run towards -x
        xc0 = NPIX / 2 + sign * PITCH * (n - 14)
        rho = (xc0 - NPIX / 2) / (14 * PITCH)
        for phi in FIELDPOS:
            length = LENGTH * (0.995 - 0.09 * rho**2) * (1 + 0.005 * (tau - 0.5))
            xc = NPIX / 2 + (xc0 - NPIX / 2) * (1 - DRIFT * (tau - 0.5))
            px = xc - 0.5 * length * (phi + BARREL * phi**3) / (1 + BARREL)
            py = (TIER_Y[tier] + d_span / 2 - disp(lam) + SMILE * (1 + 0.3 * rho**2) * phi**2
                  + TILT * rho * phi)
            rmsx = 2.0 + 2.4 * w + 0.4 * phi**2 + 0.3 * rho**2
            rmsy = 2.0 + 2.7 * w + 0.3 * phi**2 + 0.3 * rho**2
            to_mm = PIX_UM / 1000.0
            rows.append(np.stack([np.full_like(lam, s), np.full_like(lam, phi), lam,
                                  (px - NPIX / 2) * to_mm, (py - NPIX / 2) * to_mm, rmsx, rmsy], axis=1))
    return np.concatenate(rows)


def main(argv):
    disp, k = dispersion_px()
    lam = lbda_nodes(disp)
    table = layout(disp, lam)
    np.savetxt(OUT, table, fmt=["%d", "%.2f", "%.4f", "%.5f", "%.5f", "%.3f", "%.3f"],
               header="slice fieldpos lbda x y rmsx_um rmsy_um",
               comments="")
    print(f"K = {k:.4f}; {lam.size} lbda nodes {lam[0]}-{lam[-1]} um; {table.shape[0]} rows -> {OUT}")
    print(f"x {table[:, 3].min() * 100 + 2048:.1f}-{table[:, 3].max() * 100 + 2048:.1f} px, "
          f"y {table[:, 4].min() * 100 + 2048:.1f}-{table[:, 4].max() * 100 + 2048:.1f} px, "
          f"rms {table[:, 5:].min():.2f}-{table[:, 5:].max():.2f} um")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
