"""Silva's configuration: YAML validated into typed, frozen objects.

A configuration has six sections (``data``, ``tiling``, ``features``, ``cascade``,
``cluster``, ``output``); every key has a default, so an empty file (or no file) is valid
until data is given. :func:`load_config` reads a YAML file, applies ``--set KEY=VALUE``
overrides to the raw mapping, then validates everything at once. Every problem becomes a
:class:`~pipeline.errors.ConfigError` with one line that names the dotted key, what was
received and what is allowed::

    config error: unknown key 'tiling.chunksize' (did you mean 'chunk_size'?)
    config error: features.r1 must be > 0, got -1

A key left empty in YAML (``n_estimators:``) means its default. Derived values are
resolved during validation: ``features.r2`` becomes ``r1 / 2`` and ``tiling.halo`` becomes
the largest radius (``features.r1``) when unset, so :func:`dump_config` writes out exactly
what a run used and loading that text again gives an equal configuration.

:func:`fingerprint` hashes the parts of a configuration that affect one workflow step, so a
rerun redoes what a changed key invalidates and nothing else.
"""

import difflib
import glob
import hashlib
import json
import math
import os
import re
import types
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, Literal, Union, get_args, get_origin

import yaml
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from pipeline.errors import ConfigError, InputError, MissingFileError

FEATURE_SETS = ("paper",)
STEPS = ("ingest", "features", "stage", "export", "evaluate")
SCENES = ("train", "test", "predict")
_FINGERPRINT_VERSION = "silva-config-1"  # bump when the meaning of a fingerprinted key changes


# -- field types ---------------------------------------------------------------------------
# Booleans are ints in Python (and pydantic's lax mode accepts them as numbers): refuse them,
# so "stages: true" is an error instead of one stage.
def _not_bool(kind: str):
    def check(value):
        if isinstance(value, bool):
            raise PydanticCustomError("silva_field", f"must be {kind}")
        return value

    return BeforeValidator(check)


Integer = Annotated[int, _not_bool("an integer")]
Number = Annotated[float, _not_bool("a number"), Field(allow_inf_nan=False)]


def _fail(message: str) -> PydanticCustomError:
    """An error whose message already names its full dotted key."""
    return PydanticCustomError("silva", message)


def _field_error(phrase: str) -> PydanticCustomError:
    """An error about the value at the error's location: '<key> <phrase>, got <value>'."""
    return PydanticCustomError("silva_field", phrase)


class _Section(BaseModel):
    """Common behaviour: unknown keys are errors, values are frozen, null means default."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    @model_validator(mode="before")
    @classmethod
    def _null_is_default(cls, data: Any) -> Any:
        # "key:" with nothing after it in YAML is None; for keys whose default is not None
        # that means "use the default" (a template with its values commented out).
        if isinstance(data, dict):
            fields = cls.model_fields
            return {
                k: v for k, v in data.items()
                if not (v is None and k in fields and not _defaults_to_none(fields[k]))
            }
        return data


def _defaults_to_none(field) -> bool:
    return field.default_factory is None and field.default is None


# -- data ------------------------------------------------------------------------------------
class SplitConfig(_Section):
    """One labelled cloud cut by a plane: coordinate < ``at`` trains, >= ``at`` tests."""

    axis: Literal["x", "y", "z"] = Field(description="The coordinate that splits the cloud.")
    at: Number = Field(description="Points with coordinate < at train, >= at test (metres).")


def _path_list(value: Any) -> Any:
    # A single path or glob is a list of one; Path objects are written as text.
    if isinstance(value, (str, os.PathLike)):
        value = [value]
    if isinstance(value, (list, tuple)):
        value = [os.fspath(v) if isinstance(v, os.PathLike) else v for v in value]
        for item in value:
            if item == "":
                raise _field_error("must not contain an empty path")
    return value


PathList = Annotated[list[str], BeforeValidator(_path_list)]


class DataConfig(_Section):
    """Inputs, labels and classes.

    ``classes`` maps a class name to its source label codes; the order of the mapping is
    the class index and the first code of a class is its output code.
    """

    train: PathList = Field(
        default_factory=list,
        description="Paths or globs (LAS, LAZ, Oakland text) of the labelled training tiles; "
        "the files of one list are tiles of one scene.",
    )
    test: PathList = Field(
        default_factory=list, description="Labelled tiles that are classified and evaluated."
    )
    predict: PathList = Field(
        default_factory=list, description="Unlabelled tiles that are only classified."
    )
    label_field: str = Field(
        "classification", min_length=1,
        description="The point dimension that holds the source labels.",
    )
    classes: dict[str, list[Integer]] = Field(
        default_factory=dict,
        description="Class name -> source label codes; order = class index; the output code "
        "of a class is its first code. Required whenever train or test is given.",
    )
    ignore: list[Union[str, int]] = Field(
        default_factory=list,
        description="Class names or raw codes dropped from training and evaluation.",
    )
    background: list[str] = Field(
        default_factory=list,
        description="Class names trained on but left out of the metric averages.",
    )
    split: SplitConfig | None = Field(
        None, description="Cut the labelled training cloud into a training and a test part.",
    )
    drop_unlisted: bool = Field(
        False,
        description="Remove labelled points whose code is in no class and not in ignore "
        "before anything is computed (the Oakland benchmark protocol); they are exported "
        "with PredictedClassification 0. By default they stay as unlabelled neighbours.",
    )

    @field_validator("classes", mode="before")
    @classmethod
    def _classes_shape(cls, value: Any) -> Any:
        if not isinstance(value, dict):
            return value
        result = {}
        for name, codes in value.items():
            if not isinstance(name, str) or not name:
                raise _fail(f"data.classes: class names must be non-empty text, got "
                            f"{_show(name)}; quote it ('{name}')")
            # "tree: 5" is a class with one code
            result[name] = [codes] if isinstance(codes, int) and not isinstance(codes, bool) \
                else codes
        return result

    @field_validator("ignore", mode="before")
    @classmethod
    def _ignore_items(cls, value: Any) -> Any:
        if isinstance(value, (list, tuple)):
            for i, item in enumerate(value):
                if isinstance(item, bool) or not isinstance(item, (str, int)):
                    raise _fail(f"data.ignore[{i}] must be a class name or an integer label "
                                f"code, got {_show(item)}")
        return value

    @model_validator(mode="after")
    def _check_classes(self) -> "DataConfig":
        owner: dict[int, str] = {}
        for name, codes in self.classes.items():
            if not codes:
                raise _fail(f"data.classes.{name} has no label codes; give at least one, "
                            f"e.g. {name}: [2]")
            for code in codes:
                if code in owner:
                    where = ("twice under" if owner[code] == name
                             else f"under both '{owner[code]}' and")
                    raise _fail(f"data.classes: label code {code} is listed {where} "
                                f"'{name}'; each source code belongs to one class")
                owner[code] = name
        labelled = [scene for scene in ("train", "test") if getattr(self, scene)]
        if labelled and not self.classes:
            raise _fail(f"data.classes is empty but data.{labelled[0]} is given; list the "
                        "classes, e.g. classes: {ground: [2], vegetation: [3, 4, 5]}")
        known = ", ".join(self.classes) or "none"
        for i, item in enumerate(self.ignore):
            if isinstance(item, str) and item not in self.classes:
                raise _fail(f"data.ignore[{i}] '{item}' is not a class in data.classes "
                            f"(classes: {known}); use a class name or an integer code")
        for i, name in enumerate(self.background):
            if name not in self.classes:
                raise _fail(f"data.background[{i}] '{name}' is not a class in data.classes "
                            f"(classes: {known})")
            if name in self.ignore:
                raise _fail(f"data.background '{name}' is also in data.ignore; a class is "
                            "either trained on (background) or dropped (ignore), not both")
        ignored_codes = {c for c in self.ignore if isinstance(c, int)}
        for name, codes in self.classes.items():
            if name not in self.ignore and codes and set(codes) <= ignored_codes:
                raise _fail(f"data.ignore drops every code of class '{name}' "
                            f"({_show(codes)}); ignore the class by name instead")
        if self.classes and not self.class_names:
            raise _fail("data.ignore drops every class in data.classes; keep at least one")
        if self.split is not None and not self.train:
            raise _fail("data.split cuts the data.train cloud, but data.train is empty; "
                        "give data.train or remove data.split")
        return self

    # -- class helpers ----------------------------------------------------------------------
    @property
    def class_names(self) -> list[str]:
        """Names of the classes the model learns and predicts (ignored ones removed), in order."""
        return [name for name in self.classes if name not in self.ignore]

    @property
    def class_codes(self) -> list[int]:
        """The output code of each class of :attr:`class_names`: its first source code."""
        return [self.classes[name][0] for name in self.class_names]

    @property
    def code_to_class(self) -> dict[int, int]:
        """Source label code -> index in :attr:`class_names`; ignored codes are absent."""
        ignored_codes = {c for c in self.ignore if isinstance(c, int)}
        return {
            code: index
            for index, name in enumerate(self.class_names)
            for code in self.classes[name]
            if code not in ignored_codes
        }

    @property
    def listed_codes(self) -> list[int]:
        """Every source code named by a class or by ignore (kept by drop_unlisted)."""
        codes = {code for codes in self.classes.values() for code in codes}
        return sorted(codes | {c for c in self.ignore if isinstance(c, int)})

    @property
    def background_indices(self) -> list[int]:
        """Indices in :attr:`class_names` of the background classes."""
        names = self.class_names
        return [names.index(name) for name in self.background]


# -- tiling and features ---------------------------------------------------------------------
class FeaturesConfig(_Section):
    """The per-point features: moment invariants in S1 and context in S1 and S2."""

    set: str = Field(
        "paper",
        description="The feature set; 'paper' = the 11 moment invariants and the context "
        "features as published.",
    )
    r1: Number = Field(0.5, gt=0, description="Radius of the sphere S1 in metres.")
    r2: Number | None = Field(
        None, description="Radius of the inner context sphere S2 in metres; default r1 / 2."
    )
    max_neighbors: Integer = Field(
        64, ge=3, description="At most this many nearest points of S1 form the local surface."
    )
    context_max_neighbors: Integer | None = Field(
        None, ge=1, description="Unset: every point within r1 counts in the context (the "
        "paper; exact and fast at any density). A number: only that many nearest points, "
        "which on dense scans shrinks the context sphere well below r1.",
    )

    @field_validator("set")
    @classmethod
    def _known_set(cls, value: str) -> str:
        if value not in FEATURE_SETS:
            raise _field_error("must be one of the feature sets "
                               + ", ".join(f"'{s}'" for s in FEATURE_SETS))
        return value

    @model_validator(mode="after")
    def _resolve_r2(self) -> "FeaturesConfig":
        if self.r2 is None:
            object.__setattr__(self, "r2", self.r1 / 2)  # the paper's r2 = r1 / 2
        elif not 0 < self.r2 <= self.r1:
            raise _fail(f"features.r2 must be > 0 and <= features.r1 ({_show(self.r1)}), "
                        f"got {_show(self.r2)}")
        return self

    @property
    def radius2(self) -> float:
        """The inner context radius, resolved (r1 / 2 unless set)."""
        return float(self.r2) if self.r2 is not None else self.r1 / 2

    @property
    def largest_radius(self) -> float:
        """The largest radius any step looks at: the halo must be at least this."""
        return max(self.r1, self.radius2)


def _chunk_size(value: Any) -> Any:
    if isinstance(value, str) and value == "auto":
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value) or value <= 0:
        raise _field_error("must be 'auto' or a number of metres > 0")
    return float(value)


ChunkSize = Annotated[Union[Literal["auto"], float], BeforeValidator(_chunk_size)]


class TilingConfig(_Section):
    """The chunk grid the tiles are cut into, and how they are streamed."""

    chunk_size: ChunkSize = Field(
        "auto",
        description="Side of a square chunk in metres, or 'auto': sized per scene from the "
        "tiles' headers so that a chunk with its halo holds about tiling.target_points "
        "points at the scene's mean density.",
    )
    target_points: Integer = Field(
        1_000_000, ge=1,
        description="With chunk_size 'auto': points wanted in a chunk with its halo; a "
        "worker holds one chunk at a time, so this bounds its memory. Ignored when "
        "chunk_size is a number.",
    )
    halo: Number | None = Field(
        None, gt=0,
        description="Width in metres of the copies of neighbouring points around a chunk; "
        "default (and minimum) = the largest radius used, features.r1.",
    )
    read_batch: Integer = Field(
        1_000_000, ge=1, description="Points per read batch when streaming tiles."
    )

    def halo_resolved(self, features: FeaturesConfig) -> float:
        """The halo in metres: as set, or the largest radius of ``features``."""
        return float(self.halo) if self.halo is not None else features.largest_radius


# -- cascade ---------------------------------------------------------------------------------
def _max_features(value: Any) -> Any:
    ok = (
        value in ("sqrt", "log2")
        or (isinstance(value, int) and not isinstance(value, bool) and value >= 1)
        or (isinstance(value, float) and 0 < value <= 1)
    )
    if not ok:
        raise _field_error("must be 'sqrt', 'log2', an integer >= 1 or a number in (0, 1]")
    return value


class CascadeConfig(_Section):
    """The cascade of random forests (auto-context)."""

    stages: Integer = Field(3, ge=1, description="Number of cascade stages (forests).")
    n_estimators: Integer = Field(20, ge=1, description="Trees per forest.")
    min_samples_leaf: Integer = Field(15, ge=1, description="Minimum samples in a leaf.")
    max_features: Annotated[Union[str, int, float], BeforeValidator(_max_features)] = Field(
        "sqrt",
        description="Features tried per split, as scikit-learn takes it: 'sqrt', 'log2', "
        "an integer or a fraction in (0, 1].",
    )
    context: Literal["hard", "soft"] = Field(
        "hard",
        description="Context from predicted classes (hard) or averaged probabilities (soft).",
    )
    out_of_fold: bool = Field(
        False,
        description="Compute the training points' context from out-of-fold predictions.",
    )
    folds: Integer = Field(5, ge=2, description="Folds used with out_of_fold.")
    max_train_points: Integer = Field(
        200_000, ge=1, description="At most this many training points per stage."
    )
    balanced: bool = Field(
        False, description="Sample the training points with equal quotas per class."
    )
    seed: Integer = Field(0, ge=0, le=2**32 - 1, description="Seed of sampling and forests.")


# -- cluster ---------------------------------------------------------------------------------
def _memory(value: Any) -> Any:
    """Dask memory syntax: 'auto', '4GiB', '500MB' or a number of bytes."""
    if isinstance(value, bool):
        raise _field_error("must be 'auto', a size such as '4GiB' or a number of bytes")
    if isinstance(value, str) and value != "auto":
        from dask.utils import parse_bytes

        try:
            if parse_bytes(value) <= 0:
                raise ValueError
        except (ValueError, TypeError):
            raise _field_error("must be 'auto', a size such as '4GiB' or a number of bytes")
    elif isinstance(value, (int, float)) and value <= 0:
        raise _field_error("must be 'auto', a size such as '4GiB' or a number of bytes > 0")
    return value


_WALLTIME = re.compile(r"^(\d+-)?\d+(:\d+){0,2}$")


def _walltime(value: Any) -> Any:
    if not isinstance(value, str) or not _WALLTIME.match(value):
        raise _field_error("must be a SLURM time such as '08:00:00', '90' or '1-12:00:00' "
                           "(quote it in YAML)")
    return value


class SlurmConfig(_Section):
    """One SLURM job runs ``processes`` workers sharing ``cores`` cores and ``memory``."""

    queue: str | None = Field(None, description="SLURM partition (-p).")
    account: str | None = Field(None, description="SLURM account (-A).")
    cores: Integer = Field(4, ge=1, description="Cores per job.")
    processes: Integer = Field(1, ge=1, description="Worker processes per job.")
    memory: Annotated[str, BeforeValidator(_memory)] = Field(
        "16GiB", description="Memory per job, dask syntax."
    )
    walltime: Annotated[str, BeforeValidator(_walltime)] = Field(
        "08:00:00", description="Time limit of a job (-t)."
    )
    jobs: Integer = Field(2, ge=1, description="Jobs to submit.")
    job_extra_directives: list[str] = Field(
        default_factory=list, description="Extra #SBATCH lines, e.g. ['--exclusive']."
    )
    local_directory: str | None = Field(
        None, description="Scratch directory of the workers on the compute nodes."
    )

    @model_validator(mode="after")
    def _processes_fit(self) -> "SlurmConfig":
        if self.processes > self.cores:
            raise _fail(f"cluster.slurm.processes ({self.processes}) is more than "
                        f"cluster.slurm.cores ({self.cores}); every worker needs a core")
        return self


class ClusterConfig(_Section):
    """Where the Dask tasks run: a local cluster, a running scheduler or SLURM jobs."""

    kind: Literal["local", "address", "slurm"] = Field(
        "local", description="local | address | slurm."
    )
    address: str | None = Field(
        None, description="Scheduler address for kind 'address', e.g. tcp://host:8786."
    )
    n_workers: Integer | None = Field(
        None, ge=1,
        description="Workers; default: the number of cores (local), workers of "
        "cluster.slurm.jobs jobs (slurm).",
    )
    threads_per_worker: Integer = Field(1, ge=1, description="Threads per local worker.")
    memory_limit: Annotated[Union[str, int, float], BeforeValidator(_memory)] = Field(
        "auto", description="Memory limit per local worker, dask syntax ('4GiB', 'auto')."
    )
    dashboard: bool = Field(True, description="Serve the Dask dashboard (local clusters).")
    slurm: SlurmConfig = Field(default_factory=SlurmConfig)

    @model_validator(mode="after")
    def _address_given(self) -> "ClusterConfig":
        if self.kind == "address" and not self.address:
            raise _fail("cluster.address is required when cluster.kind is 'address'; give "
                        "the scheduler address, e.g. tcp://host:8786")
        return self


# -- output ----------------------------------------------------------------------------------
class OutputConfig(_Section):
    """The classified tiles written back."""

    format: Literal["laz", "las"] = Field("laz", description="laz | las.")
    write_classification: bool = Field(
        False,
        description="Also overwrite the classification field with the prediction (the "
        "original is otherwise kept untouched).",
    )
    probabilities: bool = Field(True, description="One extra dimension per class.")


# -- the whole configuration -----------------------------------------------------------------
class SilvaConfig(_Section):
    """A complete, validated Silva configuration."""

    data: DataConfig = Field(default_factory=DataConfig)
    tiling: TilingConfig = Field(default_factory=TilingConfig)
    features: FeaturesConfig = Field(default_factory=FeaturesConfig)
    cascade: CascadeConfig = Field(default_factory=CascadeConfig)
    cluster: ClusterConfig = Field(default_factory=ClusterConfig)
    output: OutputConfig = Field(default_factory=OutputConfig)

    @model_validator(mode="after")
    def _resolve_halo(self) -> "SilvaConfig":
        largest = self.features.largest_radius
        halo = self.tiling.halo
        if halo is None:
            object.__setattr__(self, "tiling", self.tiling.model_copy(update={"halo": largest}))
        elif halo < largest:
            raise _fail(f"tiling.halo {_show(halo)} is smaller than the largest radius "
                        f"{_show(largest)}; use a halo >= {_show(largest)} or leave it unset")
        return self

    @property
    def halo(self) -> float:
        """The halo in metres (resolved: the largest radius unless set larger)."""
        return self.tiling.halo_resolved(self.features)

    @property
    def class_names(self) -> list[str]:
        """See :attr:`DataConfig.class_names`."""
        return self.data.class_names


# -- loading ---------------------------------------------------------------------------------
class _UniqueKeyLoader(yaml.SafeLoader):
    """A safe YAML loader that refuses a key given twice in one mapping (YAML keeps the last)."""


def _construct_unique_mapping(loader, node, deep=False):
    seen = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in seen:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key '{key}'", key_node.start_mark
            )
        seen.add(key)
    return loader.construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_constructor(
    yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_unique_mapping
)


def _read_yaml(path: Path) -> dict:
    if not path.exists():
        raise MissingFileError(f"config file {path} not found; check the path")
    if not path.is_file():
        raise ConfigError(f"config error: {path} is not a file; give a YAML config file")
    try:
        raw = yaml.load(path.read_text(), Loader=_UniqueKeyLoader)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = f" line {mark.line + 1}" if mark is not None else ""
        problem = " ".join(str(exc.problem or exc.context or "invalid YAML").split())
        raise ConfigError(f"config error: {path}{line}: {problem}") from None
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise ConfigError(f"config error: {path} is not valid YAML: "
                          f"{' '.join(str(exc).split())}") from None
    if raw is None:
        return {}
    if not isinstance(raw, dict):
        raise ConfigError(f"config error: {path} must hold a mapping of sections "
                          f"({', '.join(SilvaConfig.model_fields)}), got {_show(raw)}")
    return raw


def _resolve_path(pattern: Any, base: Path) -> Any:
    """``pattern`` made absolute against ``base`` (glob characters kept as written)."""
    if not isinstance(pattern, (str, os.PathLike)) or isinstance(pattern, bool):
        return pattern  # left for validation to reject
    text = os.path.expanduser(os.fspath(pattern))
    if not text:
        return text
    if not os.path.isabs(text):
        text = os.path.join(base, text)
    return os.path.normpath(text)


def _resolve_scene_paths(value: Any, base: Path) -> Any:
    if isinstance(value, (list, tuple)):
        return [_resolve_path(p, base) for p in value]
    return _resolve_path(value, base) if isinstance(value, str) else value


def _resolve_data_section(data: Any, base: Path) -> Any:
    if not isinstance(data, dict):
        return data
    return {k: _resolve_scene_paths(v, base) if k in SCENES else v for k, v in data.items()}


def _parse_override(text: str) -> tuple[list[str], Any]:
    form = "use KEY=VALUE with a dotted key, e.g. tiling.chunk_size=20"
    key, sep, value = text.partition("=")
    key = key.strip()
    if not sep:
        raise ConfigError(f"config error: --set '{text}' has no '='; {form}")
    parts = key.split(".")
    if not key or any(not part.strip() for part in parts):
        raise ConfigError(f"config error: --set '{text}' has an empty key or key part; {form}")
    parts = [part.strip() for part in parts]
    try:
        parsed = yaml.load(value, Loader=_UniqueKeyLoader) if value.strip() else None
    except yaml.YAMLError as exc:
        problem = getattr(exc, "problem", None) or "invalid YAML"
        raise ConfigError(
            f"config error: the value of --set '{text}' is not valid YAML ({problem}); "
            f"quote it, e.g. {key}='...' or {key}=['a/*.laz']"
        ) from None
    return parts, parsed


def _apply_override(raw: dict, parts: list[str], value: Any, text: str) -> None:
    form = "use KEY=VALUE with a dotted key, e.g. tiling.chunk_size=20"
    node, model = raw, SilvaConfig
    for depth, part in enumerate(parts[:-1]):
        # The schema says which keys are values, not sections (tiling.chunk_size.x=1).
        if model is not None and part in model.model_fields:
            sub = _submodel(model.model_fields[part].annotation)
            if sub is None and get_origin(_unwrap(model.model_fields[part].annotation)) \
                    is not dict:
                raise ConfigError(
                    f"config error: --set '{text}': '{'.'.join(parts[:depth + 1])}' is a "
                    f"value, not a section, so it has no key '{parts[depth + 1]}'; {form}"
                )
            model = sub
        else:
            model = None
        child = node.get(part)
        if child is None:
            child = node[part] = {}
        if not isinstance(child, dict):
            raise ConfigError(
                f"config error: --set '{text}': '{'.'.join(parts[:depth + 1])}' holds "
                f"{_show(child)}, not a mapping, so it has no key '{parts[depth + 1]}'; {form}"
            )
        node = child
    node[parts[-1]] = value


def load_config(
    path: str | Path | None,
    overrides: Sequence[str] = (),
    *,
    base_dir: str | Path | None = None,
) -> SilvaConfig:
    """Read, override and validate a configuration.

    Parameters
    ----------
    path
        A YAML file, or None for every default.
    overrides
        ``KEY=VALUE`` strings: KEY is a dotted path (``tiling.chunk_size``,
        ``cluster.slurm.queue``), VALUE is parsed as YAML (``20``, ``soft``,
        ``[a.laz, b/*.laz]``, ``{axis: y, at: 528}``) and replaces the value at KEY in the
        raw mapping before validation, in the order given.
    base_dir
        The directory relative data paths of the file are resolved against; default: the
        config file's directory (the current directory when ``path`` is None).

    Relative paths in ``data.train``, ``data.test`` and ``data.predict`` are made absolute
    here: those written in the file against ``base_dir``, so a config and its data can move
    together; those given by an override against the current directory, because that is
    where the command line was typed. Globs are kept as written; :func:`expand_inputs`
    expands them.

    Raises
    ------
    MissingFileError
        ``path`` does not exist.
    ConfigError
        YAML syntax (naming the file and line), a malformed override, or any invalid key or
        value (naming the dotted key, what was received and what is allowed).
    """
    if path is not None:
        path = Path(path).expanduser()
        raw = _read_yaml(path)
        base = Path(base_dir) if base_dir is not None else path.resolve().parent
    else:
        raw = {}
        base = Path(base_dir) if base_dir is not None else Path.cwd()
    base = base.expanduser().resolve()
    raw = dict(raw)
    if "data" in raw:
        raw["data"] = _resolve_data_section(raw["data"], base)

    cwd = Path.cwd()
    for text in overrides:
        parts, value = _parse_override(text)
        if parts[0] == "data" and len(parts) == 2 and parts[1] in SCENES:
            value = _resolve_scene_paths(value, cwd)
        elif parts == ["data"]:
            value = _resolve_data_section(value, cwd)
        _apply_override(raw, parts, value, text)
    return validate_config(raw)


def validate_config(raw: Any) -> SilvaConfig:
    """Validate a raw mapping (as read from YAML) into a :class:`SilvaConfig`.

    Paths are taken as they are. Raises :class:`ConfigError` with one line naming the key.
    """
    try:
        return SilvaConfig.model_validate(raw)
    except ValidationError as exc:
        errors = exc.errors()
        message = _describe(errors[0])
        if len(errors) > 1:
            message += f" (and {len(errors) - 1} more)"
        raise ConfigError(f"config error: {message}") from None


def expand_inputs(patterns: Sequence[str | Path], *, key: str | None = None) -> list[Path]:
    """The files matched by paths and globs, sorted and without duplicates.

    ``**`` matches any number of directories. ``key`` (e.g. ``"data.train"``) is named in
    errors. Raises :class:`MissingFileError` naming a pattern that matches no file, and
    :class:`InputError` for a directory given where files are expected.
    """
    where = f" in {key}" if key else ""
    found: dict[Path, Path] = {}
    for pattern in patterns:
        text = os.path.expanduser(os.fspath(pattern))
        if glob.has_magic(text):
            matches = [Path(p) for p in glob.glob(text, recursive=True) if os.path.isfile(p)]
        elif os.path.isdir(text):
            raise InputError(f"input '{text}'{where} is a directory; give its files, e.g. "
                             f"'{os.path.join(text, '*.laz')}'")
        else:
            matches = [Path(text)] if os.path.isfile(text) else []
        if not matches:
            raise MissingFileError(f"no file matches '{text}'{where}; check the path or glob")
        for match in matches:
            found.setdefault(match.resolve(), match)
    return sorted(found.values(), key=lambda p: str(p))


def dump_config(cfg: SilvaConfig) -> str:
    """The resolved configuration as YAML: every default filled in, r2 and halo written out.

    ``load_config`` of this text gives a configuration equal to ``cfg`` (data paths are
    absolute after :func:`load_config`, so the file can be saved anywhere).
    """
    return yaml.dump(
        cfg.model_dump(mode="json"), Dumper=_Dumper, sort_keys=False,
        default_flow_style=False, allow_unicode=True, width=100,
    )


class _Dumper(yaml.SafeDumper):
    """Sections as blocks, lists of plain values on one line (codes, paths)."""


def _represent_list(dumper: yaml.SafeDumper, data: list):
    flat = all(not isinstance(item, (list, dict)) for item in data)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flat)


_Dumper.add_representer(list, _represent_list)


def fingerprint(cfg: SilvaConfig, step: str) -> str:
    """A short stable hash of exactly the configuration parts that affect ``step``.

    ==========  ========================================================================
    step        hashed keys (each step includes the rows above it, except evaluate and
                export, which both build on stage)
    ==========  ========================================================================
    ingest      data.train/test/predict (patterns, order ignored), data.label_field,
                data.classes, data.ignore, data.split, data.drop_unlisted;
                tiling.chunk_size, tiling.halo, tiling.target_points (only with chunk_size
                auto)
    features    + features.set, features.r1, features.max_neighbors
    stage       + features.r2, features.context_max_neighbors, every cascade key except
                cascade.stages (adding stages keeps the finished ones)
    export      stage + output.*
    evaluate    stage + data.background
    ==========  ========================================================================

    Never hashed: cluster.*, tiling.read_batch (they change how, not what, is computed).
    The halo is hashed resolved, so with ``tiling.halo`` unset, changing ``features.r1``
    also changes the halo and thus ``ingest``. With ``chunk_size: auto`` the size ingest
    resolves also depends on the tiles' headers, which the run's inputs digest covers. Globs
    are hashed as written, not the files they match. Returns 16 hexadecimal digits of the
    SHA-256 of the canonical JSON.
    """
    if step not in STEPS:
        raise ConfigError(f"config error: unknown step '{step}' for a fingerprint; "
                          f"use one of {', '.join(STEPS)}")
    d = cfg.model_dump(mode="json")
    data = d["data"]
    parts: dict[str, Any] = {
        "version": _FINGERPRINT_VERSION,
        "ingest": {
            **{scene: sorted(set(data[scene])) for scene in SCENES},
            **{k: data[k] for k in ("label_field", "ignore", "split", "drop_unlisted")},
            # a list of pairs: the class order is the class index (sort_keys would lose it)
            "classes": [[name, codes] for name, codes in data["classes"].items()],
            "chunk_size": cfg.tiling.chunk_size,
            "halo": cfg.halo,
        },
    }
    if cfg.tiling.chunk_size == "auto":
        # only then does it matter; an explicit size keeps the fingerprint it always had
        parts["ingest"]["target_points"] = cfg.tiling.target_points
    if step != "ingest":
        parts["features"] = {k: d["features"][k] for k in ("set", "r1", "max_neighbors")}
    if step in ("stage", "export", "evaluate"):
        parts["context"] = {"r2": cfg.features.radius2,
                            "context_max_neighbors": cfg.features.context_max_neighbors}
        parts["cascade"] = {k: v for k, v in d["cascade"].items() if k != "stages"}
    if step == "export":
        parts["output"] = d["output"]
    if step == "evaluate":
        parts["background"] = data["background"]
    text = json.dumps(parts, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


# -- error messages --------------------------------------------------------------------------
def _show(value: Any) -> str:
    """A value as a user wrote it in YAML."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if value is None:
        return "null"
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, (int, float)):
        return repr(value)
    try:
        return yaml.safe_dump(value, default_flow_style=True, width=10_000).strip()
    except yaml.YAMLError:
        return repr(value)


def _unwrap(annotation: Any) -> Any:
    """The type inside Optional[...] / Annotated[...]."""
    while True:
        origin = get_origin(annotation)
        if origin is Annotated:
            annotation = get_args(annotation)[0]
        elif origin is Union or origin is types.UnionType:
            args = [a for a in get_args(annotation) if a is not type(None)]
            if len(args) != 1:
                return annotation
            annotation = args[0]
        else:
            return annotation


def _submodel(annotation: Any) -> type[BaseModel] | None:
    inner = _unwrap(annotation)
    return inner if isinstance(inner, type) and issubclass(inner, BaseModel) else None


def _model_at(loc: Sequence) -> type[BaseModel] | None:
    model = SilvaConfig
    for part in loc:
        if model is None or part not in model.model_fields:
            return None
        model = _submodel(model.model_fields[part].annotation)
    return model


def _dotted(loc: Sequence) -> str:
    text = ""
    for part in loc:
        if isinstance(part, int):
            text += f"[{part}]"
        elif part == "[key]":
            text += " key"
        else:
            text += f".{part}" if text else str(part)
    return text


_PHRASES = {
    "int_type": "must be an integer",
    "int_parsing": "must be an integer",
    "int_from_float": "must be an integer",
    "float_type": "must be a number",
    "float_parsing": "must be a number",
    "finite_number": "must be a finite number",
    "bool_type": "must be true or false",
    "bool_parsing": "must be true or false",
    "string_type": "must be text",
    "list_type": "must be a list",
    "dict_type": "must be a mapping of keys to values",
    "model_type": "must be a mapping of keys to values",
    "model_attributes_type": "must be a mapping of keys to values",
}


def _describe(error: dict) -> str:
    """One pydantic error as '<dotted key> <what is allowed>, got <value>'."""
    kind, loc, ctx = error["type"], tuple(error["loc"]), error.get("ctx") or {}
    # Union members add their type name to the location; drop them.
    loc = tuple(p for p in loc if p not in ("str", "int", "float"))
    key, got = _dotted(loc), _show(error.get("input"))
    if kind == "silva":
        return error["msg"]
    if kind == "extra_forbidden":
        model = _model_at(loc[:-1])
        valid = list(model.model_fields) if model is not None else []
        close = difflib.get_close_matches(str(loc[-1]), valid, n=1, cutoff=0.6)
        hint = (f"did you mean '{close[0]}'?" if close
                else f"valid keys here: {', '.join(valid)}" if valid else "remove it")
        return f"unknown key '{key}' ({hint})"
    if kind == "missing":
        return f"{key} is required"
    if kind == "silva_field":
        phrase = error["msg"]
    elif kind in _PHRASES:
        phrase = _PHRASES[kind]
    elif kind in ("greater_than", "greater_than_equal", "less_than", "less_than_equal"):
        op = {"greater_than": ">", "greater_than_equal": ">=",
              "less_than": "<", "less_than_equal": "<="}[kind]
        bound = next(iter(ctx.values()), "")
        if isinstance(bound, float) and bound.is_integer():
            bound = int(bound)  # "> 0", as the user would write it
        phrase = f"must be {op} {bound}"
    elif kind == "literal_error":
        phrase = f"must be {ctx.get('expected', '')}"
    elif kind == "string_too_short":
        phrase = "must not be empty"
    else:
        phrase = error["msg"][:1].lower() + error["msg"][1:]
    return f"{key} {phrase}, got {got}"
