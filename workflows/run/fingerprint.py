"""The recompute fingerprint: a hash of the configuration keys that affect one workflow step.

:data:`STEPS` is the list of fingerprinted steps, as the step table
(:mod:`workflows.run.step_table`) declares them with the configuration parts each hashes
(:data:`PARTS`, or configuration paths hashed as written); a rerun redoes a step whose
fingerprint changed and keeps the others.
"""

from __future__ import annotations

import hashlib
import json
from typing import TYPE_CHECKING, Any

from pipeline.errors import ConfigError
from workflows.config.inputs import SCENES
from workflows.run.step_table import FINGERPRINTED

if TYPE_CHECKING:
    from workflows.config.schema import SilvaConfig

#: The keys of the features section that change the features (r2 and the context cap change
#: only the cascade's context).
FEATURE_KEYS = ("set", "r1", "max_neighbors", "plane", "scales", "column", "cell", "voxel",
                "version")
STEPS = tuple(FINGERPRINTED)
_FINGERPRINT_VERSION = "silva-config-2"  # bump when the meaning of a fingerprinted key changes


def fingerprint(cfg: SilvaConfig, step: str) -> str:
    """A short stable hash of exactly the configuration parts that affect ``step``.

    ==========  ========================================================================
    step        hashed keys (each step includes the rows above it, except evaluate and
                export, which both build on stage)
    ==========  ========================================================================
    ingest      data.train/test/predict (patterns, order ignored), data.label_field,
                data.classes, data.ignore, data.split, data.drop_unlisted,
                data.exclude_codes and data.exclude_withheld (when set);
                data.densities with cascade.seed, which seeds the copies (when set);
                tiling.chunk_size, tiling.halo, tiling.target_points and tiling.layout
                (only with chunk_size auto), output.keep_features (unless auto: it
                chooses each scene's halo), features.echoes (when set: ingest then
                stores each point's return numbers)
    terrain     + terrain.*
    features    + features.set, r1, max_neighbors, plane, scales, column, cell, voxel
    stage       + features.r2, features.context_max_neighbors, every cascade key except
                cascade.stages (adding stages keeps the finished ones when tiling.halo
                is set; unset, it grows with the stages, see below)
    trees       stage + trees.* and output.canopy_classes (with output.trees)
    export      stage + output.* (except output.keep_store and output.keep_features),
                + trees.* and output.canopy_classes with output.trees
    evaluate    stage + data.background
    ==========  ========================================================================

    Never hashed: cluster.*, tiling.read_batch (they change how, not what, is computed).
    The halo is hashed resolved, so with ``tiling.halo`` unset, changing ``features.r1``
    (or ``cascade.stages``, which the default halo reaches across) also changes the halo
    and thus ``ingest``. With ``chunk_size: auto`` the size ingest
    resolves also depends on the tiles' headers, which the run's inputs digest covers. Globs
    are hashed as written, not the files they match. Returns 16 hexadecimal digits of the
    SHA-256 of the canonical JSON.
    """
    if step not in STEPS:
        raise ConfigError(f"config error: unknown step '{step}' for a fingerprint; "
                          f"use one of {', '.join(STEPS)}")
    d = cfg.model_dump(mode="json")
    parts: dict[str, Any] = {"version": _FINGERPRINT_VERSION}
    for part in FINGERPRINTED[step].fingerprint:
        parts[part] = PARTS[part](cfg, d) if part in PARTS else _config_value(d, part)
    text = json.dumps(parts, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _config_value(d: dict, path: str):
    """The value at ``path`` ("section" or "section.key") of the dumped configuration."""
    value = d
    for key in path.split("."):
        value = value[key]
    return value


def _ingest_part(cfg: SilvaConfig, d: dict) -> dict:
    data = d["data"]
    part = {
        **{scene: sorted(set(data[scene])) for scene in SCENES},
        **{k: data[k] for k in ("label_field", "ignore", "split", "drop_unlisted")},
        # a list of pairs: the class order is the class index (sort_keys would lose it)
        "classes": [[name, codes] for name, codes in data["classes"].items()],
        "chunk_size": cfg.tiling.chunk_size,
        "halo": cfg.halo,
    }
    if cfg.output.keep_features != "auto":
        # it chooses each scene's halo; only when set, so the default keeps its fingerprint
        part["keep_features"] = cfg.output.keep_features
    for key in ("exclude_codes", "exclude_withheld"):
        if data[key]:  # only when set: a config without filters keeps its fingerprint
            part[key] = sorted(set(data[key])) if key == "exclude_codes" else True
    if cfg.features.echoes:
        # the store then holds the return numbers; only when set, so a run without echoes
        # keeps its fingerprint (and the features step, built on it, its own)
        part["echoes"] = True
    if data["densities"]:  # only when set: a config without copies keeps its fingerprint
        part["densities"] = sorted(set(data["densities"]))
        part["thinning_seed"] = cfg.cascade.seed
    if cfg.tiling.chunk_size == "auto":
        # only then does it matter; an explicit size keeps the fingerprint it always had
        part["target_points"] = cfg.tiling.target_points
        part["layout"] = cfg.tiling.layout
    return part


#: The fingerprint parts with rules of their own (any other part is a configuration path).
PARTS = {
    "ingest": _ingest_part,
    "features": lambda cfg, d: {k: d["features"][k] for k in FEATURE_KEYS},
    "context": lambda cfg, d: {"r2": cfg.features.radius2,
                               "context_max_neighbors": cfg.features.context_max_neighbors},
    "cascade": lambda cfg, d: {k: v for k, v in d["cascade"].items() if k != "stages"},
    # what the store keeps does not change what is written
    "output": lambda cfg, d: {k: v for k, v in d["output"].items()
                              if k not in ("keep_store", "keep_features", "trees")},
    # the trees, with the classes their crowns grow on; nothing when none are found
    "trees": lambda cfg, d: ({**d["trees"], "canopy_classes": d["output"]["canopy_classes"]}
                             if cfg.output.trees else None),
    "background": lambda cfg, d: d["data"]["background"],
}
