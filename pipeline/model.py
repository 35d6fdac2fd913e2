"""Saved cascade models: a directory with one forest per stage and a JSON description.

::

    model/
      model.json        software version, feature set, radii, classes, one entry per stage
      stage1.skops      the stage forests, in skops format (no code runs on load)
      ...

Loading refuses a model whose feature description differs from what the caller computes, so
features and forests can never be mixed up silently.
"""

import json
import os
from pathlib import Path

import skops.io as sio

from pipeline import __version__
from pipeline.errors import ModelError

MODEL_FILE = "model.json"
# The only non-builtin types a Silva forest file may contain.
TRUSTED_TYPES = ["sklearn.tree._tree.Tree"]


def _atomic_write_text(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.partial")
    tmp.write_text(text)
    os.replace(tmp, path)


def read_description(model_dir: str | Path) -> dict:
    """The model's JSON description; ModelError when the directory holds no model."""
    path = Path(model_dir) / MODEL_FILE
    if not path.is_file():
        raise ModelError(f"no model at {model_dir} ({MODEL_FILE} missing); train one with 'silva train'")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ModelError(f"model description {path} is not valid JSON: {err}") from err


def write_description(model_dir: str | Path, description: dict) -> None:
    """Write model.json (atomically), adding the software version."""
    model_dir = Path(model_dir)
    model_dir.mkdir(parents=True, exist_ok=True)
    description = {**description, "software": f"silva {__version__}"}
    _atomic_write_text(model_dir / MODEL_FILE, json.dumps(description, indent=2))


def stage_file(model_dir: str | Path, stage: int, fold: int | None = None) -> Path:
    """Path of the forest of stage ``stage`` (0-based), or of one of its fold forests."""
    suffix = "" if fold is None else f"_fold{fold + 1}"
    return Path(model_dir) / f"stage{stage + 1}{suffix}.skops"


def save_forest(path: Path, forest) -> None:
    """Write one forest atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.partial")
    sio.dump(forest, tmp)
    os.replace(tmp, path)


def load_forest(path: Path):
    """Load one forest, refusing files with types a Silva forest never contains."""
    if not path.is_file():
        raise ModelError(f"model file {path} is missing; retrain with 'silva train'")
    try:
        untrusted = sio.get_untrusted_types(file=path)
    except Exception as err:  # skops raises several types for corrupt archives
        raise ModelError(f"cannot read model file {path}: {err}") from err
    unexpected = sorted(set(untrusted) - set(TRUSTED_TYPES))
    if unexpected:
        raise ModelError(f"model file {path} contains unexpected types {unexpected}; refusing to load it")
    return sio.load(path, trusted=untrusted)


def check_compatible(description: dict, expected: dict, model_dir) -> None:
    """ModelError unless the model's feature description equals ``expected`` key by key."""
    for key, value in expected.items():
        if key not in description:
            raise ModelError(f"model {model_dir} does not record {key}: it was written by "
                             "another version of Silva; retrain it")
        trained = description[key]
        if trained != value:
            raise ModelError(
                f"model {model_dir} was trained with {key}={json.dumps(trained)} but the "
                f"configuration has {json.dumps(value)}; set {key}={json.dumps(trained)} "
                "(e.g. with --set) or retrain"
            )
