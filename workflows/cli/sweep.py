"""``silva sweep``: run one configuration once per value of a key (and per seed), compare.

Every run is an ordinary run up to ``evaluate`` (:func:`workflows.run.loop.execute`) with
``--set KEY=VALUE`` and ``cascade.seed = 0 .. N-1``, all on one Dask client opened the way
``silva run`` opens it. Runs whose features are the same (their ``features`` fingerprint,
:func:`workflows.config.fingerprint`, is equal: any ``cascade.*`` key, ``features.r2``,
``features.context_max_neighbors``, ...) run one after the other in ONE run directory, so
the fingerprinted resume of the steps computes ingest and features once and every later run
recomputes only the cascade, export and evaluation. A key that changes the features gets a
run directory per value. Each run's ``metrics.json`` and ``config.yaml`` are copied out as
soon as it finishes::

    DIR/
      sweep.csv           one row per value x seed x stage: macro and per-class scores
      sweep.md            mean ± std over the seeds, last stage and F1 per stage
      sweep_scores.png    macro precision, recall and F1 against the value
      sweep_stages.png    macro F1 per cascade stage, one line per value
      silva.log
      run/                the shared run directory (a key that leaves the features alone)
      KEY=VALUE/run/      ... or one per value (a key that changes them)
      KEY=VALUE/seedK/    metrics.json and config.yaml of each run
"""

import contextlib
import csv
import itertools
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click
import yaml

from pipeline.errors import ConfigError, SilvaError
from workflows.run.progress import run_logging, run_progress, say

MEASURES = ("precision", "recall", "f1")


@dataclass(frozen=True)
class SweepRun:
    """One run of a sweep: the value (as typed and as YAML read it), its seed and places."""

    text: str
    value: Any
    seed: int
    cfg: Any  # SilvaConfig
    work: Path  # the run directory it computes in (shared with other runs)
    result: Path  # where its metrics.json and config.yaml are kept


def parse_values(text: str) -> list[tuple[str, Any]]:
    """``"0.5,true,paper"`` -> ``[("0.5", 0.5), ("true", True), ("paper", "paper")]``."""
    texts = [t.strip() for t in text.split(",")]
    if not text.strip() or not all(texts):
        raise ConfigError(f"--values '{text}' has an empty value; give V1,V2,... e.g. "
                          "--values 10,20,50")
    if len(set(texts)) < len(texts):
        twice = next(t for t in texts if texts.count(t) > 1)
        raise ConfigError(f"--values '{text}' lists {twice} twice; give each value once")
    values = []
    for t in texts:
        try:
            value = yaml.safe_load(t)
        except yaml.YAMLError:
            value = []
        if isinstance(value, (list, dict)):
            raise ConfigError(f"--values: '{t}' is not a single value (a number, true/false, "
                              "null or a word); sweep one scalar key at a time")
        values.append((t, value))
    return values


def plan_sweep(config: Path, key: str, values: str, seeds: int, out: Path,
               overrides=()) -> list[SweepRun]:
    """Every run of the sweep, each configuration validated, before any work is done."""
    from workflows.config import load_config
    from workflows.run.autoparams import resolve_run
    from workflows.run.directory import read_paths
    from workflows.steps.table import STEPS

    key = key.strip()
    if key.split(".")[0] == "cluster":
        raise ConfigError(f"--param {key}: cluster keys change how, not what, is computed; "
                          "sweep a key of data, tiling, features, cascade or output")
    if key == "cascade.seed" and seeds > 1:
        raise ConfigError("--param cascade.seed already sweeps the seed; drop --seeds")
    seed_list = [None] if key == "cascade.seed" else list(range(seeds))
    plan, groups, parsed = [], {}, parse_values(values)
    names = [f"{key}={re.sub(r'[^A-Za-z0-9_.+-]', '_', t)}" for t, _ in parsed]
    if len(set(names)) < len(names):
        raise ConfigError(f"--values '{values}' gives two values the same directory name; "
                          "use values that differ in letters or digits")
    for name, (text, value) in zip(names, parsed):
        for seed in seed_list:
            extra = [] if seed is None else [f"cascade.seed={seed}"]
            # the runs of a run directory share the test scenes' features too
            cfg = load_config(config, ["output.keep_features=true", *overrides, *extra,
                                       f"{key}={text}"])
            if seed == seed_list[0]:
                if not cfg.data.test and cfg.data.split is None:
                    raise ConfigError(f"config error: {config} has no labelled test points "
                                      "(data.test or data.split); a sweep compares test "
                                      "metrics")
                read_paths(cfg, config, None)  # every input exists
            # 'auto' values (r1, voxel, echoes) resolved from the tiles, as the run will
            features = STEPS.fingerprint(resolve_run(cfg).cfg, "features")
            groups.setdefault(features, out / name / "run")
            plan.append(SweepRun(text, value, cfg.cascade.seed, cfg, groups[features],
                                 out / name / f"seed{cfg.cascade.seed}"))
    if len(groups) == 1:  # the features never change: one run directory for all
        plan = [SweepRun(r.text, r.value, r.seed, r.cfg, out / "run", r.result) for r in plan]
    return plan


def run_sweep(config: Path, key: str, values: str, seeds: int, out: Path, overrides=(), *,
              quiet: bool = False, in_process: bool = False, verbose: int = 0,
              command: str = "silva sweep") -> list[dict]:
    """Run every value x seed; write sweep.csv, sweep.md and the plots; return the rows."""
    from workflows.cli.commands import LOG_NAME, Interrupted
    from workflows.exec.engine import open_engine
    from workflows.exec.kernels import prepare_kernels
    from workflows.run.directory import prepare_output

    plan = plan_sweep(config, key, values, seeds, out, overrides)
    works = list(dict.fromkeys(r.work for r in plan))
    results = []
    with contextlib.ExitStack() as stack:
        for directory in [out, *works]:
            stack.enter_context(prepare_output(directory, overwrite=False, command=command))
        stack.enter_context(run_logging(verbose, out / LOG_NAME))
        where = (f"ingest and features once, in {works[0]}" if len(works) == 1
                 else "ingest and features per value")
        say(f"sweep of {key}: {len(plan)} runs ({where})", quiet=quiet)
        kernels = stack.enter_context(prepare_kernels(quiet))  # waited for before features
        try:
            with open_engine(plan[0].cfg, quiet=quiet, in_process=in_process,
                         debug=False) as engine:
                for i, item in enumerate(plan, 1):
                    say(f"run {i}/{len(plan)}: {key}={item.text}, cascade.seed={item.seed}",
                        quiet=quiet)
                    metrics = _run_one(item, engine, quiet, command, kernels)
                    results.append((item, metrics))
                    click.echo(f"{key}={item.text} seed {item.seed}: macro F1 "
                               f"{metrics['macro']['f1']:.3f} ({item.result / 'metrics.json'})")
        except KeyboardInterrupt:
            raise Interrupted(command) from None
        rows = sweep_rows(results)
        write_csv(out / "sweep.csv", rows)
        (out / "sweep.md").write_text(markdown_table(key, results))
        write_plots(out, key, results)
    for name in ("sweep.csv", "sweep.md", "sweep_scores.png", "sweep_stages.png"):
        click.echo(f"{name}: {out / name}")
    return rows


def _run_one(item: SweepRun, engine, quiet: bool, command: str, kernels=None) -> dict:
    """Run ``item`` up to evaluate in its run directory; keep and return its metrics."""
    from pipeline.atomic import atomic_write_text
    from workflows.run.autoparams import resolve_run
    from workflows.run.directory import Run
    from workflows.run.loop import execute
    from workflows.steps.table import STEPS

    run = Run(resolve_run(item.cfg), item.work, quiet=quiet, steps=STEPS)
    run.save_config()
    steps = STEPS.progress_steps("evaluate")
    with run_progress(steps, quiet=quiet, stages=int(item.cfg.cascade.stages),
                      weights=STEPS.weights(), per_stage=STEPS.per_stage_names()) as progress:
        summary = execute(run, engine, "evaluate", command=command, kernels=kernels)
        progress.finish(summary["timings"], list(summary["timings"]))
    if "metrics" not in summary:
        raise SilvaError(f"the run with {item.text} found no labelled test points: nothing "
                         "to compare; give data.test or data.split")
    item.result.mkdir(parents=True, exist_ok=True)
    for name in ("config.yaml", "metrics.json"):
        atomic_write_text(item.result / name, (item.work / name).read_text())
    return json.loads(run.metrics_path.read_text())


# -- outputs --------------------------------------------------------------------------------
def sweep_rows(results) -> list[dict]:
    """One dict per run x stage: value, seed, stage (from 1), macro scores, F1 per class."""
    rows = []
    for item, metrics in results:
        for stage, scores in enumerate(metrics["stages"], start=1):
            rows.append({"value": item.text, "seed": item.seed, "stage": stage,
                         **{f"macro_{m}": scores["macro"][m] for m in MEASURES},
                         **{f"f1_{c}": v["f1"] for c, v in scores["per_class"].items()}})
    return rows


def write_csv(path: Path, rows: list[dict]) -> None:
    columns = list(dict.fromkeys(k for row in rows for k in row))
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns)
        writer.writeheader()
        writer.writerows(rows)


def _by_value(results) -> dict[str, dict]:
    """value text -> {"value", "last": {measure: [per seed]}, "stages": [[F1 per seed]]}."""
    summary: dict[str, dict] = {}
    for item, metrics in results:
        entry = summary.setdefault(item.text, {"value": item.value,
                                               "last": {m: [] for m in MEASURES},
                                               "stages": []})
        for m in MEASURES:
            entry["last"][m].append(metrics["macro"][m])
        for stage, scores in enumerate(metrics["stages"]):
            if stage == len(entry["stages"]):
                entry["stages"].append([])
            entry["stages"][stage].append(scores["macro"]["f1"])
    return summary


def _mean_std(values) -> tuple[float, float]:
    """Mean and sample standard deviation (0 for a single value)."""
    import numpy as np

    values = np.asarray(values, dtype=np.float64)
    return float(values.mean()), (float(values.std(ddof=1)) if len(values) > 1 else 0.0)


def _cell(values) -> str:
    mean, std = _mean_std(values)
    return f"{mean:.3f} ± {std:.3f}" if len(values) > 1 else f"{mean:.3f}"


def markdown_table(key: str, results) -> str:
    """A Markdown table: per value, runs and mean ± std of macro P/R/F1 and F1 per stage."""
    summary = _by_value(results)
    n_stages = max(len(e["stages"]) for e in summary.values())
    seeds = sorted({len(e["last"]["f1"]) for e in summary.values()})
    head = [key, "runs", "precision", "recall", "F1",
            *(f"F1 stage {s}" for s in range(1, n_stages + 1))]
    lines = [f"Sweep of `{key}`: macro scores on the test points at the last cascade stage, "
             f"mean ± sample std over the seeds ({'/'.join(map(str, seeds))} per value).", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for text, entry in summary.items():
        stages = [_cell(v) for v in entry["stages"]]
        stages += [""] * (n_stages - len(stages))
        cells = [text, str(len(entry["last"]["f1"])),
                 *(_cell(entry["last"][m]) for m in MEASURES), *stages]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_plots(out: Path, key: str, results) -> None:
    """sweep_scores.png (macro P/R/F1 against the value) and sweep_stages.png (F1 per stage),
    mean ± std over the seeds as error bars; drawn with Agg on Figure objects (no pyplot)."""
    from matplotlib.figure import Figure

    summary = _by_value(results)
    numeric = all(isinstance(e["value"], (int, float)) and not isinstance(e["value"], bool)
                  for e in summary.values())
    xs = [e["value"] if numeric else i for i, e in enumerate(summary.values())]
    n_stages = max(len(e["stages"]) for e in summary.values())
    lines = {  # file -> x label, y label, [(x, samples per x, legend)]
        "sweep_scores.png": (key, "macro score at the last stage", [
            (xs, [e["last"][m] for e in summary.values()], f"macro {m}".replace("f1", "F1"))
            for m in MEASURES]),
        "sweep_stages.png": ("cascade stage", "macro F1", [
            (range(1, len(e["stages"]) + 1), e["stages"], f"{key}={text}")
            for text, e in summary.items()]),
    }
    for name, (xlabel, ylabel, curves) in lines.items():
        fig = Figure(figsize=(6, 4), layout="constrained")
        ax = fig.add_subplot()
        for (x, samples, label), marker in zip(curves, itertools.cycle("osD^v<>ph*")):
            points = [_mean_std(v) for v in samples]
            ax.errorbar(list(x), [p[0] for p in points], yerr=[p[1] for p in points],
                        marker=marker, capsize=3, label=label)
        if name == "sweep_stages.png":
            ax.set_xticks(range(1, n_stages + 1))
        elif not numeric:
            ax.set_xticks(xs, list(summary))
        ax.set(xlabel=xlabel, ylabel=ylabel, title=f"Sweep of {key}")
        ax.grid(alpha=0.3)
        ax.legend()
        fig.savefig(out / name, dpi=120)


@click.command("sweep")
@click.argument("config", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--param", "key", required=True, metavar="KEY",
              help="The config key to vary, e.g. cascade.n_estimators or features.r1.")
@click.option("--values", required=True, metavar="V1,V2,...",
              help="Its values, comma-separated, each read as YAML (0.5, true, paper).")
@click.option("--seeds", type=click.IntRange(min=1), default=1, show_default=True,
              help="Runs per value, with cascade.seed = 0 .. N-1.")
@click.option("--out", "-o", type=click.Path(file_okay=False, path_type=Path),
              help="Output directory [default: ./silva-sweep-<config name>].")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE",
              help="Override a config value in every run, e.g. features.set=paper.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bars: a line per step.")
@click.option("--in-process", is_flag=True,
              help="Run every task in this process, without a Dask cluster.")
@click.option("-v", "--verbose", count=True, help="Info logs (-vv: debug).")
def sweep(config, key, values, seeds, out, overrides, quiet, in_process, verbose):
    """Run CONFIG once per value of a config key (and per seed); tabulate and plot the
    test metrics. Features are computed once when the key does not change them.

    \b
    Examples:
      silva sweep survey.yaml --param features.r1 --values 0.3,0.4,0.5
      silva sweep survey.yaml --param cascade.stages --values 1,2,3 --seeds 3
    """
    from workflows.cli.commands import _command_line

    out = out or Path(f"silva-sweep-{Path(config).stem}")
    run_sweep(config, key, values, seeds, out, overrides, quiet=quiet, in_process=in_process,
              verbose=verbose, command=_command_line())
