"""
SlicerMapper.show_slices: the slices on the detector
====================================================

``SlicerMapper.show_slices`` draws the H4RG with the footprint of every slice of the fields
asked for (narrow: slices 1–58, wide: 59–116) outlined and labelled with its id at the blue end of
its trace, on the wavelength grid of a spectrograph (here the Lazuli CBE grid).  Behind the
outlines: the label image (slice id per pixel), or a detector image given with ``image=``.
"""
import matplotlib.pyplot as plt

import slicersim
from slicersim.assembly import default_mapper

sn = slicersim.LazuliSupernova(redshift=0.5)
mapper = default_mapper()
fig = mapper.show_slices(("narrow", "wide"), spectrograph=sn)
plt.show()
