"""Accuracy and time of the ground model (pipeline.terrain) on the real tiles of ../shared/data.

    python benchmarks/bench_terrain.py [--cell C] [--slope S] [--window W]
                                       [--threshold T] [--scalar K]

Airborne tiles: RMSE of z - DTM at the reference ground points (class 2), and the share of
high vegetation (5) and building (6) points less than 1 m above the DTM (ground taken for an
object). Noise (7) is dropped before the model is built. Terrestrial plot (unlabelled): the
interpolated fraction and the share of points more than 2 m above the DTM.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from pipeline.terrain import TerrainParams, ground_elevation, terrain_model

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
AIRBORNE = ("Topography.laz", "StBarth_IGN_LiDARHD_100m.laz", "AHN4_Amsterdam_2496_9727.laz")
TERRESTRIAL = ("LPine1_demo.laz",)
NOISE = 7


def _percent(mask) -> str:
    return f"{100.0 * mask.mean():6.2f}" if mask.size else "     -"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    defaults = TerrainParams()
    for name in ("cell", "slope", "window", "threshold", "scalar"):
        parser.add_argument(f"--{name}", type=float, default=getattr(defaults, name))
    args = parser.parse_args(argv)
    params = TerrainParams(args.cell, args.slope, args.window, args.threshold, args.scalar)
    if not DATA.is_dir():
        print(f"no data at {DATA}: nothing to measure", file=sys.stderr)
        return 0
    import laspy

    print(f"{params}")
    print(f"{'tile':32} {'points':>9} {'RMSE m':>7} {'5<1m %':>7} {'6<1m %':>7} "
          f"{'>2m %':>7} {'interp':>7} {'time s':>7}")
    for folder, names in (("als", AIRBORNE), ("tls", TERRESTRIAL)):
        for name in names:
            path = DATA / folder / name
            if not path.is_file():
                print(f"{name:32} missing")
                continue
            las = laspy.read(path)
            xyz = np.column_stack((las.x, las.y, las.z)).astype(np.float64)
            code = np.asarray(las.classification)
            xyz, code = xyz[code != NOISE], code[code != NOISE]
            start = time.perf_counter()
            model = terrain_model(xyz, params)
            seconds = time.perf_counter() - start
            height = xyz[:, 2] - ground_elevation(model.dtm, xyz[:, :2])
            ground = code == 2
            rmse = f"{np.sqrt(np.mean(height[ground] ** 2)):7.3f}" if ground.any() else "      -"
            print(f"{name:32} {len(xyz):9d} {rmse} {_percent(height[code == 5] < 1.0):>7} "
                  f"{_percent(height[code == 6] < 1.0):>7} {_percent(height > 2.0):>7} "
                  f"{model.interpolated:7.3f} {seconds:7.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
