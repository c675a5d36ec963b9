"""Figures from arrays and duck-typed models (NumPy, matplotlib; nothing above ``io``).

The ``show_*`` methods of the model objects (``Target.show_spectrum``, ``Simulation.show_cube``,
``Spectrograph.show_throughput``, ``SlicerMapper.show_slices``, ``Detector.show_qe``, ...) are
thin calls of these functions; :mod:`slicersim.app.plotting` re-exports them next to the
figures that need the configuration (both fields, PSF profiles, the default slice map).
Every function returns the matplotlib Figure, writes it with ``savefile`` (atomically, then
releases it from pyplot), imports pyplot lazily and never calls ``plt.show``.
"""
from slicersim.plotting.campaign import plot_bias_vs_redshift, plot_snr_vs_etc
from slicersim.plotting.figures import (MAX_PANELS, check_axes, check_savefile, colorbar, figure_writer, finish,
                                        image_norm, new_axes, save_figure)
from slicersim.plotting.images import (check_region, draw_slices, plot_cube_slices, plot_ramp_group, sky_extent,
                                       source_zoom)
from slicersim.plotting.spectra import (SOURCE_STYLES, plot_curves, plot_instrument, plot_spectrum,
                                        plot_variance_budget, readout_title)

__all__ = ["MAX_PANELS", "check_axes", "check_savefile", "colorbar", "figure_writer", "finish", "image_norm",
           "new_axes", "save_figure", "check_region",
           "draw_slices", "plot_cube_slices", "plot_ramp_group", "sky_extent", "source_zoom", "SOURCE_STYLES",
           "plot_curves", "plot_instrument", "plot_spectrum", "plot_variance_budget", "readout_title",
           "plot_bias_vs_redshift", "plot_snr_vs_etc"]
