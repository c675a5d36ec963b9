"""Targets: a source (spectrum, optional host) observed with an instrument configuration.

``base`` holds :class:`Target` and the built-in point sources (SN Ia, black body) with their
Lazuli variants and the ETC shortcuts; the modules beside it add further target kinds.
"""
from slicersim.targets.base import (SPECTRUM_NOISE_STREAM, BlackBody, LazuliBlackBody, LazuliSupernova,
                                    LazuliTarget, Supernova, Target, build_simulation, config_default_field,
                                    lazuli_etc, lazuli_sn_etc)

__all__ = ["SPECTRUM_NOISE_STREAM", "BlackBody", "LazuliBlackBody", "LazuliSupernova", "LazuliTarget", "Supernova",
           "Target", "build_simulation", "config_default_field", "lazuli_etc", "lazuli_sn_etc"]
