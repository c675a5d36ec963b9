"""slicersim: simulate image-slicer integral-field spectrograph observations (Lazuli IFS).

Layers (:data:`slicersim.layers.LAYERS`, lowest first), each importing only the ones before it,
never a private (``_``) name of another, nor this package root (the facade above them all):
``layers`` → ``errors`` → ``constants`` → ``keywords`` → ``validation`` → ``versioning`` → ``memo`` →
``data`` → ``rng`` → ``io`` → ``plotting`` → ``physics`` → ``kernels`` → ``backends`` → ``instrument`` →
``sources`` → ``products`` → ``ramps`` → ``cube`` → ``snr`` → ``simulation`` → ``assembly`` → ``etc`` →
``targets`` → ``campaign`` → ``reduction`` → ``app`` → ``__main__``.
"""
from slicersim.versioning import __version__

from slicersim.io.config import load_config
from slicersim.instrument.detector import Detector
from slicersim.sources.scene import Background, Scene
from slicersim.sources.spectra import PointSource
from slicersim.errors import (ConfigError, ETCError, GalaxyDataUnavailable, ParameterError, RampFileError, ReadoutError,
                              SlicersimError, SpectrumError)
from slicersim.simulation import Simulation
from slicersim.instrument.spectrograph import MLASpectrograph, OpticalThroughput, SlicerSpectrograph, Spectrograph
from slicersim.targets import (BlackBody, LazuliBlackBody, LazuliSupernova, LazuliTarget, Supernova, Target,
                      build_simulation, lazuli_etc, lazuli_sn_etc)
from slicersim.instrument.telescope import Telescope
from slicersim.instrument.mapper import SlicerMapper, detector_rate_image
from slicersim.instrument.footprints import (FieldFootprints, SliceFootprint, detector_label_image, field_footprints,
                                             save_footprints)
from slicersim.sources.extended import CubeSource, Host, ImageProfile, SersicProfile
from slicersim.sources.galaxies import GalaxyModel, known_galaxies
from slicersim.sources.lamps import CalibrationLamp, FabryPerotEtalon, TabulatedEtalon, fabry_perot_lamp, qth_lamp
from slicersim.targets import (CalSpec, Flat3DCalibration, FlatFieldStructure, Galaxy, Kilonova, Lazuli3DFlat,
                               LazuliCalSpec, LazuliGalaxy, LazuliKilonova, LazuliPowerLaw, LazuliSncosmoTarget,
                               PowerLaw, SncosmoTarget)
# registers the reduction of streaming campaigns (products.reduce) with the campaign layer below it
from slicersim.reduction import streaming as _streaming  # noqa: E402
del _streaming

__all__ = ["ConfigError", "load_config", "Detector", "ReadoutError", "Background", "Host", "SersicProfile", "CubeSource", "PointSource",
           "Scene", "SpectrumError", "ETCError", "Simulation", "MLASpectrograph", "OpticalThroughput",
           "SlicerSpectrograph", "Spectrograph", "BlackBody", "LazuliBlackBody", "LazuliSupernova",
           "LazuliTarget", "Supernova", "Target", "build_simulation", "lazuli_etc", "lazuli_sn_etc",
           "Telescope", "SlicerMapper", "detector_rate_image", "SlicersimError", "ParameterError",
           "RampFileError", "__version__",
           "FieldFootprints", "SliceFootprint", "detector_label_image", "field_footprints", "save_footprints",
           "ImageProfile", "GalaxyDataUnavailable", "GalaxyModel", "known_galaxies", "CalibrationLamp",
           "FabryPerotEtalon", "TabulatedEtalon", "fabry_perot_lamp", "qth_lamp", "CalSpec", "Flat3DCalibration",
           "FlatFieldStructure", "Galaxy", "Kilonova", "Lazuli3DFlat", "LazuliCalSpec", "LazuliGalaxy",
           "LazuliKilonova", "LazuliPowerLaw", "LazuliSncosmoTarget", "PowerLaw", "SncosmoTarget"]
