"""Throughput of the whole workflow on the real TLS plot: a wrapper of ``silva bench pipeline``.

Trains a cascade on a synthetic 30 m forest plot (the demo config, in this process), then
runs ``silva bench pipeline`` on the TLS plot with the saved model: 1 worker, N workers and
one chunk per scene.

    python benchmarks/bench_workflow.py [--tile PATH] [--workers 2] [--plot-size 30] [--set KEY=VALUE ...]

Default tile: ../shared/data/tls/LPine1_demo.laz (1.54 M points). With a model at hand,
call ``silva bench pipeline CONFIG --model DIR`` directly.

``--cpu-overhead --model MODEL``: what cutting the tile into chunks costs in CPU seconds,
which a loaded machine inflates far less than wall time. ``silva predict --in-process`` of
the tile, cut as ``--set`` says (default: the bench's 1-worker layout), against the same
run in one chunk, in this process, taking turns ``--repeat`` times (which goes first
alternates); the CPU seconds are
this process's and its children's (``getrusage``). A small predict in several chunks and a
whole one in one chunk run first, so that neither kind pays for what the process loads or
allocates once (the kernels, the forests, the code of either path, its memory).
``--profile DIR`` keeps a cProfile (CPU time) of every run there: what grows with the
number of chunks.

    python benchmarks/bench_workflow.py --cpu-overhead --model forest-tls-synthetic --repeat 2
"""

import argparse
import json
import resource
import shutil
import tempfile
import time
from pathlib import Path
from statistics import median

from pipeline.synth import write_synthetic_plot
from workflows.cli.main import main as silva
from workflows.cli.templates import write_template

DEFAULT_TILE = Path(__file__).resolve().parents[2] / "shared" / "data" / "tls" / "LPine1_demo.laz"
#: One worker plans the layout (a local cluster would share a scene out among its cores).
ONE_WORKER = ("cluster.n_workers=1",)
CHUNKED = (*ONE_WORKER, "tiling.chunk_size=auto")
ONE_CHUNK = (*ONE_WORKER, "tiling.chunk_size=auto", "tiling.layout=balanced",
             "tiling.target_points=1000000000000")
#: Points of the warm-up tile cut from the start of the measured one.
WARM_POINTS = 20_000


def cpu_seconds() -> tuple[float, float]:
    """User and system CPU seconds of this process and its waited-for children."""
    return tuple(sum(getattr(resource.getrusage(who), field)
                     for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
                 for field in ("ru_utime", "ru_stime"))  # fmt: skip


def predict(tile: Path, model: str, out: Path, sets, profile: Path | None = None) -> dict:
    """``silva predict --in-process`` of ``tile``: its CPU and wall seconds and chunks."""
    import cProfile

    shutil.rmtree(out, ignore_errors=True)
    args = ["predict", "--model", model, "--out", str(out), "--in-process", "-q",
            *[x for s in sets for x in ("--set", s)], str(tile)]
    profiler = cProfile.Profile(time.process_time) if profile else None
    cpu, wall = cpu_seconds(), time.perf_counter()
    if profiler:
        profiler.enable()
    try:
        silva(args, standalone_mode=False)
    finally:
        if profiler:
            profiler.disable()
            profiler.dump_stats(profile)
    (user, system), wall = [b - a for a, b in zip(cpu, cpu_seconds())], time.perf_counter() - wall
    chunks = len(list((out / "store.zarr" / "scenes").glob("*/chunks/*/zarr.json")))
    shutil.rmtree(out, ignore_errors=True)
    return {"cpu_seconds": round(user + system, 2), "user": round(user, 2),
            "system": round(system, 2), "seconds": round(wall, 1), "chunks": chunks}


def warm_tile(tile: Path, dst: Path) -> Path:
    """The first :data:`WARM_POINTS` points of ``tile`` in ``dst`` (a small predict in
    several chunks loads the code of the chunked path for every later one)."""
    import laspy

    with laspy.open(tile) as reader:
        points = reader.read_points(WARM_POINTS)
        with laspy.open(dst, mode="w", header=reader.header) as writer:
            writer.write_points(points)
    return dst


def cpu_overhead(tile: Path, model: str, overrides, repeat: int, profile: Path | None) -> dict:
    """The CPU seconds of ``tile`` predicted in chunks and in one chunk (see module)."""
    work = Path(tempfile.mkdtemp(prefix="silva-bench-overhead-"))
    try:
        # what a process pays once is no chunk's overhead: the forests and kernels, the code
        # of the chunked path (a small tile in several chunks), and the memory a whole run
        # takes from the system (the first whole run took 6-11 CPU s more than later ones)
        predict(warm_tile(tile, work / "warm.laz"), model, work / "warm",
                (*CHUNKED, f"tiling.target_points={WARM_POINTS // 4}"))
        predict(tile, model, work / "warm", ONE_CHUNK)
        rounds = []
        for turn in range(repeat):
            runs = {}
            kinds = [("chunks", (*CHUNKED, *overrides)), ("one chunk", (*ONE_CHUNK, *overrides))]
            # the order alternates: a shared machine's load drifts, and CPU seconds too
            for kind, sets in kinds[::-1] if turn % 2 else kinds:
                dump = profile / f"{kind.replace(' ', '-')}-{turn}.prof" if profile else None
                runs[kind] = predict(tile, model, work / "out", sets, dump)
                print(f"round {turn + 1}, {kind}: {runs[kind]}", flush=True)
            runs["overhead_cpu"] = round(
                runs["chunks"]["cpu_seconds"] / runs["one chunk"]["cpu_seconds"] - 1, 4)
            rounds.append(runs)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return {"tile": str(tile), "model": model, "overrides": list(overrides), "rounds": rounds,
            "overhead_cpu_median": median(r["overhead_cpu"] for r in rounds)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tile", type=Path, default=DEFAULT_TILE)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--plot-size", type=float, default=30.0)
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        help="A config override of the classification runs (repeatable).")
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--cpu-overhead", action="store_true",
                        help="Only the CPU seconds of chunks against one chunk, in this "
                        "process (needs --model).")
    parser.add_argument("--model", default=None,
                        help="A saved model (directory or installed name) for --cpu-overhead.")
    parser.add_argument("--repeat", type=int, default=2, help="Rounds of --cpu-overhead.")
    parser.add_argument("--profile", type=Path, default=None,
                        help="With --cpu-overhead: a cProfile of every run in this folder.")
    args = parser.parse_args()
    if args.cpu_overhead:
        if args.model is None:
            parser.error("--cpu-overhead needs --model (e.g. forest-tls-synthetic)")
        if args.profile:
            args.profile.mkdir(parents=True, exist_ok=True)
        result = cpu_overhead(args.tile, args.model, args.overrides, args.repeat, args.profile)
        print(json.dumps(result))
        return
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
