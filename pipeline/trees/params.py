"""The parameters of the tree step, validated once where they are built.

The configuration schema declares the ``trees`` section and delegates its checks here, so a
default and its rule are written once. Lengths are in metres; ``smoothing`` is in CHM cells.
"""

import math
import numbers
from dataclasses import dataclass

from pipeline.errors import ConfigError

METHODS = ("auto", "crowns", "stems")


@dataclass(frozen=True)
class TreeParams:
    """How trees are found: crowns on a canopy height model, stems in a slice at breast height.

    method : "crowns" (segment a CHM), "stems" (fit circles to stem points), or "auto" (stems
    when the scene shows them, else crowns). min_height : lowest canopy height of a tree (m).
    resolution : CHM cell side (m). smoothing : Gaussian sigma of the CHM in cells (0 = none).
    window : local-maximum window diameter a + b * height (m), lidR's variable window.
    crown_radius : largest crown radius a + b * height of its top (m).
    breast_height, slice_half_width, fallback_offsets : the slice of stem points fitted for the
    DBH (1.3 m, +- half width) and the offsets of the sections tried when it fails.
    stem_cluster_eps, stem_min_points : clustering of a slice's points into stems.
    stem_voxel : thinning voxel of stem points (m). max_dbh : largest credible DBH (m).
    """

    method: str = "auto"
    min_height: float = 2.0
    resolution: float = 0.5
    smoothing: float = 1.0
    window: tuple[float, float] = (3.0, 0.07)
    crown_radius: tuple[float, float] = (1.0, 0.15)
    breast_height: float = 1.3
    slice_half_width: float = 0.15
    fallback_offsets: tuple[float, ...] = (0.3, -0.3, 0.6)
    stem_cluster_eps: float = 0.1
    stem_min_points: int = 10
    stem_voxel: float = 0.01
    max_dbh: float = 1.5

    def __post_init__(self):
        if self.method not in METHODS:
            raise ConfigError(f"trees.method must be one of {', '.join(METHODS)}, "
                              f"got {self.method!r}")
        for name in ("resolution", "breast_height", "slice_half_width", "stem_cluster_eps",
                     "stem_voxel", "max_dbh"):
            self._set(name, _number(name, getattr(self, name), positive=True))
        for name in ("min_height", "smoothing"):
            self._set(name, _number(name, getattr(self, name), positive=False))
        for name in ("window", "crown_radius"):
            self._set(name, _linear(name, getattr(self, name)))
        self._set("fallback_offsets", _offsets(self.fallback_offsets))
        count = self.stem_min_points
        if (not isinstance(count, numbers.Integral) or isinstance(count, bool)
                or int(count) < 3):
            raise ConfigError(f"trees.stem_min_points must be an integer >= 3 (a circle needs "
                              f"three points), got {count!r}")
        self._set("stem_min_points", int(count))

    def _set(self, name, value):
        object.__setattr__(self, name, value)


def _number(name, raw, positive):
    """``raw`` as a finite float, > 0 when ``positive`` else >= 0, or a ConfigError."""
    try:
        value = float(raw)
    except (TypeError, ValueError):
        value = math.nan
    if not math.isfinite(value) or value < 0.0 or (positive and value == 0.0):
        bound = "> 0" if positive else ">= 0"
        raise ConfigError(f"trees.{name} must be a finite number {bound}, got {raw!r}; "
                          f"the default is {getattr(TreeParams, name)}")
    return value


def _linear(name, raw):
    """A pair (a, b) of ``a + b * height``: a > 0 metres, b >= 0 metres per metre."""
    default = getattr(TreeParams, name)
    try:
        a, b = (float(v) for v in raw)
    except (TypeError, ValueError):
        a = b = math.nan
    if not (math.isfinite(a) and math.isfinite(b) and a > 0.0 and b >= 0.0):
        raise ConfigError(f"trees.{name} must be a pair [a, b] (a + b * height) with a > 0 "
                          f"and b >= 0, got {raw!r}; the default is {list(default)}")
    return (a, b)


def _offsets(raw):
    """The fallback section offsets as a tuple of finite floats (metres from breast height)."""
    try:
        values = tuple(float(v) for v in raw)
    except (TypeError, ValueError):
        values = (math.nan,)
    if not all(math.isfinite(v) for v in values):
        raise ConfigError(f"trees.fallback_offsets must be a list of finite numbers (metres "
                          f"from breast height), got {raw!r}; use [] for no fallback")
    return values
