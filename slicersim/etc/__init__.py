"""Batch exposure-time calculation over configurations: the batch solver
:func:`solve_many` (:mod:`~slicersim.etc.solve`)."""
from slicersim.etc.solve import solve_many

__all__ = ["solve_many"]
