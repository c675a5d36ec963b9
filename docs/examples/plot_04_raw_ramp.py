"""
A raw ramp: one group and a group difference
============================================

Raw MACC(8, 4, 0) ramps of a small 256 × 256 rate image (a faint sky of 0.5 e-/s per pixel, a
point-like source and a 40-pixel square at 30 e-/s) with cosmic rays, inter-pixel capacitance
and nonlinearity, seed 1.  A raw group holds the bias pedestal (2000 ADU) plus the charge
accumulated since the reset, under the read noise; the difference of the last and the first
group removes the pedestal and shows the charge collected in between: the source, and the
cosmic-ray hits of that time.  Values in ADU (gain 1 ADU/e-).
"""
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from slicersim.io.rampfile import read_ramps
from slicersim.products.ramps import simulate

yy, xx = np.mgrid[:256, :256]
rate = 0.5 + 400.0 * np.exp(-((yy - 80) ** 2 + (xx - 170) ** 2) / (2 * 2.0 ** 2))   # e-/s per pixel
rate[150:190, 60:100] += 30.0
path = simulate(rate, nmd=(8, 4, 0), nramps=1, seed=1, out=Path(tempfile.mkdtemp()) / "raw.h5", overwrite=True,
                effects="cosmic_rays,ipc,nonlinearity", progress=False)

sci, groupdq, pixeldq, attrs = read_ramps(path)
sci = sci.astype(float)                              # (ramps, groups, ny, nx) [ADU]
print("readout:", attrs["READPATT"], "groups:", sci.shape[1])
raw = sci[0, -1]
diff = sci[0, -1] - sci[0, 0]

fig, axes = plt.subplots(1, 3, figsize=(13, 4), constrained_layout=True)
for ax, img, title, label in ((axes[0], rate, "input rate", "rate [e-/s/px]"),
                              (axes[1], raw, "raw group 8 of 8", "group mean [ADU]"),
                              (axes[2], diff, "group 8 − group 1", "difference [ADU]")):
    lo, hi = np.percentile(img, (1, 99.7))
    im = ax.imshow(img, origin="lower", cmap="viridis", vmin=lo, vmax=hi)
    ax.set_title(title)
    ax.set_xlabel("x [px]")
    fig.colorbar(im, ax=ax, label=label)
axes[0].set_ylabel("y [px]")
fig.suptitle("MACC(8, 4, 0), seed 1, effects: cosmic rays, IPC, nonlinearity")
plt.show()
