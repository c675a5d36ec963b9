"""Exposure-time calculation: readout searches (:mod:`~slicersim.etc.search`), the band-SNR
table of many targets × readouts (:mod:`~slicersim.etc.snr_table`) and the batch solver
:func:`solve_many` (:mod:`~slicersim.etc.solve`)."""
from slicersim.etc.solve import solve_many

__all__ = ["solve_many"]
