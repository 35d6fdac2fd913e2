"""``silva status``: how far a run got, read from its store and output directory."""

from pathlib import Path

import yaml

from pipeline.errors import ModelError
from pipeline.model import MODEL_FILE, read_description
from pipeline.store import open_store
from workflows.run.directory import has_test_points
from workflows.run.lock import describe, held_by_other, read_lock
from workflows.run.progress import counted
from workflows.store.layout import chunk_path
from workflows.store.retention import removed_record
from workflows.store.scenes import RunLayout


def run_status(out: Path) -> list[str]:
    """Lines describing each step of the run in ``out``."""
    holder = read_lock(out)
    running = ([f"running now: {describe(holder)}"] if held_by_other(holder) else [])
    return running + _steps(out)


def _steps(out: Path) -> list[str]:
    store_path = out / "store.zarr"
    if not store_path.exists():
        return [f"{out}: nothing ingested yet (no store.zarr)"]
    root = open_store(store_path, mode="r")
    if not root.attrs.get("layout"):
        return [f"{out}: ingest did not finish; rerun the command to resume"]
    layout = RunLayout.from_dict(root.attrs["layout"])
    lines = [f"{out}: {counted(len(layout.tiles), 'tile')}, {counted(layout.n_points, 'point')}"]
    removed = removed_record(root) is not None
    if removed:
        lines.append("store: its chunks were removed after the run completed (output.keep_store: "
                     "false); the same run again has nothing to do, any other recomputes them")
    for scene, info in (() if removed else layout.scenes.items()):
        steps: dict[str, int] = {}
        for chunk in info.chunks:
            path = chunk_path(scene, chunk)
            done = root[path].attrs.get("done", {}) if path in root else {}
            for step in done:
                steps[step] = steps.get(step, 0) + 1
        total = len(info.chunks)
        # steps in the order they ran (the order of the chunks' done records)
        done_text = ", ".join(f"{s} {n}/{total}" for s, n in steps.items()) or "no step done"
        lines.append(f"scene {scene}: {counted(total, 'chunk')} {info.grid.label}; {done_text}")
    model = out / "model"
    if (model / MODEL_FILE).is_file():
        try:
            stages = read_description(model)["stages"]
            lines.append(f"model: {len(stages)} stage(s) trained in {model}")
        except ModelError as err:
            lines.append(f"model: unusable ({err})")
    exported = _exported(root, out, layout)
    lines.append(f"predictions: {exported} of {len(layout.tiles)} tiles exported")
    metrics = out / "metrics.json"
    if metrics.is_file():
        lines.append(f"metrics: {metrics}")
    elif has_test_points(layout.scenes, _saved_split(out)):
        lines.append("metrics: not written yet")
    else:
        lines.append("metrics: none (no labelled test points: data.test or data.split)")
    return lines


def _exported(root, out: Path, layout: RunLayout) -> int:
    """Tiles of the run whose prediction file, in the configured format, was written by a
    finished export (files of other formats or of tiles dropped since are not counted)."""
    suffix = "." + str(_saved(out, "output").get("format", "laz"))
    count = 0
    for tile in layout.tiles:
        marker = f"exports/{tile.index}"
        done = marker in root and "export" in root[marker].attrs.get("done", {})
        count += done and (out / "predictions" / f"{tile.name}{suffix}").is_file()
    return count


def _saved(out: Path, section: str) -> dict:
    """A section of the configuration saved in ``out`` ({} when absent or unreadable)."""
    try:
        saved = yaml.safe_load((out / "config.yaml").read_text()) or {}
    except (OSError, yaml.YAMLError):
        return {}
    value = saved.get(section) if isinstance(saved, dict) else None
    return value if isinstance(value, dict) else {}


def _saved_split(out: Path):
    """data.split of the configuration saved in ``out`` (None when absent or unreadable)."""
    return _saved(out, "data").get("split")
