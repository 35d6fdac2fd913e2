"""Throughput of the whole workflow: points per second per step, peak memory, worker scaling.

Trains a cascade on a synthetic forest plot, then classifies a real TLS tile (or, without it,
a second synthetic plot) with the saved model, twice in this process: once with every task in
this process (one core, the baseline) and once on a LocalCluster. Prints points/s for each
step and the ratio of the two runs.

    python benchmarks/bench_workflow.py [--tile PATH] [--workers 2] [--plot-size 30] [--chunk-size auto]

Default tile: ../shared/data/tls/LPine1_demo.laz (1.54 M points) when present.
"""

import argparse
import resource
import shutil
import tempfile
import time
from pathlib import Path

import yaml

from pipeline.synth import write_synthetic_plot
from workflows.config import load_config
from workflows.engine import Engine
from workflows.run import Run
from workflows.workflow import execute

DEFAULT_TILE = Path(__file__).resolve().parents[2] / "shared" / "data" / "tls" / "LPine1_demo.laz"


def _config(path: Path, data: dict, workers: int, chunk_size="auto") -> Path:
    path.write_text(yaml.safe_dump({
        "data": {**data, "classes": {"terrain": [2], "tree": [5], "dead_wood": [64], "misc": [1]}},
        "tiling": {"chunk_size": chunk_size},
        "cascade": {"stages": 3, "max_train_points": 60_000},
        "cluster": {"kind": "local", "n_workers": workers, "dashboard": False},
    }, sort_keys=False))
    return path


def _timed_run(config: Path, out: Path, model: Path | None, client) -> dict:
    run = Run(load_config(config), out, quiet=True, model_dir=model)
    run.save_config()
    started = time.perf_counter()
    summary = execute(run, Engine(client, quiet=True), "export")
    summary["total"] = time.perf_counter() - started
    return summary


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tile", type=Path, default=DEFAULT_TILE)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--plot-size", type=float, default=30.0)
    parser.add_argument("--chunk-size", default="auto",
                        help="tiling.chunk_size of the classified tile: metres or auto")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="silva-bench-"))
    try:
        train = work / "train"
        write_synthetic_plot(train, seed=1, size=args.plot_size)
        tile = args.tile
        if not tile.is_file():
            print(f"{tile} not found: classifying a synthetic plot instead")
            tile = write_synthetic_plot(work / "other", seed=2, size=args.plot_size)[0]
        train_config = _config(work / "train.yaml", {"train": [str(train / "*.laz")]}, 1)
        chunk_size = args.chunk_size if args.chunk_size == "auto" else float(args.chunk_size)
        config = _config(work / "bench.yaml", {"predict": [str(tile)]}, args.workers, chunk_size)
        # the model: trained once, in this process
        trained = _timed_run(train_config, work / "train-out", None, None)
        print(f"training run ({trained['points']:,} points): {trained['total']:.1f} s "
              f"{trained['timings']}")
        model = work / "train-out" / "model"
        results = {}
        from distributed import Client, LocalCluster

        for label in ("in-process", f"{args.workers} workers"):
            out = work / label.replace(" ", "-")
            if label == "in-process":
                results[label] = _timed_run(config, out, model, None)
            else:
                with LocalCluster(n_workers=args.workers, threads_per_worker=1,
                                  host="127.0.0.1", dashboard_address=None) as cluster, \
                        Client(cluster) as client:
                    results[label] = _timed_run(config, out, model, client)
        base = results["in-process"]
        print(f"\nclassifying {tile.name}: {base['points']:,} points")
        print(f"{'step':<10}" + "".join(f"{k:>22}" for k in results) + f"{'ratio':>8}")
        for step in base["timings"]:
            cells = "".join(
                f"{r['points'] / max(r['timings'][step], 1e-9):>14,.0f} pts/s" for r in results.values())
            ratio = base["timings"][step] / max(list(results.values())[1]["timings"][step], 1e-9)
            print(f"{step:<10}{cells}{ratio:>8.2f}")
        totals = "".join(f"{r['points'] / r['total']:>14,.0f} pts/s" for r in results.values())
        print(f"{'total':<10}{totals}{base['total'] / list(results.values())[1]['total']:>8.2f}")
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        print(f"\npeak memory of this process (in-process run included): {peak:,.0f} MiB")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
