"""Data products computed from a model: cubes (:mod:`~slicersim.products.cube`) and raw
MACC ramps (:mod:`~slicersim.products.ramps`)."""
