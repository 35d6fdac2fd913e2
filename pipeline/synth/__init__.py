"""Labelled synthetic forest plots, scanned by a simulated terrestrial laser scanner.

A plot is a square of forest floor with the classes of the 3DForest benchmark:

- ``terrain``: a sloping surface with undulations, micro-relief and centimetre roughness;
- ``tree``: stems of 8-25 m with a butt flare and taper, branches (and, on broadleaves,
  second-order branches), foliage as scattered clusters in conical or ellipsoidal crowns;
- ``dead_wood``: lying logs (with branch stubs) and thin fallen branches in contact with the
  ground, and snags (broken standing stems with a jagged top and no crown);
- ``misc``: shrubs (scattered blobs near the ground) and half-buried bumpy rocks.

Every surface is first sampled uniformly at ``BASE_DENSITY`` points per square metre (foliage
at an equivalent density), then "scanned" from a few scanner positions: a sample is kept with
a probability that falls as 1/r^2 beyond ``FULL_DENSITY_RANGE`` (summed over the nearest
scanners, capped at 1), samples hidden behind a standing stem from the scanner that recorded
them are dropped, and range noise is added along the beam. Everything is vectorised per
object; one :class:`numpy.random.Generator`, seeded once, draws everything in a fixed order,
so the same seed gives the same points and labels bit for bit.

A :class:`~pipeline.synth.params.Stand` makes the stand closer to real ones: crowns that touch
and interlock, suppressed trees under dominant crowns, stems leaning a few degrees
(:data:`REAL_STAND` has all three); the default stand is the plain plot, bit for bit.
The truth table marks the trees standing outside the plot whose crowns reach in
(:mod:`~pipeline.synth.truth`).

Coordinates are put at UTM-like positions (``DEFAULT_ORIGIN``) so that code reading the plot
meets coordinates in the millions, as with real survey tiles.

Modules: :mod:`~pipeline.synth.params` (the numbers), :mod:`~pipeline.synth.terrain`,
:mod:`~pipeline.synth.layout` (where objects stand), :mod:`~pipeline.synth.primitives` and
:mod:`~pipeline.synth.surfaces` (uniform samples), :mod:`~pipeline.synth.scanner` (thinning,
occlusion, noise), :mod:`~pipeline.synth.scene` (one plot from a seed) and
:mod:`~pipeline.synth.tiles` (LAZ tiles).
"""

from pipeline.synth.layout import Stem
from pipeline.synth.params import (
    CRS_WKT,
    DEFAULT_ORIGIN,
    DEFAULT_SIZE,
    DEFAULT_TILE_SIZE,
    MAX_SIZE,
    MIN_SIZE,
    REAL_STAND,
    SYNTH_CLASSES,
    Stand,
)
from pipeline.synth.scene import SynthScene, synthetic_plot, synthetic_scene
from pipeline.synth.terrain import Terrain
from pipeline.synth.tiles import write_synthetic_plot

__all__ = [
    "CRS_WKT",
    "DEFAULT_ORIGIN",
    "DEFAULT_SIZE",
    "DEFAULT_TILE_SIZE",
    "MAX_SIZE",
    "MIN_SIZE",
    "REAL_STAND",
    "SYNTH_CLASSES",
    "Stand",
    "Stem",
    "SynthScene",
    "Terrain",
    "synthetic_plot",
    "synthetic_scene",
    "write_synthetic_plot",
]
