"""The terrain in fixed blocks: how far it moves from a model of the whole scene, and what it
costs when the points lie in plots far apart.

    python benchmarks/bench_terrain_blocks.py compare [DATA_DIR] [--blocks 1000 50 25]
    python benchmarks/bench_terrain_blocks.py plots [--gap G] [--size S] [--mode blocks|box]
    python benchmarks/bench_terrain_blocks.py truth [--density 500000 250000 62500 10000]
                                                    [--seeds 0 1] [--code DIR]

``compare``: on every airborne tile of the shared data (``als/*.laz`` and the airborne and
drone clips of ``trees/``), the heights above ground of the tile's points under the blocked
terrain (:func:`pipeline.terrain.scene_terrain`, as the terrain step) and under one model of
the whole tile (:func:`pipeline.terrain.terrain_model`): RMSE and largest difference, per
block size (metres; small blocks cut a 100 m tile in many). ``plots``: two synthetic plots of
S x S m, the second G m east and G m north of the first; ``box`` filters one raster over
their bounding box (the model before blocks), ``blocks`` the scene's blocks; prints the
seconds and the cells modelled. ``truth``: one 1 km block of a synthetic survey whose ground
is known (:class:`pipeline.synth.Terrain`: a 5 % slope, waves of 10 to 600 m, 0.03 m of
noise; a forest over a third of it, 60 % of its points on crowns 2 to 20 m up; houses 7 m
high), at each number of points a km² over the block and its region, modelled as a terrain
task models it (:func:`pipeline.terrain.block_model`): the DTM's error against the true
ground (RMSE, 99th percentile and largest, every 2 m of the block's core), the heights
above ground of the core's ground points (RMSE) and of its crowns and roofs (RMSE, and the
share under 1 m) against their true heights, and the seconds (wall, CPU). ``--code DIR``
measures the checkout at DIR (default: this one) on the same points.
"""

import argparse
import sys
import time
from pathlib import Path

import laspy
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"


def airborne_tiles(data: Path) -> list[Path]:
    return sorted(data.glob("als/*.laz")) + [data / "trees" / name for name in
                                             ("ALS_Clip.laz", "UAS_Clip.laz")]


def compare(data: Path, blocks: list[float]) -> None:
    from pipeline.terrain import TerrainParams, ground_elevation, scene_terrain, terrain_model

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
    from pipeline.terrain import (
        TerrainParams, cell_minima, ground_model, minima_offsets, minima_raster, scene_terrain,
    )

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


#: The block of ``truth``: 1 km at the default 1 m cells, its south-west corner here.
ORIGIN = (600_000.0, 6_400_000.0)


def known_ground(seed: int):
    """The true ground of ``truth``'s survey: z = f(x, y) in map coordinates."""
    from pipeline.synth import Terrain

    rng = np.random.default_rng(seed)
    waves = []
    # (count, wavelengths in m, amplitude per metre of wavelength): hills, then undulations
    for count, (low, high), amplitude in ((6, (60.0, 600.0), 0.015), (10, (10.0, 60.0), 0.01)):
        wavelength = np.exp(rng.uniform(np.log(low), np.log(high), count))
        direction = rng.uniform(0.0, 2 * np.pi, count)
        k = 2 * np.pi / wavelength
        waves.append(np.c_[k * np.cos(direction), k * np.sin(direction),
                           rng.uniform(0.0, 2 * np.pi, count),
                           amplitude * wavelength * rng.uniform(0.5, 1.0, count)])
    terrain = Terrain(slope=np.array([0.05, -0.03]), waves=np.concatenate(waves))
    return lambda x, y: 200.0 + terrain.height(x - ORIGIN[0], y - ORIGIN[1])


def known_survey(per_km2: int, seed: int, side: float, pad: float):
    """``per_km2`` points a km² over the square of ``side`` m at ORIGIN and ``pad`` m around
    it: xyz (N, 3), kind (0 ground, 1 crown, 2 roof) and the true ground."""
    truth = known_ground(seed)
    rng = np.random.default_rng(seed + 1000)
    span = side + 2 * pad
    n = int(per_km2 * (span / 1000.0) ** 2)
    xy = np.asarray(ORIGIN) - pad + rng.random((n, 2)) * span
    z = truth(xy[:, 0], xy[:, 1]) + rng.normal(0.0, 0.03, n)
    stand = np.sin(xy[:, 0] / 90.0) * np.sin(xy[:, 1] / 120.0) > 0.3
    house = (np.abs(np.mod(xy[:, 0], 250.0) - 125.0) < 8) & (
        np.abs(np.mod(xy[:, 1], 250.0) - 125.0) < 6) & ~stand
    r = np.hypot(*(xy - np.round(xy / 5.0) * 5.0).T)  # conifers on a 5 m lattice
    crown = stand & (rng.random(n) < 0.6)
    z[crown] += np.maximum(20.0 - 6.0 * r[crown], 2.0) * rng.uniform(0.9, 1.0, crown.sum())
    z[house] += 7.0
    return np.column_stack((xy, z)), np.where(crown, 1, np.where(house, 2, 0)), truth


def truth(densities: list[int], seeds: list[int]) -> None:
    from pipeline.terrain import (
        BlockGrid, TerrainParams, block_model, cell_minima, ground_elevation,
    )

    params = TerrainParams()
    grid = BlockGrid.of(params)
    block = tuple(int(o // (grid.size * grid.cell)) for o in ORIGIN)
    side = grid.size * grid.cell
    print(f"{'pts/km2':>9s} {'seed':>4s} {'DTM rmse':>8s} {'p99':>6s} {'max':>6s} "
          f"{'ground':>7s} {'above':>7s} {'<1 m':>6s} {'wall s':>7s} {'cpu s':>7s}")
    for per_km2 in densities:
        for seed in seeds:
            xyz, kind, ground = known_survey(per_km2, seed, side, grid.buffer * grid.cell + 5)
            keys, zmin, xy = cell_minima(xyz, params.cell)
            wall, cpu = time.perf_counter(), time.process_time()
            model = block_model(keys, zmin, xy, grid, block, params).terrain
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            gx, gy = np.meshgrid(ORIGIN[0] + np.arange(1.0, side, 2.0),
                                 ORIGIN[1] + np.arange(1.0, side, 2.0))
            error = ground_elevation(model, np.column_stack((gx.ravel(), gy.ravel()))) - ground(
                gx.ravel(), gy.ravel())
            core = ((xyz[:, :2] >= ORIGIN) & (xyz[:, :2] < np.asarray(ORIGIN) + side)).all(axis=1)
            height = xyz[core, 2] - ground_elevation(model, xyz[core, :2])
            wrong = height - (xyz[core, 2] - ground(xyz[core, 0], xyz[core, 1]))
            above = kind[core] > 0
            print(f"{per_km2:9,d} {seed:4d} {np.sqrt(np.mean(error ** 2)):8.3f} "
                  f"{np.quantile(np.abs(error), 0.99):6.2f} {np.abs(error).max():6.2f} "
                  f"{np.sqrt(np.mean(wrong[~above] ** 2)):7.3f} "
                  f"{np.sqrt(np.mean(wrong[above] ** 2)):7.3f} "
                  f"{np.mean(height[above] < 1.0):6.1%} {wall:7.2f} {cpu:7.2f}", flush=True)


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
    three = sub.add_parser("truth")
    three.add_argument("--density", type=int, nargs="+",
                       default=[500_000, 250_000, 62_500, 10_000], help="points a km²")
    three.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    for command in (one, two, three):
        command.add_argument("--code", type=Path, default=ROOT,
                             help="the checkout to measure (default: this one)")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(args.code.resolve()))
    if args.what == "compare":
        compare(args.data, args.blocks)
    elif args.what == "plots":
        plots(args.size, args.gap, args.mode)
    else:
        truth(args.density, args.seeds)
    return 0


if __name__ == "__main__":
    sys.exit(main())
