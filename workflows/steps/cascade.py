"""The cascade across chunks: per stage, context (per chunk), fit (coordinator), predict (per chunk).

A stage is a barrier: the context of stage t needs the stage t-1 probabilities of every point
within r1, including halo points owned by neighbouring chunks, which are read back from those
chunks by global id. Training rows are chosen by a hash of (global id, seed) and sorted by id
before fitting, so the forests do not depend on the chunking or the number of workers.
"""

import logging
import os
from functools import lru_cache
from pathlib import Path

import numpy as np

from pipeline import cascade as method
from pipeline.errors import ConfigError, StoreError
from pipeline.features.context import uniform_context
from pipeline.model import (
    check_compatible,
    load_forest,
    read_description,
    save_forest,
    stage_file,
    write_description,
)
from pipeline.store import (
    ROLE_TRAIN,
    chunk_path,
    context_array,
    is_done,
    mark_done,
    open_store,
    proba_array,
    read_array,
    write_arrays,
)
from pipeline.tiling import Grid
from workflows.run import Run
from workflows.steps.features import chunk_tasks

log = logging.getLogger(__name__)


# -- worker side ----------------------------------------------------------------------------
def _stage_context(group, stage, n_classes, n_points):
    if stage == 0:
        return uniform_context(n_points, n_classes)
    return read_array(group, context_array(stage))


def _halo_proba(root, scene, grid, halo_xyz, halo_gid, stage, n_classes):
    """Stage probabilities of halo points, read from the chunks that own them."""
    proba = np.empty((len(halo_gid), n_classes), dtype=np.float32)
    owners = grid.chunk_of(halo_xyz)
    for owner in np.unique(owners):
        rows = np.flatnonzero(owners == owner)
        group = root[chunk_path(scene, grid.chunk_name(int(owner)))]
        gid = read_array(group, "gid")
        pos = np.searchsorted(gid, halo_gid[rows])
        pos = np.minimum(pos, len(gid) - 1)
        if not np.array_equal(gid[pos], halo_gid[rows]):
            raise StoreError(f"halo points of scene '{scene}' missing from their owner chunk "
                             f"{grid.chunk_name(int(owner))}; rerun with --overwrite")
        proba[rows] = read_array(group, proba_array(stage))[pos]
    return proba


def chunk_context(store_path, scene, chunk, grid, stage, r1, r2, max_neighbors, n_classes,
                  mode, fingerprint):
    """Worker task: the context features of stage ``stage`` (>= 1) for one chunk's core."""
    root = open_store(store_path)
    group = root[chunk_path(scene, chunk)]
    if is_done(group, f"context{stage + 1}", fingerprint):
        return None
    grid = Grid(**grid)
    xyz, gid = read_array(group, "xyz"), read_array(group, "gid")
    halo_xyz, halo_gid = read_array(group, "halo_xyz"), read_array(group, "halo_gid")
    proba = np.concatenate([
        read_array(group, proba_array(stage - 1)),
        _halo_proba(root, scene, grid, halo_xyz, halo_gid, stage - 1, n_classes),
    ])
    context = method.stage_context(
        np.concatenate([xyz, halo_xyz]), proba, mode, r1=r1, r2=r2, max_neighbors=max_neighbors,
        query=np.arange(len(gid), dtype=np.int64), ids=np.concatenate([gid, halo_gid]),
    )
    write_arrays(group, {context_array(stage): context})
    mark_done(group, f"context{stage + 1}", fingerprint)
    return None


def chunk_training_rows(store_path, scene, chunk, stage, n_classes, fractions, seed):
    """Worker task: the sampled training rows (features, labels, ids) of one chunk."""
    group = open_store(store_path)[chunk_path(scene, chunk)]
    label, role, gid = (read_array(group, k) for k in ("label", "role", "gid"))
    mask = method.training_mask(gid, np.where(role == ROLE_TRAIN, label, -1), fractions, seed)
    if not mask.any():
        return None
    invariants = read_array(group, "invariants")[mask]
    context = _stage_context(group, stage, n_classes, len(gid))[mask]
    return method.feature_matrix(invariants, context), label[mask].astype(np.int64), gid[mask]


@lru_cache(maxsize=8)
def _cached_forest(path: str, mtime: float):
    return load_forest(Path(path))


def _forest(path: Path):
    return _cached_forest(str(path), os.path.getmtime(path))


def chunk_predict(store_path, scene, chunk, stage, forest_path, fold_paths, n_classes,
                  fractions, seed, fingerprint):
    """Worker task: stage probabilities of one chunk's core points."""
    group = open_store(store_path)[chunk_path(scene, chunk)]
    if is_done(group, f"predict{stage + 1}", fingerprint):
        return None
    label, role, gid = (read_array(group, k) for k in ("label", "role", "gid"))
    features = method.feature_matrix(
        read_array(group, "invariants"), _stage_context(group, stage, n_classes, len(gid))
    )
    training = method.training_mask(gid, np.where(role == ROLE_TRAIN, label, -1), fractions, seed)
    proba = method.predict_stage(
        _forest(Path(forest_path)),
        [_forest(Path(p)) for p in fold_paths],
        features,
        gid,
        training,
        n_classes=n_classes,
        seed=seed,
    )
    write_arrays(group, {proba_array(stage): proba})
    mark_done(group, f"predict{stage + 1}", fingerprint)
    return None


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


def _fit(run: Run, engine, layout, stage, fractions, seed, fingerprint):
    """Gather the sampled rows of every chunk, fit the stage's forests, save them."""
    tasks = chunk_tasks(
        run, layout, f"sample-{stage + 1}", chunk_training_rows,
        lambda scene, chunk, info: dict(
            store_path=str(run.store_path), scene=scene, chunk=chunk, stage=stage,
            n_classes=run.n_classes, fractions=fractions, seed=seed,
        ),
        fingerprint,
        "train",
    )
    rows = [r for r in engine.map(f"sample-{stage + 1}", tasks).values() if r is not None]
    if not rows:
        raise ConfigError("no labelled training points: check data.train, data.classes and "
                          "data.label_field")
    features, labels, ids = (np.concatenate(parts) for parts in zip(*rows))
    cascade = run.cfg.cascade
    params = method.ForestParams(
        int(cascade.n_estimators), int(cascade.min_samples_leaf), cascade.max_features,
        n_jobs=os.cpu_count() or 1,
    )
    log.info("stage %d: fitting on %d rows", stage + 1, len(ids))
    forest, fold_forests = method.fit_stage(
        features, labels, ids, params=params, seed=seed, stage=stage,
        out_of_fold=bool(cascade.out_of_fold), folds=int(cascade.folds),
    )
    for fitted in (forest, *fold_forests):  # workers predict single-threaded, in parallel
        fitted.set_params(n_jobs=1)
    save_forest(stage_file(run.model_path, stage), forest)
    for k, fold_forest in enumerate(fold_forests):
        save_forest(stage_file(run.work_path / "folds", stage, k), fold_forest)
    return len(ids)


def _model_description(run: Run, fractions, seed, stages) -> dict:
    return {
        **run.feature_description(),
        "classes": [{"name": n, "code": c} for n, c in zip(run.classes, run.class_codes)],
        "seed": seed,
        "training_fractions": [float(f) for f in fractions],
        "stages": stages,
    }


def cascade(run: Run, engine, layout: dict, train_counts: np.ndarray | None, *, fit: bool,
            only: str | None = None) -> None:
    """Run every stage: context, fit (when training), predict, over every chunk."""
    n_stages = int(run.cfg.cascade.stages)
    seed = int(run.cfg.cascade.seed)
    if fit:
        check_training_classes(run, train_counts)
        fractions = method.sampling_fractions(
            train_counts, run.cfg.cascade.max_train_points, bool(run.cfg.cascade.balanced)
        )
        try:
            stages = read_description(run.model_path).get("stages", [])
        except Exception:  # noqa: BLE001 - no model yet: everything is fitted below
            stages = []
    else:
        description = read_description(run.model_path)
        check_compatible(description, run.feature_description(), run.model_path)
        names = [c["name"] for c in description["classes"]]
        if names != run.classes:
            raise ConfigError(f"model {run.model_path} predicts classes {names} but "
                              f"data.classes lists {run.classes}; use the model's classes")
        fractions = np.zeros(run.n_classes)  # no training points: no out-of-fold answers
        stages = description["stages"]
        n_stages = len(stages)

    def per_chunk(step, fn, extra):
        tasks = chunk_tasks(run, layout, step, fn, lambda scene, chunk, info: dict(
            store_path=str(run.store_path), scene=scene, chunk=chunk, **extra(info)),
            extra_fp, "train" if fit else "predict", only)
        engine.map(step, tasks)

    for stage in range(n_stages):
        if fit:
            fingerprint = run.stage_fingerprint(stage)
            fitted = (
                stage < len(stages)
                and stages[stage]["fingerprint"] == fingerprint
                and stage_file(run.model_path, stage).is_file()
            )
        else:
            fingerprint = stages[stage]["fingerprint"]
            fitted = True
        # Chunk results depend on this run's features and on the stage's forest.
        extra_fp = f"{run.fingerprint('features')}-{fingerprint}"
        if stage > 0:
            per_chunk(f"context-{stage + 1}", chunk_context, lambda info: dict(
                grid=info["grid"], stage=stage, r1=run.r1, r2=run.r2,
                max_neighbors=run.cfg.features.context_max_neighbors,
                n_classes=run.n_classes, mode=run.cfg.cascade.context, fingerprint=extra_fp))
        if not fitted:
            n_rows = _fit(run, engine, layout, stage, fractions, seed, extra_fp)
            stages = stages[:stage] + [{"index": stage + 1, "fingerprint": fingerprint,
                                        "file": stage_file(run.model_path, stage).name,
                                        "training_rows": n_rows}]
            write_description(run.model_path, _model_description(run, fractions, seed, stages))
        folds = []
        if fit and run.cfg.cascade.out_of_fold:
            folds = [str(stage_file(run.work_path / "folds", stage, k))
                     for k in range(int(run.cfg.cascade.folds))]
        per_chunk(f"predict-{stage + 1}", chunk_predict, lambda info: dict(
            stage=stage, forest_path=str(stage_file(run.model_path, stage)), fold_paths=folds,
            n_classes=run.n_classes, fractions=fractions, seed=seed, fingerprint=extra_fp))
    if fit and len(stages) > n_stages:  # fewer stages than a previous run: keep the model honest
        write_description(run.model_path, _model_description(run, fractions, seed, stages[:n_stages]))
