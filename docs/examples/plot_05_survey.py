"""
Survey time and data volume against redshift
============================================

The batch ETC (:func:`slicersim.campaign.plan.plan_survey`) gives every SN Ia its readout, total
exposure time and raw data volume; here SNe Ia at peak (hsiao-subsampled template,
M_B = −19.3, Planck18) from z = 0.1 to 1.5, SNR 20 and 25 per resolution element in the rest
frame 4000–6800 Å, narrow field below z = 0.8 and wide field from it (Lazuli CBE, exact search).
The points are the numbers the slicersim paper gives in its text: exposure times of 5 min
(z = 0.2), 72.4 and 81 min (z = 1) and 4.8 h (z = 1.5) at SNR 20; 6.5 min, 97 min and 7.6 h at
SNR 25; raw volumes of about 1 GB at z = 0.2 and 23 GB at z = 1.5.  The plan's data volume is in
bytes (16-bit reads, every group of every ramp of the 4096² detector).
"""
import matplotlib.pyplot as plt
import numpy as np

from slicersim.campaign.plan import plan_survey
from slicersim.campaign.population import snia_fluxes
from slicersim.campaign.products import spectrum_grid

z = np.round(np.arange(0.1, 1.51, 0.1), 2)
lbda = spectrum_grid()                                            # [Å]
flux = np.nan_to_num(snia_fluxes(lbda, z, np.zeros(z.size), np.full(z.size, -19.3)))   # erg/s/cm²/Å

PAPER_HOURS = {20: ([0.2, 1.0, 1.0, 1.5], [5 / 60, 72.4 / 60, 81 / 60, 4.8]),
               25: ([0.2, 1.0, 1.5], [6.5 / 60, 97 / 60, 7.6])}
PAPER_GB = ([0.2, 1.5], [1.0, 23.0])

fig, (ax_t, ax_v) = plt.subplots(1, 2, figsize=(12, 4.5), constrained_layout=True)
for snr, colour in ((20, "C0"), (25, "C1")):
    plan = plan_survey(z, lbda, flux, snr=snr, z_switch=0.8)
    table = plan.table
    hours = np.asarray(table["exposure_time"]) / 3600.0            # s → h
    gigabytes = np.asarray(table["data_volume"]) / 1e9             # bytes → GB
    ax_t.plot(z, hours, "-o", color=colour, ms=4, label=f"slicersim, SNR {snr}")
    ax_v.plot(z, gigabytes, "-o", color=colour, ms=4, label=f"slicersim, SNR {snr}")
    pz, ph = PAPER_HOURS[snr]
    ax_t.plot(pz, ph, "*", color=colour, ms=13, mec="k", label=f"paper, SNR {snr}")
    print(f"SNR {snr}: z = 1.5 needs {hours[-1]:.2f} h and {gigabytes[-1]:.1f} GB "
          f"({table['n'][-1]}, {table['m'][-1]}, {table['d'][-1]}) × {table['nramps'][-1]}")
ax_v.plot(*PAPER_GB, "k*", ms=13, label="paper (text)")
ax_t.set_ylabel("exposure time [h]")
ax_v.set_ylabel("raw data volume [GB]")
for ax in (ax_t, ax_v):
    ax.axvline(0.8, color="0.6", lw=0.8, ls=":")
    ax.set_xlabel("redshift")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
ax_t.set_title("total exposure time per SN Ia (narrow | wide field)")
ax_v.set_title("raw group-level data volume per SN Ia")
plt.show()
