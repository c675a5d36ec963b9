"""
The source in a raw ramp: slope next to a raw group
===================================================

What ``make demo`` draws: a SN Ia at z = 0.5, the readout the ETC chose for SNR 20 per resolution
element in the rest-frame band 4000–6800 Å, and one raw MACC ramp of that readout on a
600 × 500 px window of the H4RG around the source (the detector terms of the Lazuli
configuration).  Left: the slope (last group − first group) / Δt [ADU/s], where the supernova's
trace runs along the dispersion (y) across a few slices; right: the last raw group [ADU], the
bias pedestal plus the charge under the read noise.  Axes in detector pixels.
"""
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt

import slicersim
from slicersim.plotting import plot_ramp_group, source_zoom
from slicersim.products.ramps import simulate

sn = slicersim.LazuliSupernova(redshift=0.5)
etc = sn.setup_to_snr(20, lbda_range=(4000, 6800), frame="rest")
n, m, d = etc["nmd"]
rate = sn.get_detector_image()                                     # [e-/s/px]
r0, r1, c0, c1 = source_zoom(rate, half=(300, 250))                # the window around the source
sim, det = sn.simulation, sn.simulation.detector
path = simulate(rate[r0:r1, c0:c1], nmd=(n, m, d), nramps=1, seed=1, out=Path(tempfile.mkdtemp()) / "raw.h5",
                progress=False, tframe=det.tframe, ron=det.ron, dark=det.dark, thermal_dark=sim.thermal_dark,
                roic_glow=det.roic_glow, gain=det.gain, saturation=min(det.saturation, 65535.0))

fig = plot_ramp_group(path, origin=(r0, c0),
                      title=f"SN Ia at z = 0.5; ETC readout (n, m, d) = ({n}, {m}, {d}) × {etc['nramps']} ramp(s), "
                            f"{etc['exposure_time']:.0f} s")
plt.show()
