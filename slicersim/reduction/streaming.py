"""Streaming campaigns: the reduction a campaign task runs on a target's ramps as soon as they are
simulated (``[products] reduce`` of a campaign spec, :mod:`slicersim.campaign.products`).

Campaigns sit below reductions in the layers, so this module registers :func:`reduce_ramps` with
:func:`slicersim.campaign.products.register_reducer` on import (``import slicersim`` imports it).
The reduction is the one ``slicersim reduce DATASET [--spectra]`` runs on each target of a dataset,
with the same defaults (no option given, the target's own field), so a streamed campaign's reduced
products are those of simulating the campaign and reducing it afterwards, byte for byte.
"""
from __future__ import annotations

from slicersim.campaign.products import register_reducer

__all__ = ["reduce_ramps"]


def reduce_ramps(ramps_path, out_path, mode, field):
    """Reduce one target's raw ramps as ``slicersim reduce DATASET`` does, defaults included.

    Parameters
    ----------
    ramps_path : str
        The target's ramp file (HDF5, :mod:`slicersim.io.rampfile` layout).
    out_path : str
        The reduced product, written atomically (replaced when present): rates, cubes and spectra
        (``reduced.h5``) with ``mode="spectra"`` (spectra; "cubes": and the cubes, as ``--spectra
        --cubes``), rates only (``rates.h5``) with ``mode="rates"``.
    mode : {"spectra", "cubes", "rates"}
    field : str
        The target's field ("narrow" or "wide"; empty: "narrow"), whose cube and spectrum are made.

    Returns
    -------
    str
        ``out_path``.
    """
    from slicersim.errors import ParameterError
    from slicersim.reduction.campaign import reduce_file
    if mode not in ("spectra", "cubes", "rates"):
        raise ParameterError(f"mode must be 'spectra', 'cubes' or 'rates', got {mode!r}")
    spectra = mode != "rates"
    options = {"field": field or "narrow"} if spectra else {}       # as reduce_dataset's task
    if mode == "cubes":
        options["cubes"] = True
    reduce_file(ramps_path, out_path, spectra=spectra, overwrite=True, progress=False, fit_options={},
                mapper=None, **options)
    return out_path


register_reducer(reduce_ramps)
