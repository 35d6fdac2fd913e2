"""The steps of a run, in order, each resumable: ingest, terrain, features, train (the
cascade), export, evaluate, report.

The features and the stage-by-stage cascade cover the scenes the forests train on (and
every scene with ``output.keep_features``); the other scenes are classified afterwards, in
one pass per chunk (:mod:`workflows.steps.one_pass`), which stores no features. A run
without labelled test points surveys its predictions before the export, so that its report's
figures are drawn while the workers write the tiles.

Every command is a target: it runs the steps up to and including its own. Steps skip the work
a previous run finished with the same configuration, so rerunning a killed command resumes it.

With ``output.keep_store: false`` a run that completed removes the chunks of its store and
records what it completed (:func:`pipeline.store.remove_chunks`); the same run again then
only says so, and any other command starts afresh from the input tiles.
"""

import logging
import os
import platform
import time
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime, timezone

from pipeline import __version__
from pipeline.errors import StoreError
from pipeline.store import forget_removed, remove_chunks, removed_record
from workflows.durations import accumulate, totals
from workflows.engine import check_chunk
from workflows.progress import fold_step, say
from workflows.run import Run, has_test_points
from workflows.steps.cascade import cascade, check_model
from workflows.steps.evaluate import evaluate, write_metrics
from workflows.steps.export import check_point_formats, export
from workflows.steps.features import features
from workflows.steps.ingest import ingest
from workflows.steps.one_pass import classify_in_one_pass, one_pass_scenes
from workflows.steps.survey import canopy_samples, survey
from workflows.steps.terrain import terrain

log = logging.getLogger(__name__)

STEPS = ("ingest", "features", "train", "export", "evaluate", "report")


def execute(run: Run, engine, target: str, *, only: str | None = None, command: str = "",
            kernels=None) -> dict:
    """Run the steps up to ``target``; return a summary (durations, counts, output paths).

    ``kernels`` (:class:`workflows.commands.Kernels`, optional): the feature kernels
    compiling in the background while ingest runs; waited for before the features step.
    """
    last = STEPS.index(target)
    timings = {}
    summary = {"out": str(run.out), "timings": timings}  # timings fill in as steps finish
    stamp = run.forget_stale_results()  # a rerun that changes nothing keeps metrics, report
    if _already_complete(run, target, only, summary, stamp):
        return summary
    model_stages = None if run.model_dir is None else check_model(run)  # before any work:
    # a wrong model must not cost a night

    def timed(step, fn, *args, **kwargs):
        started = time.monotonic()
        try:
            result = fn(*args, **kwargs)
        except StoreError:
            run.drop_results()  # a damaged store certifies no metrics made from it
            raise
        finally:  # what the result cost, a stopped or failed run's share too
            accumulate(run.out, {step: time.monotonic() - started})
        timings[step] = round(timings.get(step, 0) + time.monotonic() - started, 2)
        return result

    layout = timed("ingest", ingest, run, engine)
    summary["points"] = sum(t["n_points"] for t in layout["tiles"])
    summary["chunks"] = sum(len(s["chunks"]) for s in layout["scenes"].values())
    summary["chunk size (m)"] = ", ".join(
        f"{scene} {info['grid']['size']:g}" if "size" in info["grid"] else f"{scene} balanced"
        for scene, info in layout["scenes"].items())
    summary["excluded points"] = sum(t.get("excluded", 0) for t in layout["tiles"])
    check_point_formats(run, layout["tiles"])  # output.point_format: keep, before any work
    if last < 1:
        return summary
    timed("terrain", terrain, run, engine, scenes_of(layout, lambda s: True, only))
    if kernels is not None:
        kernels.wait()  # started with the run; the workers need the kernels from here on
    fit = model_stages is None
    passes = one_pass_scenes(layout) if last >= 2 else set()
    if only is not None:  # one chunk alone: the steps of its scene only
        check_chunk(layout, only)
    staged = scenes_of(layout, lambda s: s not in passes, only)
    one_pass = scenes_of(layout, lambda s: s in passes, only)
    if one_pass["scenes"] and not staged["scenes"]:
        fold_step("features", "computed with the stages, in one pass per chunk")
    counts = timed("features", features, run, engine, staged, only)
    if last < 2:
        return summary
    if staged["scenes"]:
        stages = timed("train" if fit else "apply", cascade, run, engine, staged, counts,
                       fit=fit, only=only)
    else:
        stages = model_stages or check_model(run)  # --chunk of a scene classified in one pass
    if one_pass["scenes"]:
        timed("apply", classify_in_one_pass, run, engine, one_pass, stages, only)
    if only is not None or last < 3:
        return summary
    n_stages = len(stages)
    labelled = has_test_points(layout, run.cfg.data.split)
    drawn = None
    with ThreadPoolExecutor(max_workers=1) as painter:
        if last >= 5 and not labelled:  # the report's figures are drawn while workers export
            drawn = _draw_survey(run, engine, layout, n_stages - 1, timed, painter, "export")
        summary["predictions"] = timed(
            "export", export, run, engine, layout, n_stages - 1, stages[-1]["fingerprint"]
        )
    if last < 4:
        return summary
    metrics = plots = None
    if labelled:
        metrics, plots = timed("evaluate", evaluate, run, engine, layout, n_stages)
        if metrics["n_test_points"] == 0:  # no score over no points: say so, report what is
            say(f"warning: the test points carry none of the codes of data.classes in their "
                f"'{run.cfg.data.label_field}' field: no metrics; check data.label_field and "
                "data.classes (the report shows what was predicted)")
            metrics = None
    if metrics is None:
        if not labelled:
            say("evaluate: no labelled test points (data.test or data.split): no metrics",
                quiet=run.quiet)
        if last >= 5:  # the report of what was predicted, without scores
            from workflows.report.survey import write_survey_report

            if drawn is None:  # labelled test tiles that hold none of the classes
                with ThreadPoolExecutor(max_workers=1) as painter:
                    drawn = _draw_survey(run, engine, layout, n_stages - 1, timed, painter,
                                         "report")
            found, images = drawn
            timed("report", write_survey_report, run.out, found, images.result(),
                  run_info=_run_info(run, summary, command),
                  config_text=(run.out / "config.yaml").read_text())
            summary["report"] = str(run.report_path)
        _finish(run, target, only, summary, stamp)
        return summary
    if last < 5:
        write_metrics(run, metrics)
        summary["metrics"] = str(run.metrics_path)
        return summary
    from workflows.report import write_report

    run_info = _run_info(run, summary, command)
    run.metrics_path.unlink(missing_ok=True)  # until the new report is written in full
    write_report(run.out, metrics, pr_data=plots["pr_data"], topdown=plots["topdown"],
                 run_info=run_info, config_text=(run.out / "config.yaml").read_text(),
                 importances=[s.get("importances") for s in stages],
                 no_features=_no_features(run, layout), terrain=plots["terrain"])
    # metrics.json last: its presence means the whole run completed.
    write_metrics(run, metrics)
    summary.update(metrics=str(run.metrics_path), report=str(run.report_path),
                   macro_f1=metrics["macro"]["f1"])
    _finish(run, target, only, summary, stamp)
    return summary


def _draw_survey(run: Run, engine, layout: dict, final_stage: int, timed, painter,
                 counted_in: str):
    """The survey of an unlabelled run's predictions (its tasks counted in the progress of
    step ``counted_in``) and a future of its figures, which ``painter`` (a thread) draws
    meanwhile."""
    found = timed("report", survey, run, engine, layout, final_stage, counted_in=counted_in)
    maps = {scene: data["map"] for scene, data in found["scenes"].items()}
    return found, painter.submit(_survey_images, found, canopy_samples(run, maps))


def _survey_images(found: dict, terrain: dict) -> dict:
    from workflows.report.survey import survey_images  # matplotlib: only runs that report

    return survey_images(found, terrain)


def _run_info(run: Run, summary: dict, command: str) -> dict:
    """The report's table of the run: command, date, software, counts, and the seconds
    of each step summed over every run of this output directory (resumes too)."""
    spent = totals(run.out)
    return {
        "command": command,
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "software": f"silva {__version__}, Python {platform.python_version()}",
        "input points": summary["points"],
        "chunks": summary["chunks"],
        "chunk size (m)": summary["chunk size (m)"],
        **({"excluded points": summary["excluded points"]} if summary["excluded points"]
           else {}),
        "durations (s)": ", ".join(f"{k} {v:.2f}" for k, v in spent.items()),
    }


def scenes_of(layout: dict, keep, only: str | None = None) -> dict:
    """``layout`` with the scenes ``keep(scene)`` holds (and only the scene of ``only``, a
    "scene/chunk" computed alone, when given)."""
    scenes = {s: info for s, info in layout["scenes"].items() if keep(s)}
    if only is not None:
        scenes = {s: info for s, info in scenes.items() if s == only.split("/", 1)[0]}
    return {**layout, "scenes": scenes}


# -- output.keep_store: false ----------------------------------------------------------------
_SUMMARY_KEYS = ("points", "chunks", "chunk size (m)", "excluded points", "predictions",
                 "metrics", "report", "macro_f1")


def _outputs(run: Run, summary: dict) -> list[str]:
    """The files a complete run leaves, relative to its output directory."""
    paths = [*summary.get("predictions", ()), summary.get("metrics"), summary.get("report")]
    if run.model_dir is None:
        paths.append(str(run.model_path / "model.json"))
    return sorted(os.path.relpath(p, run.out) for p in paths if p)


def _finish(run: Run, target: str, only, summary: dict, stamp: str) -> None:
    """After a complete run (its results stamp ``stamp``): remove the store's chunks unless
    output.keep_store."""
    if target != STEPS[-1] or only is not None or run.cfg.output.keep_store:
        return
    record = {"completed": stamp,
              "outputs": _outputs(run, summary),
              "summary": {k: summary[k] for k in _SUMMARY_KEYS if k in summary}}
    remove_chunks(run.store, record)
    say(f"store: chunks removed from {run.store_path} (output.keep_store: false)",
        quiet=run.quiet)


def _already_complete(run: Run, target: str, only, summary: dict, stamp: str) -> bool:
    """Whether the store was removed after a complete run of this very configuration (results
    stamp ``stamp``) whose outputs are all still there (then say so and fill ``summary``); a
    removed store that does not qualify is cleared, so that the steps start afresh."""
    if not run.store_path.exists():  # never create the store before ingest checks the inputs
        return False
    record = removed_record(run.store)
    if record is None:
        return False
    complete = (target == STEPS[-1] and only is None
                and record.get("completed") == stamp
                and all((run.out / p).is_file() for p in record.get("outputs", ())))
    if complete:
        summary.update(record.get("summary", {}))
        say(f"{run.out}: the results of this configuration are complete (its store was removed "
            "after the run: output.keep_store false); nothing to do. To compute them again, "
            "rerun with --overwrite")  # even with --quiet: it explains why nothing runs
        return True
    say(f"{run.store_path}: its chunks were removed after the last run (output.keep_store "
        "false); computing again from the input tiles")
    forget_removed(run.store)
    return False


def _no_features(run: Run, layout: dict) -> dict:
    """The points written without features (NoFeatures = 1), as export counted them."""
    root = run.store
    markers = [f"exports/{t['index']}" for t in layout["tiles"]]
    points = sum(int(root[m].attrs.get("no_features", 0)) for m in markers if m in root)
    return {"points": points, "total": sum(t["n_points"] for t in layout["tiles"])}
