"""Write the real airborne tiles of ../shared/data/als as two scenes for training and scoring
a model across sites: each tile cut at its median x, the west halves side by side in one
scene, the east halves in another.

The tiles come from three sites, three CRSs and three densities (0.9-58 points/m²); a scene
is one cloud, so each half is moved (by its header offset: every point keeps its integer
coordinates and every dimension) to its own place, 1 km apart, in a local frame without a
CRS. Every feature of Silva is invariant to that move (coordinates are recentred, heights
are taken above the scene's own terrain model). Noise (7, 18) stays: Silva excludes it.

    python benchmarks/als_scenes.py OUT_DIR     # OUT_DIR/west/*.laz, OUT_DIR/east/*.laz
"""

import argparse
import sys
from pathlib import Path

import laspy
import numpy as np

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "als"
TILES = ("StBarth_IGN_LiDARHD_100m.laz", "AHN4_Amsterdam_2496_9727.laz", "Topography.laz")
SPACING = 1000.0  # metres between the halves in the local frame


def write_half(las: laspy.LasData, keep: np.ndarray, place: float, dst: Path) -> int:
    """Write the points ``keep`` of ``las`` moved so that their box starts at (place, 0)."""
    header = laspy.LasHeader(point_format=las.header.point_format, version=las.header.version)
    header.scales = las.header.scales
    x, y = np.asarray(las.x)[keep], np.asarray(las.y)[keep]
    shift = np.array([place - x.min(), -y.min(), 0.0])
    header.offsets = las.header.offsets + shift
    out = laspy.LasData(header)
    out.points = las.points[keep].copy()
    out.header.offsets = header.offsets
    out.write(dst)
    return int(keep.sum())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    args = parser.parse_args(argv)
    if not DATA.is_dir():
        print(f"no airborne tiles at {DATA}: nothing to write", file=sys.stderr)
        return 1
    for side in ("west", "east"):
        (args.out / side).mkdir(parents=True, exist_ok=True)
    for i, name in enumerate(TILES):
        las = laspy.read(DATA / name)
        x = np.asarray(las.x)
        west = x < np.median(x)
        stem = Path(name).stem
        for side, keep in (("west", west), ("east", ~west)):
            n = write_half(las, keep, i * SPACING, args.out / side / f"{stem}_{side}.laz")
            print(f"{side}/{stem}_{side}.laz: {n:,} points")
    return 0


if __name__ == "__main__":
    sys.exit(main())
