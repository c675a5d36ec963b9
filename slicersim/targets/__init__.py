"""Targets: a source (spectrum, optional host) observed with an instrument configuration.

``base``: :class:`Target` and the built-in point sources (SN Ia, black body) with their Lazuli
variants and the ETC shortcuts (the ETC and product methods of a target: ``observation``, its
detector image and ramps: ``detector``); ``sources``: power laws, any sncosmo source, kilonovae, CALSPEC
stars; ``galaxy``: galaxies alone with aperture extraction; ``calibration``: QTH flats and
Fabry–Perot exposures (their flat-field structure: ``flatfield``).
"""
from slicersim.targets.base import (SPECTRUM_NOISE_STREAM, BlackBody, LazuliBlackBody, LazuliSupernova,
                                    LazuliTarget, Supernova, Target, build_simulation, config_default_field,
                                    lazuli_etc, lazuli_sn_etc)
from slicersim.targets.calibration import Flat3DCalibration, FlatFieldStructure, Lazuli3DFlat, locate_peaks
from slicersim.targets.galaxy import Galaxy, LazuliGalaxy
from slicersim.targets.sources import (CalSpec, Kilonova, LazuliCalSpec, LazuliKilonova, LazuliPowerLaw,
                                       LazuliSncosmoTarget, PowerLaw, SncosmoTarget)

__all__ = ["SPECTRUM_NOISE_STREAM", "BlackBody", "LazuliBlackBody", "LazuliSupernova", "LazuliTarget", "Supernova",
           "Target", "build_simulation", "config_default_field", "lazuli_etc", "lazuli_sn_etc",
           "Flat3DCalibration", "FlatFieldStructure", "Lazuli3DFlat", "locate_peaks", "Galaxy", "LazuliGalaxy",
           "CalSpec", "Kilonova", "LazuliCalSpec", "LazuliKilonova", "LazuliPowerLaw", "LazuliSncosmoTarget",
           "PowerLaw", "SncosmoTarget"]
