"""Band SNR of one model, below :mod:`slicersim.simulation` in the layers (it calls them):
the coverage rule of an SNR band (:mod:`~slicersim.snr.bands`), the band-SNR table of models ×
readouts (:mod:`~slicersim.snr.snr_table`) and the readout searches for an SNR goal
(:mod:`~slicersim.snr.search`, used by ``Simulation.fetch_snr`` and by the batch ETC
:func:`slicersim.etc.solve_many`).  Models are duck-typed: nothing here imports the simulation."""
