"""Thinned copies of the training scene (``data.densities``): their plan and their parts.

A copy is a training scene of its own, ``train@5ppm`` (:func:`~workflows.store.layout.
copy_scene`): the points of the training tiles that :func:`~pipeline.cascade.thinning.
thinned_mask` keeps at the fraction target / the scene's density, with their global ids,
labels and roles. Ingest writes its parts in the same pass as the scene's (:class:`CopyWriter`),
under the same keys and on the same chunk grid; from there on it is a scene like any other,
with its own terrain model, features and context computed on its thinned points (a sparse
crown's neighbourhoods), and its labelled points train the forests. It is never exported,
scored or surveyed (:meth:`~workflows.store.scenes.RunLayout.without_copies`).

The scene's density is counted over all its tiles before any copy is written (ingest's
density pass, the points ingest keeps over the 2 m cells they occupy, as
:func:`~pipeline.cascade.thinning.point_density` defines it), never a chunk's; a density at
or above it makes no copy. A copy keeps a point by a hash of its global id seeded by
``cascade.seed`` (apart from the training sample's): the same points every run, whatever the
chunking, and a sparser copy is a subset of a denser one. Since a copy's points keep their
ids, a point and its copies fall in the same out-of-fold fold: no forest predicts a point
that one of its copies trained.
"""

from dataclasses import replace

from pipeline.cascade.thinning import cells_density, thinned_mask, thinning_fraction
from workflows.run.progress import say
from workflows.store.assembly import restart_unit
from workflows.store.layout import copy_scene, unit_path
from workflows.store.marks import is_done, mark_done
from workflows.store.scenes import RunLayout, SceneLayout, Thinning

#: The scene that gets thinned copies.
SOURCE = "train"


def plan_copies(scenes: dict[str, SceneLayout], densities, measure
                ) -> dict[str, SceneLayout]:
    """``scenes`` (ingest's layouts, by scene) with a thinned copy of the training scene
    after it for every density of ``densities`` (points per m², densest first) below its
    own; ``measure(scene)`` gives (points, occupied 2 m cells) of the whole scene.

    The training scene's layout records its ``density`` (``points``, ``cells``,
    ``value``); a copy's is its scene's (the same grid, halo, read units and part keys),
    stage by stage, with its :class:`~workflows.store.scenes.Thinning`. A density whose
    copy would keep about no point (fewer than half a point expected) makes none either: an
    empty scene has no terrain and trains nothing (said by :func:`copy_lines`).
    """
    if not densities or SOURCE not in scenes:
        return scenes
    points, cells = measure(SOURCE)
    density = cells_density(points, cells)
    result = {}
    for scene, info in scenes.items():
        if scene != SOURCE:
            result[scene] = info
            continue
        result[scene] = replace(info, density={"points": int(points), "cells": int(cells),
                                               "value": density})
        for target in sorted(set(map(float, densities)), reverse=True):
            if target >= density:
                continue  # a copy is never denser than its scene (said by copy_lines)
            fraction = float(thinning_fraction(density, target))
            expected = int(round(points * fraction))
            if expected == 0:
                continue  # the copy would be empty (said by copy_lines)
            result[copy_scene(scene, target)] = replace(
                info, one_pass=False, estimate=None, thinning=Thinning(
                    scene, target, fraction, expected))
    return result


def copies_of(scenes: dict[str, SceneLayout], scene: str) -> tuple[tuple[str, float], ...]:
    """(copy, fraction) of every thinned copy of ``scene`` in ``scenes``, in layout order."""
    return tuple((name, info.thinning.fraction) for name, info in scenes.items()
                 if info.thinning is not None and info.thinning.copy_of == scene)


def copy_lines(scenes: dict[str, SceneLayout], densities, seed: int,
               applies_model: bool = False) -> list[str]:
    """What ``silva plan`` and the ingest log say of the thinned copies: one line per copy
    (scene, density, fraction, expected points) and per density that makes none."""
    if not densities:
        return []
    if applies_model:
        return ["data.densities: no thinned copies: the run applies a saved model"]
    if SOURCE not in scenes:
        return [f"data.densities: no thinned copies: the run has no data.{SOURCE}"]
    density = scenes[SOURCE].density["value"]
    points = scenes[SOURCE].density["points"]
    copies = {name: info.thinning for name, info in scenes.items() if info.thinning}
    lines = [f"copy {name}: scene {copy.copy_of} ({density:,.1f} points/m² in its "
             f"occupied 2 m cells) thinned to {copy.target:g} points/m², fraction "
             f"{copy.fraction:.4f} (seed {seed}): about {copy.expected:,} points, "
             "trained on, not exported or scored"
             for name, copy in copies.items()]
    made = {copy.target for copy in copies.values()}
    lines += [no_copy_line(target, density, points)
              for target in sorted(set(map(float, densities)), reverse=True)
              if target not in made]
    return lines


def no_copy_line(target: float, density: float, points: int) -> str:
    """Why the density ``target`` of ``data.densities`` makes no copy of the training scene
    (``density`` points per m², ``points`` points)."""
    if target >= density:
        return (f"data.densities {target:g}: no copy of scene {SOURCE}, whose density is "
                f"{density:,.1f} points/m² (a copy is never denser than its scene)")
    return (f"data.densities {target:g}: no copy of scene {SOURCE}: thinned from "
            f"{density:,.1f} to {target:g} points/m², its {points:,} points would leave "
            "about none (an empty copy has no terrain and trains nothing); remove "
            f"{target:g} from data.densities or train on a larger scene")


def without_empty_copies(scenes: dict[str, SceneLayout], quiet: bool = False
                         ) -> dict[str, SceneLayout]:
    """``scenes`` (ingest's layouts, their ``chunks`` set from the points written) without
    the thinned copies in which the thinning kept no point after all (a few points
    expected, none drawn), each said in one line."""
    kept = {}
    for name, info in scenes.items():
        if info.thinning is not None and not info.chunks:
            say(f"ingest: copy {name}: the thinning kept none of the points of scene "
                f"{info.thinning.copy_of} (fraction {info.thinning.fraction:.4g}, about "
                f"{info.thinning.expected:,} expected): skipped, an empty copy has no "
                f"terrain and trains nothing; remove {info.thinning.target:g} from "
                "data.densities to silence this", quiet=quiet)
            continue
        kept[name] = info
    return kept


def trained_copies(layout: RunLayout) -> list[dict]:
    """What a model records of the copies it was trained on: each copy's scene, the scene
    it was thinned from, its density and that scene's, the fraction kept."""
    return [{"scene": name, "copy_of": info.thinning.copy_of, "density": info.thinning.target,
             "scene_density": layout.scenes[info.thinning.copy_of].density["value"],
             "fraction": info.thinning.fraction}
            for name, info in layout.scenes.items() if info.thinning is not None]


# -- ingest: the parts of the copies ------------------------------------------------------
def _marker(root, scene: str, key):
    return root.require_group(unit_path(scene, key))


def copies_done(root, key, copies, fingerprint: str) -> bool:
    """Whether the parts of read unit ``key`` are ingested in every copy of ``copies``
    ((scene, fraction) pairs)."""
    return all(is_done(_marker(root, scene, key), "ingest", fingerprint) for scene, _ in copies)


def copy_counts(root, key, copies) -> dict:
    """What an ingest task returns of its copies: {"copies": {copy: core points per chunk}}
    ({} without copies)."""
    if not copies:
        return {}
    return {"copies": {scene: dict(_marker(root, scene, key).attrs.get("core_counts", {}))
                       for scene, _ in copies}}


class CopyWriter:
    """The part writer of a read unit (``writer``, see :func:`~workflows.steps.ingest.
    ingest_tile`) that also writes each copy's kept points to that copy's parts.

    ``make_writer(marker)`` gives a part writer of a copy's marker; ``seal`` marks every
    copy done before it seals the scene's parts, whose done-mark ingest writes last: a unit
    whose scene is done has its copies.
    """

    def __init__(self, writer, root, key, copies, seed: int, fingerprint: str, make_writer):
        self.writer, self.seed, self.fingerprint = writer, seed, fingerprint
        self.copies = []
        for scene, fraction in copies:
            marker = _marker(root, scene, key)
            restart_unit(root, scene, marker)
            self.copies.append((fraction, marker, make_writer(marker)))

    @property
    def counts(self) -> dict[str, int]:
        """The scene's core points written per chunk."""
        return self.writer.counts

    def write(self, xyz, gid, *columns) -> None:
        """Append points to the scene's parts and their kept subsets to the copies'; the
        ``columns`` (labels, roles, return numbers, ...) hold one value per point."""
        self.writer.write(xyz, gid, *columns)
        for fraction, _, writer in self.copies:
            kept = thinned_mask(gid, fraction, self.seed)
            if kept.any():
                writer.write(xyz[kept], gid[kept], *(column[kept] for column in columns))

    def seal(self) -> dict[str, list[str]]:
        """Seal and mark done every copy's parts, then seal the scene's (returned)."""
        for _, marker, writer in self.copies:
            parts = writer.seal()
            mark_done(marker, "ingest", self.fingerprint, core_counts=writer.counts,
                      parts=parts)
        return self.writer.seal()


def with_copies(writer, root, key, copies, seed: int, fingerprint: str, make_writer):
    """``writer`` itself without ``copies``, else a :class:`CopyWriter` around it."""
    if not copies:
        return writer
    return CopyWriter(writer, root, key, copies, seed, fingerprint, make_writer)

