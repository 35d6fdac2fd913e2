"""The built-in steps as the table of steps (:data:`workflows.steps.table.STEPS`) runs them:
each takes the run's :class:`~workflows.steps.state.StepState`, calls its step module and
leaves what it found on the state for the steps after it. Each imports its step module when it
runs, so that the table, which the command line reads, stays light.

The features and the stage-by-stage cascade cover the scenes the forests train on (and
every scene with ``output.keep_features``); the other scenes are classified afterwards, in
one pass per chunk (:mod:`workflows.steps.one_pass`), which stores no features. The thinned
copies of the training scene (``data.densities``) are scenes the forests train on, which
the steps after the cascade leave out (:attr:`StepState.outputs`). A run
without labelled test points surveys its predictions before the export, so that its report's
figures are drawn while the workers write the tiles.
"""

from __future__ import annotations

import platform
from datetime import datetime, timezone
from typing import TYPE_CHECKING

from pipeline import __version__
from workflows.run.durations import totals
from workflows.run.progress import fold_step, say

if TYPE_CHECKING:
    from workflows.steps.state import StepState
    from workflows.store.scenes import RunLayout


def scenes_of(layout: RunLayout, keep, only: str | None = None) -> RunLayout:
    """``layout`` with the scenes ``keep(scene)`` holds (and only the scene of ``only``, a
    "scene/chunk" computed alone, when given)."""
    return layout.with_scenes(
        lambda s: keep(s) and (only is None or s == only.split("/", 1)[0]))


def check_trees(run, tiles: list[dict]) -> None:
    """Before the cluster starts: the trees' settings against the scan."""
    from workflows.steps.trees import check_tree_settings

    check_tree_settings(run, tiles)


def check_export(run, tiles: list[dict]) -> None:
    """Before the cluster starts: the output point format, the output names and the
    rasters' size."""
    from workflows.steps.export import check_output_names, check_point_formats, check_raster_size

    check_point_formats(run, tiles)
    check_output_names(run, tiles)
    check_raster_size(run, tiles)


def ingest_step(state: StepState) -> None:
    """Ingest the tiles; the summary counts points, chunks and excluded points."""
    from workflows.steps.export import check_point_formats, check_raster_size
    from workflows.steps.ingest import ingest
    from workflows.steps.trees import check_tree_settings

    layout = state.layout = state.timed("ingest", ingest, state.run, state.engine)
    state.summary["points"] = layout.n_points
    state.summary["chunks"] = sum(len(info.chunks) for info in layout.scenes.values())
    state.summary["chunk size (m)"] = ", ".join(
        f"{scene} {info.chunk_size:g}" if info.chunk_size else f"{scene} balanced"
        for scene, info in layout.scenes.items())
    state.summary["excluded points"] = sum(t.excluded for t in layout.tiles)
    check_point_formats(state.run, layout.tiles)  # output.point_format: keep, before work
    check_raster_size(state.run, layout.tiles)  # the points' boxes: a stale header hid them
    if state.reaches("trees"):
        check_tree_settings(state.run, layout.tiles)  # likewise, before the classification


def terrain_step(state: StepState) -> None:
    from workflows.steps.terrain import terrain

    state.timed("terrain", terrain, state.run, state.engine,
                scenes_of(state.layout, lambda s: True, state.only))


def features_step(state: StepState) -> None:
    """The features of the scenes classified stage by stage (every scene when the run stops
    at the features)."""
    from workflows.exec.engine import check_chunk
    from workflows.steps.features import features
    from workflows.steps.one_pass import one_pass_scenes

    if state.kernels is not None:
        state.kernels.wait()  # started with the run; the workers need the kernels from here on
    layout, only = state.layout, state.only
    passes = one_pass_scenes(layout) if state.reaches("train") else set()
    if only is not None:  # one chunk alone: the steps of its scene only
        check_chunk(layout, only)
    state.staged = scenes_of(layout, lambda s: s not in passes, only)
    state.one_pass = scenes_of(layout, lambda s: s in passes, only)
    if state.one_pass.scenes and not state.staged.scenes:
        fold_step("features", "computed with the stages, in one pass per chunk")
    state.counts = state.timed("features", features, state.run, state.engine, state.staged,
                               only)


def cascade_step(state: StepState) -> None:
    """Train (or apply) the cascade stage by stage, then classify the other scenes in one
    pass per chunk."""
    from workflows.steps.cascade import cascade, model_stages
    from workflows.steps.one_pass import classify_in_one_pass

    run, engine, only = state.run, state.engine, state.only
    if state.staged.scenes:
        state.stages = state.timed("train" if state.fits else "apply", cascade, run, engine,
                                   state.staged, state.counts, fit=state.fits, only=only)
    else:  # --chunk of a scene classified in one pass
        state.stages = model_stages(run)
    if state.one_pass.scenes:
        state.timed("apply", classify_in_one_pass, run, engine, state.one_pass, state.stages,
                    only)


def trees_step(state: StepState) -> None:
    """The trees of every scene (output.trees), before the export writes their IDs."""
    from workflows.steps.trees import trees

    state.trees = state.timed("trees", trees, state.run, state.engine, state.outputs,
                              state.n_stages - 1, state.stages[-1]["fingerprint"])


def tree_sections(state: StepState) -> tuple:
    """The report's trees section (HTML and figures), when the run found trees."""
    if state.trees is None:
        return ()
    from workflows.report.trees import trees_html, trees_images

    scenes = state.trees["scenes"]
    images = trees_images(scenes)
    scores = state.metrics.get("trees") if state.metrics else None
    return ((trees_html(scenes, images, scores), images),)


def survey_step(state: StepState) -> None:
    """An unlabelled run's report surveys the predictions before the export, whose progress
    counts its tasks, and draws its figures while the workers export."""
    if state.reaches("report") and not state.labelled:
        draw_survey(state, "export")


def draw_survey(state: StepState, counted_in: str) -> None:
    """The survey of the predictions (its tasks counted in the progress of step
    ``counted_in``) and a future of its figures, which the state's painter draws."""
    from workflows.steps.survey import canopy_samples, survey

    found = state.timed("report", survey, state.run, state.engine, state.outputs,
                        state.n_stages - 1, counted_in=counted_in)
    maps = {scene: data["map"] for scene, data in found["scenes"].items()}
    images = state.painter().submit(_survey_images, found, canopy_samples(state.run, maps))
    state.drawn = found, images


def _survey_images(found: dict, terrain: dict) -> dict:
    from workflows.report.survey import survey_images  # matplotlib: only runs that report

    return survey_images(found, terrain)


def export_step(state: StepState) -> None:
    from workflows.steps.export import export

    state.summary["predictions"] = state.timed(
        "export", export, state.run, state.engine, state.outputs, state.n_stages - 1,
        state.stages[-1]["fingerprint"])


def evaluate_step(state: StepState) -> None:
    """The metrics of the labelled test points (none without them: said); written here
    when the run stops at evaluate, else after the report."""
    from workflows.steps.evaluate import evaluate, write_metrics
    from workflows.steps.trees import score_trees

    run = state.run
    if state.labelled:
        state.metrics, state.plots = state.timed("evaluate", evaluate, run, state.engine,
                                                 state.outputs, state.n_stages)
        if state.trees is not None:
            scores = score_trees(run, state.outputs, state.trees["scenes"])
            if scores is not None:
                state.metrics["trees"] = scores
        if state.metrics["n_test_points"] == 0:  # no score over no points: say so
            say(f"warning: the test points carry none of the codes of data.classes in their "
                f"'{run.cfg.data.label_field}' field: no metrics; check data.label_field and "
                "data.classes (the report shows what was predicted)")
            state.metrics = None
    else:
        say("evaluate: no labelled test points (data.test or data.split): no metrics",
            quiet=run.quiet)
    if state.metrics is not None and not state.reaches("report"):
        write_metrics(run, state.metrics)
        state.summary["metrics"] = str(run.metrics_path)


def report_step(state: StepState) -> None:
    """The report with the metrics (written last: their presence means the whole run
    completed), or, without metrics, the report of what was predicted."""
    from workflows.steps.evaluate import write_metrics

    if state.metrics is None:
        _survey_report(state)
        return
    from workflows.report import write_report

    run, metrics = state.run, state.metrics
    run_info = _run_info(state)
    run.metrics_path.unlink(missing_ok=True)  # until the new report is written in full
    write_report(run.out, metrics, pr_data=state.plots["pr_data"],
                 topdown=state.plots["topdown"], run_info=run_info,
                 config_text=(run.out / "config.yaml").read_text(),
                 importances=[s.get("importances") for s in state.stages],
                 no_features=_no_features(state), terrain=state.plots["terrain"],
                 sections=tree_sections(state))
    write_metrics(run, metrics)
    state.summary.update(metrics=str(run.metrics_path), report=str(run.report_path),
                         macro_f1=metrics["macro"]["f1"])


def _survey_report(state: StepState) -> None:
    from workflows.report.survey import write_survey_report

    if state.drawn is None:  # labelled test tiles that hold none of the classes
        draw_survey(state, "report")
    found, images = state.drawn
    run = state.run
    state.timed("report", write_survey_report, run.out, found, images.result(),
                run_info=_run_info(state), config_text=(run.out / "config.yaml").read_text(),
                sections=tree_sections(state))
    state.summary["report"] = str(run.report_path)


def _run_info(state: StepState) -> dict:
    """The report's table of the run: command, date, software, counts, and the seconds
    of each step summed over every run of this output directory (resumes too)."""
    summary, spent = state.summary, totals(state.run.out)
    return {
        "command": state.command,
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "software": f"silva {__version__}, Python {platform.python_version()}",
        "input points": summary["points"],
        "chunks": summary["chunks"],
        "chunk size (m)": summary["chunk size (m)"],
        **({"excluded points": summary["excluded points"]} if summary["excluded points"]
           else {}),
        "echo features": echo_features_text(state.run),
        "durations (s)": ", ".join(f"{k} {v:.2f}" for k, v in spent.items()),
    }


def echo_features_text(run) -> str:
    """Whether the model used the points' return numbers (features.echoes), for the
    report."""
    if run.features.echoes:
        return ("yes: the model uses each point's return number and number of returns "
                "(features.echoes: true)")
    return "no: the model does not use the return numbers (features.echoes: false)"


def _no_features(state: StepState) -> dict:
    """The points written without features (NoFeatures = 1), as export counted them."""
    root, tiles = state.run.store, state.layout.tiles
    markers = [f"exports/{t.index}" for t in tiles]
    points = sum(int(root[m].attrs.get("no_features", 0)) for m in markers if m in root)
    return {"points": points, "total": sum(t.n_points for t in tiles)}
