"""Classes on steep ground: synthetic plots on hillsides, classified by the real workflow.

    python benchmarks/bench_slopes.py [--model NAME|DIR] [--seeds 2] [--size 30]
                                      [--cases 0 20 40 40r] [--tolerance M] [--work DIR]
                                      [--json]
    python benchmarks/bench_slopes.py --tiles "DIR/*.laz" --model NAME|DIR [--tolerance M]
                                      [--shear 0 20 30 40]

Each case is a plot written by ``silva synth --seed S --size SIZE --slope DEGREES`` (a
trailing ``r``: ``--ridge``), classified by ``silva predict --model MODEL`` (default
forest-tls-synthetic, the shipped terrestrial model) with the classifier in the loop, as a
user runs it. Per case it prints the share of the true terrain points called terrain, the F1
of terrain, tree and dead wood (over the points but misc, the background class, as the
model's evaluation and card score them), and the terrain model's own
error on the true terrain points: the median and the 95th percentile of their
|HeightAboveGround| (the output dimension: their distance to the run's DTM).

``--tolerance M`` applies a copy of the model that records ``terrain.ground_tolerance: M``
(the rule that a point within M metres of seen ground is ground), re-digested: the same
forests with the rule on, to measure it without retraining. ``0``: the rule off.

``--tiles`` classifies labelled tiles instead (e.g. the east halves of
benchmarks/als_scenes.py with the airborne model) and prints, per tile and over all their
points, the ground F1 (ASPRS code 2 against the predicted code), the share of true ground
called ground, the share of vegetation (3-5) called building (6) and the DTM's error on the
true ground (its |HeightAboveGround|); unclassified, water and noise (1, 9, 7, 18) are left
out as the airborne model's card leaves them out. ``--shear D1 D2 ...`` classifies, per
value, copies of the tiles whose ground slopes D degrees more: z += tan(D) * x (from each
tile's west edge), real airborne forests and towns on a synthetic hillside whose trees and
walls stay vertical.

Plots are kept under ``--work`` (default: a temporary directory) and written once.
"""

import argparse
import glob
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import laspy
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from als_scenes import raised  # noqa: E402
from pipeline.io import read_points  # noqa: E402
from pipeline.model import DIGEST_KEY, MODEL_FILE, description_digest  # noqa: E402
from pipeline.synth import SYNTH_CLASSES  # noqa: E402

CLASSES = ("terrain", "tree", "dead_wood")
PREDICTED = "PredictedClassification"
#: Ground, and what the airborne model's card leaves out of its scores: unclassified and
#: water (its ignored classes) and noise (excluded).
GROUND, UNSCORED = 2, (1, 7, 9, 18)
VEGETATION, BUILDING = (3, 4, 5), 6
HEIGHT = "HeightAboveGround"


def silva(*args) -> None:
    """Run a ``silva`` command in a child process (quiet), failing loudly."""
    done = subprocess.run([sys.executable, "-m", "workflows", *map(str, args)],
                          cwd=ROOT, capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    if done.returncode:
        raise SystemExit(f"silva {' '.join(map(str, args))} failed:\n{done.stderr[-2000:]}")


def model_dir(name: str) -> Path:
    """The directory of a shipped model by name, or the path given."""
    shipped = ROOT / "workflows" / "models" / name
    return shipped if shipped.is_dir() else Path(name)


def with_tolerance(model: Path, tolerance: float, dest: Path) -> Path:
    """A copy of ``model`` whose model.json records terrain.ground_tolerance (re-digested)."""
    if dest.exists():
        shutil.rmtree(dest)
    shutil.copytree(model, dest)
    description = json.loads((dest / MODEL_FILE).read_text())
    description["terrain.ground_tolerance"] = tolerance if tolerance > 0 else None
    description[DIGEST_KEY] = description_digest(description)
    (dest / MODEL_FILE).write_text(json.dumps(description, indent=2))
    return dest


def plot(work: Path, seed: int, size: float, case: str) -> Path:
    """The plot of one case, written once."""
    out = work / f"plot_s{seed}_{size:g}m_{case}"
    if not any(out.glob("*.laz")):
        ridge = ("--ridge",) if case.endswith("r") else ()
        silva("synth", out, "--seed", seed, "--size", size, "--tile-size", size,
              "--slope", case.rstrip("r"), *ridge)
    return out


def case_name(case: str) -> str:
    """How a table names a case: its slope and shape (0: the plain plot's gentle grade)."""
    if float(case.rstrip("r")) == 0:
        return "plain (3-18 % grade)" + (" ridge" if case.endswith("r") else "")
    return f"{case.rstrip('r')}° {'ridge' if case.endswith('r') else 'hillside'}"


def scores(plot_dir: Path, predictions: Path) -> dict:
    """The case's scores from the input tiles' truth and the predicted tiles."""
    truth, predicted, height = [], [], []
    for tile in sorted(plot_dir.glob("*.laz")):
        truth.append(read_points(tile).fields["classification"])
        out = read_points(predictions / tile.name, fields=(PREDICTED, HEIGHT))
        predicted.append(out.fields[PREDICTED])
        height.append(out.fields[HEIGHT])
    truth, predicted, height = (np.concatenate(a) for a in (truth, predicted, height))
    terrain = truth == SYNTH_CLASSES["terrain"]
    row = {"points": int(truth.size), "terrain_points": int(terrain.sum()),
           "terrain_called_terrain": round(float(np.mean(predicted[terrain]
                                                         == SYNTH_CLASSES["terrain"])), 4),
           "terrain_hag_median": round(float(np.median(np.abs(height[terrain]))), 3),
           "terrain_hag_p95": round(float(np.percentile(np.abs(height[terrain]), 95)), 3)}
    scored = truth != SYNTH_CLASSES["misc"]  # the background, as the model's evaluation
    for name in CLASSES:
        code = SYNTH_CLASSES[name]
        true, said = (truth == code) & scored, (predicted == code) & scored
        both = np.count_nonzero(true & said)
        row[f"f1_{name}"] = round(2 * both / max(np.count_nonzero(true)
                                                 + np.count_nonzero(said), 1), 4)
    return row


def tile_arrays(predicted_tile: Path) -> dict:
    """The scored points of one predicted tile (its input classes kept beside the prediction):
    truth, prediction and HeightAboveGround, :data:`UNSCORED` left out."""
    fields = read_points(predicted_tile, fields=("classification", PREDICTED, HEIGHT)).fields
    scored = ~np.isin(fields["classification"], UNSCORED)
    return {"truth": fields["classification"][scored], "said": fields[PREDICTED][scored],
            "height": fields[HEIGHT][scored]}


def ground_scores(truth: np.ndarray, said: np.ndarray, height: np.ndarray) -> dict:
    """Ground F1, the share of true ground called ground, the share of vegetation (3-5)
    called building (6), and the DTM's error on true ground (median and 95th percentile of
    its |HeightAboveGround|)."""
    true, called = truth == GROUND, said == GROUND
    vegetation = np.isin(truth, VEGETATION)
    both = np.count_nonzero(true & called)
    return {"points": int(truth.size),
            "ground_f1": round(2 * both / max(np.count_nonzero(true)
                                              + np.count_nonzero(called), 1), 4),
            "ground_called_ground": round(both / max(np.count_nonzero(true), 1), 4),
            "vegetation_called_building": (round(float(np.mean(said[vegetation] == BUILDING)), 4)
                                           if vegetation.any() else None),
            "ground_hag_median": round(float(np.median(np.abs(height[true]))), 3),
            "ground_hag_p95": round(float(np.percentile(np.abs(height[true]), 95)), 3)}


def sheared(pattern: str, degrees: float, work: Path) -> str:
    """Copies of the tiles of ``pattern`` whose ground slopes ``degrees`` more, eastwards:
    z += tan(degrees) * (x - the tile's min x). Trees and walls stay vertical, the ground
    tilts; every other dimension is kept. Returns the copies' pattern."""
    out = work / f"shear{degrees:g}"
    out.mkdir(parents=True, exist_ok=True)
    for tile in sorted(Path(p) for p in glob.glob(pattern)):
        las = laspy.read(tile)
        x = np.asarray(las.x)
        las.Z = raised(np.asarray(las.Z), x - x.min(), degrees, las.header.scales[2])
        las.write(out / tile.name)
    return str(out / "*.laz")


def tile_line(name: str, row: dict) -> str:
    """A tile's row of the printed table."""
    building = row["vegetation_called_building"]
    return (f"| {name} | {row.get('shear', 0):g}° | {row['ground_f1']:.4f} "
            f"| {row['ground_called_ground']:.1%} "
            f"| {'–' if building is None else f'{building:.1%}'} "
            f"| {row['ground_hag_median']:.2f} / {row['ground_hag_p95']:.2f} |")


def score_tiles(pattern: str, model: Path, work: Path, shear: float = 0.0) -> list[dict]:
    """Each tile of ``pattern`` (sheared by ``shear`` degrees) classified by ``model`` in one
    run: its :func:`ground_scores`, and theirs over all the tiles' points."""
    if shear:
        pattern = sheared(pattern, shear, work)
    out = work / f"tiles_{model.parent.name}_{model.name}_shear{shear:g}"
    if out.exists():
        shutil.rmtree(out)
    silva("predict", "--model", model, "--out", out, "--quiet", pattern)
    rows, pooled = [], []
    for tile in sorted(Path(p) for p in glob.glob(pattern)):
        pooled.append(tile_arrays(out / "predictions" / tile.name))
        rows.append({"tile": tile.stem, "shear": shear, **ground_scores(**pooled[-1])})
        print(tile_line(tile.stem, rows[-1]), flush=True)
    rows.append({"tile": "all", "shear": shear, **ground_scores(
        **{key: np.concatenate([p[key] for p in pooled]) for key in pooled[0]})})
    print(tile_line("**all**", rows[-1]), flush=True)
    return rows


def predicted(model: Path, plot_dir: Path, work: Path) -> Path:
    """The predictions directory of ``model`` applied to one plot (made afresh)."""
    out = work / f"predict_{model.parent.name}_{model.name}_{plot_dir.name}"
    if out.exists():
        shutil.rmtree(out)
    silva("predict", "--model", model, "--out", out, "--quiet", str(plot_dir / "*.laz"))
    return out / "predictions"


def table_line(row: dict) -> str:
    """A plot's row of the printed table."""
    return (f"| {case_name(row['case'])} | {row['seed']} | {row['terrain_called_terrain']:.1%} "
            f"| {row['f1_terrain']:.3f} | {row['f1_tree']:.3f} | {row['f1_dead_wood']:.3f} "
            f"| {row['terrain_hag_median']:.2f} / {row['terrain_hag_p95']:.2f} |")


def score_plots(args, model: Path, work: Path) -> list[dict]:
    """Every case of every seed: written once, classified by ``model``, scored."""
    rows = []
    print("| plot | seed | terrain called terrain | F1 terrain | F1 tree | F1 dead wood "
          "| DTM |HAG| median / p95 (m) |\n|---|---|---|---|---|---|---|")
    for seed in args.seeds:
        for case in args.cases:
            plot_dir = plot(work, seed, args.size, case)
            rows.append({"case": case, "seed": seed, "model": str(args.model),
                         "tolerance": args.tolerance,
                         **scores(plot_dir, predicted(model, plot_dir, work))})
            print(table_line(rows[-1]), flush=True)
    return rows


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", default="forest-tls-synthetic")
    parser.add_argument("--seeds", type=int, nargs="+", default=[2])
    parser.add_argument("--size", type=float, default=30.0)
    parser.add_argument("--cases", nargs="+", default=["0", "20", "40", "40r"],
                        help="slopes in degrees; a trailing r makes a ridge")
    parser.add_argument("--tolerance", type=float, default=None,
                        help="apply the model with terrain.ground_tolerance set to this")
    parser.add_argument("--work", type=Path, default=None)
    parser.add_argument("--tiles", default=None,
                        help="labelled tiles to score ground F1 on, instead of the plots")
    parser.add_argument("--shear", type=float, nargs="+", default=[0.0],
                        help="with --tiles: tilt the tiles' ground by these many degrees")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_slopes_"))
    work.mkdir(parents=True, exist_ok=True)
    model = model_dir(args.model)
    if args.tolerance is not None:
        model = with_tolerance(model, args.tolerance,
                               work / f"{model.name}_tol{args.tolerance:g}")
    if args.tiles:
        print("| tile | shear | ground F1 | ground called ground | vegetation called building "
              "| DTM |HAG| of ground, median / p95 (m) |\n|---|---|---|---|---|---|")
        rows = [row for shear in args.shear for row in score_tiles(args.tiles, model, work,
                                                                  shear)]
    else:
        rows = score_plots(args, model, work)
    if args.json:
        print(json.dumps(rows))
    return rows


if __name__ == "__main__":
    main()
