"""The run's loop: the steps of the run's table (:attr:`workflows.run.directory.Run.steps`,
a :class:`~workflows.run.step_table.StepTable` the commands give) in order, each
resumable, up to the command's target.

Every command is a target: it runs the steps up to and including its own. Steps skip the work
a previous run finished with the same configuration, so rerunning a killed command resumes it.

With ``output.keep_store: false`` a run that completed removes the chunks of its store and
records what it completed (:func:`workflows.store.retention.remove_chunks`); the same run, or
any step command of its configuration, again then only says so; the whole run with another
configuration starts afresh from the input tiles, and a step command that would have to
(or ``--chunk``) says so in one line instead.
"""

import logging
import os

from pipeline.errors import StoreError
from workflows.run.directory import Run
from workflows.run.progress import say
from workflows.store.retention import forget_removed, remove_chunks, removed_record

log = logging.getLogger(__name__)

def execute(run: Run, engine, target: str, *, only: str | None = None, command: str = "",
            kernels=None) -> dict:
    """Run the steps of ``run``'s table up to ``target``; return a summary (durations,
    counts, output paths).

    ``kernels`` (:class:`workflows.exec.kernels.Kernels`, optional): the feature kernels
    compiling in the background while ingest runs; waited for before the features step.
    """
    state = run.table.state(run, engine, target, only, command, kernels)
    # before the stamp of metrics and report is renewed: a refusal keeps them
    if _already_complete(run, target, only, state.summary, run.results_stamp()):
        return state.summary
    state.stamp = run.forget_stale_results()  # a rerun that changes nothing keeps metrics
    state.adds_durations = not run.report_path.is_file()  # complete: it costs nothing more
    try:
        for step in run.table.until(target, run.cfg):
            if only is not None and not step.per_chunk:
                break
            missing = [need for need in step.needs if getattr(state, need) is None]
            if missing:
                raise RuntimeError(f"step {step.name} needs {', '.join(missing)}, which no "
                                   "step before it set; check the order of the step table")
            step.function(state)
    finally:
        state.close()
    _finish(run, target, only, state.summary, state.stamp)
    return state.summary


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
    if target != run.table.targets[-1] or only is not None or run.cfg.output.keep_store:
        return
    record = {"completed": stamp,
              "outputs": _outputs(run, summary),
              "summary": {k: summary[k] for k in _SUMMARY_KEYS if k in summary}}
    remove_chunks(run.store, record)
    say(f"store: chunks removed from {run.store_path} (output.keep_store: false)",
        quiet=run.quiet)


def _already_complete(run: Run, target: str, only, summary: dict, stamp: str) -> bool:
    """Whether the store was removed after a complete run of this very configuration (results
    stamp ``stamp``) whose outputs are all still there (then say so and fill ``summary``):
    every step command's work is part of that run. Otherwise the whole run (its last
    target) starts afresh from the input tiles, the removed store cleared; a step command or
    ``--chunk``, which would redo everything for a part of it, is refused in one line that
    says so and how to ask for it (StoreError)."""
    if not run.store_path.exists():  # never create the store before ingest checks the inputs
        return False
    record = removed_record(run.store)
    if record is None:
        return False
    same = record.get("completed") == stamp
    missing = [p for p in record.get("outputs", ()) if not (run.out / p).is_file()]
    complete = only is None and same and not missing
    if not complete and (target != run.table.targets[-1] or only is not None):
        why = ("--chunk needs the chunks" if only is not None and same and not missing
               else "it completed with another configuration, other inputs or another model"
               if not same else f"{missing[0]} is no longer there")
        raise StoreError(
            f"{run.store_path}: its chunks were removed after the run completed "
            f"(output.keep_store: false) and {why}; 'silva {target}' would compute every "
            "step up to it again from the input tiles: to do so, rerun it with --overwrite "
            "(set output.keep_store: true to keep the chunks of the next run)")
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
