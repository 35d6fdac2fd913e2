"""Reading a configuration: YAML, relative data paths, ``--set`` overrides, validation, dumping.

:func:`load_config` reads a YAML file (refusing a key given twice), makes the data paths
absolute, applies ``--set KEY=VALUE`` overrides to the raw mapping and validates it all at
once with :func:`validate_config`; :func:`dump_config` writes the resolved configuration.
"""

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any, get_origin

import yaml
from pydantic import ValidationError

from pipeline.errors import ConfigError, MissingFileError
from workflows.config.inputs import SCENES
from workflows.config.messages import describe, show, submodel, unwrap
from workflows.config.schema import SilvaConfig


class _UniqueKeyLoader(yaml.SafeLoader):
    """A safe YAML loader that refuses a key given twice in one mapping (YAML keeps the last)
    and a key that is a list or a mapping (Python cannot hash it)."""


class _KeyError(yaml.constructor.ConstructorError):
    """A mapping key that is a list or a mapping."""


def _construct_unique_mapping(loader, node, deep=False):
    seen = set()
    for key_node, _ in node.value:
        if isinstance(key_node, (yaml.SequenceNode, yaml.MappingNode)):
            kind = "a list" if isinstance(key_node, yaml.SequenceNode) else "a mapping"
            key = show(loader.construct_object(key_node, deep=True))
            raise _KeyError(None, None, f"the key {key} is {kind}; a key must be a name such "
                            "as chunk_size", key_node.start_mark)
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
    except RecursionError:
        raise ConfigError(f"config error: {path} nests lists or mappings too deeply to read; "
                          "a Silva config needs at most a few levels (see silva init)") from None
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise ConfigError(f"config error: {path} is not valid YAML: "
                          f"{' '.join(str(exc).split())}") from None
    if raw is None:
        return {}
    if not isinstance(raw, dict):
        raise ConfigError(f"config error: {path} must hold a mapping of sections "
                          f"({', '.join(SilvaConfig.model_fields)}), got {show(raw)}")
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
    except RecursionError:
        raise ConfigError(
            f"config error: the value of --set {key}=... nests lists or mappings too deeply "
            f"to read; give a plain value, a list or a mapping, e.g. {key}=['a/*.laz']"
        ) from None
    except _KeyError as exc:
        raise ConfigError(f"config error: --set '{text}': {exc.problem}") from None
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
            sub = submodel(model.model_fields[part].annotation)
            if sub is None and get_origin(unwrap(model.model_fields[part].annotation)) \
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
                f"{show(child)}, not a mapping, so it has no key '{parts[depth + 1]}'; {form}"
            )
        node = child
    node[parts[-1]] = value


def load_raw(
    path: str | Path | None,
    overrides: Sequence[str] = (),
    *,
    base_dir: str | Path | None = None,
) -> dict:
    """Read and override a configuration: the mapping as written, not yet validated.

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
    return raw


def load_config(
    path: str | Path | None,
    overrides: Sequence[str] = (),
    *,
    base_dir: str | Path | None = None,
) -> SilvaConfig:
    """:func:`load_raw` validated into a :class:`SilvaConfig` (ConfigError naming the key)."""
    return validate_config(load_raw(path, overrides, base_dir=base_dir))


#: How deep lists and mappings may nest in a config; Silva's own keys need at most 4 levels
#: (data.classes.tree[0]), and a deeper value would only be refused later, less clearly.
MAX_DEPTH = 16


def _check_depth(raw: Any) -> None:
    """ConfigError naming the key (at most three parts) whose value nests deeper than
    :data:`MAX_DEPTH`; iterative, so no depth exhausts Python's recursion limit."""
    todo = [(raw, [], 0)]
    while todo:
        value, where, depth = todo.pop()
        if depth > MAX_DEPTH:
            raise ConfigError(f"config error: {'.'.join(where) or 'the config'} nests lists "
                              f"or mappings more than {MAX_DEPTH} levels deep; give a plain "
                              "value, a list or a mapping, as silva init writes them")
        if isinstance(value, dict):  # the key named: its first three parts, outside lists
            todo += [(v, where if len(where) != depth or depth >= 3 else [*where, str(k)],
                      depth + 1) for k, v in value.items()]
        elif isinstance(value, list):
            todo += [(v, where, depth + 1) for v in value]


def validate_config(raw: Any) -> SilvaConfig:
    """Validate a raw mapping (as read from YAML) into a :class:`SilvaConfig`.

    Paths are taken as they are. Raises :class:`ConfigError` with one line naming the key.
    """
    _check_depth(raw)
    try:
        return SilvaConfig.model_validate(raw)
    except ValidationError as exc:
        errors = exc.errors()
        message = describe(errors[0], SilvaConfig)
        if len(errors) > 1:
            message += f" (and {len(errors) - 1} more)"
        raise ConfigError(f"config error: {message}") from None


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
