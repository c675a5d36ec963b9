"""
Cube slices at a few wavelengths
================================

A noisy (λ, y, x) cube of a SN Ia at z = 0.5 with its Airy PSF, in the narrow field, read out
with MACC(16, 8, 0) × 1 ramp.  Each panel is one wavelength bin of the noisy cube, in ADU
summed over the ramps; y runs across the slices, x along them (positions in cells).
"""
import matplotlib.pyplot as plt
import numpy as np

import slicersim

sn = slicersim.LazuliSupernova(redshift=0.5, field="narrow")
sn.change_detector(nmd=(16, 8, 0), nramps=1)
signal, variance, noisy = sn.simulation.get_cube(seed=42, psf_profile="airy")
lbda = sn.simulation.lbda                     # bin centres [Å]
print("cube shape (λ, y, x):", noisy.shape)

wanted = (6000.0, 9000.0, 12000.0, 15000.0)
fig, axes = plt.subplots(1, len(wanted), figsize=(13, 3.4), constrained_layout=True)
for ax, w in zip(axes, wanted):
    k = int(np.argmin(np.abs(lbda - w)))
    im = ax.imshow(noisy[k], origin="lower", cmap="magma", aspect="auto")
    ax.set_title(f"λ = {lbda[k]:.0f} Å")
    ax.set_xlabel("x [cells along the slice]")
    fig.colorbar(im, ax=ax, label="signal per cell [ADU]")
axes[0].set_ylabel("y [slice]")
fig.suptitle("Noisy cube of a SN Ia at z = 0.5, narrow field, MACC(16, 8, 0) × 1")
plt.show()
