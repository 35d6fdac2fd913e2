"""Saved cascade models: a directory with one forest per stage and a JSON description.

::

    model/
      model.json        software version, feature set, radii, classes, one entry per stage
      stage1.skops      the stage forests, in skops format (no code runs on load)
      ...

Loading refuses a model whose feature description differs from what the caller computes, so
features and forests can never be mixed up silently. The whole bundle is under one digest:
model.json records the SHA-256 of each stage file, and its ``digest`` is the SHA-256 of the
rest of model.json (canonical JSON: sorted keys, no spaces), stage digests included. An
edited model.json (its classes, r1, its stages) or a forest file that does not match its
digest (replaced, swapped with another stage, damaged) is refused. A model.json without a
digest (saved before digests were written) still loads, with a warning.
"""

import hashlib
import json
import logging
import zipfile
from pathlib import Path

from pipeline import __version__
from pipeline.atomic import atomic_path, atomic_write_text
from pipeline.errors import ModelError

MODEL_FILE = "model.json"
#: The key of model.json that holds the digest of the rest of it.
DIGEST_KEY = "digest"
# The only non-builtin types a Silva forest file may contain.
TRUSTED_TYPES = ["sklearn.tree._tree.Tree"]

log = logging.getLogger(__name__)
_warned_undigested: set[str] = set()


def file_digest(path: str | Path) -> str:
    """SHA-256 (hexadecimal) of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def description_digest(description: dict) -> str:
    """SHA-256 (hexadecimal) of a model description without its own ``digest``: of its
    canonical JSON (sorted keys, no spaces, ASCII), so it does not depend on the layout."""
    body = {key: value for key, value in description.items() if key != DIGEST_KEY}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(text.encode("ascii")).hexdigest()


def read_description(model_dir: str | Path) -> dict:
    """The model's JSON description; ModelError when the directory holds no complete model
    or when model.json does not match the digest it records (it was edited).

    A complete description lists its classes (name and code) and at least one stage (file,
    fingerprint and the SHA-256 of the file).
    """
    return read_model_file(model_dir)[0]


def read_model_file(model_dir: str | Path) -> tuple[dict, str]:
    """The model's description (:func:`read_description`) and the SHA-256 (hexadecimal) of
    the bytes of its model.json, from one reading of the file."""
    path = Path(model_dir) / MODEL_FILE
    if not path.is_file():
        raise ModelError(f"no model at {model_dir} ({MODEL_FILE} missing); train one with 'silva train'")
    try:
        data = path.read_bytes()
        description = json.loads(data.decode())
    except (ValueError, UnicodeDecodeError) as err:  # JSONDecodeError is a ValueError
        reason = " ".join(str(err).split()) or type(err).__name__
        raise _unusable(path, f"is not valid JSON: {reason}") from None
    except RecursionError:
        raise _unusable(path, "nests lists or objects too deeply to read") from None
    except OSError as err:
        raise ModelError(f"cannot read model description {path}: {err.strerror}") from None
    _check_description(description, path)
    _check_digest(description, path)
    return description, hashlib.sha256(data).hexdigest()


def _unusable(path: Path, reason: str) -> ModelError:
    return ModelError(f"model description {path} {reason}; restore the model's own "
                      f"{MODEL_FILE} or retrain the model with 'silva train'")


def _check_digest(description: dict, path: Path) -> None:
    recorded = description.get(DIGEST_KEY)
    if recorded is None:
        if str(path) not in _warned_undigested:
            _warned_undigested.add(str(path))
            log.warning("%s records no digest (it was saved before model digests): an edit "
                        "of it cannot be detected; retrain the model to add one", path)
        return
    try:
        actual = description_digest(description)
    except (RecursionError, ValueError):
        raise _unusable(path, "nests lists or objects too deeply to read") from None
    if recorded != actual:
        raise ModelError(
            f"model description {path} was changed after the model was saved (it does not "
            "match the digest it records): a model's classes, radii and stages cannot be "
            "edited; restore the model's own model.json or retrain it with 'silva train'")


_ENTRIES = {"classes": {"name": str, "code": int},
            "stages": {"file": str, "fingerprint": str, "sha256": str}}


def _check_description(description, path: Path) -> None:
    if not isinstance(description, dict):
        raise ModelError(f"model description {path} is not a JSON object; retrain the model "
                         "with 'silva train'")
    for key, fields in _ENTRIES.items():
        entries = description.get(key)
        if not isinstance(entries, list) or not entries:
            raise ModelError(f"model description {path} lists no {key}: it is incomplete or "
                             "was not written by this version of Silva; retrain the model "
                             "with 'silva train'")
        for i, entry in enumerate(entries):
            for field, kind in fields.items():
                if not isinstance(entry, dict) or not isinstance(entry.get(field), kind) \
                        or isinstance(entry.get(field), bool):
                    raise ModelError(f"model description {path}: {key}[{i}] has no valid "
                                     f"'{field}'; retrain the model with 'silva train'")


def software_versions() -> dict[str, str]:
    """The versions of the packages a saved model depends on."""
    from importlib.metadata import PackageNotFoundError, version

    versions = {"silva": __version__}
    for name in ("scikit-learn", "skops", "numpy", "numba"):
        try:
            versions[name] = version(name)
        except PackageNotFoundError:
            versions[name] = "absent"
    return versions


def check_versions(description: dict, model_dir) -> None:
    """ModelError when the model's forests come from another scikit-learn minor version:
    its tree format is not guaranteed across them (a model without versions passes)."""
    saved = description.get("versions", {}).get("scikit-learn")
    current = software_versions()["scikit-learn"]
    if saved and saved.split(".")[:2] != current.split(".")[:2]:
        raise ModelError(f"model {model_dir} was saved by scikit-learn {saved}, this is "
                         f"{current}: install scikit-learn=={saved} or retrain the model")


def write_description(model_dir: str | Path, description: dict) -> None:
    """Write model.json (atomically), adding the software version, the SHA-256 of every
    stage file (``stages[i]["file"]``, which must exist) and the digest of it all
    (:func:`description_digest`)."""
    model_dir = Path(model_dir)
    model_dir.mkdir(parents=True, exist_ok=True)
    stages = [{**stage, "sha256": file_digest(model_dir / stage["file"])}
              for stage in description.get("stages", [])]
    description = {**description, "stages": stages, "software": f"silva {__version__}",
                   "versions": software_versions()}
    description[DIGEST_KEY] = description_digest(description)
    atomic_write_text(model_dir / MODEL_FILE, json.dumps(description, indent=2))


def verify_stage_files(model_dir: str | Path, description: dict) -> None:
    """ModelError unless every stage file exists and matches the digest model.json records."""
    for stage in description["stages"]:
        _verify(Path(model_dir) / stage["file"], stage["sha256"])


def _verify(path: Path, expected: str) -> None:
    if not path.is_file():
        raise ModelError(f"model file {path} is missing; retrain with 'silva train'")
    if file_digest(path) != expected:
        raise ModelError(f"model file {path} does not match the digest {MODEL_FILE} records "
                         "for it (it was replaced, swapped with another stage's file or "
                         "damaged); restore the model's own files or retrain with 'silva train'")


def forest_inputs(path: str | Path) -> int:
    """The number of input columns the forest saved at ``path`` was fitted on (its
    ``n_features_in_``), read from the skops archive's schema without building the trees;
    the whole forest is loaded only when the schema does not say."""
    try:
        with zipfile.ZipFile(path) as archive:
            schema = json.loads(archive.read("schema.json"))
        node = schema["content"]["content"]["n_features_in_"]
        if node.get("is_json"):
            return int(json.loads(node["content"]))
    except (OSError, KeyError, TypeError, ValueError, zipfile.BadZipFile):
        pass
    try:
        return int(load_forest(path).n_features_in_)
    except AttributeError:
        raise ModelError(f"model file {path} holds no fitted forest; restore the model's own "
                         "files or retrain with 'silva train'") from None


def _recorded_digest(path: Path) -> str | None:
    """The digest the model.json beside ``path`` records for it (None: not a stage file)."""
    if not (path.parent / MODEL_FILE).is_file():
        return None
    for stage in read_description(path.parent)["stages"]:
        if stage["file"] == path.name:
            return stage["sha256"]
    return None


def stage_file(model_dir: str | Path, stage: int, fold: int | None = None) -> Path:
    """Path of the forest of stage ``stage`` (0-based), or of one of its fold forests."""
    suffix = "" if fold is None else f"_fold{fold + 1}"
    return Path(model_dir) / f"stage{stage + 1}{suffix}.skops"


def save_forest(path: Path, forest) -> None:
    """Write one forest atomically."""
    import skops.io as sio  # here, not above: reading a model's description needs no forest

    with atomic_path(path) as tmp:
        sio.dump(forest, tmp)


def load_forest(path: Path):
    """Load one forest, refusing files with types a Silva forest never contains and a stage
    file that does not match the digest its model.json records."""
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"model file {path} is missing; retrain with 'silva train'")
    expected = _recorded_digest(path)
    if expected is not None:
        _verify(path, expected)
    import skops.io as sio

    try:
        untrusted = sio.get_untrusted_types(file=path)
    except Exception as err:  # skops raises several types for corrupt archives
        raise ModelError(f"cannot read model file {path}: {err}") from err
    unexpected = sorted(set(untrusted) - set(TRUSTED_TYPES))
    if unexpected:
        raise ModelError(f"model file {path} contains unexpected types {unexpected}; refusing to load it")
    return sio.load(path, trusted=untrusted)


#: Keys a model description gained after models were first saved, with what a model.json
#: without them means: a model saved before echoes existed was trained without them, one
#: saved before feature versions existed on version 1
#: (:data:`pipeline.features.sets.FEATURE_VERSION`), one saved before the ground rule
#: (:mod:`pipeline.cascade.ground_rule`) without it, one saved before terrain versions on
#: heights above the terrain model of version 1 (:data:`pipeline.terrain.TERRAIN_VERSION`).
LATER_KEYS = {"features.echoes": False, "features.version": 1,
              "terrain.ground_tolerance": None, "terrain.version": 1}


def recorded(description: dict, key: str):
    """The value a model description records for ``key``, with the meaning of
    :data:`LATER_KEYS` for a model.json saved before the key existed; KeyError for another
    key it lacks."""
    if key not in description and key in LATER_KEYS:
        return LATER_KEYS[key]
    return description[key]


def trained_densities(description: dict) -> list[float]:
    """The ``data.densities`` a model (its model.json ``description``) was trained with:
    points per m² of the thinned copies of its training scene ([] for a model saved
    without copies, or before they existed)."""
    return [float(d) for d in description.get("data.densities", [])]


def check_compatible(description: dict, expected: dict, model_dir) -> None:
    """ModelError unless the model's feature description equals ``expected`` key by key
    (a key of :data:`LATER_KEYS` it lacks has that key's old meaning)."""
    for key, value in expected.items():
        if key not in description and key not in LATER_KEYS:
            raise ModelError(f"model {model_dir} does not record {key}: it was written by "
                             "another version of Silva; retrain it")
        trained = recorded(description, key)
        if trained != value and key == "features.columns":
            # derived from the other keys, not a key to set: another version's columns
            raise ModelError(
                f"model {model_dir} was trained on the feature columns "
                f"{', '.join(map(str, trained))}, which this version of Silva does not compute "
                f"for features.set {description.get('features.set')!r} (it computes "
                f"{', '.join(map(str, value))}); retrain the model with this version")
        if trained != value:
            raise ModelError(
                f"model {model_dir} was trained with {key}={json.dumps(trained)} but the "
                f"configuration has {json.dumps(value)}; set {key}={json.dumps(trained)} "
                "(e.g. with --set) or retrain"
            )
