"""``silva status``: how far a run got, read from its store and output directory."""

from pathlib import Path

import yaml

from pipeline.model import MODEL_FILE, read_description
from pipeline.store import chunk_path, open_store
from workflows.progress import counted
from workflows.run import has_test_points


def run_status(out: Path) -> list[str]:
    """Lines describing each step of the run in ``out``."""
    store_path = out / "store.zarr"
    if not store_path.exists():
        return [f"{out}: nothing ingested yet (no store.zarr)"]
    root = open_store(store_path, mode="r")
    layout = root.attrs.get("layout")
    if not layout:
        return [f"{out}: ingest did not finish; rerun the command to resume"]
    lines = [f"{out}: {counted(len(layout['tiles']), 'tile')}, "
             f"{counted(sum(t['n_points'] for t in layout['tiles']), 'point')}"]
    for scene, info in layout["scenes"].items():
        steps: dict[str, int] = {}
        for chunk in info["chunks"]:
            path = chunk_path(scene, chunk)
            done = root[path].attrs.get("done", {}) if path in root else {}
            for step in done:
                steps[step] = steps.get(step, 0) + 1
        total = len(info["chunks"])
        # steps in the order they ran (the order of the chunks' done records)
        done_text = ", ".join(f"{s} {n}/{total}" for s, n in steps.items()) or "no step done"
        lines.append(f"scene {scene}: {counted(total, 'chunk')} of {info['grid']['size']:g} m; "
                     f"{done_text}")
    model = out / "model"
    if (model / MODEL_FILE).is_file():
        stages = read_description(model)["stages"]
        lines.append(f"model: {len(stages)} stage(s) trained in {model}")
    predictions = list((out / "predictions").glob("*.la[sz]"))
    lines.append(f"predictions: {len(predictions)} of {len(layout['tiles'])} tiles exported")
    metrics = out / "metrics.json"
    if metrics.is_file():
        lines.append(f"metrics: {metrics}")
    elif has_test_points(layout, _saved_split(out)):
        lines.append("metrics: not written yet")
    else:
        lines.append("metrics: none (no labelled test points: data.test or data.split)")
    return lines


def _saved_split(out: Path):
    """data.split of the configuration saved in ``out`` (None when absent or unreadable)."""
    try:
        saved = yaml.safe_load((out / "config.yaml").read_text()) or {}
    except (OSError, yaml.YAMLError):
        return None
    return (saved.get("data") or {}).get("split")
