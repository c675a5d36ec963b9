"""A target's truth as its ramp files record it (:mod:`slicersim.io.target_truth`).

The expected point-source rate is the simulation's own: F_λ × f2p (telescope area, throughput,
bin width, λ/hc) → photons/s per bin, × QE, through the LSF (``Simulation.get_extraction_model``'s
``signal_rate`` / gain) [e-/s per native bin]; the ETC variance is that of the simulation's
extracted spectrum for the readout used, as a rate (ADU² / (gain · t_int · nramps)²).
"""
from __future__ import annotations

import numpy as np

from slicersim.io.target_truth import TargetTruth
from slicersim.physics.readout import readout_times

__all__ = ["target_truth", "PHASE_FRAME"]

#: phases are rest-frame days from B-band peak everywhere
PHASE_FRAME = "rest"


def target_truth(target, nmd, nramps, **meta):
    """The :class:`~slicersim.io.target_truth.TargetTruth` of ``target`` (a Target with a
    ``simulation``) observed with readout ``nmd`` = (n, m, d) and ``nramps`` ramps.

    Parameters
    ----------
    target : Target
        Its simulation gives the native bins, F_λ, the expected rate and the ETC variance.
    nmd : tuple of int
        The readout (n, m, d) of the ramps.
    nramps : int
        Number of ramps.
    **meta
        Further scalar attributes (catalog values: ``target_id``, ``phase``, ``peak_absmag``,
        ``x1``, ``c``, ``source``, ``band``, ...), over the target's own (a Supernova's ``phase``,
        ``peak_absmag``, ``source``); None values are left out.

    Returns
    -------
    TargetTruth
        Arrays on the native bins (n,): ``lbda``, ``dlbda`` [Å], ``flambda`` [erg/s/cm²/Å],
        ``rate`` [e-/s], ``etc_variance`` [(e-/s)²].
    """
    sim = target.simulation
    gain = float(sim.detector.gain)
    model = sim.get_extraction_model("gaussian")
    rate = np.asarray(model.signal_rate, float) / gain
    _, _, variance = sim.get_spectrum(nmd=tuple(nmd), nramps=int(nramps))
    scale = gain * readout_times(tuple(nmd), sim.detector.tframe)["integration_time_per_ramp"] * int(nramps)
    pos = sim.position
    attrs = {"redshift": getattr(target, "redshift", None) or 0.0, "phase_frame": PHASE_FRAME,
             "field": getattr(target, "field", None), "position_x": float(pos[0]), "position_y": float(pos[1]),
             "cell_scale": float(sim.spectrograph.spatial_scale), "nmd": list(map(int, nmd)), "nramps": int(nramps),
             "gain": gain}
    for key in ("phase", "peak_absmag", "source", "temperature"):      # a Supernova's (BlackBody's) own
        value = getattr(target, key, None)
        if isinstance(value, (int, float, str, np.integer, np.floating)) and not isinstance(value, bool):
            attrs[key] = value
    attrs.update({k: v for k, v in meta.items() if v is not None})
    return TargetTruth(attrs, np.asarray(sim.lbda, float), np.asarray(sim.spectrograph.dlbda, float)
                       * np.ones(sim.lbda.size), np.asarray(sim.pointsource_flambda, float), rate,
                       etc_variance=np.asarray(variance, float) / scale**2)
