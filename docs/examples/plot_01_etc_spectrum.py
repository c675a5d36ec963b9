"""
SN Ia spectrum and its SNR (ETC)
================================

The exposure-time calculator finds the cheapest readout that reaches SNR 20 per resolution
element in the rest-frame band 4000–6800 Å for a type Ia supernova at z = 0.5 (Lazuli
current-best-estimate configuration, narrow field).  The figure shows the extracted spectrum
with its ±1σ band and one noisy realisation (top), and the SNR per spectral bin (bottom) with
the ETC band shaded.  Signal and variance are summed over the ramps, in ADU and ADU².
"""
import matplotlib.pyplot as plt

import slicersim
from slicersim.app.plotting import plot_spectrum

sn = slicersim.LazuliSupernova(redshift=0.5)
result = sn.setup_to_snr(20, lbda_range=(4000, 6800), frame="rest")
print("readout:", sn.get_readout_config())
print(f"exposure time: {sn.get_exposure_time():.1f} s (all ramps)")
print(f"band SNR: {result['snr_per_resolution']:.2f} per resolution element, {result['snr']:.2f} per bin")

fig = plot_spectrum(sn, seed=1)
plt.show()
