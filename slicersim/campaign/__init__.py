"""Campaigns: populations, survey plans and mock datasets on Dask.

* :mod:`~slicersim.campaign.population` — SN Ia populations and user catalogs;
* :mod:`~slicersim.campaign.plan` — the batch ETC of a population: readouts, times, volumes, totals;
* :mod:`~slicersim.campaign.spec` — campaign specs (TOML);
* :mod:`~slicersim.campaign.products` — one target's products (the unit of work of a worker);
* :mod:`~slicersim.campaign.runner` — the Dask runner (embedded LocalCluster or a scheduler).

Submodules are imported on use (a worker needs only ``products``).
"""
__all__ = ["population", "plan", "spec", "products", "runner", "distributions"]
