"""The terrain in fixed blocks: how far it moves from a model of the whole scene, and what it
costs when the points lie in plots far apart.

    python benchmarks/bench_terrain_blocks.py compare [DATA_DIR] [--blocks 1000 50 25]
    python benchmarks/bench_terrain_blocks.py plots [--gap G] [--size S] [--mode blocks|box]

``compare``: on every airborne tile of the shared data (``als/*.laz`` and the airborne and
drone clips of ``trees/``), the heights above ground of the tile's points under the blocked
terrain (:func:`pipeline.terrain.scene_terrain`, as the terrain step) and under one model of
the whole tile (:func:`pipeline.terrain.terrain_model`): RMSE and largest difference, per
block size (metres; small blocks cut a 100 m tile in many). ``plots``: two synthetic plots of
S x S m, the second G m east and G m north of the first; ``box`` filters one raster over
their bounding box (the model before blocks), ``blocks`` the scene's blocks; prints the
seconds and the cells modelled.
"""

import argparse
import sys
import time
from pathlib import Path

import laspy
import numpy as np

from pipeline.terrain import (
    TerrainParams, cell_minima, ground_elevation, ground_model, minima_offsets, minima_raster,
    scene_terrain, terrain_model,
)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def airborne_tiles(data: Path) -> list[Path]:
    return sorted(data.glob("als/*.laz")) + [data / "trees" / name for name in
                                             ("ALS_Clip.laz", "UAS_Clip.laz")]


def compare(data: Path, blocks: list[float]) -> None:
    params = TerrainParams()
    print(f"{'tile':32s} {'points':>9s} {'block m':>8s} {'blocks':>6s} {'rmse m':>9s} "
          f"{'max m':>9s} {'s whole':>8s} {'s blocks':>8s}")
    for path in airborne_tiles(data):
        las = laspy.read(path)
        xyz = np.column_stack([las.x, las.y, las.z])
        keep = ~np.isin(np.asarray(las.classification), [7, 18])  # noise, as the model
        xyz = xyz[keep]
        start = time.perf_counter()
        whole = ground_elevation(terrain_model(xyz, params).dtm, xyz[:, :2])
        whole_s = time.perf_counter() - start
        for block in blocks:
            start = time.perf_counter()
            terrain = scene_terrain(xyz, params, block)
            blocked = ground_elevation(terrain, xyz[:, :2])
            seconds = time.perf_counter() - start
            diff = blocked - whole
            print(f"{path.name:32s} {len(xyz):9,d} {block:8g} {len(terrain.blocks):6d} "
                  f"{np.sqrt(np.mean(diff ** 2)):9.2e} {np.abs(diff).max():9.2e} "
                  f"{whole_s:8.2f} {seconds:8.2f}")


def two_plots(size: float, gap: float) -> np.ndarray:
    from pipeline.synth import synthetic_plot
    from pipeline.synth.params import DEFAULT_ORIGIN

    x0, y0, z0 = DEFAULT_ORIGIN
    first, _ = synthetic_plot(1, size, origin=(x0, y0, z0))
    second, _ = synthetic_plot(2, size, origin=(x0 + gap, y0 + gap, z0))
    return np.concatenate([first, second])


def plots(size: float, gap: float, mode: str) -> None:
    params = TerrainParams()
    xyz = two_plots(size, gap)
    start = time.perf_counter()
    if mode == "box":
        keys, zmin, xy = cell_minima(xyz, params.cell)
        minima = minima_raster(keys, zmin, params.cell)
        ground_model(minima, params, minima_offsets(keys, xy, minima))
        cells = minima.values.size
    else:
        terrain = scene_terrain(xyz, params)
        cells = sum(d.values.size for r in range(len(terrain.blocks))
                    for d in terrain.load(r).dtms)
    print(f"{mode}: {cells} cells modelled, {time.perf_counter() - start:.2f} s")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="what", required=True)
    one = sub.add_parser("compare")
    one.add_argument("data", nargs="?", type=Path, default=DATA)
    one.add_argument("--blocks", type=float, nargs="+", default=[1000.0, 50.0, 25.0])
    two = sub.add_parser("plots")
    two.add_argument("--gap", type=float, default=1000.0, help="metres east and north")
    two.add_argument("--size", type=float, default=20.0, help="side of each plot, metres")
    two.add_argument("--mode", choices=("blocks", "box"), default="blocks")
    args = parser.parse_args(argv)
    if args.what == "compare":
        compare(args.data, args.blocks)
    else:
        plots(args.size, args.gap, args.mode)
    return 0


if __name__ == "__main__":
    sys.exit(main())
