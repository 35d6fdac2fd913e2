"""Individual trees (pipeline.trees) on the ponderosa-pine patch of ../shared/data/trees.

    python benchmarks/bench_trees.py [--resolution R] [--smoothing S] [--window A B]
                                     [--peer lidr|window] [--peer-window W] [--png PATH]
    python benchmarks/bench_trees.py --stems [--stem-png-dir DIR]
    python benchmarks/bench_trees.py --instances [--real-stand] [--peer lidr|window]

The same patch scanned from an aircraft (ALS_Clip) and a drone (UAS_Clip); classes 2 ground,
3-5 vegetation, 7 noise (dropped). There is no reference list of trees: the bench counts
trees, their heights and crowns, and how well the two platforms agree (ALS tops with a UAS
top within 2 m). Heights are above the ground model of pipeline.terrain; the canopy is classes
3-5. Silva's chain (canopy cells, CHM, variable-window tops, bounded watershed crowns) is shown
beside the peer's tops (below: lidR's ``lmf`` variable window, or its re-implemented fixed
window of ``--peer-window`` metres on the same unsmoothed CHM as the fallback). ``--png``
draws the ALS CHM with both sets of tops and the crown outlines.

``--stems`` measures the stems instead: on synthetic plots (seeds SYNTH_SEEDS, the true tree
class as the stem mask, heights above the ground model) the stems found against trees.csv
(precision, recall, DBH RMSE of the matched stems); on the unclassified terrestrial plots
TreeLS_pine_plot and tls/LPine1_demo (every point but ground and noise a candidate) the stems
and their DBH; on the four scans of the patch what sees_stems says. ``--stem-png-dir`` draws
each plot's breast-height section with the fitted circles.

``--instances`` scores whole trees on synthetic plots written as ``silva synth`` writes them
(seeds SYNTH_SEEDS, 30 m, tiles with TreeID and trees.csv; ``--real-stand``: with touching
crowns, suppressed trees and leaning stems), the true tree class as canopy and stem mask:
find_trees with method stems and crowns beside the peer: point-level instance precision,
recall and F1 against TreeID, detection F1 against trees.csv (2 m, height within 40 %),
height and DBH RMSE of the matched trees, with and without the buffer rule (the trees
standing outside the plot, and the trees matched to them, left out).

The peer (``--peer lidr``, the default) is lidR itself, run through ``Rscript`` on the same
points written to LAS with their height above Silva's ground model as Z: ``locate_trees(las,
lmf(function(x) x * 0.07 + 3))`` then ``segment_trees`` with dalponte2016 and silva2016 on
its own p2r CHM; R finds lidR on its library path (``R_LIBS=DIR``). Where Rscript or lidR is
absent the bench says so in one line and uses its fallback, the re-implemented window peer
(``--peer window``: lmf with a fixed ``--peer-window`` on Silva's CHM, crowns by a marker
watershed of that CHM), named as such in every row.
"""

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from pipeline.synth import CRS_WKT, SYNTH_CLASSES
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
from pipeline.trees.stems import QUALITY_GOOD, find_stems, sees_stems, stem_slice

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


def draw(path, chm, table, crowns, peer, peer_name: str) -> None:
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
    ax.plot(peer[:, 0], peer[:, 1], "wx", ms=7, label=f"{peer_name} ({len(peer)})")
    ax.legend(loc="upper right")
    fig.colorbar(shown, ax=ax, label="canopy height (m)")
    ax.set_title("ALS_Clip: canopy height model, tree tops and crowns")
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


# --- stems ------------------------------------------------------------------------------------
#: The terrestrial plots whose stems are counted and drawn (unclassified: every point but
#: ground and noise is a stem candidate), and the scans of one patch sees_stems is asked about.
STEM_PLOTS = (DATA / "TreeLS_pine_plot.laz", DATA.parent / "tls" / "LPine1_demo.laz")
PLATFORM_CLIPS = ("ALS_Clip.laz", "UAS_Clip.laz", "TLS_Clip.laz", "MLS_Clip.laz")
NOT_STEMS = (2, NOISE)  # ground and noise
SYNTH_SEEDS = (0, 1, 2, 3, 4)
STEM_MATCH = 0.3  # metres between a true stem base and a fitted centre counted as a match


def stem_candidates(path: Path):
    """xyz (N, 3), height above the ground model (N,) and the stem candidates (N,) bool."""
    import laspy

    las = laspy.read(path)
    code = np.asarray(las.classification)
    xyz = np.column_stack((las.x, las.y, las.z)).astype(np.float64)
    height = xyz[:, 2] - ground_elevation(terrain_model(xyz).dtm, xyz[:, :2])
    return xyz, height, ~np.isin(code, NOT_STEMS)


def stems_table(stems) -> np.ndarray:
    """The fitted stems as a table for pipeline.trees.instances (IDs 1..n, height unknown)."""
    table = np.zeros(len(stems), dtype=[("tree_id", "u4"), ("x", "f8"), ("y", "f8"),
                                        ("height", "f8"), ("dbh", "f8")])
    table["tree_id"] = np.arange(1, len(stems) + 1)
    table["x"], table["y"], table["dbh"] = stems.x, stems.y, stems.dbh
    table["height"] = np.nan
    return table


def synthetic_stem_scores(params: TreeParams) -> None:
    """Stems of synthetic plots (true tree class as the stem mask, heights above the ground
    model) against their trees.csv truth (the trees standing inside the plot), and the point
    instances of the whole chain (crowns alone, crowns with stems) against the TreeID of every
    point (match_instances: IoU above 0.5)."""
    from pipeline.synth import synthetic_scene
    from pipeline.trees.instances import match_instances, match_tables

    print(f"{'seed':>4} {'trees':>6} {'stems':>6} {'good':>5} {'precision':>9} {'recall':>7} "
          f"{'dbh rmse cm':>11} {'bias cm':>8}   instance F1: crowns, crowns + stems")
    errors = []
    for seed in SYNTH_SEEDS:
        scene = synthetic_scene(seed)
        xyz, tree = scene.xyz, scene.labels == SYNTH_CLASSES["tree"]
        height = xyz[:, 2] - ground_elevation(terrain_model(xyz).dtm, xyz[:, :2])
        stems = find_stems(stem_slice(xyz, height, tree, params), params)
        ox, oy, _ = scene.origin
        trees = scene.trees
        truth = trees[(trees["x"] >= ox) & (trees["x"] < ox + scene.size)
                      & (trees["y"] >= oy) & (trees["y"] < oy + scene.size)]
        found = stems_table(stems)
        matching = match_tables(truth, found, STEM_MATCH)
        rows = np.searchsorted(truth["tree_id"], matching.true_ids)  # truth is sorted by ID
        error = found["dbh"][matching.pred_ids - 1] - truth["dbh"][rows]
        errors.append(error)
        good = int(np.count_nonzero(stems.quality == QUALITY_GOOD))
        f1 = [match_instances(scene.tree_ids, point_trees(xyz, height, tree, with_stems,
                                                          params)).f1
              for with_stems in (None, stems)]
        print(f"{seed:4d} {len(truth):6d} {len(stems):6d} {good:5d} {matching.precision:9.2f} "
              f"{matching.recall:7.2f} {100 * np.sqrt(np.mean(error**2)):11.2f} "
              f"{100 * error.mean():8.2f}   {f1[0]:.2f} {f1[1]:.2f}")
    every = np.concatenate(errors)
    print(f" all: {len(every)} matched stems, DBH RMSE {100 * np.sqrt(np.mean(every**2)):.2f} cm, "
          f"bias {100 * every.mean():.2f} cm, largest error {100 * np.abs(every).max():.1f} cm")


def point_trees(xyz, height, tree, stems, params: TreeParams) -> np.ndarray:
    """uint32 (N,) the tree ID of every point by the whole chain, all points in one chunk:
    crowns of the tree points' CHM, with the stems when given (the tree class their mask)."""
    chm = chm_raster(canopy_cells(xyz, height, tree, params.resolution), params.resolution)
    model = tree_model(segment_crowns(chm, params), stems, params)
    return assign_trees(model, xyz, height, tree, None if stems is None else tree, params)


def draw_stems(path, points: np.ndarray, stems, title: str) -> None:
    """The breast-height section of a slice seen from above, with the fitted circles."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    section = points[np.abs(points[:, 3] - 1.3) <= 0.15]
    fig, ax = plt.subplots(figsize=(8, 8))
    ax.scatter(section[:, 0], section[:, 1], s=0.3, c="0.4")
    for x, y, dbh, quality in zip(stems.x, stems.y, stems.dbh, stems.quality):
        colour = "red" if quality == QUALITY_GOOD else "orange"
        ax.add_patch(Circle((x, y), dbh / 2, fill=False, color=colour, lw=1.2))
        ax.annotate(f"{100 * dbh:.0f}", (x, y), color=colour, fontsize=7)
    ax.set_aspect("equal")
    ax.set_title(f"{title}: 1.15-1.45 m section, circles (red 1.3 m, orange fallback; cm)")
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def stems_main(params: TreeParams, png_dir: Path | None) -> int:
    """The stems section: synthetic truth, real terrestrial plots, sees_stems per platform."""
    print(params)
    synthetic_stem_scores(params)
    print(f"{'plot':18} {'points':>8} {'slice':>6} {'stems':>6} {'good':>5} "
          f"{'dbh cm p10 p50 p90':>18} {'max':>5} {'time s':>7}")
    for path in STEM_PLOTS:
        if not path.is_file():
            print(f"{path.name}: absent")
            continue
        xyz, height, mask = stem_candidates(path)
        start = time.perf_counter()
        points = stem_slice(xyz, height, mask, params)
        stems = find_stems(points, params)
        seconds = time.perf_counter() - start
        dbh = 100 * np.percentile(stems.dbh, [10, 50, 90, 100]) if len(stems) else [np.nan] * 4
        good = int(np.count_nonzero(stems.quality == QUALITY_GOOD))
        print(f"{path.stem:18} {len(xyz):8d} {len(points):6d} {len(stems):6d} {good:5d} "
              f"{dbh[0]:6.0f}{dbh[1]:6.0f}{dbh[2]:6.0f} {dbh[3]:5.0f} {seconds:7.2f}")
        if png_dir is not None:
            draw_stems(png_dir / f"stems-{path.stem}.png", points, stems, path.stem)
    for name in PLATFORM_CLIPS:
        xyz, height, mask = stem_candidates(DATA / name)
        area = float(np.ptp(xyz[:, 0]) * np.ptp(xyz[:, 1]))
        points = stem_slice(xyz, height, mask, params)
        stems = find_stems(points, params)
        good = int(np.count_nonzero(stems.quality == QUALITY_GOOD))
        print(f"{name:14} stems {len(stems):3d}, at 1.3 m {good:3d} ({good / area * 1e4:5.0f} "
              f"per ha): sees_stems {sees_stems(points, area, params)}")
        if png_dir is not None:
            draw_stems(png_dir / f"stems-{Path(name).stem}.png", points, stems, name)
    return 0


# --- lidR itself ------------------------------------------------------------------------------
#: lidR's documented variable window (the same as Silva's default window) and its two crown
#: segmentations that grow from tops on a CHM. Arguments: LAS in, tree IDs out (int32 per
#: point, in the file's order, 0 in no tree), CHM cell, algorithm (none: tops only, every
#: ID 0), tops table out (CSV), hmin.
LIDR_SCRIPT = r"""
options(rgl.useNULL = TRUE, lidR.progress = FALSE)
suppressPackageStartupMessages(library(lidR))
a <- commandArgs(trailingOnly = TRUE)
las <- readLAS(a[1], select = "xyz")
tops <- locate_trees(las, lmf(function(x) x * 0.07 + 3, hmin = as.numeric(a[6])))
ids <- integer(npoints(las))
if (a[4] != "none") {
  chm <- rasterize_canopy(las, res = as.numeric(a[3]), algorithm = p2r())
  algo <- if (a[4] == "silva2016") silva2016(chm, tops) else dalponte2016(chm, tops)
  las <- segment_trees(las, algo)
  ids <- las$treeID
  ids[is.na(ids)] <- 0L
}
writeBin(as.integer(ids), a[2], size = 4, endian = "little")
xyz <- sf::st_coordinates(tops)
data.table::fwrite(data.table::data.table(tree_id = tops$treeID, x = xyz[, 1], y = xyz[, 2],
                                          height = xyz[, 3]), a[5])
"""
LIDR_ALGORITHMS = ("dalponte2016", "silva2016")
TABLE_DTYPE = [("tree_id", "u4"), ("x", "f8"), ("y", "f8"), ("height", "f8"), ("dbh", "f8")]


def lidr_missing() -> str | None:
    """None when ``Rscript`` runs and loads lidR (from R's library path, e.g. ``R_LIBS``),
    else why not, in one line."""
    if shutil.which("Rscript") is None:
        return "Rscript not found"
    done = subprocess.run(["Rscript", "-e", "suppressPackageStartupMessages(library(lidR))"],
                          capture_output=True, text=True, env={**os.environ,
                                                               "RGL_USE_NULL": "TRUE"})
    if done.returncode:
        lines = done.stderr.strip().splitlines() or ["no message"]
        return f"lidR does not load ({lines[0]})"
    return None


def lidr_trees(xyz, height, mask, params: TreeParams, algorithm: str):
    """lidR's trees of the ``mask`` points, given with their height above Silva's ground
    model as Z (lidR's normalised cloud, so both see the same heights): lmf tops (variable
    window 3 + 0.07 h, hmin = min_height), crowns by ``algorithm`` (none: tops only) on lidR's
    own p2r CHM of ``params.resolution``. Returns (tree ID per point (N,) uint32, table of
    the tops)."""
    from pipeline.io import write_las

    with tempfile.TemporaryDirectory(prefix="lidr-") as tmp:
        work = Path(tmp)
        (work / "trees.R").write_text(LIDR_SCRIPT)
        points = np.column_stack((xyz[mask, :2], height[mask]))
        # lidR's rasters need a CRS; nothing is reprojected, so any projected one gives the
        # same trees
        write_las(work / "points.las", points, crs_wkt=CRS_WKT,
                  offset=(*np.floor(points[:, :2].min(axis=0)), 0.0))
        done = subprocess.run(["Rscript", str(work / "trees.R"), str(work / "points.las"),
                               str(work / "ids.bin"), str(params.resolution), algorithm,
                               str(work / "tops.csv"), str(params.min_height)],
                              capture_output=True, text=True,
                              env={**os.environ, "RGL_USE_NULL": "TRUE"})
        if done.returncode:
            raise RuntimeError(f"lidR {algorithm} failed: {done.stderr.strip()[-500:]}")
        found = np.fromfile(work / "ids.bin", dtype="<i4")
        tops = np.loadtxt(work / "tops.csv", delimiter=",", skiprows=1, ndmin=2)
    ids = np.zeros(len(xyz), np.uint32)
    ids[mask] = found
    table = np.zeros(len(tops), dtype=TABLE_DTYPE)
    for column, name in enumerate(("tree_id", "x", "y", "height")):
        table[name] = tops[:, column]
    table["dbh"] = np.nan
    return ids, table


# --- synthetic instances ----------------------------------------------------------------------
TREE_CLASS = SYNTH_CLASSES["tree"]
TREE_MATCH = 2.0  # metres between a true stem base and a found tree counted as a match
HEIGHT_TOLERANCE = 0.4  # a matched tree's height within 40 % of the true height
#: The re-implemented peer, used only when lidR itself cannot run here.
WINDOW_PEER = "lmf re-implemented"


def read_synthetic_plot(out_dir: Path, seed: int, stand=None):
    """Write the plot of ``seed`` (with ``stand``'s realism, pipeline.synth.Stand, or none)
    as tiles into ``out_dir`` (as ``silva synth`` does) and read them back: xyz (N, 3), class
    (N,), TreeID (N,) and the trees.csv truth table."""
    import laspy

    from pipeline.synth import Stand, write_synthetic_plot

    paths = write_synthetic_plot(out_dir, seed, stand=stand or Stand())
    tiles = [laspy.read(path) for path in paths]
    xyz = np.concatenate([np.column_stack((t.x, t.y, t.z)) for t in tiles]).astype(np.float64)
    code = np.concatenate([np.asarray(t.classification) for t in tiles])
    tree_id = np.concatenate([np.asarray(t["TreeID"]) for t in tiles]).astype(np.uint32)
    truth = np.genfromtxt(out_dir / "trees.csv", delimiter=",", names=True,
                          dtype=["u4"] + ["f8"] * 5 + ["u1", "f8"])
    return xyz, code, tree_id, np.atleast_1d(truth)


def lmf_trees(xyz, height, tree, params: TreeParams, window: float):
    """The peer's trees: lidR-like lmf tops (fixed window) on the unsmoothed CHM of the tree
    points, crowns by a marker watershed of the CHM from those tops (cells above min_height),
    every tree point in its cell's crown. Returns (tree ID per point, table)."""
    from skimage.segmentation import watershed

    chm = chm_raster(canopy_cells(xyz, height, tree, params.resolution), params.resolution)
    tops = lmf_tops(chm, window, params.min_height)
    values = np.where(np.isfinite(chm.values), chm.values, 0.0)
    markers = np.zeros(chm.shape, np.int32)
    rows = ((tops[:, 1] - chm.y0) / chm.cell).astype(int)
    cols = ((tops[:, 0] - chm.x0) / chm.cell).astype(int)
    markers[rows, cols] = np.arange(1, len(tops) + 1)
    labels = watershed(-values, markers, mask=values >= params.min_height)
    row = np.clip(((xyz[:, 1] - chm.y0) // chm.cell).astype(int), 0, chm.shape[0] - 1)
    col = np.clip(((xyz[:, 0] - chm.x0) // chm.cell).astype(int), 0, chm.shape[1] - 1)
    ids = np.where(tree, labels[row, col], 0).astype(np.uint32)
    table = np.zeros(len(tops), dtype=[("tree_id", "u4"), ("x", "f8"), ("y", "f8"),
                                       ("height", "f8"), ("dbh", "f8")])
    table["tree_id"] = np.arange(1, len(tops) + 1)
    table["x"], table["y"], table["height"] = tops[:, 0], tops[:, 1], tops[:, 2]
    table["dbh"] = np.nan
    return ids, table


def instance_scores(true_ids, pred_ids, truth, table, left_out=None) -> dict:
    """Point-level instance and detection scores of one method on one plot; ``left_out``
    the true trees left out of the counts (the buffer rule), None for every tree."""
    from pipeline.trees.instances import match_instances, match_tables, matched_errors

    points = match_instances(true_ids, pred_ids, left_out)
    detection = match_tables(truth, table, TREE_MATCH, HEIGHT_TOLERANCE, left_out)
    errors = matched_errors(detection, truth, table)
    return {"precision": points.precision, "recall": points.recall, "f1": points.f1,
            "detection_f1": detection.f1, "found": points.n_pred,
            "height": errors["height"], "dbh": errors["dbh"]}


def _rmse_cell(error: dict, scale: float) -> str:
    return "-" if error["n"] == 0 else f"{scale * error['rmse']:.2f} ({error['n']})"


def print_instance_row(label: str, method: str, s: dict) -> None:
    print(f"{label:>10} {method:>18} {s['found']:5d} {s['precision']:9.3f} {s['recall']:6.3f} "
          f"{s['f1']:6.3f} {s['detection_f1']:7.3f} {_rmse_cell(s['height'], 1.0):>12} "
          f"{_rmse_cell(s['dbh'], 100.0):>12}")


def pooled(scores: list[dict]) -> dict:
    """Means of the scores over the plots; RMSEs pooled over every matched tree."""
    def pool(key):
        n = sum(s[key]["n"] for s in scores)
        sse = sum(s[key]["n"] * s[key]["rmse"] ** 2 for s in scores if s[key]["n"])
        return {"rmse": float(np.sqrt(sse / n)) if n else float("nan"), "n": n}
    mean = {k: float(np.mean([s[k] for s in scores]))
            for k in ("precision", "recall", "f1", "detection_f1")}
    return {**mean, "found": sum(s["found"] for s in scores),
            "height": pool("height"), "dbh": pool("dbh")}


def peer_methods(peer: str) -> tuple[str, ...]:
    """The peer's rows: lidR's segmentations when ``peer`` is lidr and lidR runs here, else
    (with one line saying why) the re-implemented window peer."""
    if peer == "lidr":
        missing = lidr_missing()
        if missing is None:
            return tuple(f"lidR {name}" for name in LIDR_ALGORITHMS)
        print(f"lidR peer skipped: {missing}; the re-implemented lmf window peer instead")
    return (WINDOW_PEER,)


def method_trees(method: str, xyz, height, tree, peer_window: float):
    """(tree ID per point, tree table) of one method's row on one plot."""
    from pipeline.trees import find_trees

    if method == WINDOW_PEER:
        return lmf_trees(xyz, height, tree, TreeParams(), peer_window)
    if method.startswith("lidR "):
        return lidr_trees(xyz, height, tree, TreeParams(), method.split()[1])
    ids, table, _, _ = find_trees(xyz, height, tree, tree, TreeParams(method=method))
    return ids, table


def synthetic_instances(peer_window: float, peer: str, stand=None) -> int:
    """Silva stems, Silva crowns and the peer on the synthetic plots SYNTH_SEEDS: point
    instances against every point's TreeID, detection against trees.csv. Each plot's rows
    leave out the trees standing outside the plot (trees.csv's ``inside`` 0: their crowns
    reach in, their stems cannot be found) and the found trees matched to them, as a forest
    inventory's buffer rule does; the pooled rows are given with and without that rule."""
    from pipeline.synth import DEFAULT_ORIGIN

    methods = ("stems", "crowns") + peer_methods(peer)
    print(f"{'seed':>10} {'method':>18} {'trees':>5} {'precision':>9} {'recall':>6} {'F1':>6} "
          f"{'det. F1':>7} {'height RMSE m':>12} {'DBH RMSE cm':>12}")
    scores = {(method, rule): [] for method in methods for rule in ("every tree", "buffer")}
    outside, total = 0, 0
    for seed in SYNTH_SEEDS:
        with tempfile.TemporaryDirectory() as tmp:
            xyz, code, true_ids, truth = read_synthetic_plot(Path(tmp), seed, stand)
        height = xyz[:, 2] - ground_elevation(terrain_model(xyz).dtm, xyz[:, :2])
        tree = code == TREE_CLASS
        left_out = truth["tree_id"][truth["inside"] == 0]
        outside, total = outside + len(left_out), total + len(truth)
        for method in methods:
            ids, table = method_trees(method, xyz, height, tree, peer_window)
            scores[method, "every tree"].append(instance_scores(true_ids, ids, truth, table))
            scores[method, "buffer"].append(instance_scores(true_ids, ids, truth, table,
                                                            left_out))
            print_instance_row(str(seed), method, scores[method, "buffer"][-1])
    for rule in ("every tree", "buffer"):
        for method in methods:
            print_instance_row(f"all {rule}", method, pooled(scores[method, rule]))
    print(f"true trees (trees.csv): {total}, of which {outside} stand outside the plot "
          f"(left out by the buffer rule, with the trees matched to them); origin "
          f"{DEFAULT_ORIGIN[:2]}")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    defaults = TreeParams()
    parser.add_argument("--resolution", type=float, default=defaults.resolution)
    parser.add_argument("--smoothing", type=float, default=defaults.smoothing)
    parser.add_argument("--window", type=float, nargs=2, default=defaults.window,
                        metavar=("A", "B"), help="tops' window diameter A + B * height (m)")
    parser.add_argument("--peer", choices=("lidr", "window"), default="lidr",
                        help="lidR itself through Rscript (lidR from R's library path, e.g. "
                             "R_LIBS); window: the re-implemented lmf, lidR's fallback")
    parser.add_argument("--peer-window", type=float, default=3.0,
                        help="the re-implemented peer's fixed window diameter (m)")
    parser.add_argument("--png", type=Path, default=None)
    parser.add_argument("--stems", action="store_true",
                        help="measure the stems instead (synthetic truth, terrestrial plots)")
    parser.add_argument("--instances", action="store_true",
                        help="score stems, crowns and the peer on synthetic plots instead")
    parser.add_argument("--real-stand", action="store_true",
                        help="with --instances: plots with touching crowns, suppressed trees "
                             "and leaning stems (pipeline.synth.REAL_STAND)")
    parser.add_argument("--stem-png-dir", type=Path, default=None,
                        help="draw each plot's section and circles as stems-<plot>.png here")
    args = parser.parse_args(argv)
    if args.instances:
        from pipeline.synth import REAL_STAND

        return synthetic_instances(args.peer_window, args.peer,
                                   REAL_STAND if args.real_stand else None)
    if args.stems:
        if not DATA.is_dir():
            print(f"no data at {DATA}: nothing to measure", file=sys.stderr)
            return 0
        return stems_main(TreeParams(method="stems"), args.stem_png_dir)
    params = TreeParams(method="crowns", resolution=args.resolution, smoothing=args.smoothing,
                        window=tuple(args.window))
    if not DATA.is_dir():
        print(f"no data at {DATA}: nothing to measure", file=sys.stderr)
        return 0
    print(params)
    peer = (WINDOW_PEER if args.peer == "window" or peer_methods("lidr") == (WINDOW_PEER,)
            else "lidR")
    print(f"{'tile':14} {'points':>8} {'method':>18} {'trees':>6} {'height min med max':>18} "
          f"{'crown m2':>9} {'time s':>7}")
    tops = {}
    for name in PLATFORMS:
        xyz, height, canopy = load_scene(DATA / name)
        start = time.perf_counter()
        table, crowns, chm = silva_trees(xyz, height, canopy, params)
        seconds = time.perf_counter() - start
        start = time.perf_counter()
        if peer == "lidR":  # lidR's tops only (no crowns are drawn)
            found = lidr_trees(xyz, height, canopy, params, "none")[1]
            others = np.column_stack((found["x"], found["y"], found["height"]))
        else:
            others = lmf_tops(chm, args.peer_window, params.min_height)
        peer_seconds = time.perf_counter() - start
        tops[name] = {"silva": np.column_stack((table["x"], table["y"])), peer: others[:, :2]}
        print(f"{name:14} {len(xyz):8d} {'silva':>18} {len(table):6d} "
              f"{_heights(table['height']):>18} {np.median(table['crown_area']):9.1f} "
              f"{seconds:7.2f}")
        print(f"{'':14} {'':8} {peer:>18} {len(others):6d} {_heights(others[:, 2]):>18} "
              f"{'':9} {peer_seconds:7.2f}")
        if args.png is not None and name == PLATFORMS[0]:
            draw(args.png, chm, table, crowns, others, peer)
    als, uas = PLATFORMS
    for method in ("silva", peer):
        print(f"{method:>18}: ALS tops with a UAS top within {AGREEMENT:g} m: "
              f"{agreement(tops[als][method], tops[uas][method])}, UAS tops with an ALS top: "
              f"{agreement(tops[uas][method], tops[als][method])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
