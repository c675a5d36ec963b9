"""slicersim: simulate image-slicer integral-field spectrograph observations (Lazuli IFS).

Physical model (one module per stage): :mod:`scene`, :mod:`telescope`,
:mod:`spectrograph`, :mod:`detector`, :mod:`simulation`; exposure-time search in
:mod:`search` (single target) and :mod:`etc` (batch); high-level targets in
:mod:`targets`.  OpenCL plumbing lives only in :mod:`opencl`.
"""
__version__ = "0.1.0"

from .config import ConfigError, load_config
from .detector import Detector, ReadoutError
from .scene import Background, CubeSource, Host, PointSource, Scene, SersicProfile, SpectrumError
from .search import ETCError
from .simulation import Simulation
from .spectrograph import MLASpectrograph, OpticalThroughput, SlicerSpectrograph, Spectrograph
from .targets import (BlackBody, LazuliBlackBody, LazuliSupernova, LazuliTarget, Supernova, Target,
                      build_simulation, lazuli_etc, lazuli_sn_etc)
from .telescope import Telescope
from .mapper import SlicerMapper, detector_rate_image

__all__ = ["ConfigError", "load_config", "Detector", "ReadoutError", "Background", "Host", "SersicProfile", "CubeSource", "PointSource",
           "Scene", "SpectrumError", "ETCError", "Simulation", "MLASpectrograph", "OpticalThroughput",
           "SlicerSpectrograph", "Spectrograph", "BlackBody", "LazuliBlackBody", "LazuliSupernova",
           "LazuliTarget", "Supernova", "Target", "build_simulation", "lazuli_etc", "lazuli_sn_etc",
           "Telescope", "SlicerMapper", "detector_rate_image", "__version__"]
