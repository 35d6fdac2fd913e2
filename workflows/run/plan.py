"""A run's plan (:class:`RunPlan`): its resolved configuration, the saved model it
applies (read and checked once), its input files and the catalogue of their tiles (each
header read once), frozen before the first step starts.

:func:`workflows.run.autoparams.resolve_run` builds it, the one place a run's configuration is
resolved; :class:`workflows.run.directory.Run` holds it beside the run's paths and store.
"""

import hashlib
import json
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from pipeline.errors import ConfigError, ModelError
from pipeline.features.sets import ECHO_SETS, feature_set
from pipeline.io.catalogue import Tile, file_identity, read_catalogue
from pipeline.model import check_compatible, check_versions, forest_inputs, verify_stage_files
from workflows.config import SilvaConfig
from workflows.config.inputs import SCENES, InputFile, find_inputs


@dataclass(frozen=True)
class AppliedModel:
    """A saved model a run applies: its directory, its model.json (``description``, checked
    against the run's configuration) and the SHA-256 of model.json's bytes."""

    path: Path
    description: dict
    digest: str

    @property
    def stages(self) -> list[dict]:
        """The model's stage records."""
        return self.description["stages"]


def config_inputs(cfg: SilvaConfig) -> tuple[InputFile, ...]:
    """The input files of ``cfg`` (:func:`~workflows.config.inputs.find_inputs` of its data
    paths)."""
    return find_inputs({scene: getattr(cfg.data, scene) for scene in SCENES})


def check_overlap(inputs: tuple[InputFile, ...], allowed: bool) -> None:
    """Refuse a file that is both a training and a test tile, unless ``allowed``."""
    if allowed:
        return
    train = {file_identity(f.path): f.path for f in inputs if f.scene == "train"}
    for path in (f.path for f in inputs if f.scene == "test"):
        if file_identity(path) in train:
            raise ConfigError(
                f"tile {path} is both in data.test and in data.train (as "
                f"{train[file_identity(path)]}): its test "
                "scores would be scores on training points; remove it from one of them, or "
                "set data.allow_overlap: true")


def catalogue(cfg: SilvaConfig, inputs: tuple[InputFile, ...]) -> tuple[Tile, ...]:
    """The tiles of the ``inputs`` of ``cfg`` (:func:`~pipeline.io.catalogue.read_catalogue`:
    each header read once), after the overlap of its training and test files is checked."""
    check_overlap(inputs, cfg.data.allow_overlap)
    return read_catalogue((f.scene, f.path) for f in inputs)


@dataclass(frozen=True)
class RunPlan:
    """What a run computes, resolved: the configuration ('auto' values and an applied
    model's values set), the applied model (None: the run trains its own), the input
    files (:func:`~workflows.config.inputs.find_inputs`) and their tiles (:func:`catalogue`)."""

    cfg: SilvaConfig
    model: AppliedModel | None = None
    inputs: tuple[InputFile, ...] = ()
    tiles: tuple[Tile, ...] = ()

    @property
    def inputs_digest(self) -> str:
        """A digest of the input files (paths, scenes, sizes, times): a replaced or added
        file invalidates the stored chunks; every fingerprint of the run follows it."""
        state = [(str(f.path), f.scene, f.size, f.mtime_ns) for f in self.inputs]
        return hashlib.sha256(json.dumps(state).encode()).hexdigest()[:16]

    @property
    def n_stages(self) -> int:
        """The cascade stages the run computes (an applied model's: see
        :func:`workflows.run.autoparams.adopt_model`)."""
        return self.cfg.cascade.stages


def feature_description(cfg: SilvaConfig) -> dict:
    """What a model must agree with to be applied to the features of ``cfg`` (resolved)."""
    # keyed by config path, so a mismatch names the key to set
    terrain = cfg.terrain.params
    params = replace(cfg.features.params, terrain=terrain)  # as the steps receive them
    return {
        "features.set": params.set,
        "features.columns": list(feature_set(params).columns),
        "features.r1": params.r1,
        "features.r2": params.r2,
        "features.max_neighbors": params.max_neighbors,
        "features.context_max_neighbors": params.context_max_neighbors,
        "features.plane": params.plane,
        "features.scales": list(params.scales),
        "features.column": params.column,
        "features.cell": params.cell,
        "features.voxel": params.voxel,
        "features.echoes": params.echoes,
        "features.version": params.version,
        "cascade.context": cfg.cascade.context,
        **{f"terrain.{k}": v for k, v in asdict(terrain).items()},
        "terrain.ground_tolerance": cfg.terrain.ground_tolerance,
    }


def check_model(cfg: SilvaConfig, model: AppliedModel) -> None:
    """ModelError/ConfigError unless ``model`` can be applied with ``cfg`` (resolved): its
    versions, features, classes and stage files.

    Called before any work, so that a wrong model never costs an ingest and features.
    """
    description, path = model.description, model.path
    check_versions(description, path)
    expected = feature_description(cfg)
    check_echo_columns(cfg, description, path)
    check_compatible(description, expected, path)
    for key in ("classes", "stages"):
        if not description.get(key):
            raise ModelError(f"model {path} records no {key}; retrain it")
    names = [c["name"] for c in description["classes"]]
    codes = [c["code"] for c in description["classes"]]
    classes, class_codes = cfg.data.class_names, cfg.data.class_codes
    if names != classes or codes != class_codes:
        raise ConfigError(
            f"model {path} predicts classes {dict(zip(names, codes))} but data.classes gives "
            f"{dict(zip(classes, class_codes))}; use the model's classes and codes"
        )
    verify_stage_files(path, description)
    check_forest_inputs(description, path, len(expected["features.columns"]), len(names))


def check_echo_columns(cfg: SilvaConfig, description: dict, path) -> None:
    """ModelError when the feature columns ``description`` (a model.json) records are those
    of the other value of its ``features.echoes`` (``cfg`` took the model's keys): the key
    was edited after training, and the line names it."""
    trained = description.get("features.columns")
    params = replace(cfg.features.params, terrain=cfg.terrain.params)
    if trained is None or trained == list(feature_set(params).columns):
        return
    if params.set not in ECHO_SETS:
        return
    other = replace(params, echoes=not params.echoes)
    if trained != list(feature_set(other).columns):
        return
    echo = [name for name in trained if name not in feature_set(params).columns] or \
        [name for name in feature_set(params).columns if name not in trained]
    raise ModelError(
        f"model {path} records features.echoes={json.dumps(params.echoes)}, but its feature "
        f"columns are those of features.echoes={json.dumps(other.echoes)} (with"
        f"{'' if other.echoes else 'out'} the {len(echo)} echo columns, {echo[0]}, ...): "
        "features.echoes was edited in its model.json after training; restore the model's "
        f"own model.json (features.echoes: {json.dumps(other.echoes)}) or retrain the model "
        "with 'silva train'")


def check_forest_inputs(description: dict, path, n_columns: int, n_classes: int) -> None:
    """ModelError unless every stage forest of the model at ``path`` takes the inputs its
    model.json ``description`` describes: ``n_columns`` feature columns and the context
    (two columns per class, ``n_classes``), so that a model.json edited consistently (its
    keys, columns and digest) is refused before any work, not by the forests."""
    expected = n_columns + 2 * n_classes
    for i, stage in enumerate(description["stages"]):
        file = Path(path) / stage["file"]
        got = forest_inputs(file)
        if got != expected:
            raise ModelError(
                f"model {path}: the forest of stage {i + 1} ({file.name}) was fitted on {got} "
                f"input columns, but its model.json describes {expected} ({n_columns} feature "
                f"columns and 2 x {n_classes} context columns): its model.json was edited "
                "after training (its keys, columns or classes no longer fit its forests); "
                "restore the model's own model.json or retrain the model with 'silva train'")
