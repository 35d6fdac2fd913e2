"""The cascade across the chunks of the store: :class:`StoreCascade`, the workflow's side of
:func:`pipeline.cascade.run_cascade`.

Per stage: context (per chunk), training rows (per chunk, gathered by the coordinator, which
fits the forests), predict (per chunk). A stage is a barrier: the context of stage t needs
the stage t-1 probabilities of every point within r1, including halo points owned by
neighbouring chunks, which are read back from those chunks by global id. Training rows are
chosen by a hash of (global id, seed) and sorted by id before fitting, so the forests do not
depend on the chunking or the number of workers.
"""

import logging
import os
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from pipeline.cascade import (
    FittedStage,
    chunk_proba,
    labels_from_proba,
    run_cascade,
    stage_context,
    training_rows,
)
from pipeline.errors import ChunkError, ConfigError, ModelError, StoreError
from pipeline.features.sets import FeatureParams
from pipeline.model import (
    load_forest,
    read_description,
    read_model_file,
    save_forest,
    stage_file,
    write_description,
)
from pipeline.store import rows_of
from pipeline.terrain import TERRAIN_VERSION
from pipeline.tiling import BalancedLayout, Grid
from workflows.exec.engine import chunk_tasks
from workflows.run.autoparams import data_filters
from workflows.run.directory import Run
from workflows.run.plan import AppliedModel, check_model
from workflows.run.progress import say
from workflows.steps.copies import trained_copies
from workflows.steps.terrain import GroundRule
from workflows.store.layout import ROLE_TRAIN, context_array, labels_array, proba_array
from workflows.store.scenes import RunLayout

log = logging.getLogger(__name__)
FIT_LINE_SECONDS = 60  # with --quiet, a line at most this often while the forests grow


# -- worker side ----------------------------------------------------------------------------
@dataclass(frozen=True)
class ContextTask:
    features: FeatureParams
    mode: str  # "hard" or "soft"
    stage: int  # the stage the context feeds (>= 1)
    n_classes: int
    grid: Grid | BalancedLayout


@dataclass(frozen=True)
class StageTask:
    stage: int
    n_classes: int
    fractions: tuple[float, ...]
    seed: int
    forest_path: str = ""
    fold_paths: tuple[str, ...] = ()
    ground: GroundRule = GroundRule()


def _chunk_inputs(view, task):
    """(features, context or None for the first stage, training labels, ids) of a chunk."""
    label, role, gid = view.read("label", "role", "gid")
    context = view.read(context_array(task.stage)) if task.stage > 0 else None
    labels = np.where(role == ROLE_TRAIN, label, -1).astype(np.int64)
    return view.read("features"), context, labels, gid


def _halo_proba(view, grid, halo_xyz, halo_gid, stage, n_classes):
    """Stage probabilities of halo points, read from the chunks that own them."""
    proba = np.empty((len(halo_gid), n_classes), dtype=np.float32)
    owners = grid.chunk_of(halo_xyz)
    for owner in np.unique(owners):
        rows = np.flatnonzero(owners == owner)
        neighbour = view.neighbour(grid.chunk_name(int(owner)))
        pos, found = rows_of(neighbour.read("gid"), halo_gid[rows])
        if not found.all():
            raise StoreError(f"halo points of scene '{view.scene}' missing from their owner "
                             f"chunk {neighbour.chunk}; rerun with --overwrite")
        proba[rows] = neighbour.read(proba_array(stage))[pos]
    return proba


def chunk_context(view, task: ContextTask):
    """Worker task: the context that feeds stage ``task.stage`` for one chunk's core."""
    xyz, gid, halo_xyz, halo_gid = view.read("xyz", "gid", "halo_xyz", "halo_gid")
    proba = np.concatenate([
        view.read(proba_array(task.stage - 1)),
        _halo_proba(view, task.grid, halo_xyz, halo_gid, task.stage - 1,
                    task.n_classes),
    ])
    context = stage_context(
        np.concatenate([xyz, halo_xyz]), proba, task.mode, r1=task.features.r1,
        r2=task.features.r2, max_neighbors=task.features.context_max_neighbors,
        query=np.arange(len(gid), dtype=np.int64), ids=np.concatenate([gid, halo_gid]),
    )
    view.write(**{context_array(task.stage): context})


def chunk_training_rows(view, task: StageTask):
    """Worker task: the sampled training rows (X, y, ids) of one chunk, or None."""
    features, context, labels, gid = _chunk_inputs(view, task)
    return training_rows(features, context, labels, gid, np.asarray(task.fractions),
                         task.seed, task.n_classes)


@lru_cache(maxsize=8)
def _loaded_forest(path: str, mtime: float):
    return load_forest(Path(path))


def cached_forest(path: str):
    """The forest saved at ``path``, loaded once per worker (again when the file changes)."""
    return _loaded_forest(path, os.path.getmtime(path))


def chunk_predict(view, task: StageTask):
    """Worker task: stage probabilities of one chunk's core points, and its labels, which a
    chunk classified in one pass keeps too (evaluate reads them whatever the mode)."""
    features, context, labels, gid = _chunk_inputs(view, task)
    proba = chunk_proba(cached_forest(task.forest_path),
                        [cached_forest(p) for p in task.fold_paths], features, context, labels,
                        gid, np.asarray(task.fractions), task.seed, task.n_classes)
    override = task.ground.override(view)  # the mask stored with the chunk's features
    if override is not None:
        proba = override.apply(proba)
    view.write(**{proba_array(task.stage): proba,
                  labels_array(task.stage): labels_from_proba(proba)})


# -- coordinator side -----------------------------------------------------------------------
def check_training_classes(run: Run, counts: np.ndarray) -> None:
    """Refuse to train when a class has no labelled training point."""
    missing = [name for name, n in zip(run.classes, counts) if n == 0]
    if missing:
        name = missing[0]
        raise ConfigError(
            f"class '{name}' (codes {list(run.cfg.data.classes[name])}) has no labelled "
            f"training points in data.train (field '{run.cfg.data.label_field}'); add tiles "
            "that contain it, or remove it from data.classes (or list it in data.ignore)"
        )


def model_stages(run: Run) -> list[dict]:
    """The stages of the model ``run`` applies (read and checked by its plan) or, when it
    trains, of the model it trained (read and checked now: a chunk classified in one pass
    applies it)."""
    if run.model is not None:
        return run.model.stages
    description, digest = read_model_file(run.model_path)
    trained = AppliedModel(run.model_path, description, digest)
    check_model(run.cfg, trained)
    return trained.stages


class StoreCascade:
    """:class:`pipeline.cascade.CascadeData` of a run: the chunks of its store, mapped over
    the engine's workers. Its forests live in files that the workers load."""

    def __init__(self, run: Run, engine, layout: RunLayout, *, fit: bool, only: str | None):
        self.run, self.engine, self.layout, self.fit, self.only = run, engine, layout, fit, only
        self.n_classes = run.n_classes
        self.params = run.cascade_params(n_jobs=os.cpu_count() or 1)
        self.fractions = ()
        self._said = time.monotonic()  # the last line while fitting
        if fit:
            try:
                previous = read_description(run.model_path)
            except ModelError:  # no model yet: every stage is fitted
                previous = {}
            self.stages = previous.get("stages", [])
            self.fractions = tuple(previous.get("training_fractions", ()))
        else:
            self.stages = model_stages(run)

    def stage_fingerprint(self, stage: int) -> str:
        if self.fit:
            return self.run.stage_fingerprint(stage)
        return self.stages[stage]["fingerprint"]

    def _chunk_fingerprint(self, stage: int) -> str:
        # chunk results depend on this run's features and on the stage's forest
        return f"{self.run.fingerprint('features')}-{self.stage_fingerprint(stage)}"

    def _map(self, step: str, fn, params, stage: int, *, marks: bool = True):
        """The tasks' results, in task order (scene by scene), not in the order they
        finished: a point and its thinned copies share a global id, and the stable sort by
        id before fitting keeps their rows in scene order, whatever the chunking."""
        tasks = chunk_tasks(self.run, self.layout, step, fn, params,
                            self._chunk_fingerprint(stage),
                            "train" if self.fit else "predict", only=self.only, marks=marks)
        results = self.engine.map(step, tasks)
        return {task.key: results[task.key] for task in tasks}

    def _stage_task(self, stage, fractions, seed) -> StageTask:
        folds = ()
        if self.fit and self.params.out_of_fold:
            folds = tuple(str(stage_file(self.run.work_path / "folds", stage, k))
                          for k in range(self.params.folds))
        return StageTask(stage, self.n_classes, tuple(float(f) for f in fractions), seed,
                         str(stage_file(self.run.model_path, stage)), folds,
                         GroundRule.of(self.run))

    # -- the CascadeData interface ------------------------------------------------------
    def update_context(self, stage):
        run = self.run
        self._map(f"context-{stage + 1}", chunk_context, lambda info: ContextTask(
            run.features, self.params.context, stage, self.n_classes, info.grid), stage)

    def training_rows(self, stage, fractions, seed):
        self.fractions = fractions
        results = self._map(f"sample-{stage + 1}", chunk_training_rows,
                            StageTask(stage, self.n_classes, tuple(map(float, fractions)), seed),
                            stage, marks=False)
        rows = [r for r in results.values() if r is not None]
        if not rows:
            raise ConfigError("no labelled training points: check data.train, data.classes "
                              "and data.label_field")
        x, y, ids = (np.concatenate(parts) for parts in zip(*rows))
        log.info("stage %d: fitting on %d rows", stage + 1, len(ids))
        return x, y, ids

    def fitted(self, stage):
        path = stage_file(self.run.model_path, stage)
        # applying a model, its own fingerprint is the stage's: only a missing file fails
        if (stage < len(self.stages) and path.is_file()
                and self.stages[stage]["fingerprint"] == self.stage_fingerprint(stage)):
            return FittedStage(path, [], self.stages[stage].get("training_rows", 0))
        if not self.fit:
            raise ModelError(f"model file {path} is missing; retrain with 'silva train'")
        if self.only is not None:
            # one chunk cannot train a stage: draw its training rows, where a failure would
            # show, and stop before any forest is fitted on them
            self._map(f"sample-{stage + 1}", chunk_training_rows, StageTask(
                stage, self.n_classes, self.fractions or (1.0,) * self.n_classes,
                self.params.seed), stage, marks=False)
            raise ChunkError(
                f"--chunk {self.only}: stage {stage + 1} of the model is not trained yet and "
                f"one chunk cannot train it; the chunk's steps up to its training sample ran "
                f"without error. Train with 'silva train CONFIG --out {self.run.out}' first")
        return None

    def fitting(self, stage, n_stages, forest, n_forests, trees, n_trees):
        """With --quiet, a line a minute while the forests grow (a long training is not
        silence; the progress bars show the time otherwise); every round in the log."""
        which = ("its forest" if forest == 0
                 else f"out-of-fold forest {forest} of {n_forests - 1}")
        line = f"train: stage {stage + 1} of {n_stages}, {which}: {trees} of {n_trees} trees"
        now = time.monotonic()
        if self.run.quiet and now - self._said >= FIT_LINE_SECONDS:
            self._said = now
            say(line)
        else:
            log.info("%s", line)

    def save(self, stage, fitted):
        for forest in (fitted.forest, *fitted.fold_forests):
            forest.set_params(n_jobs=1)  # workers predict single-threaded, in parallel
        save_forest(stage_file(self.run.model_path, stage), fitted.forest)
        for k, fold_forest in enumerate(fitted.fold_forests):
            save_forest(stage_file(self.run.work_path / "folds", stage, k), fold_forest)
        self.stages = self.stages[:stage] + [{
            "index": stage + 1, "fingerprint": self.stage_fingerprint(stage),
            "file": stage_file(self.run.model_path, stage).name,
            "training_rows": fitted.training_rows,
            "importances": self._importances(fitted.forest),
        }]
        self._describe(self.stages)

    def _importances(self, forest) -> dict[str, float]:
        """The forest's impurity importance of each feature column and context column."""
        classes = self.run.classes
        names = (self.run.feature_description()["features.columns"]
                 + [f"context_r1_{c}" for c in classes] + [f"context_r2_{c}" for c in classes])
        return {name: round(float(v), 6) for name, v in zip(names, forest.feature_importances_)}

    def predict(self, stage, fitted, fractions, seed):
        self._map(f"predict-{stage + 1}", chunk_predict,
                  self._stage_task(stage, fractions, seed), stage)

    def keep_stages(self, n_stages: int) -> None:
        """Drop the stages a previous run fitted beyond ``n_stages``: the model stays honest."""
        if len(self.stages) > n_stages:
            self.stages = self.stages[:n_stages]
            self._describe(self.stages)

    def _describe(self, stages):
        run = self.run
        write_description(run.model_path, {
            **run.feature_description(),
            "terrain.version": TERRAIN_VERSION,
            "classes": [{"name": n, "code": c} for n, c in zip(run.classes, run.class_codes)],
            **data_filters(run.cfg),
            "seed": self.params.seed,
            "training_fractions": [float(f) for f in self.fractions],
            **self._densities(),
            "stages": stages,
        })

    def _densities(self) -> dict:
        """What model.json records of the thinned copies it was trained on (data.densities
        and each copy made; nothing without data.densities)."""
        densities = self.run.cfg.data.densities
        if not densities:
            return {}
        return {"data.densities": [float(d) for d in densities],
                "training_copies": trained_copies(self.layout)}


def cascade(run: Run, engine, layout: RunLayout, train_counts: np.ndarray | None, *, fit: bool,
            only: str | None = None) -> list[dict]:
    """Run every stage over every chunk (fitting the stages a model lacks when ``fit``);
    return the model's stage records."""
    data = StoreCascade(run, engine, layout, fit=fit, only=only)
    n_stages = data.params.stages if fit else len(data.stages)
    if only is not None:  # one chunk applies the forests and sampling the whole run fitted
        run_cascade(data, data.params, n_stages=n_stages, fractions=data.fractions or None)
        return data.stages
    if fit:
        check_training_classes(run, train_counts)
    run_cascade(data, data.params, train_counts if fit else None, n_stages=n_stages)
    if fit:
        data.keep_stages(n_stages)
    return data.stages
