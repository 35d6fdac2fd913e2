"""The recompute fingerprint: a hash of the configuration parts that affect one step.

Each step of the table says which parts its fingerprint hashes
(:class:`workflows.run.step_table.Fingerprint`); a rerun redoes a step whose fingerprint
changed and keeps the others.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from workflows.config.schema import SilvaConfig

_FINGERPRINT_VERSION = "silva-config-2"  # bump when the meaning of a fingerprinted key changes


def fingerprint(cfg: SilvaConfig, parts: Mapping[str, Any]) -> str:
    """A short stable hash of the configuration's ``parts``, each under its name: a
    configuration path as written ("terrain": the whole section, "output.trees": one key)
    or a function of the configuration and its JSON dump. Returns 16 hexadecimal digits of
    the SHA-256 of the canonical JSON (the names sorted: their order changes nothing)."""
    d = cfg.model_dump(mode="json")
    hashed: dict[str, Any] = {"version": _FINGERPRINT_VERSION}
    for name, rule in parts.items():
        hashed[name] = _config_value(d, rule) if isinstance(rule, str) else rule(cfg, d)
    text = json.dumps(hashed, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _config_value(d: dict, path: str):
    """The value at ``path`` ("section" or "section.key") of the dumped configuration."""
    value = d
    for key in path.split("."):
        value = value[key]
    return value
