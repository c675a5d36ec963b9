"""The layers of the package, as data (no slicersim imports).

:data:`LAYERS` lists every top-level module and subpackage of ``slicersim``, lowest first, each
with what it holds.  A layer imports only the layers listed before it (imports inside functions
included); it never imports a name starting with ``_`` from another layer, nor the package root.
The root ``slicersim/__init__.py`` is the facade above them all: it re-exports the public API and
nothing inside the package imports it.  ``tests/test_layers.py`` checks all of this with ``ast``
(0 cycles between subpackages, 0 upward imports, 0 private names imported across them) and that
the layer chain in the package docstring is :func:`chain`.

Decisions recorded here:

* ``rng`` (the Philox core and the grids of draws the detector effects need) sits below
  ``physics``; ``backends.noise`` registers its device kernel as the engine of those grids
  (:func:`slicersim.rng.register_grid_engine`), so ``physics`` runs on the device without
  importing ``backends``.
* ``snr`` (band coverage, band-SNR tables, readout searches) sits below ``simulation``, whose
  ``band_mask`` / ``fetch_snr`` call it; the batch ETC ``etc.solve_many`` builds models
  (``assembly``) and therefore sits above.
* The Dask helpers shared by campaigns and reductions (``check_workers``, ``dask_client``,
  ``QuietDask``, ``run_task_window`` in ``campaign.runner``; ``limit_threads``,
  ``mark_failed`` in ``campaign.products``) are public names of ``campaign``, which
  ``reduction`` sits above.
"""
from __future__ import annotations

__all__ = ["LAYERS", "names", "rank", "chain"]

#: (name, content) of every layer, lowest first
LAYERS = (
    ("layers", "this list"),
    ("errors", "every exception (SlicersimError and its subclasses)"),
    ("constants", "physical constants"),
    ("keywords", "names of user input in messages, choices, renamed keywords, dataclass fields"),
    ("validation", "argument checkers"),
    ("versioning", "the release number and the change tracking of model objects"),
    ("memo", "byte-bounded caches keyed by content"),
    ("data", "instrument data files"),
    ("rng", "counter-based Philox draws (NumPy)"),
    ("io", "file formats, no physics"),
    ("plotting", "figures from arrays and duck-typed models (NumPy, matplotlib)"),
    ("physics", "readout, ramps, detector effects, LSF, PSF, thermal emission"),
    ("kernels", "OpenCL C sources (package data)"),
    ("backends", "OpenCL kernels and their NumPy twins"),
    ("instrument", "telescope, spectrograph, detector, detector-plane mapper"),
    ("sources", "spectra, scene, extended sources, lamps"),
    ("products", "cubes, raw ramps and their effects"),
    ("ramps", "import path of products.ramps"),
    ("cube", "import path of products.cube"),
    ("snr", "band coverage, band-SNR tables, readout searches"),
    ("simulation", "the Simulation model"),
    ("assembly", "configuration to model"),
    ("etc", "the batch exposure-time calculator"),
    ("targets", "high-level targets"),
    ("campaign", "populations, survey plans, campaigns on Dask"),
    ("reduction", "pipeline steps on raw ramps, campaign reductions"),
    ("app", "command line, demo, plots"),
    ("__main__", "python -m slicersim"),
)


def names():
    """Layer names, lowest first."""
    return tuple(name for name, _ in LAYERS)


def rank(name):
    """Position of layer ``name`` in :data:`LAYERS` (0: lowest); KeyError for an unknown name."""
    try:
        return names().index(name)
    except ValueError:
        raise KeyError(f"{name!r} is not a layer of slicersim (slicersim.layers.LAYERS)") from None


def chain():
    """The layer chain as written in the package docstring: ``a`` → ``b`` → …"""
    return " → ".join(f"``{name}``" for name in names())
