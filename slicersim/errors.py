"""Every exception slicersim raises on purpose.

All user-facing errors derive from :class:`SlicersimError`, so a script (or the
CLI) can catch them in one place; each is also a ``ValueError``, ``OSError`` or
``RuntimeError`` as its meaning suggests, so code catching those keeps working.
"""
from __future__ import annotations

__all__ = ["SlicersimError", "ConfigError", "ReadoutError", "SpectrumError", "ETCError",
           "ParameterError", "RampFileError", "OpenCLUnavailableError", "OpenCLForkError", "DatasetError", "EffectsError",
           "ReductionError", "CurveError", "GalaxyDataUnavailable", "ResourceError",
           "ImplausibleValueWarning"]


class SlicersimError(Exception):
    """Base class of every slicersim error."""


class ConfigError(SlicersimError, ValueError):
    """Invalid configuration: unknown key, bad or unphysical value, missing curve file."""


class ParameterError(SlicersimError, ValueError):
    """Invalid model parameter (``update``, ``set_*``, ``change_*``, constructors)."""


class ReadoutError(SlicersimError, ValueError):
    """Impossible readout mode or number of ramps."""


class SpectrumError(SlicersimError, ValueError):
    """Invalid input spectrum, or a band the spectrum/grid does not cover."""


class ETCError(SlicersimError, ValueError):
    """Impossible exposure-time request."""


class RampFileError(SlicersimError, OSError):
    """Raw-ramp file cannot be written or read (exists, disk full, incomplete, foreign layout)."""


class OpenCLUnavailableError(SlicersimError, RuntimeError):
    """No usable OpenCL platform/device (or the selected one does not exist or lacks fp64)."""


class OpenCLForkError(SlicersimError, RuntimeError):
    """OpenCL used in a process forked after OpenCL was initialised."""


class DatasetError(SlicersimError, OSError):
    """A campaign dataset or one of its files cannot be written, read or trusted."""


class EffectsError(SlicersimError, ValueError):
    """Invalid detector-systematics request: unknown effect name, negative rate or fraction,
    IPC kernel summing to more than 1, non-invertible nonlinearity."""


class ReductionError(SlicersimError, RuntimeError):
    """A reduction step that cannot give a trustworthy result on these data: a point-source fit that
    does not converge, lands on the field edge, or finds no source near the light's centroid."""


class CurveError(ConfigError):
    """A throughput, QE or spectrum curve file cannot be read: missing, malformed, unknown unit."""


class GalaxyDataUnavailable(SlicersimError, ImportError):
    """A named real galaxy was asked for without the optional ``lazuli-astrosim-data`` package."""


class ResourceError(SlicersimError, MemoryError):
    """Not enough memory (host or OpenCL device) for a request: names what was being allocated and
    the option that bounds it (``max_bytes``, ``--max-bytes``, ``--memory-per-task``), or an input
    whose declared size exceeds the machine's memory."""


class ImplausibleValueWarning(UserWarning):
    """A bare number far outside the plausible range of its documented unit (``guiding_sigma=10``
    is 10 arcsec, not the paper's 10 mas): the value is used; pass an astropy Quantity to be explicit."""
