"""Write the real airborne tiles of ../shared/data as two scenes for training and scoring
a model across sites: each tile cut at its median x, the west halves side by side in one
scene, the east halves in another.

The tiles: the three of ../shared/data/als (a town, a city, a hillside) and the ponderosa-pine
patch of ../shared/data/trees seen from a plane and from a drone (ALS_Clip, UAS_Clip), the
forest among the sites. They come from four sites, four CRSs and densities of 0.9-559
points/m²; a scene
is one cloud, so each half is moved (by its header offset: every point keeps its integer
coordinates and every dimension) to its own place, 1 km apart, in a local frame without a
CRS. Every feature of Silva is invariant to that move (coordinates are recentred, heights
are taken above the scene's own terrain model). Noise (7, 18) stays: Silva excludes it.

With ``--density D`` each half denser than D points/m² (its points over its box) is thinned
to D by :func:`pipeline.cascade.thinning.thinned_mask` (a hash of each point's index, as the
thinned copies of the cards); ``--copies K`` writes K such copies of each half, thinned with
seeds 0 to K-1 (different points, the same density), each in its own place.

    python benchmarks/als_scenes.py OUT_DIR     # OUT_DIR/west/*.laz, OUT_DIR/east/*.laz
    python benchmarks/als_scenes.py OUT_DIR --density 1 --copies 4
    python benchmarks/als_scenes.py OUT_DIR --west-share 0.25   # half the west area

``--whole`` also writes each whole tile, in one piece, to OUT_DIR/whole: the west and east
halves of a tile lie at the same place in their two scenes, so a scene of both directories
would overlay them; a model trained on all the data trains on OUT_DIR/whole/*.laz.
``--tilt DEGREES`` also writes the west halves with their ground sloping DEGREES northwards
(z += tan(DEGREES) * (y - min y): trees and walls stay vertical) to OUT_DIR/west-tilted,
each beside the west halves in the same frame: a model trained on both has seen slopes (the
east halves are scored tilted eastwards by ``bench_slopes.py --shear``).
``--west-share Q`` keeps as the west side only the points west of the Q-quantile of x (the
east side is unchanged): 0.25 gives the western half of each west half, to measure what
a model gains from twice the training area.
"""

import argparse
import sys
from pathlib import Path

import laspy
import numpy as np

from pipeline.cascade.thinning import thinned_mask, thinning_fraction

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
TILES = ("als/StBarth_IGN_LiDARHD_100m.laz", "als/AHN4_Amsterdam_2496_9727.laz",
         "als/Topography.laz", "trees/ALS_Clip.laz", "trees/UAS_Clip.laz")
SPACING = 1000.0  # metres between the halves in the local frame


def raised(Z: np.ndarray, run: np.ndarray, degrees: float, z_scale: float) -> np.ndarray:
    """The integer coordinates ``Z`` raised by tan(degrees) * run (metres from the foot of
    the slope): the ground tilted by ``degrees``, trees and walls still vertical, every other
    dimension untouched."""
    return Z + np.round(np.tan(np.radians(degrees)) * run / z_scale).astype(Z.dtype)


def write_half(las: laspy.LasData, keep: np.ndarray, place: float, dst: Path,
               tilt: float = 0.0) -> int:
    """Write the points ``keep`` of ``las`` moved so that their box starts at (place, 0),
    with their ground sloping ``tilt`` degrees northwards (z += tan(tilt) * (y - min y)):
    trees and walls stay vertical."""
    header = laspy.LasHeader(point_format=las.header.point_format, version=las.header.version)
    header.scales = las.header.scales
    x, y = np.asarray(las.x)[keep], np.asarray(las.y)[keep]
    shift = np.array([place - x.min(), -y.min(), 0.0])
    header.offsets = las.header.offsets + shift
    out = laspy.LasData(header)
    points = las.points[keep].copy()
    if tilt:
        points.Z = raised(np.asarray(points.Z), y - y.min(), tilt, header.scales[2])
    out.points = points
    out.header.offsets = header.offsets
    out.write(dst)
    return int(keep.sum())


def box_fraction(x: np.ndarray, y: np.ndarray, density: float | None) -> float:
    """The share of the points ``x``, ``y`` that thins them to ``density`` points/m² over
    their box (1: not denser, or ``density`` None)."""
    if density is None:
        return 1.0
    return thinning_fraction(len(x) / (np.ptp(x) * np.ptp(y)), density)


def thinned_to(x: np.ndarray, y: np.ndarray, density: float | None, seed: int) -> np.ndarray:
    """bool: the points of a half kept at ``density`` points/m² over its box
    (:func:`box_fraction`), by a hash of each point's index."""
    return thinned_mask(np.arange(len(x), dtype=np.int64), box_fraction(x, y, density), seed)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--density", type=float, default=None,
                        help="thin each half to this many points/m² (if denser)")
    parser.add_argument("--copies", type=int, default=1,
                        help="copies of each half, thinned with seeds 0 to copies-1")
    parser.add_argument("--whole", action="store_true",
                        help="also write each whole tile to OUT_DIR/whole (to train on all)")
    parser.add_argument("--tilt", type=float, default=None, metavar="DEGREES",
                        help="also write the west halves with their ground tilted this many "
                        "degrees northwards to OUT_DIR/west-tilted, placed beside the west "
                        "halves (to train on slopes)")
    parser.add_argument("--west-share", type=float, default=0.5,
                        help="the west side: the points west of this quantile of x (<= 0.5)")
    args = parser.parse_args(argv)
    if not 0 < args.west_share <= 0.5:
        parser.error("--west-share must be in (0, 0.5]: the west side stays west of the east")
    if args.copies < 1 or (args.density is not None and not args.density > 0):
        parser.error("--copies must be >= 1 and --density > 0")
    missing = [name for name in TILES if not (DATA / name).is_file()]
    if missing:
        print(f"no {', '.join(missing)} in {DATA}: nothing written", file=sys.stderr)
        return 1
    tilted = ("west-tilted",) if args.tilt else ()
    for side in ("west", "east") + (("whole",) if args.whole else ()) + tilted:
        (args.out / side).mkdir(parents=True, exist_ok=True)
    for i, name in enumerate(TILES):
        las = laspy.read(DATA / name)
        x = np.asarray(las.x)
        west, east = x < np.quantile(x, args.west_share), x >= np.median(x)
        stem = Path(name).stem
        y = np.asarray(las.y)
        whole = (("whole", np.ones(len(x), dtype=bool)),) if args.whole else ()
        for side, half in (("west", west), ("east", east)) + whole + (
                (("west-tilted", west),) if args.tilt else ()):
            rows = np.flatnonzero(half)
            thinned = box_fraction(x[rows], y[rows], args.density) < 1.0
            for copy in range(args.copies if thinned else 1):  # unthinned: one copy
                keep = np.zeros(len(x), dtype=bool)
                keep[rows[thinned_to(x[rows], y[rows], args.density, copy)]] = True
                name = f"{stem}_{side}" + (f"_{copy}" if args.copies > 1 else "") + ".laz"
                tilt = args.tilt if side == "west-tilted" else 0.0
                # the tilted copies after the flat ones: one frame holds both sides
                slot = copy + (args.copies if tilt else 0)
                place = (slot * len(TILES) + i) * SPACING
                n = write_half(las, keep, place, args.out / side / name, tilt)
                print(f"{side}/{name}: {n:,} points")
    return 0


if __name__ == "__main__":
    sys.exit(main())
