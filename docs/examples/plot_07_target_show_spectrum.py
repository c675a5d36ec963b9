"""
Target.show_spectrum and Target.show_variance_contribution
==========================================================

slicersim 1.4.2's figure methods of a target.  After the ETC has chosen the readout of a SN Ia
at z = 0.8 (SNR 15 per resolution element in the rest-frame band 4000–6800 Å),
``show_spectrum`` draws the extracted spectrum [ADU, all ramps] with its ±1σ band and a noisy
draw, and the SNR per bin with the ETC band shaded; ``show_variance_contribution`` draws the
paper's variance budget: each source's contribution [ADU²] and its fraction of the total.
Both are thin calls of :func:`slicersim.plotting.spectra.plot_spectrum` and
:func:`slicersim.plotting.spectra.plot_variance_budget` and return the matplotlib Figure.
"""
import matplotlib.pyplot as plt

import slicersim

sn = slicersim.LazuliSupernova(redshift=0.8)
sn.setup_to_snr(15, lbda_range=(4000, 6800), frame="rest")
print("readout:", sn.get_readout_config(), f"exposure {sn.get_exposure_time():.0f} s")

fig = sn.show_spectrum(seed=1)

# %%
# The variance budget of the same exposure.
fig = sn.show_variance_contribution()
plt.show()
