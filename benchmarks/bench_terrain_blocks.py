"""Time of a scene's ground model when its points lie in plots far apart.

    python benchmarks/bench_terrain_blocks.py [--gap G] [--size S] [--mode blocks|box]

Two synthetic plots of S x S m, the second G m east and G m north of the first. ``box``: one
minima raster over the scene's bounding box, filtered whole (the model before blocks);
``blocks``: the ground model of each connected block of occupied cells on its own raster
(:func:`pipeline.terrain.block_models`, as the terrain step). Prints the seconds of the
ground model (the coordinator's share of the terrain step) and the cells it covered.
"""

import argparse
import sys
import time

import numpy as np

from pipeline.synth import synthetic_plot
from pipeline.synth.params import DEFAULT_ORIGIN
from pipeline.terrain import TerrainParams, cell_minima, ground_model, minima_offsets, minima_raster


def two_plots(size: float, gap: float) -> np.ndarray:
    x0, y0, z0 = DEFAULT_ORIGIN
    first, _ = synthetic_plot(1, size, origin=(x0, y0, z0))
    second, _ = synthetic_plot(2, size, origin=(x0 + gap, y0 + gap, z0))
    return np.concatenate([first, second])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gap", type=float, default=1000.0, help="metres east and north")
    parser.add_argument("--size", type=float, default=20.0, help="side of each plot, metres")
    parser.add_argument("--mode", choices=("blocks", "box"), default="blocks")
    args = parser.parse_args(argv)
    params = TerrainParams()
    keys, zmin, xy = cell_minima(two_plots(args.size, args.gap), params.cell)
    start = time.perf_counter()
    if args.mode == "box":
        minima = minima_raster(keys, zmin, params.cell)
        ground_model(minima, params, minima_offsets(keys, xy, minima))
        cells = minima.values.size
    else:
        from pipeline.terrain import block_models

        blocks, _ = block_models(keys, zmin, xy, params)
        cells = sum(dtm.values.size for dtm in blocks.dtms)
    seconds = time.perf_counter() - start
    print(f"{args.mode}: {len(zmin)} occupied cells, {cells} cells modelled, {seconds:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
