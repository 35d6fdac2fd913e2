"""The commands of ``silva``: ``run``, one per step, ``predict``, ``plan``, ``status``,
``demo``, ``synth`` and ``init`` (``sweep``, which runs through these, is in its own module).

Each step command is a target: it runs the steps up to and including its own, skipping what a
previous run finished with the same configuration (see :mod:`workflows.run.loop`).
:mod:`workflows.cli.main` gathers :data:`COMMANDS` into the ``silva`` group; this module does not
import it. The modules that run steps (Dask, numba, zarr) are imported only when a run starts,
so ``silva --help`` and ``silva init`` answer at once.
"""

import contextlib
import functools
import json
import logging
import shlex
import sys
from dataclasses import dataclass
from pathlib import Path

import click

from workflows.cli.templates import TEMPLATES, template_path, write_template
from workflows.exec.kernels import prepare_kernels
from workflows.run.progress import (
    counted,
    log_line,
    run_logging,
    run_progress,
    say,
)
from workflows.run.step_table import examples
from workflows.steps.table import STEPS

log = logging.getLogger(__name__)

LOG_NAME = "silva.log"


class Interrupted(KeyboardInterrupt):
    """Ctrl-C during a run; ``command`` is what resumes it."""

    def __init__(self, command: str):
        super().__init__(command)
        self.command = command


def resume_command(command: str) -> str:
    """``command`` without ``--overwrite``: what resumes a run it started, instead of
    emptying its output directory again."""
    try:
        words = shlex.split(command)
    except ValueError:  # not a command line shlex wrote
        return command
    return shlex.join(word for word in words if word != "--overwrite")


def os_error_line(err: OSError) -> str:
    """One line for an operating-system error: what failed where, and what to do."""
    reason = err.strerror or str(err) or type(err).__name__
    where = f" {err.filename}" if err.filename else ""
    return (f"cannot write or read{where}: {reason}; fix it (free space, permissions) and run "
            "the same command again: finished work is kept")


def error_line(err: BaseException) -> str | None:
    """The one line the command line shows for ``err`` (a Silva error, an operating-system
    error, Ctrl-C), or None for an error it does not explain."""
    from pipeline.errors import SilvaError

    if isinstance(err, SilvaError):
        return f"silva: error: {err}"
    if isinstance(err, OSError):  # a full disk, a read-only or vanished output directory
        return f"silva: error: {os_error_line(err)}"
    if isinstance(err, KeyboardInterrupt):
        command = getattr(err, "command", None)
        return (f"silva: interrupted; run the same command again to resume: {command}"
                if command else "silva: interrupted")
    return None


def _command_line() -> str:
    """The command as the user typed it (``silva ...``), for the report and for resuming."""
    ctx = click.get_current_context(silent=True)
    if Path(sys.argv[0]).name in ("silva", "silva.exe", "__main__.py"):
        return shlex.join(["silva", *sys.argv[1:]])
    return ctx.command_path if ctx is not None else "silva"


@dataclass(frozen=True)
class RunOptions:
    """What the options of a command that runs steps ask (:func:`run_options`)."""

    out: Path | None = None  # None: ./silva-<config name>, or ./silva-predict
    overrides: tuple[str, ...] = ()  # --set KEY=VALUE
    overwrite: bool = False
    quiet: bool = False
    in_process: bool = False
    chunk: str | None = None  # "scene/chunk": that chunk alone, in this process
    verbose: int = 0


def run_options(out_help: str = "Output directory [default: ./silva-<config name>]."):
    """The options of every command that runs steps, handed to the command as one
    :class:`RunOptions` (its parameter ``options``)."""
    flags = [
        click.option("--out", "-o", type=click.Path(file_okay=False, path_type=Path),
                     help=out_help),
        click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE",
                     help="Override a config value with a YAML value, e.g. tiling.chunk_size=20."),
        click.option("--overwrite", is_flag=True, help="Start from an empty output directory."),
        click.option("--quiet", "-q", is_flag=True, help="No progress bars: a line per step."),
        click.option("--in-process", is_flag=True,
                     help="Run every task in this process, without a Dask cluster."),
        click.option("--chunk", metavar="SCENE/CHUNK",
                     help="Rerun one chunk in this process, showing the full error."),
        click.option("-v", "--verbose", count=True,
                     help="Show the resolved configuration and info logs (-vv: debug)."),
    ]

    def decorate(fn):
        @functools.wraps(fn)
        def command(*, out, overrides, overwrite, quiet, in_process, chunk, verbose, **given):
            return fn(options=RunOptions(out, tuple(overrides), overwrite, quiet, in_process,
                                         chunk, verbose), **given)

        for flag in reversed(flags):
            command = flag(command)
        return command

    return decorate


def _kernels_of(run, steps, quiet: bool, kernels=None):
    """The kernels of ``run`` as a context: ``kernels`` when the caller started them, else
    their compilation started now when the ``steps`` include features, else None."""
    if kernels is not None:
        return contextlib.nullcontext(kernels)
    if "features" in steps:
        return prepare_kernels(quiet, run.features)
    return contextlib.nullcontext(None)


def check_before_start(run, target: str, in_process: bool = False) -> tuple:
    """Check everything a run up to ``target`` can check without workers, before its cluster
    starts and its kernels compile, so that a mistake is refused in seconds (the input globs,
    files and headers were checked as the run's plan catalogued its tiles: no file, an empty
    tile, the same tile in train and test, two tiles of one name, mixed CRS): the tiles'
    return fields (with echo features), each step's own check (the trees' settings against
    the scan, the output point format, the rasters' size: the ``check`` of its row) and that a
    local cluster's workers have the memory for the largest chunk (the saved model a run
    applies was checked with its plan); warns when r1 is too small for the tiles' density
    and when the model applied was trained on another terrain version's heights.
    Raises the error the step would raise later; returns the run's tiles."""
    from workflows.cli.plan import check_memory, warn_before_work
    from workflows.steps.ingest import plan_tiles

    tiles = plan_tiles(run)
    steps = run.table.until(target, run.cfg)
    for step in steps:
        if step.check is not None:
            step.check(run, tiles)
    if "features" in (step.name for step in steps):
        warn_before_work(run)
        if not in_process:
            check_memory(run, tiles)
    return tiles


@contextlib.contextmanager
def _logged_error():
    """Write the line the command line shows for an error leaving the block (see
    :func:`error_line`) to the run's log too, as its last line."""
    try:
        yield
    except BaseException as err:
        line = error_line(err)
        if line is not None:  # Ctrl-C is the user's choice, not an error of the run
            log_line(line, logging.INFO if isinstance(err, KeyboardInterrupt) else logging.ERROR)
        raise


def start_run(config, options: RunOptions, target: str, *, model_dir=None, command=None,
              config_path=None, kernels=None, inputs=()):
    """Load the config, prepare the output directory and run the steps up to ``target``, as
    ``options`` ask; ``kernels``: the run's :class:`~workflows.exec.kernels.Kernels` when the
    caller already started them.

    What can be checked without workers is checked before the cluster starts and the
    kernels compile (:func:`check_before_start`); an error or Ctrl-C also ends the run's log
    with the line the command line shows. The resume hint never carries ``--overwrite``.
    """
    from workflows.cli.plan import step_weights
    from workflows.exec.cluster import plan_workers
    from workflows.config import validate_config
    from workflows.config.inputs import written_inputs
    from workflows.exec.engine import open_engine
    from workflows.run.autoparams import read_run, resolve_run
    from workflows.run.directory import (
        Run, applied_model, prepare_output, read_paths, record_applied_model,
    )
    from workflows.run.durations import reset
    from workflows.run.loop import execute

    out = options.out or Path(f"silva-{Path(config).stem if config else 'predict'}")
    overwrite, quiet = options.overwrite, options.quiet
    if model_dir is None and not overwrite:
        model_dir = applied_model(out)  # a later step of a 'silva predict' output
    raw = read_run(config_path or config, options.overrides, inputs)
    # found once: before the output directory when there is none (a wrong path leaves none)
    found = written_inputs(raw) if overwrite or not out.exists() else None
    command = command or _command_line()
    # --overwrite never deletes what this command reads (its config, model or inputs)
    keep = (read_paths(validate_config(raw), config_path or config, model_dir, found)
            if overwrite else ())
    lock = prepare_output(out, overwrite=overwrite, keep=keep, command=command)
    if overwrite:
        reset(out)  # the durations of the runs emptied start again
    steps = STEPS.progress_steps(target, applies_model=model_dir is not None)
    resume = resume_command(command)
    with run_logging(options.verbose, out / LOG_NAME), lock, _logged_error():
        log.info("start: %s (steps %s)", command, ", ".join(steps))
        try:
            plan = resolve_run(raw, model_dir, found)  # the model's values: a bad one logged
            steps = STEPS.progress_steps(target, model_dir is not None, plan.cfg)  # asked
            if model_dir is not None:
                record_applied_model(out, model_dir)
            run = Run(plan, out, quiet=quiet, steps=STEPS)
            text = run.save_config()
            if options.verbose:
                click.echo(f"# resolved configuration (saved to {out / 'config.yaml'})\n"
                           f"{text}", err=True)
            tiles = check_before_start(run, target, options.in_process)  # before cluster, kernels
            weights = step_weights(run, tiles, plan_workers(run))  # the ETA counts training
            with run_progress(steps, quiet=quiet, stages=run.n_stages, weights=weights,
                              per_stage=STEPS.per_stage_names()) as progress, \
                    _kernels_of(run, steps, quiet, kernels) as ready:
                with open_engine(plan.cfg, quiet=quiet, in_process=options.in_process,
                                 debug=options.chunk is not None) as engine:
                    summary = execute(run, engine, target, only=options.chunk, command=command,
                                      kernels=ready)
                done = [*summary["timings"], *(["report"] if "report" in summary else [])]
                progress.finish(summary["timings"], done)
        except KeyboardInterrupt:
            raise Interrupted(resume) from None
        log.info("done: %s", command)
    if summary.get("predictions"):
        click.echo(f"predictions: {run.predictions_path} "
                   f"({counted(len(summary['predictions']), 'tile')})")
    for key in ("metrics", "report"):
        if key in summary:
            click.echo(f"{key}: {summary[key]}")
    if "macro_f1" in summary:
        click.echo(f"macro F1 on the test points: {summary['macro_f1']:.3f}")
    return summary


def _step_command(name: str, target: str, doc: str) -> click.Command:
    @click.argument("config", type=click.Path(dir_okay=False, path_type=Path))
    @run_options()
    def command(config, options):
        start_run(config, options, target)

    command.__doc__ = doc
    return click.command(name)(command)


# command -> (the step it runs up to, its help): 'run' and the commands of the step table
STEP_COMMANDS = {
    "run": ("report", f"Run every step on CONFIG: {', '.join(STEPS.targets)}. A rerun resumes: "
                      "finished work with the same configuration is kept." + examples(
                          "silva run survey.yaml --out results/",
                          "silva run survey.yaml --out results/ --set features.r1=0.4 -q",
                      )),
    **{step.name: (step.name, step.command) for step in STEPS if step.command is not None},
}


def config_and_tiles(inputs) -> tuple[Path | None, tuple[str, ...]]:
    """The configuration (a .yaml file, at most one) and the tiles among a command's
    ``[CONFIG] [TILE_OR_GLOB]...`` arguments; UsageError for none, two configurations or a
    configuration that does not exist."""
    configs = [Path(p) for p in inputs if Path(p).suffix.lower() in (".yaml", ".yml")]
    tiles = tuple(p for p in inputs if Path(p).suffix.lower() not in (".yaml", ".yml"))
    if len(configs) > 1:
        raise click.UsageError(f"one configuration at most, got {', '.join(map(str, configs))}")
    if not configs and not tiles:
        raise click.UsageError("give the tiles to classify (TILE_OR_GLOB...) or a CONFIG")
    config = configs[0] if configs else None
    if config is not None and not config.is_file():
        raise click.UsageError(f"configuration {config} does not exist")
    return config, tiles


@click.command("predict")
@click.argument("inputs", nargs=-1, metavar="[CONFIG] [TILE_OR_GLOB]...")
@click.option("--model", "model_dir", required=True, metavar="MODEL",
              help="A model directory written by 'silva train' or 'silva run' (OUT/model), "
              "or the name of a model installed with Silva (see 'silva models').")
@run_options("Output directory [default: ./silva-<config name>, or ./silva-predict].")
def predict(inputs, model_dir, options):
    """Classify tiles with a saved model; evaluate when a CONFIG gives labelled test tiles.

    The model decides everything its predictions depend on (features, context, terrain,
    stages, classes): no configuration is needed. A CONFIG (a .yaml file) may set the rest
    (data, tiling, cluster, output); a key it sets otherwise than the model is refused
    before any work. TILE_OR_GLOB arguments are the tiles to classify (they replace the
    configuration's data.train, data.test and data.predict).

    \b
    Examples:
      silva predict --model results/model --out classified/ "survey/*.laz"
      silva predict --model als-ground-vegetation-building --out als/ t.laz
      silva predict new-tiles.yaml --model results/model --out new-results/
    """
    from workflows.models import model_path

    config, tiles = config_and_tiles(inputs)
    start_run(config, options, "report", model_dir=model_path(model_dir), inputs=tuple(tiles))


@click.command("plan")
@click.argument("inputs", nargs=-1, metavar="[CONFIG] [TILE_OR_GLOB]...")
@click.option("--model", "model_dir", default=None, metavar="MODEL",
              help="Plan a 'silva predict' run applying MODEL (a model directory or the name "
              "of a model installed with Silva): CONFIG is then optional, as for predict.")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE",
              help="Override a config key, e.g. --set tiling.chunk_size=20 (repeatable).")
@click.option("--picture", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write a PNG of each scene's chunk layout over its tiles.")
def plan(inputs, model_dir, overrides, picture):
    """Show what a run of CONFIG (or a 'silva predict' run with --model) will do, from the
    tiles' headers (and a quick count of the points for balanced chunks): tiles, points,
    chunk layout, terrain blocks, memory per worker, store size and duration (rough
    estimates); refuse in one line what will not fit. Nothing is written.

    \b
    Examples:
      silva plan survey.yaml
      silva plan survey.yaml --set tiling.target_points=500000 --picture grid.png
      silva plan --model als-ground-vegetation-building "tiles/*.laz"
    """
    from workflows.cli.plan import plan as plan_run
    from workflows.exec.cluster import plan_workers
    from workflows.models import model_path
    from workflows.run.autoparams import read_run, resolve_run
    from workflows.run.directory import Run

    if model_dir is None and (len(inputs) != 1 or not str(inputs[0]).endswith((".yaml", ".yml"))):
        raise click.UsageError("give one CONFIG (or --model MODEL with the tiles to classify)")
    config, tiles = config_and_tiles(inputs)
    model = model_path(model_dir) if model_dir is not None else None
    run = Run(resolve_run(read_run(config, overrides, tiles), model), Path("."), quiet=True,
              steps=STEPS)
    for line in plan_run(run, plan_workers(run), picture):
        click.echo(line)


@click.command("status")
@click.argument("out", type=click.Path(file_okay=False, exists=True, path_type=Path))
def status(out):
    """Show how far the run in OUT got.

    \b
    Examples:
      silva status results/
    """
    from workflows.cli.status import run_status

    for line in run_status(out):
        click.echo(line)


@click.command("demo")
@click.option("--out", "-o", type=click.Path(file_okay=False, path_type=Path),
              default=Path("silva-demo"), show_default=True, help="Output directory.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bars: a line per step.")
@click.option("--in-process", is_flag=True, help="Run without a Dask cluster.")
@click.option("--overwrite", is_flag=True, help="Start from an empty output directory.")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE",
              help="Override a value of the demo config (silva init --template demo shows it).")
@click.option("--plot-size", type=float, default=None,
              help="Side of the synthetic plots in metres [default: the generator's].")
@click.option("-v", "--verbose", count=True,
              help="Show the resolved configuration and info logs (-vv: debug).")
def demo(out, quiet, in_process, overwrite, overrides, plot_size, verbose):
    """Synthesise a training and a test forest plot, run the whole workflow, report.

    \b
    Examples:
      silva demo
      silva demo --out /tmp/silva-demo --plot-size 20 -q
    """
    from pipeline.synth import write_synthetic_plot
    from workflows.config import load_config
    from workflows.run.directory import prepare_output

    from workflows.run.durations import reset

    prepare_output(out, overwrite=overwrite)
    if overwrite:
        reset(out)
    data = out / "data"
    overrides = (
        f"data.train=[{(data / 'train').resolve()}/*.laz]",
        f"data.test=[{(data / 'test').resolve()}/*.laz]",
        *overrides,
    )
    with template_path("demo") as config:
        # the kernels compile while the plots are synthesised (the set is in the config)
        with prepare_kernels(quiet, load_config(config, overrides).features) as kernels:
            for role, seed in (("train", 1), ("test", 2)):
                if not any((data / role).glob("*.laz")):
                    say(f"synthesising the {role} plot (seed {seed}) into {data / role}",
                        quiet=quiet)
                    size = ({} if plot_size is None
                            else {"size": plot_size, "tile_size": plot_size / 2})
                    write_synthetic_plot(data / role, seed=seed, **size)
            summary = start_run(config, RunOptions(out, overrides, quiet=quiet,
                                                   in_process=in_process, verbose=verbose),
                                "report", kernels=kernels)
    if "report" in summary:
        click.echo(f"open {summary['report']} in a browser to see the report")
    return summary


@click.command("synth")
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--seed", default=0, show_default=True, help="Random seed: same seed, same points.")
@click.option("--size", default=None, type=float, help="Side of the square plot in metres.")
@click.option("--tile-size", default=None, type=float, help="Side of the square LAZ tiles.")
@click.option("--stand", type=click.Choice(["plain", "real"]), default="plain",
              show_default=True,
              help="real: touching crowns, suppressed trees under dominant ones and stems "
                   "leaning up to 5 degrees, as in real stands.")
@click.option("--slope", default=0.0, type=float, show_default=True, metavar="DEGREES",
              help="A hillside this steep (up to 60), in a random direction; 0: a gentle "
                   "3-18 % grade.")
@click.option("--ridge", is_flag=True,
              help="A ridge along the plot's middle, its faces falling at the slope.")
@click.option("--origin", type=float, nargs=3, default=None, metavar="X Y Z",
              help="The plot's lower-left corner at ground level [default: 500000 5500000 "
                   "400, UTM 32N]: plots written apart then lie side by side in one scene.")
def synth(out_dir, seed, size, tile_size, stand, slope, ridge, origin):
    """Write a labelled synthetic forest plot as LAZ tiles into OUT_DIR, with the trees'
    truth in OUT_DIR/trees.csv.

    \b
    Examples:
      silva synth plots/train --seed 1
      silva synth plots/test --seed 2 --size 30 --tile-size 15
      silva synth plots/real --seed 3 --stand real
      silva synth plots/ridge --seed 5 --slope 40 --ridge
      silva synth plots/hill --seed 11 --slope 35 --origin 500100 5500000 400
    """
    from dataclasses import replace

    from pipeline.synth import REAL_STAND, Stand, write_synthetic_plot

    kwargs = {k: v for k, v in {"size": size, "tile_size": tile_size,
                                "origin": origin}.items() if v is not None}
    kwargs["stand"] = replace(REAL_STAND if stand == "real" else Stand(), slope=slope,
                              ridge=ridge)
    paths = write_synthetic_plot(out_dir, seed=seed, **kwargs)
    for path in paths:
        click.echo(str(path))


@click.command("init")
@click.argument("path", type=click.Path(path_type=Path))
@click.option("--template", "-t", type=click.Choice(list(TEMPLATES)), default="forest",
              show_default=True,
              help="forest: survey tiles; demo: the synthetic plots; oakland: the urban "
                   "benchmark.")
@click.option("--force", is_flag=True, help="Overwrite PATH when it exists.")
def init(path, template, force):
    """Write a template config to PATH to edit.

    \b
    Examples:
      silva init my-survey.yaml
      silva init urban.yaml --template oakland
    """
    write_template(template, path, force=force)
    click.echo(f"wrote {path} from the {template} template ({TEMPLATES[template]}); edit "
               f"data.train, data.test and data.classes, then: silva run "
               f"{shlex.quote(str(path))} --out results/")


@click.command("models")
@click.option("--json", "as_json", is_flag=True,
              help="A JSON list of objects instead: name, kind, classes, feature set, echoes, "
                   "densities, training data, licences, every score.")
def models(as_json):
    """List the models installed with Silva: per model its kind, classes (with their output
    codes), the densities it was trained at, whether it needs echoes, and its headline score.
    Use one with --model NAME wherever a model directory is accepted. Reads the models' cards,
    never their forests.

    \b
    Examples:
      silva models
      silva models --json
    """
    from workflows.models import installed_models, model_summary

    found = [model_summary(name, path) for name, path in installed_models().items()]
    if as_json:
        click.echo(json.dumps(found, indent=2))
        return
    if not found:
        click.echo("no models are installed with this Silva")
        return
    for line in models_table(found):
        click.echo(line)


#: What 'silva models' calls the kinds its cards record.
MODEL_KINDS = {"als": "airborne", "tls": "terrestrial"}


def models_table(found: list[dict]) -> list[str]:
    """The lines of 'silva models': a header, a row per model (``found``: model_summary's
    dicts), then what the columns mean and where the rest is."""
    header = ("MODEL", "KIND", "CLASSES (CODE)", "TRAINED AT", "ECHOES", "SCORE")
    rows = []
    for model in found:
        density = model.get("trained_density", "-")
        if model["densities"]:
            copies = ", ".join(f"{d:g}" for d in model["densities"])
            density = f"{density}; copies at {copies} pts/m²"
        headline = model.get("headline")
        score = (f"{headline['value']:.3f} {headline['metric']}, {headline['on']}"
                 if headline else "-")
        rows.append((model["name"], MODEL_KINDS.get(model["kind"], model["kind"]),
                     ", ".join(f"{name} {code}" for name, code in model["classes"].items()),
                     density, "yes" if model["echoes"] else "no", score))
    widths = [max(len(row[i]) for row in (header, *rows)) for i in range(len(header) - 1)]
    lines = ["  ".join([*(cell.ljust(w) for cell, w in zip(row, widths)), row[-1]]).rstrip()
             for row in (header, *rows)]
    lines.append("")
    if any(model["echoes"] for model in found):
        lines.append("ECHOES yes: needs each point's return number and number of returns "
                     "(airborne LAS tiles record them).")
    lines += ["Use one: silva predict --model NAME --out OUT TILES.",
              "Every score, the training data and licences: silva models --json; the cards: "
              "docs/MODELS.md."]
    return lines


COMMANDS = [
    *(_step_command(name, target, doc) for name, (target, doc) in STEP_COMMANDS.items()),
    predict, plan, status, demo, synth, init, models,
]
