"""
Instrument curves: throughput, QE, thermal emission
===================================================

The figure methods of the instrument models of a Lazuli simulation (current best estimate,
narrow field): ``Spectrograph.show_throughput`` (telescope + IFS throughput, the fraction of the
photons that reach the detector), ``Detector.show_qe`` (quantum efficiency [e-/ph]) and
``Telescope.show_thermal_radiance`` (the mirrors' photon radiance [ph/s/m²/sr/Å], log scale).
Each accepts ``ax`` to draw into an existing Axes and returns the Figure.
"""
import matplotlib.pyplot as plt

import slicersim

sim = slicersim.LazuliSupernova(redshift=0.5).simulation
fig, (ax_t, ax_q, ax_r) = plt.subplots(1, 3, figsize=(15, 4), layout="constrained")
sim.spectrograph.show_throughput(ax=ax_t)
sim.detector.show_qe(sim.lbda, ax=ax_q)
sim.telescope.show_thermal_radiance(sim.lbda[sim.lbda > 9000], ax=ax_r)   # negligible bluewards
plt.show()
