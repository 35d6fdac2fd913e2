"""The ground of a plot: a sloping surface with random undulations, and its samples."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.synth.params import BATCH


@dataclass(frozen=True)
class Terrain:
    """Ground height as a smooth function of local (x, y): a plane plus random sinusoids.

    ``waves`` is (M, 4) float64: wave-vector x, wave-vector y (radians per metre), phase,
    amplitude (metres). ``crest``: None for a plane; else the ground is a ridge, two faces
    falling at the plane's grade on either side of the line where the plane's height is
    ``crest`` (a plane folded down along it).
    """

    slope: np.ndarray  # (2,) dz/dx, dz/dy
    waves: np.ndarray
    crest: float | None = None

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Ground height (metres, local frame) at local coordinates ``x``, ``y`` (same shape)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        z = self.slope[0] * x + self.slope[1] * y
        if self.crest is not None:
            z = -np.abs(z - self.crest)
        for kx, ky, phase, amp in self.waves:
            z = z + amp * np.sin(kx * x + ky * y + phase)
        return z


def random_terrain(rng: np.random.Generator, size: float, slope: float = 0.0,
                   ridge: bool = False) -> Terrain:
    """A plot's ground: a 3-18 % grade in a random direction, or a hillside of ``slope``
    degrees (> 0) in one; with ``ridge``, folded into a ridge along the plot's middle. The
    draws are the same whatever ``slope`` and ``ridge``: only the heights change."""
    grade = rng.uniform(0.03, 0.18)  # a 3-18 % slope in a random direction
    aspect = rng.uniform(0, 2 * np.pi)
    if slope > 0:
        grade = math.tan(math.radians(slope))
    gradient = grade * np.array([np.cos(aspect), np.sin(aspect)])
    # (count, wavelength range in m, amplitude per metre of wavelength):
    # undulations, micro-relief (hummocks, pits), centimetre roughness.
    bands = ((6, (6.0, 30.0), 0.02), (8, (1.0, 4.0), 0.012), (6, (0.25, 0.8), 0.015))
    waves = []
    for count, (lo, hi), amp_per_m in bands:
        wavelength = np.exp(rng.uniform(np.log(lo), np.log(hi), count))
        direction = rng.uniform(0, 2 * np.pi, count)
        k = 2 * np.pi / wavelength
        waves.append(
            np.c_[
                k * np.cos(direction),
                k * np.sin(direction),
                rng.uniform(0, 2 * np.pi, count),
                amp_per_m * wavelength * rng.uniform(0.5, 1.0, count),
            ]
        )
    crest = float(gradient @ np.array([size / 2, size / 2])) if ridge else None
    return Terrain(slope=gradient, waves=np.concatenate(waves), crest=crest)


def terrain_surface(rng, terrain: Terrain, size: float, density: float):
    """Ground samples in strips (bounded memory), yielding (n, 3) arrays."""
    n_strips = max(1, math.ceil(density * size * size / BATCH))
    edges = np.linspace(0.0, size, n_strips + 1)
    for y0, y1 in zip(edges[:-1], edges[1:]):
        n = rng.poisson(density * size * (y1 - y0))
        x = rng.uniform(0.0, size, n)
        y = rng.uniform(y0, y1, n)
        # Litter and moss: a centimetre of roughness on top of the smooth relief.
        z = terrain.height(x, y) + rng.normal(0.0, 0.008, n)
        yield np.c_[x, y, z]
