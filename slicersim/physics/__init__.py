"""Physics as functions of numbers: MACC readout and variance models, ramp sampling physics,
line-spread function, PSF profiles, thermal emission."""
