"""Diagnostic figures: extracted spectrum and SNR, variance budget, instrument curves, cube
slices, raw-ramp groups (from :mod:`slicersim.plotting`, the low-level layer that the model
objects' ``show_*`` methods call); and (from :mod:`slicersim.app.pictures`, which needs the
configuration) both fields' scene and cube, PSF profiles, the slice map.

Every function accepts either a :class:`~slicersim.targets.Target` (anything
with a ``.simulation``) or a :class:`~slicersim.simulation.Simulation`, returns
the matplotlib :class:`~matplotlib.figure.Figure` and, with ``savefile``,
writes it to disk and releases it from pyplot.  pyplot is imported lazily and
``plt.show`` is never called, so the functions work with the Agg backend
(scripts, tests, headless machines) as well as interactively.
"""
from __future__ import annotations

from slicersim.app.pictures import show_fields, show_psf_profiles, show_slice_map
from slicersim.plotting import (SOURCE_STYLES, plot_cube_slices, plot_curves, plot_instrument, plot_ramp_group,
                                plot_spectrum, plot_variance_budget, save_figure)

__all__ = ["plot_spectrum", "plot_variance_budget", "plot_instrument", "plot_ramp_group", "plot_cube_slices",
           "plot_curves", "save_figure", "SOURCE_STYLES", "show_fields", "show_psf_profiles", "show_slice_map"]
