"""A survey, not a plot: the memory of every process and each step's time of a predict with
the shipped airborne model on synthetic contiguous surveys of growing area.

    python benchmarks/bench_survey.py [--areas 1 4 16 64] [--points N | --density D]
                                      [--tile M] [--trees] [--rasters] [--out DIR]
    python benchmarks/bench_survey.py --block 10000 62500 250000 [--seed S]

Each survey is square, of ``--areas`` km², cut into tiles of ``--tile`` metres (LAZ, with
two returns on the crowns: the model's echo features need them): rolling ground, conifer
crowns over a third of it, a few buildings. ``--points``: the same number of points whatever
the area (sparser over a larger one); ``--density``: points per m² (the points grow with the
area). Every survey is classified by ``silva predict --model als-ground-vegetation-building``
without a configuration (``--trees``: with output.trees, ``--rasters``: with the DTM and
CHM rasters); the process tree is sampled every half second. Prints per survey the points,
the peak resident memory of the command's process (the coordinator) and of the largest
other process (a worker), the wall time and each step's seconds (OUT/work/durations.json).

``--block``: one terrain block of 1 km at the default 1 m cells, modelled in this process as
a terrain task models it (:func:`pipeline.terrain.block_model`), from the same survey's
points at each given number per km² over the block and its region (1,000 points a km² is a
survey of 100 km² holding 100,000; 10,000 one of 100 km² holding 1 M): prints the seconds
(wall and CPU), the cells with a point, the DTM's cells, the cells the filter's solves and
passes visited (:data:`pipeline.terrain.grid.WORK`, where the code has it) and the
process's peak memory so far.

``--code DIR``: measure the checkout at DIR (default: this one) on the same data, e.g. a
``git worktree`` of an earlier commit.
"""

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import laspy
import numpy as np
import psutil

ROOT = Path(__file__).resolve().parents[1]
ORIGIN = (600_000.0, 6_400_000.0)
CRS = 2154  # a projected CRS in metres (Lambert-93)


def survey_points(x0: float, y0: float, side: float, n: int, rng
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``n`` points over the square of ``side`` m at (x0, y0): xyz (n, 3), their class (2
    ground, 5 crown, 6 roof), number of returns and return number."""
    xy = np.column_stack([x0 + rng.random(n) * side, y0 + rng.random(n) * side])
    ground = (200.0 + 8.0 * np.sin(xy[:, 0] / 300.0) + 6.0 * np.cos(xy[:, 1] / 410.0))
    stand = np.sin(xy[:, 0] / 90.0) * np.sin(xy[:, 1] / 120.0) > 0.3  # a third in forest
    house = (np.abs(np.mod(xy[:, 0], 250.0) - 125.0) < 8) & (
        np.abs(np.mod(xy[:, 1], 250.0) - 125.0) < 6) & ~stand
    # conifers on a 5 m lattice: cones of 20 m, the points' share on the crown 60 %
    cx, cy = np.round(xy[:, 0] / 5.0) * 5.0, np.round(xy[:, 1] / 5.0) * 5.0
    r = np.hypot(xy[:, 0] - cx, xy[:, 1] - cy)
    on_crown = stand & (rng.random(n) < 0.6)
    z = ground.copy()
    z[on_crown] += np.maximum(20.0 - 6.0 * r[on_crown], 2.0) * rng.uniform(0.9, 1.0,
                                                                           on_crown.sum())
    z[house] += 7.0
    classification = np.where(on_crown, 5, np.where(house, 6, 2)).astype(np.uint8)
    returns = np.where(stand, 2, 1).astype(np.uint8)
    number = np.where(on_crown, 1, returns).astype(np.uint8)
    return np.column_stack([xy, z]), classification, returns, number


def write_tile(path: Path, x0: float, y0: float, side: float, n: int, seed) -> None:
    """One tile of ``n`` points: ground, crowns and roofs, with return numbers."""
    xyz, classification, returns, number = survey_points(x0, y0, side, n,
                                                         np.random.default_rng(seed))
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = [0.01] * 3, [x0, y0, 0.0]
    header.add_crs(__import__("pyproj").CRS.from_epsg(CRS))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.classification = classification
    las.number_of_returns, las.return_number = returns, number
    las.write(path)


def write_survey(root: Path, km2: float, points: int, tile: float) -> list[Path]:
    side = 1000.0 * np.sqrt(km2)
    n_side = max(1, int(round(side / tile)))
    tile = side / n_side
    per_tile = max(1, points // n_side ** 2)
    root.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(n_side):
        for j in range(n_side):
            path = root / f"t{i:03d}_{j:03d}.laz"
            if not path.exists():
                write_tile(path, ORIGIN[0] + i * tile, ORIGIN[1] + j * tile, tile, per_tile,
                           (i, j))
            paths.append(path)
    return paths


def watch(command: list[str], code: Path) -> dict:
    """Run ``command`` in the checkout ``code``; the peak RSS of its process and of every
    descendant, and the wall."""
    start = time.monotonic()
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        filter(None, [str(code), os.environ.get("PYTHONPATH")])))
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                               cwd=code, env=env)
    main = psutil.Process(process.pid)
    peaks = {}
    while process.poll() is None:
        try:
            for p in [main, *main.children(recursive=True)]:
                rss = p.memory_info().rss
                peaks[p.pid] = max(peaks.get(p.pid, 0), rss)
        except psutil.Error:
            pass
        time.sleep(0.5)
    coordinator = peaks.pop(process.pid, 0)
    return {"code": process.returncode, "seconds": time.monotonic() - start,
            "coordinator": coordinator, "worker": max(peaks.values(), default=0),
            "stderr": process.stderr.read().decode()[-2000:]}


def one_block(per_km2: int, seed: int) -> None:
    """Model the block at ORIGIN from ``per_km2`` points a km² over its region."""
    import resource

    from pipeline.terrain import BlockGrid, TerrainParams, block_model, cell_minima
    from pipeline.terrain import grid as terrain_grid

    params = TerrainParams()
    grid = BlockGrid.of(params)
    block = tuple(int(o // (grid.size * grid.cell)) for o in ORIGIN)
    x0, y0, x1, _ = grid.region_box(block)
    side = x1 - x0
    xyz = survey_points(x0, y0, side, int(per_km2 * (side / 1000.0) ** 2),
                        np.random.default_rng(seed))[0]
    keys, zmin, xy = cell_minima(xyz, params.cell)
    work = getattr(terrain_grid, "WORK", None)
    if work is not None:
        work.clear()
    wall, cpu = time.perf_counter(), time.process_time()
    model = block_model(keys, zmin, xy, grid, block, params)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    cells = sum(d.values.size for d in model.terrain.dtms)
    visited = "-" if work is None else f"{sum(v for k, v in work.items() if k != 'output'):,d}"
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    print(f"{per_km2:9,d} {len(keys):10,d} {cells:11,d} {visited:>13s} {wall:8.2f} {cpu:8.2f} "
          f"{peak:9.2f}", flush=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--areas", type=float, nargs="+", default=[1.0, 4.0, 16.0, 64.0])
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--density", type=float, default=None)
    parser.add_argument("--tile", type=float, default=500.0)
    parser.add_argument("--trees", action="store_true")
    parser.add_argument("--rasters", action="store_true")
    parser.add_argument("--out", type=Path, default=Path("bench-survey"))
    parser.add_argument("--block", type=int, nargs="+", default=None, metavar="PER_KM2",
                        help="model one 1 km terrain block at these points a km² instead")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--code", type=Path, default=ROOT,
                        help="the checkout to measure (default: this one)")
    args = parser.parse_args(argv)
    code, args.out = args.code.resolve(), args.out.resolve()
    sys.path.insert(0, str(code))
    if args.block:
        print(f"{'pts/km2':>9s} {'occupied':>10s} {'DTM cells':>11s} {'visited':>13s} "
              f"{'wall s':>8s} {'cpu s':>8s} {'peak GiB':>9s}")
        for per_km2 in args.block:
            one_block(per_km2, args.seed)
        return 0
    print(f"{'km2':>6s} {'points':>11s} {'coord GiB':>9s} {'worker GiB':>10s} {'wall':>8s}  "
          "steps (s)")
    for km2 in args.areas:
        points = int(args.density * km2 * 1e6) if args.density else args.points
        name = f"{km2:g}km2-{points}"
        tiles = write_survey(args.out / "data" / name, km2, points, args.tile)
        out = args.out / "runs" / name
        command = [sys.executable, "-m", "workflows", "predict", "--model",
                   "als-ground-vegetation-building", "--out", str(out), "--overwrite", "-q",
                   str(tiles[0].parent / "*.laz")]
        if args.trees:
            command += ["--set", "output.trees=true"]
        if args.rasters:
            command += ["--set", "output.rasters=[dtm,chm]"]
        result = watch(command, code)
        steps = json.loads((out / "work" / "durations.json").read_text()) \
            if (out / "work" / "durations.json").exists() else {}
        status = "" if result["code"] == 0 else f"  FAILED ({result['stderr'].strip()[-300:]})"
        print(f"{km2:6g} {points:11,d} {result['coordinator'] / 2**30:9.2f} "
              f"{result['worker'] / 2**30:10.2f} {result['seconds']:8.0f}  "
              + " ".join(f"{k} {v:.0f}" for k, v in steps.items()) + status, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
