"""One synthetic plot generated from a seed: checked arguments, layout, surfaces, scan."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from pipeline.checks import finite_number
from pipeline.errors import ConfigError
from pipeline.synth.layout import random_layout
from pipeline.synth.params import (
    DEFAULT_ORIGIN,
    DEFAULT_SIZE,
    MAX_LEAN,
    MAX_SIZE,
    MAX_SLOPE,
    MIN_SIZE,
    Stand,
)
from pipeline.synth.scanner import scan
from pipeline.synth.surfaces import sample_surfaces
from pipeline.synth.terrain import Terrain
from pipeline.synth.truth import tree_truth

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SynthScene:
    """A scanned synthetic plot with what generated it.

    ``xyz`` is (N, 3) float64 in the projected CRS, ``labels`` (N,) uint8 LAS codes from
    :data:`SYNTH_CLASSES`, ``scanners`` (K, 3) float64 the scan positions (same CRS),
    ``stems`` (M, 4) float64 the standing stems (trees and snags, also those just outside the
    plot): x, y, z of the axis at its base and the radius 1.3 m above it. ``tree_ids`` (N,)
    uint32 is the living tree each point belongs to (0: terrain, dead wood including snags,
    shrubs, rocks) and ``trees`` their truth (:data:`~pipeline.synth.truth.TRUTH_DTYPE`, one
    row per ID found in ``tree_ids``).
    """

    xyz: np.ndarray
    labels: np.ndarray
    scanners: np.ndarray
    stems: np.ndarray
    terrain: Terrain
    origin: tuple[float, float, float]
    size: float
    seed: int
    tree_ids: np.ndarray
    trees: np.ndarray

    def ground_height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """True ground height (CRS metres) under CRS coordinates ``x``, ``y`` (same shape)."""
        ox, oy, oz = self.origin
        return self.terrain.height(np.asarray(x) - ox, np.asarray(y) - oy) + oz


def synthetic_scene(
    seed: int = 0, size: float = DEFAULT_SIZE, *, origin=DEFAULT_ORIGIN, stand: Stand = Stand()
) -> SynthScene:
    """Generate a labelled synthetic forest plot of ``size`` x ``size`` metres.

    The plot covers [origin_x, origin_x + size) x [origin_y, origin_y + size); the ground is
    near ``origin_z``. About 220 points per m^2 of plot (200,000 at the default 30 m).
    Same ``seed``, same points and labels; a different seed gives a different plot.
    ``stand`` (:class:`~pipeline.synth.params.Stand`) adds touching crowns, suppressed trees
    and leaning stems; the default adds none and changes nothing.
    """
    seed, size, origin = check_plot_args(seed, size, origin)
    stand = check_stand(stand)
    xyz, labels, ids, order, layout, shares = scanned_plot(seed, size, stand)
    xyz = xyz[order]
    xyz += np.asarray(origin)
    labels = labels[order]
    ids = ids[order]
    return SynthScene(
        xyz=xyz,
        labels=labels,
        scanners=layout.scanners + np.asarray(origin),
        stems=np.array([np.r_[s.base + origin, s.radius(1.3)] for s in layout.occluders]
                       ).reshape(-1, 4),
        terrain=layout.terrain,
        origin=origin,
        size=size,
        seed=seed,
        tree_ids=ids,
        trees=tree_truth(layout, origin, np.unique(ids[ids > 0]), shares),
    )


def scanned_plot(seed: int, size: float, stand: Stand = Stand()):
    """The scanned points of a plot before they are shuffled, and the shuffle.

    Returns xyz (N, 3) float64 in the local frame, labels (N,) uint8, tree IDs (N,) uint32,
    ``order`` (N,) int64 (the plot's points are ``xyz[order] + origin``, ``labels[order]``: no
    spatial or per-class order in the output), the :class:`~pipeline.synth.layout.Layout` and
    each tree's share of its surface inside the plot (a dict by tree ID).
    Arguments are trusted (see :func:`check_plot_args`). Memory: about 41 bytes per point.
    """
    rng = np.random.default_rng(seed)
    layout = random_layout(rng, size, stand)
    shares = {}
    parts = sample_surfaces(rng, layout, shares)
    xyz, labels, ids, _ = scan(rng, parts, layout)
    order = rng.permutation(len(xyz))
    log.debug("synthetic plot seed=%d size=%.1f m: %d points", seed, size, len(xyz))
    return xyz, labels, ids, order, layout, shares


def synthetic_plot(
    seed: int = 0, size: float = DEFAULT_SIZE, *, origin=DEFAULT_ORIGIN, stand: Stand = Stand()
) -> tuple[np.ndarray, np.ndarray]:
    """Points and labels of :func:`synthetic_scene`: xyz (N, 3) float64, labels (N,) uint8."""
    scene = synthetic_scene(seed, size, origin=origin, stand=stand)
    return scene.xyz, scene.labels


def check_stand(stand) -> Stand:
    """``stand`` checked: a :class:`Stand` whose shares are in 0-1, lean in 0-MAX_LEAN,
    slope in 0-MAX_SLOPE and ridge a bool."""
    if not isinstance(stand, Stand):
        raise ConfigError(f"stand must be a pipeline.synth.Stand, got {stand!r}")
    if not isinstance(stand.ridge, (bool, np.bool_)):
        raise ConfigError(f"stand.ridge must be true or false, got {stand.ridge!r}")
    limits = {"touching": 1.0, "suppressed": 1.0, "lean": MAX_LEAN, "slope": MAX_SLOPE}
    for name, top in limits.items():
        value = getattr(stand, name)
        try:
            ok = math.isfinite(float(value)) and 0.0 <= float(value) <= top
        except (TypeError, ValueError):
            ok = False
        if not ok:
            unit = " degrees" if name in ("lean", "slope") else ""
            raise ConfigError(f"stand.{name} must be a number from 0 to {top:g}{unit}, got "
                              f"{value!r}")
    return stand


def check_plot_args(seed, size, origin) -> tuple[int, float, tuple[float, float, float]]:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"seed must be a non-negative integer, got {seed!r}")
    size = finite_number(size, "size", hint="the plot's side in metres")
    if not MIN_SIZE <= size <= MAX_SIZE:
        raise ConfigError(
            f"size must be between {MIN_SIZE:g} and {MAX_SIZE:g} metres, got {size:g}; "
            "write several plots with different seeds for more data"
        )
    try:
        origin = tuple(float(v) for v in origin)
    except (TypeError, ValueError):
        raise ConfigError(f"origin must be three numbers (x, y, z), got {origin!r}") from None
    if len(origin) != 3 or not all(math.isfinite(v) for v in origin):
        raise ConfigError(f"origin must be three finite numbers (x, y, z), got {origin!r}")
    return int(seed), size, origin
