"""Slice numbering of the Lazuli image slicer: slices 1–58 feed the narrow field, 59–116 the wide
field (the spot table's ``slice`` column)."""

__all__ = ["NARROW_SLICES", "WIDE_SLICES"]

#: slice numbers of the narrow field
NARROW_SLICES = tuple(range(1, 59))
#: slice numbers of the wide field
WIDE_SLICES = tuple(range(59, 117))
