"""Export: one classified LAS/LAZ per input tile, every point in its original order.

Each task streams its input tile, finds each point's chunk from its coordinates (the same grid
as ingest) and its row there by global id, and writes the original dimensions plus the
predicted class, one probability per class, a confidence and ``NoFeatures`` (1 where the
point's features could not be computed: too few neighbours, or collinear ones; its prediction
then rests on what the forests make of missing values). Files are written atomically.
"""

from pathlib import Path

import numpy as np

from pipeline.atomic import remove_parts
from pipeline.errors import StoreError
from pipeline.io import ExtraDim, export_with_extra_dims
from pipeline.store import (
    chunk_path, is_done, mark_done, open_store, proba_array, read_array, rows_of,
)
from pipeline.tiling import global_ids, layout_from_dict
from workflows.engine import Task
from workflows.progress import counted, say
from workflows.run import Run

PREDICTED = "PredictedClassification"
CONFIDENCE = "Confidence"
ENTROPY = "Entropy"
NO_FEATURES = "NoFeatures"


def probability_dim(name: str) -> str:
    return f"Probability_{name}"


def entropy(proba: np.ndarray) -> np.ndarray:
    """float32 Shannon entropy (nats) of each row of probabilities (Myria3D's convention):
    0 for a certain prediction, log C when every class is equally likely."""
    p = np.asarray(proba, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        terms = np.where(p > 0, p * np.log(p), 0.0)
    return (-terms.sum(axis=1)).astype(np.float32)


def extra_dims(classes: list[str], codes: list[int], probabilities: bool) -> list[ExtraDim]:
    """The dimensions Silva adds to every exported point."""
    dtype = "uint8" if max(codes) <= 255 else "uint16"
    dims = [
        ExtraDim(PREDICTED, dtype, "Predicted class code"),
        ExtraDim(CONFIDENCE, "float32", "Probability of predicted class"),
        ExtraDim(ENTROPY, "float32", "Entropy of class probabilities"),
        ExtraDim(NO_FEATURES, "uint8", "1: features undefined"),
    ]
    if probabilities:
        dims += [ExtraDim(probability_dim(n), "float32", f"Probability of {n}"[:32])
                 for n in classes]
    return dims


class _ChunkPredictions:
    """Final probabilities of the chunks a tile touches, loaded once each."""

    def __init__(self, root, scene, grid, stage, allow_missing):
        self.root, self.scene, self.grid, self.stage = root, scene, grid, stage
        self.allow_missing = allow_missing  # points left out at ingest (data.drop_unlisted)
        self.cache = {}

    def _load(self, chunk, n_classes):
        """(sorted global ids, probabilities) of one chunk; empty for a chunk never stored."""
        name = self.grid.chunk_name(chunk)
        try:
            group = self.root[chunk_path(self.scene, name)]
        except KeyError:
            # ingest stores only chunks with points: every point here was left out
            if not self.allow_missing:
                raise StoreError(f"chunk {name} of scene '{self.scene}' is missing from the "
                                 "store; rerun with --overwrite") from None
            return (np.empty(0, np.int64), np.empty((0, n_classes), np.float32),
                    np.empty(0, bool))
        undefined = np.isnan(read_array(group, "features")).any(axis=1)
        return read_array(group, "gid"), read_array(group, proba_array(self.stage)), undefined

    def lookup(self, xyz, gid, n_classes):
        """float32 (n, C) probabilities, a bool mask of the points the store holds and one
        of the points whose features are undefined."""
        chunks = self.grid.chunk_of(xyz)
        proba = np.zeros((len(gid), n_classes), dtype=np.float32)
        found = np.ones(len(gid), dtype=bool)
        undefined = np.zeros(len(gid), dtype=bool)
        for chunk in np.unique(chunks):
            rows = np.flatnonzero(chunks == chunk)
            if chunk not in self.cache:
                if len(self.cache) >= 8:  # bounded memory on tiles spanning many chunks
                    self.cache.clear()
                self.cache[chunk] = self._load(int(chunk), n_classes)
            ids, chunk_proba, chunk_undefined = self.cache[chunk]
            pos, hit = rows_of(ids, gid[rows])
            if not hit.all() and not self.allow_missing:
                raise StoreError(f"points of scene '{self.scene}' missing from chunk "
                                 f"{self.grid.chunk_name(int(chunk))}; rerun with --overwrite")
            proba[rows[hit]] = chunk_proba[pos[hit]]
            undefined[rows[hit]] = chunk_undefined[pos[hit]]
            found[rows[~hit]] = False
        return proba, found, undefined


def export_tile(store_path, tile, grid, stage, classes, codes, dst, probabilities,
                write_classification, read_batch, fingerprint, allow_missing=False):
    """Worker task: write the classified copy of one input tile; return its path and the
    number of its points without features."""
    root = open_store(store_path)
    marker = root.require_group(f"exports/{tile['index']}")
    if is_done(marker, "export", fingerprint) and Path(dst).is_file():
        return {"path": dst, "no_features": marker.attrs.get("no_features", 0)}
    predictions = _ChunkPredictions(root, tile["scene"], layout_from_dict(grid), stage, allow_missing)
    codes_array = np.asarray(codes)
    n_undefined = 0

    def compute(batch):
        nonlocal n_undefined
        gid = global_ids(tile["index"], batch.start, len(batch.xyz))
        proba, found, undefined = predictions.lookup(batch.xyz, gid, len(classes))
        n_undefined += int(np.count_nonzero(undefined))
        best = np.argmax(proba, axis=1)
        predicted = np.where(found, codes_array[best], 0)  # 0: never classified (LAS)
        values = {
            PREDICTED: predicted,
            CONFIDENCE: proba[np.arange(len(best)), best],
            ENTROPY: entropy(proba),
            NO_FEATURES: undefined.astype(np.uint8),
        }
        if probabilities:
            for index, name in enumerate(classes):
                values[probability_dim(name)] = proba[:, index]
        if write_classification:
            values["classification"] = predicted
        return values

    export_with_extra_dims(
        tile["path"], dst, extra_dims(classes, codes, probabilities), compute,
        batch_size=read_batch, set_classification=write_classification,
    )
    mark_done(marker, "export", fingerprint, no_features=n_undefined)
    return {"path": dst, "no_features": n_undefined}


def export(run: Run, engine, layout: dict, final_stage: int, stage_fp: str) -> list[str]:
    """Write predictions/<tile>.laz (or .las) for every input tile; remove every other
    file of predictions/ (tiles no longer in the run, the other format, parts of files a
    killed export left)."""
    fingerprint = f"{run.fingerprint('export')}-{stage_fp}"
    out_dir = run.predictions_path
    out_dir.mkdir(parents=True, exist_ok=True)
    remove_parts(out_dir)
    suffix = "." + run.cfg.output.format
    tasks = []
    for tile in layout["tiles"]:
        dst = out_dir / f"{tile['name']}{suffix}"
        tasks.append(Task(
            key=f"export-{tile['index']}-{fingerprint[:8]}",
            fn=export_tile,
            kwargs=dict(
                store_path=str(run.store_path), tile=tile,
                grid=layout["scenes"][tile["scene"]]["grid"], stage=final_stage,
                classes=run.classes, codes=run.class_codes, dst=str(dst),
                probabilities=bool(run.cfg.output.probabilities),
                write_classification=bool(run.cfg.output.write_classification),
                read_batch=int(run.cfg.tiling.read_batch), fingerprint=fingerprint,
                allow_missing=bool(run.cfg.data.drop_unlisted) and tile["scene"] != "predict",
            ),
            where=f"export of tile {tile['path']}",
            reproduce=f"silva export CONFIG --out {run.out} --in-process",
        ))
    results = list(engine.map("export", tasks).values())
    written = [r["path"] for r in results]
    remove_stale(out_dir, written)
    undefined = sum(r["no_features"] for r in results)
    if undefined:
        total = sum(t["n_points"] for t in layout["tiles"])
        say(f"export: {counted(undefined, 'point')} ({undefined / max(total, 1):.2%}) have no "
            "features (too few neighbours within features.r1 to form a surface, or collinear "
            f"ones); their predictions are unreliable and marked {NO_FEATURES}=1",
            quiet=run.quiet)  # -q keeps one line per step; the log has it
    return written


def remove_stale(out_dir: Path, keep: list[str]) -> list[Path]:
    """Remove the point-cloud files of ``out_dir`` that are not in ``keep``; return them."""
    kept = {Path(p).name for p in keep}
    stale = [p for p in out_dir.iterdir()
             if p.suffix.lower() in (".las", ".laz") and p.name not in kept
             and (p.is_file() or p.is_symlink())]
    for path in stale:
        path.unlink(missing_ok=True)
    return stale
