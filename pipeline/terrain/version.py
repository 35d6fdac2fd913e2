"""Which terrain code a scene's heights come from: a saved model records it, so a model
applied after the DTM changed can say so (its forests learned heights above another DTM)."""

#: The version of the terrain model's code: raised whenever a change moves the DTM values
#: of data a model may have been trained on (not for a refactor that keeps every bit). The
#: terrain step's fingerprint holds it: a store of another version redoes its terrain.
#:
#: 1. Before the DTM that follows steep slopes (fb47284): a ground cell's value was its
#:    lowest point's z, wherever in the cell it lay, and the fill levelled off at the edges.
#:    A model.json without the key (``terrain.version``) is taken for it, even one saved
#:    later but before the key existed: the warning it brings errs towards speaking.
#: 2. The DTM follows steep slopes (fb47284): a ground cell's lowest point is carried to
#:    the cell's centre along the local slope, and the fill continues the known cells'
#:    plane to the raster's edges (a 40° hillside's DTM bias -0.36 -> -0.003 m).
#: 3. A sparse raster (its points see fewer than a quarter of their neighbouring cells
#:    with a point) is filtered at the data's own resolution (73c81ab, ``sparse_factor``):
#:    other DTMs of sparse surveys; a dense raster's DTM keeps every bit of version 2.
#:
#: Not counted (each kept the DTMs of the shared airborne, terrestrial, mobile and Oakland
#: clouds and of the synthetic scenes to the bit): deep multipath pits emptied before the
#: filter (9b3fe11), far-apart groups of cells and fixed blocks modelled apart (4600fee,
#: c23d750: a scene smaller than a block keeps its model), seen ground cells kept (6e8734d).
TERRAIN_VERSION = 3
