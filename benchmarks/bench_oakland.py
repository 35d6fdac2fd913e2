"""Oakland 3-D accuracy against the paper's Table 2: macro precision, recall and F1 per stage.

Runs ``configs/oakland.yaml`` (train on the training scene, score the five classes on the
validation scene) once per seed, in this process, into one output directory: the features are
computed once and every seed only refits the cascade. The paper averages five runs; so does
this by default. Its Table 2 rows are printed alongside. Note the paper scores the official
test set (15 files, not shipped in ../shared/data); this scores the validation scene.

    python benchmarks/bench_oakland.py [--seeds 5] [--out DIR] [--set KEY=VALUE ...]

Needs ../shared/data/oakland.
"""

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from workflows.config import load_config
from workflows.exec.engine import Engine
from workflows.run.autoparams import resolve_run
from workflows.run.directory import Run
from workflows.run.loop import execute
from workflows.steps.table import STEPS

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "oakland.yaml"
PAPER = {  # Table 2, averaged over the five classes
    "paper, invariants only": (0.678, 0.710, 0.655),
    "paper, invariants + context": (0.736, 0.798, 0.695),
    "paper, best in table (M3N)": (0.730, 0.902, 0.778),
}
MEASURES = ("precision", "recall", "f1")


def run_seed(seed: int, out: Path, overrides: list[str]) -> dict:
    """metrics.json of one run of the Oakland config with ``cascade.seed = seed``."""
    cfg = load_config(CONFIG, [*overrides, f"cascade.seed={seed}"])
    run = Run(resolve_run(cfg), out, quiet=True, steps=STEPS)
    run.save_config()
    execute(run, Engine(None, quiet=True), "evaluate")
    return json.loads((out / "metrics.json").read_text())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="silva-oakland-"))
    per_stage: dict[int, list[tuple]] = {}
    per_class: list[dict] = []
    started = time.perf_counter()
    for seed in range(args.seeds):
        metrics = run_seed(seed, out, args.overrides)
        for stage, stage_metrics in enumerate(metrics["stages"], start=1):
            per_stage.setdefault(stage, []).append(
                tuple(stage_metrics["macro"][m] for m in MEASURES))
        per_class.append({c: v["f1"] for c, v in metrics["per_class"].items()})
        print(f"seed {seed}: macro F1 {metrics['macro']['f1']:.3f} "
              f"({time.perf_counter() - started:.0f} s so far)")
    print(f"\nOakland validation scene, {metrics['n_test_points']:,} points, mean ± std over "
          f"{args.seeds} seeds (output: {out})")
    print(f"{'':<30}{'precision':>16}{'recall':>16}{'F1':>16}")
    for stage, rows in per_stage.items():
        values = np.array(rows)
        cells = "".join(f"{m:>10.3f} ± {s:.3f}" for m, s in
                        zip(values.mean(axis=0), values.std(axis=0)))
        print(f"{f'Silva, stage {stage}':<30}{cells}")
    for name, values in PAPER.items():
        print(f"{name:<30}" + "".join(f"{v:>16.3f}" for v in values))
    print("\nF1 per class, final stage: " + ", ".join(
        f"{c} {np.mean([row[c] for row in per_class]):.3f}" for c in per_class[0]))


if __name__ == "__main__":
    main()
