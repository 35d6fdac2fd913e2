"""Throughput of the whole workflow on the real TLS plot: a wrapper of ``silva bench pipeline``.

Trains a cascade on a synthetic 30 m forest plot (the demo config, in this process), then
runs ``silva bench pipeline`` on the TLS plot with the saved model: 1 worker, N workers and
one chunk per scene.

    python benchmarks/bench_workflow.py [--tile PATH] [--workers 2] [--plot-size 30] [--set KEY=VALUE ...]

Default tile: ../shared/data/tls/LPine1_demo.laz (1.54 M points). With a model at hand,
call ``silva bench pipeline CONFIG --model DIR`` directly.
"""

import argparse
import shutil
import tempfile
from pathlib import Path

from pipeline.synth import write_synthetic_plot
from workflows.cli.main import main as silva
from workflows.cli.templates import write_template

DEFAULT_TILE = Path(__file__).resolve().parents[2] / "shared" / "data" / "tls" / "LPine1_demo.laz"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tile", type=Path, default=DEFAULT_TILE)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--plot-size", type=float, default=30.0)
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        help="A config override of the classification runs (repeatable).")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="silva-bench-workflow-"))
    try:
        config = work / "demo.yaml"
        write_template("demo", config)
        train = work / "train"
        write_synthetic_plot(train, seed=1, size=args.plot_size)
        try:  # the model: trained once, in this process
            silva(["train", str(config), "--out", str(work / "train-out"), "--in-process",
                   "-q", "--set", f"data.train=[{train}/*.laz]"])
        except SystemExit as done:
            if done.code:
                raise
        sets = [f"data.predict=[{args.tile.resolve()}]", *args.overrides]
        silva(["bench", "pipeline", str(config), "--model", str(work / "train-out" / "model"),
               "--workers", str(args.workers), *(["--json"] if args.json else []),
               *[x for s in sets for x in ("--set", s)]])
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
