"""The parameters of the tree step, validated once where they are built.

The configuration schema declares the ``trees`` section and delegates its checks here, so a
default and its rule are written once. Lengths are in metres; ``smoothing`` is in CHM cells.
"""

import math
import numbers
from dataclasses import dataclass

from pipeline.checks import finite_number
from pipeline.errors import ConfigError
from pipeline.grid import MAX_CELLS, MAX_INDEX

METHODS = ("auto", "crowns", "stems")
#: The finest canopy height cell a scan resolves, as a share of its points' mean spacing
#: (all points, from the headers): finer, most cells hold no point and the crowns fall
#: apart. Measured on airborne tiles (43, 25 and 0.9 points/m²): trees of one or two points
#: (median) at 0.5-0.65 spacings, fair crowns from about one spacing.
FINEST_CELL_PER_SPACING = 0.75


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
    return finite_number(raw, f"trees.{name}", positive=positive,
                         hint=f"the default is {getattr(TreeParams, name)}")


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


def check_scan(params: TreeParams, density: float, width: float, depth: float,
               reach: float) -> None:
    """Refuse, with one line naming the key, settings that cannot give trees on a scan of
    ``density`` points per m² over a scene of ``width`` x ``depth`` metres whose XY
    coordinates reach ``reach`` metres from 0 (largest absolute value): a canopy height cell
    finer than the points resolve (trees of a point) or coarser than the smallest crown the
    window and crown radius allow (one cell, one crown for several trees), a raster beyond
    memory (stems, found on the whole scene; crowns are found in blocks) or the cell keys, a top window wider than the scene. Raises ConfigError."""
    r = params.resolution
    fix = "(e.g. --set trees.resolution={:g})"
    if density > 0 and math.isfinite(density):
        spacing = 1.0 / math.sqrt(density)
        finest = FINEST_CELL_PER_SPACING * spacing
        if r < finest:
            raise ConfigError(
                f"config error: trees.resolution={r:g} m is finer than the points resolve: at "
                f"{_amount(density)} points/m² (about {spacing:.2g} m apart) most canopy cells would "
                f"hold no point and every tree would be a point or two; use at least "
                f"{_up(finest):g} m " + fix.format(
                    min(max(TreeParams.resolution, _up(spacing)), coarsest_cell(params))))
    coarsest = coarsest_cell(params)
    if r > coarsest:
        raise ConfigError(
            f"config error: trees.resolution={r:g} m is coarser than the smallest crown the "
            f"settings allow ({coarsest:g} m across: trees.window starts at "
            f"{params.window[0]:g} m, trees.crown_radius at {params.crown_radius[0]:g} m), so "
            f"neighbouring trees would share cells and one crown swallow several; use at most "
            f"{coarsest:g} m " + fix.format(min(TreeParams.resolution, coarsest)))
    if reach / r >= MAX_INDEX:
        raise ConfigError(
            f"config error: trees.resolution={r:g} m gives cell indices beyond {MAX_INDEX} at "
            f"the tiles' coordinates (up to {reach:,.0f} m from 0); use a coarser resolution "
            + fix.format(TreeParams.resolution))
    cells = math.ceil(width / r + 1) * math.ceil(depth / r + 1)
    if params.method == "stems" and cells > MAX_CELLS:  # crowns are found in blocks
        raise ConfigError(
            f"config error: trees.resolution={r:g} m gives the scene's canopy height model "
            f"about {cells:,} cells ({width:,.0f} x {depth:,.0f} m), more than {MAX_CELLS:,}; "
            "use a coarser resolution " + fix.format(TreeParams.resolution)
            + " or split the scene")
    if params.window[0] > max(width, depth):
        raise ConfigError(
            f"config error: trees.window={list(params.window)} starts at {params.window[0]:g} "
            f"m, wider than the scene ({width:,.0f} x {depth:,.0f} m): it would find one tree "
            f"top at most; use a window of a few metres (the default is "
            f"{list(TreeParams.window)})")


def auto_resolution(density: float, params: TreeParams = TreeParams()) -> float:
    """The canopy height cell (m) for a scan of ``density`` points per m² (all points):
    the default 0.5 m, or where the points are sparser the finest cell they resolve
    (:data:`FINEST_CELL_PER_SPACING` of their spacing, rounded up to two digits): 0.75 m at
    1 point/m², 1.5 m at 0.25. Raises ConfigError when that cell is coarser than the
    smallest crown ``params`` allow: the scan is too sparse for trees."""
    if not (density > 0 and math.isfinite(density)):
        return TreeParams.resolution
    cell = max(TreeParams.resolution, _up(FINEST_CELL_PER_SPACING / math.sqrt(density)))
    if cell > coarsest_cell(params):
        raise ConfigError(
            f"config error: at {_amount(density)} points/m² the points are too sparse for "
            f"trees: the finest canopy cell they resolve ({cell:g} m, trees.resolution auto) "
            f"is coarser than the smallest crown the settings allow ({coarsest_cell(params):g} "
            "m across: trees.window and trees.crown_radius); set output.trees=false, or "
            "widen trees.window and trees.crown_radius for large crowns only")
    return cell


def coarsest_cell(params: TreeParams) -> float:
    """The coarsest canopy cell that still tells crowns apart (m): the narrowest top window
    or the smallest crown's diameter, whichever is less."""
    return min(params.window[0], 2.0 * params.crown_radius[0])


def _amount(value: float) -> str:
    """A density as text: whole numbers from 10 on, two significant digits below."""
    return f"{value:,.0f}" if value >= 10 else f"{value:.2g}"


def _up(value: float) -> float:
    """``value`` (> 0) rounded up to two significant digits."""
    step = 10.0 ** (math.floor(math.log10(value)) - 1)
    return float(f"{math.ceil(value / step - 1e-9) * step:.10g}")
