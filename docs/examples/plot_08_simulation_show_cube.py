"""
Simulation.show_cube: the cube at a few wavelengths
===================================================

``Simulation.show_cube`` (also on a target, ``Target.show_cube``) draws images of the cube
[ADU, summed over the ramps] at the wavelength bins nearest to the ones asked for, in arcsec on
the sky (x along the slices, square cells); with ``seed=`` a noisy cube instead of the signal.
Here the signal cube of a SN Ia at z = 0.3 in a Sérsic host galaxy, narrow field: the point
source on the host's light, and the PSF that widens with wavelength.
"""
import matplotlib.pyplot as plt

import slicersim

sn = slicersim.LazuliSupernova(redshift=0.3, host="sersic")
fig = sn.simulation.show_cube(lbda=(5000, 8000, 12000, 16000))
plt.show()
