"""A survey, not a plot: the memory of every process and each step's time of a predict with
the shipped airborne model on synthetic contiguous surveys of growing area.

    python benchmarks/bench_survey.py [--areas 1 4 16 64] [--points N | --density D]
                                      [--tile M] [--trees] [--rasters] [--out DIR]

Each survey is square, of ``--areas`` km², cut into tiles of ``--tile`` metres (LAZ, with
two returns on the crowns: the model's echo features need them): rolling ground, conifer
crowns over a third of it, a few buildings. ``--points``: the same number of points whatever
the area (sparser over a larger one); ``--density``: points per m² (the points grow with the
area). Every survey is classified by ``silva predict --model als-ground-vegetation-building``
without a configuration (``--trees``: with output.trees, ``--rasters``: with the DTM and
CHM rasters); the process tree is sampled every half second. Prints per survey the points,
the peak resident memory of the command's process (the coordinator) and of the largest
other process (a worker), the wall time and each step's seconds (OUT/work/durations.json).
"""

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import laspy
import numpy as np
import psutil

ORIGIN = (600_000.0, 6_400_000.0)
CRS = 2154  # a projected CRS in metres (Lambert-93)


def write_tile(path: Path, x0: float, y0: float, side: float, n: int, seed) -> None:
    """One tile of ``n`` points: ground, crowns and roofs, with return numbers."""
    rng = np.random.default_rng(seed)
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
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = [0.01] * 3, [x0, y0, 0.0]
    header.add_crs(__import__("pyproj").CRS.from_epsg(CRS))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xy[:, 0], xy[:, 1], z
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


def watch(command: list[str]) -> dict:
    """Run ``command``; the peak RSS of its process and of every descendant, and the wall."""
    start = time.monotonic()
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
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


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--areas", type=float, nargs="+", default=[1.0, 4.0, 16.0, 64.0])
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--density", type=float, default=None)
    parser.add_argument("--tile", type=float, default=500.0)
    parser.add_argument("--trees", action="store_true")
    parser.add_argument("--rasters", action="store_true")
    parser.add_argument("--out", type=Path, default=Path("bench-survey"))
    args = parser.parse_args(argv)
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
        result = watch(command)
        steps = json.loads((out / "work" / "durations.json").read_text()) \
            if (out / "work" / "durations.json").exists() else {}
        status = "" if result["code"] == 0 else f"  FAILED ({result['stderr'].strip()[-300:]})"
        print(f"{km2:6g} {points:11,d} {result['coordinator'] / 2**30:9.2f} "
              f"{result['worker'] / 2**30:10.2f} {result['seconds']:8.0f}  "
              + " ".join(f"{k} {v:.0f}" for k, v in steps.items()) + status, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
