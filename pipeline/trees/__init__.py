"""Individual trees of a scene: tree IDs, tops, crowns, heights and stem diameters.

Parameters are in :mod:`pipeline.trees.params`.
"""

from pipeline.trees.params import TreeParams

__all__ = ["TreeParams"]
