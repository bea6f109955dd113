"""The z-buffer rasteriser of the synthetic 3D head: :mod:`keyshape.base.raster` (shared with the rig
preview, which only sees the base), re-exported under its old name."""
from keyshape.base.raster import Fragments, rasterize

__all__ = ["Fragments", "rasterize"]
