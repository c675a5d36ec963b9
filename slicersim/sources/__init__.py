"""Astrophysical sources: spectra and point sources, extended hosts, background, the scene."""
