"""NumPy oracle of the cube, independent of the cube builder: the whole photon cube of
``Simulation.get_projected_scene`` (scipy LSF), QE, then ``Simulation.cell_variance`` (formerly
the public ``Simulation.get_cube_numpy``)."""
import numpy as np

from slicersim.products.components import check_switch_off


def cube_numpy(sim, nmd=None, nramps=None, switch_off=None):
    """(signal [ADU] (NaN where saturated), variance [ADU²]) of ``sim``, all ramps summed."""
    off = check_switch_off(switch_off)
    times = sim.get_times(nmd, nramps)
    nmd, nramps, tint = times["nmd"], times["nramps"], times["integration_time_per_ramp"]
    photons = sim.get_projected_scene(off, backend="numpy")      # ph/s/cell
    electrons = photons * sim.qe[:, None, None]                  # e-/s/cell
    variance, saturated = sim.cell_variance(electrons, nmd, off)  # ADU² per ramp
    signal = np.where(saturated, np.nan, electrons * tint * sim.detector.gain) * nramps
    return signal, variance * nramps
