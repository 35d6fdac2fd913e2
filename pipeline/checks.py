"""One check for the numbers every parameter set and entry point takes.

A parameter set (:class:`~pipeline.terrain.TerrainParams`, :class:`~pipeline.trees.TreeParams`,
:class:`~pipeline.features.sets.FeatureParams`, :class:`~pipeline.cascade.CascadeParams`)
raises :class:`~pipeline.errors.ConfigError` naming the configuration's key; a function of
arrays raises :class:`~pipeline.errors.InputError` naming its argument. Both are
``ValueError``s.
"""

import math

import numpy as np

from pipeline.errors import ConfigError


def finite_number(raw, key: str, *, positive: bool = True, hint: str = "",
                  error: type[ValueError] = ConfigError) -> float:
    """``raw`` as a float, if it is a finite number > 0 (>= 0 unless ``positive``); else
    ``error``: "<key> must be a finite number > 0, got <raw>[; <hint>]". A bool is no
    number."""
    try:
        value = math.nan if isinstance(raw, (bool, np.bool_)) else float(raw)
    except (TypeError, ValueError):
        value = math.nan
    if not (math.isfinite(value) and (value > 0.0 if positive else value >= 0.0)):
        bound = "> 0" if positive else ">= 0"
        raise error(f"{key} must be a finite number {bound}, got {raw!r}"
                    + (f"; {hint}" if hint else ""))
    return value


def finite_numbers(raw, key: str, *, error: type[ValueError] = ConfigError) -> tuple[float, ...]:
    """``raw`` (a number or a sequence of them) as a tuple of distinct floats, each finite and
    > 0, at least one; else ``error`` naming ``key``."""
    values = tuple(float(v) for v in np.atleast_1d(np.asarray(raw, dtype=np.float64)))
    if not values or not all(v > 0.0 and math.isfinite(v) for v in values):
        raise error(f"{key} must be one or more finite numbers > 0, got {raw!r}")
    if len(set(values)) != len(values):
        raise error(f"{key} must be distinct, got {raw!r}")
    return values
