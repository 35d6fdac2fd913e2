"""Individual trees (pipeline.trees) on the ponderosa-pine patch of ../shared/data/trees.

    python benchmarks/bench_trees.py [--resolution R] [--smoothing S] [--window A B]
                                     [--peer-window W] [--png PATH]

The same patch scanned from an aircraft (ALS_Clip) and a drone (UAS_Clip); classes 2 ground,
3-5 vegetation, 7 noise (dropped). There is no reference list of trees: the bench counts
trees, their heights and crowns, and how well the two platforms agree (ALS tops with a UAS
top within 2 m). Heights are above the ground model of pipeline.terrain; the canopy is classes
3-5. Silva's chain (canopy cells, CHM, variable-window tops, bounded watershed crowns) is shown
beside a plain peer: lidR's documented ``lmf`` with a fixed circular window of
``--peer-window`` metres diameter and hmin = min_height, run with scikit-image on the same
unsmoothed CHM. ``--png`` draws the ALS CHM with both sets of tops and the crown outlines.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from pipeline.terrain import ground_elevation, terrain_model
from pipeline.trees import (
    TreeParams,
    assign_trees,
    canopy_cells,
    chm_raster,
    segment_crowns,
    tree_model,
    tree_stats,
    tree_table,
)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "trees"
PLATFORMS = ("ALS_Clip.laz", "UAS_Clip.laz")
CANOPY = (3, 4, 5)
NOISE = 7
AGREEMENT = 2.0  # metres between an ALS top and a UAS top counted as the same tree


def load_scene(path: Path):
    """xyz (N, 3), height above the ground model (N,) and canopy mask (N,), noise dropped."""
    import laspy

    las = laspy.read(path)
    code = np.asarray(las.classification)
    keep = code != NOISE
    xyz = np.column_stack((las.x, las.y, las.z)).astype(np.float64)[keep]
    dtm = terrain_model(xyz).dtm
    height = xyz[:, 2] - ground_elevation(dtm, xyz[:, :2])
    return xyz, height, np.isin(code[keep], CANOPY)


def silva_trees(xyz, height, canopy, params: TreeParams):
    """The tree table, the crowns and the CHM of a scene, all points in one chunk."""
    chm = chm_raster(canopy_cells(xyz, height, canopy, params.resolution), params.resolution)
    crowns = segment_crowns(chm, params)
    model = tree_model(crowns, None, params)
    ids = assign_trees(model, xyz, height, canopy, None, params)
    return tree_table(model, tree_stats(ids, xyz, height)), crowns, chm


def lmf_tops(chm, window: float, min_height: float) -> np.ndarray:
    """float64 (n, 3) x, y, height of lidR's lmf tops (fixed circular window of ``window``
    metres diameter, hmin = min_height) on the CHM's cells."""
    from skimage.feature import peak_local_max
    from skimage.morphology import disk

    values = np.where(np.isfinite(chm.values), chm.values, 0.0)
    radius = max(int(round(window / (2.0 * chm.cell))), 1)
    peaks = peak_local_max(values, footprint=disk(radius), threshold_abs=min_height,
                           exclude_border=False)
    rows, cols = peaks[:, 0], peaks[:, 1]
    return np.column_stack((chm.x0 + (cols + 0.5) * chm.cell,
                            chm.y0 + (rows + 0.5) * chm.cell, values[rows, cols]))


def agreement(als_xy: np.ndarray, uas_xy: np.ndarray) -> str:
    """'k/n': how many ALS tops have a UAS top within AGREEMENT metres."""
    if len(als_xy) == 0 or len(uas_xy) == 0:
        return f"0/{len(als_xy)}"
    distance, _ = cKDTree(uas_xy).query(als_xy)
    return f"{int(np.count_nonzero(distance <= AGREEMENT))}/{len(als_xy)}"


def _heights(h: np.ndarray) -> str:
    if h.size == 0:
        return "-"
    return f"{h.min():5.1f} {np.median(h):5.1f} {h.max():5.1f}"


def draw(path, chm, table, crowns, peer) -> None:
    """The CHM with Silva's tops and crown outlines and the peer's tops, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from skimage.segmentation import find_boundaries

    ny, nx = chm.shape
    extent = (chm.x0, chm.x0 + nx * chm.cell, chm.y0, chm.y0 + ny * chm.cell)
    fig, ax = plt.subplots(figsize=(8, 8))
    shown = ax.imshow(chm.values, origin="lower", extent=extent, cmap="viridis")
    outline = np.zeros((ny, nx, 4))
    outline[find_boundaries(crowns.labels, mode="inner") & (crowns.labels > 0)] = (0, 0, 0, 0.7)
    ax.imshow(outline, origin="lower", extent=extent)
    ax.plot(table["x"], table["y"], "r^", ms=8, label=f"silva ({len(table)})")
    ax.plot(peer[:, 0], peer[:, 1], "wx", ms=7, label=f"lmf peer ({len(peer)})")
    ax.legend(loc="upper right")
    fig.colorbar(shown, ax=ax, label="canopy height (m)")
    ax.set_title("ALS_Clip: canopy height model, tree tops and crowns")
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    defaults = TreeParams()
    parser.add_argument("--resolution", type=float, default=defaults.resolution)
    parser.add_argument("--smoothing", type=float, default=defaults.smoothing)
    parser.add_argument("--window", type=float, nargs=2, default=defaults.window,
                        metavar=("A", "B"), help="tops' window diameter A + B * height (m)")
    parser.add_argument("--peer-window", type=float, default=3.0)
    parser.add_argument("--png", type=Path, default=None)
    args = parser.parse_args(argv)
    params = TreeParams(method="crowns", resolution=args.resolution, smoothing=args.smoothing,
                        window=tuple(args.window))
    if not DATA.is_dir():
        print(f"no data at {DATA}: nothing to measure", file=sys.stderr)
        return 0
    print(params)
    print(f"{'tile':14} {'points':>8} {'method':>8} {'trees':>6} {'height min med max':>18} "
          f"{'crown m2':>9} {'time s':>7}")
    tops = {}
    for name in PLATFORMS:
        xyz, height, canopy = load_scene(DATA / name)
        start = time.perf_counter()
        table, crowns, chm = silva_trees(xyz, height, canopy, params)
        seconds = time.perf_counter() - start
        peer = lmf_tops(chm, args.peer_window, params.min_height)
        tops[name] = {"silva": np.column_stack((table["x"], table["y"])), "lmf": peer[:, :2]}
        print(f"{name:14} {len(xyz):8d} {'silva':>8} {len(table):6d} "
              f"{_heights(table['height']):>18} {np.median(table['crown_area']):9.1f} "
              f"{seconds:7.2f}")
        print(f"{'':14} {'':8} {'lmf':>8} {len(peer):6d} {_heights(peer[:, 2]):>18}")
        if args.png is not None and name == PLATFORMS[0]:
            draw(args.png, chm, table, crowns, peer)
    als, uas = PLATFORMS
    for method in ("silva", "lmf"):
        print(f"{method:>5}: ALS tops with a UAS top within {AGREEMENT:g} m: "
              f"{agreement(tops[als][method], tops[uas][method])}, UAS tops with an ALS top: "
              f"{agreement(tops[uas][method], tops[als][method])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
