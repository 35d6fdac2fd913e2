"""The values a configuration leaves to the data ('auto') or to the model it applies,
resolved once as a run starts.

A run that applies a saved model takes from it every value that decides its predictions
(:func:`adopt_model`): the feature, context and terrain parameters the model records, its
stage count and its classes. A configuration may leave them out (``silva predict`` then
needs none); one that sets them otherwise is refused before any work, naming the key and the
model's value.

``features.r1: auto`` comes from the point density of the training tiles' headers (or, when
a saved model is applied, from the model: its forests know only the radius they were
trained with); ``features.voxel: auto`` from r1 and ``features.max_neighbors``;
``features.echoes: auto`` on when every tile's header counts later returns
(:func:`~workflows.run.echoes.multi_return`). The run then holds an ordinary, fully resolved
configuration: saved in OUT/config.yaml, hashed by the fingerprints, shown by the report.
"""

import copy
import json
import logging
import math
from pathlib import Path

from pipeline.errors import ConfigError
from pipeline.features.sets import ECHO_SETS, auto_radius, auto_voxel
from pipeline.io.catalogue import header_density
from pipeline.model import LATER_KEYS, read_model_file
from pipeline.trees.params import auto_resolution
from workflows.config import SilvaConfig, validate_config
from workflows.config.loading import load_raw
from workflows.config.inputs import InputFile
from workflows.run.echoes import multi_return
from workflows.run.plan import AppliedModel, RunPlan, catalogue, check_model, config_inputs

log = logging.getLogger(__name__)


def training_density(cfg: SilvaConfig, tiles) -> float:
    """Points per m² (XY) of the training tiles (of all tiles without training tiles) of
    the catalogue ``tiles``, from their headers (:func:`header_density`)."""
    scenes = ("train",) if cfg.data.train else ("test", "predict")
    return header_density(t for t in tiles if t.scene in scenes)


def sparsest_density(tiles) -> float:
    """Points per m² of the sparsest scene of the catalogue ``tiles``, from their headers;
    0 without tiles."""
    densities = [header_density(t for t in tiles if t.scene == scene)
                 for scene in ("train", "test", "predict")]
    return min((d for d in densities if d > 0), default=0.0)


def resolve_tree_resolution(cfg: SilvaConfig, tiles) -> SilvaConfig:
    """``cfg`` with ``trees.resolution: auto`` as a number (:func:`auto_resolution` of the
    sparsest scene's density in the catalogue ``tiles``), when the run finds trees."""
    if not cfg.output.trees or cfg.trees.resolution != "auto":
        return cfg
    density = sparsest_density(tiles)
    resolution = auto_resolution(density, cfg.trees.params)
    log.info("trees.resolution auto: %.3g points/m² in the sparsest scene -> %g m", density,
             resolution)
    raw = cfg.model_dump(mode="json")
    raw["trees"]["resolution"] = resolution
    return validate_config(raw)


def resolve_auto(cfg: SilvaConfig, tiles) -> SilvaConfig:
    """``cfg`` with ``features.r1`` and ``features.voxel`` as numbers and
    ``features.echoes`` true or false (a model applied has set them already:
    :func:`adopt_model`), and ``trees.resolution``
    (:func:`resolve_tree_resolution`), from the headers of the catalogue ``tiles``."""
    cfg = resolve_tree_resolution(cfg, tiles)
    features = cfg.features
    if features.resolved:
        return cfg
    raw = cfg.model_dump(mode="json")
    r1 = features.r1
    if r1 == "auto":
        density = training_density(cfg, tiles)
        r1 = auto_radius(density) if density > 0 else 0.5
        log.info("features.r1 auto: %.3g points/m² in the headers -> r1 = %g m", density, r1)
    voxel = features.voxel
    if voxel == "auto":
        voxel = auto_voxel(float(r1), int(features.max_neighbors))
    echoes = features.echoes
    if echoes == "auto":
        echoes = features.set in ECHO_SETS and multi_return(tiles)
        log.info("features.echoes auto: %s", echoes)
    raw["features"].update(r1=r1, voxel=voxel, echoes=echoes)
    return validate_config(raw)


def run_config(config, overrides=(), model_dir=None, inputs=()) -> RunPlan:
    """The plan of a run (:func:`read_run`, then :func:`resolve_run`)."""
    return resolve_run(read_run(config, overrides, inputs), model_dir)


def read_run(config, overrides=(), inputs=()) -> dict:
    """A run's configuration as written: the file ``config`` (None: every default) with
    ``overrides``, and ``inputs`` (paths or globs: the only tiles, to classify) in
    data.predict."""
    raw = load_raw(config, overrides)
    if inputs:
        data = raw.get("data") if isinstance(raw.get("data"), dict) else {}
        raw["data"] = {**data, "train": [], "test": [], "split": None,
                       "predict": [str(Path(p).expanduser().absolute()) for p in inputs]}
    return raw


def resolve_run(raw: dict | SilvaConfig, model_dir=None,
                inputs: tuple[InputFile, ...] | None = None) -> RunPlan:
    """The plan of a run of ``raw`` (a configuration as written, or validated when it applies
    no model): the values of the model it applies (:func:`adopt_model`, the model read and
    checked once), its input files (``inputs`` when the command found them already, else
    found now: each glob expanded once) and their headers read (once, into the catalogue of
    its tiles), its 'auto' values resolved from them: the one place a run's configuration
    is resolved. Raises the errors of :func:`~workflows.config.inputs.expand_inputs` and
    :func:`~workflows.run.plan.catalogue`."""
    if isinstance(raw, SilvaConfig):
        if model_dir is not None:  # a validated config holds every default: none is 'auto'
            raise TypeError("resolve_run applies a model to a configuration as written only")
        return _planned(raw, None, inputs)
    model = None
    if model_dir is not None:
        description, digest = read_model_file(model_dir)
        model = AppliedModel(Path(model_dir), description, digest)
        raw = adopt_model(raw, description, model_dir)
    return _planned(validate_config(raw), model, inputs)


def _planned(cfg: SilvaConfig, model: AppliedModel | None, inputs) -> RunPlan:
    """The plan of the validated ``cfg`` applying ``model``: the model checked against it
    (before any input is read; the values it checks are the model's, set already), its
    ``inputs`` (None: found now), their tiles catalogued and its 'auto' values resolved
    from them."""
    if model is not None:
        check_model(cfg, model)
    inputs = config_inputs(cfg) if inputs is None else inputs  # 'auto' values are no data key
    tiles = catalogue(cfg, inputs)
    return RunPlan(resolve_auto(cfg, tiles), model, inputs, tiles)


#: The points a model was trained without (noise, withheld), which a run applying it leaves
#: out too unless its configuration says otherwise.
FILTER_KEYS = ("data.exclude_codes", "data.exclude_withheld")


def data_filters(cfg: SilvaConfig) -> dict:
    """The data filters of ``cfg`` as a model records them (:data:`FILTER_KEYS`)."""
    return {"data.exclude_codes": sorted(set(cfg.data.exclude_codes)),
            "data.exclude_withheld": bool(cfg.data.exclude_withheld)}


#: The sections whose recorded keys (model.json's "section.key") a run applying a model takes.
MODEL_SECTIONS = ("features", "cascade", "terrain")
#: Recorded keys that no configuration sets: the feature set's column names (derived from
#: the other keys) and the version of the terrain code that made the model's heights (this
#: code's own: a run applying a model of another version warns, see docs/MODELS.md).
NOT_SETTINGS = ("features.columns", "terrain.version")


def _same(a, b) -> bool:
    """Equal as configuration values: numbers by value (1 and 1.0), lists element-wise."""
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    numbers = (int, float)
    if isinstance(a, numbers) and isinstance(b, numbers) and not isinstance(a, bool):
        return math.isclose(float(a), float(b), rel_tol=0.0, abs_tol=0.0)
    return a == b


def adopt_model(raw: dict, description: dict, model_path) -> dict:
    """``raw`` (a configuration as written, before validation) with the values the model
    ``description`` (model.json) records for its predictions: its feature, context and
    terrain keys, ``cascade.stages`` (its stage count) and
    ``data.classes`` (each name with its output code) when ``raw`` names none. ConfigError,
    naming the key, the configured and the model's value, for a recorded key ``raw`` sets
    otherwise ('auto' leaves it to the model)."""
    raw = copy.deepcopy(raw)
    # a model.json saved before a key existed records its old meaning (LATER_KEYS)
    recorded = {k: v for k, v in {**LATER_KEYS, **description}.items()
                if k.partition(".")[0] in MODEL_SECTIONS and k not in NOT_SETTINGS}
    # the run applies every stage the model has: its stage count is one more recorded value
    recorded["cascade.stages"] = len(description.get("stages") or ())
    for key, value in recorded.items():
        section, _, name = key.partition(".")
        given = (raw.get(section) or {}).get(name, "auto")
        if given != "auto" and not (given is None and name == "r2") and not _same(given, value):
            raise ConfigError(
                f"config error: {key} is {json.dumps(given)} in the configuration, but the "
                f"model {model_path} was trained with {key}={json.dumps(value)}; remove {key} "
                "from the configuration (a run applying a model takes it from the model) or "
                "retrain")
        if not isinstance(raw.get(section), dict):
            raw[section] = {}
        raw[section][name] = value
    data = raw.get("data") if isinstance(raw.get("data"), dict) else {}
    if not data.get("classes") and description.get("classes"):
        data["classes"] = {c["name"]: [c["code"]] for c in description["classes"]}
    for key in FILTER_KEYS:  # the model's filters, unless the configuration sets its own
        name = key.partition(".")[2]
        if key in description and name not in data:
            data[name] = description[key]
    raw["data"] = data
    return raw
