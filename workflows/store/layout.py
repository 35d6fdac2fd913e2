"""The layout of a run's store: where each scene, chunk, part and terrain model lives, the
names of the cascade's arrays and the roles of the points.

Layout::

    store.zarr/                      attrs: schema_version, layout (tiles, scenes, chunks)
      scenes/<scene>/parts/<tile>/           marker of an ingested tile: attrs done, parts
      scenes/<scene>/parts/<tile>/<chunk>/   points of one tile in one chunk (written by ingest,
          core (n, 35) u1: records of xyz f8 x 3,  removed once the chunk is assembled)
              gid i8, label i2, role i1 (+ return_number, number_of_returns u1 with
              features.echoes)
          halo (m, 32) u1: records of xyz f8 x 3, gid i8 (+ the same two)
      scenes/<scene>/chunks/<chunk>/         one chunk
          points/   pack: xyz, gid, label, role (core points sorted by global id),
                          halo_xyz, halo_gid (halo copies sorted by global id); with
                          features.echoes also return_number, number_of_returns (u1) and
                          halo_return_number, halo_number_of_returns
          features/ pack: features (n, d) f4, the feature set's columns; undefined (n,)
                          bool, the points whose features are not; with
                          terrain.ground_tolerance also on_ground (n,) bool, the points
                          the ground rule takes, read by every stage
          terrain/  pack: minima_keys (k, 2) i8, minima_z (k,) f8: the lowest core point
                          of each terrain cell (pipeline.terrain.cell_minima)
          stage<t>_context (n, 2C) f4, stage<t>_proba (n, C) f4     (t = 1, 2, ...)
        attrs: done = {step: fingerprint}, results, assembled, arrays = {array: pack}
      scenes/<scene>/borders/<fingerprint>/<chunk>/   scratch of the one pass, removed when
          band/     pack: gid, features     it ends: the features of a chunk's rows by the
                                            borders of the chunks still to come
                                            (workflows.steps.borders)
      scenes/<scene>/terrain/        the scene's terrain model: blocks (B, 2) i8, the occupied
        blocks of its grid; attrs cell, size, buffer, reach, done = {"terrain": fingerprint},
        interpolated (the share of the cells with points where no ground was seen)
      scenes/<scene>/terrain/blocks/<bx>_<by>/   one block's model (its to_arrays)
      scenes/<scene>/trees/          the scene's trees, laid out the same way
        (scene models: :mod:`workflows.store.models`)

A thinned copy of a training scene (``data.densities``) is a scene of its own,
``<scene>@<density>ppm`` (:func:`copy_scene`), laid out as every scene: its parts hold the
kept points of the same tiles, under the same keys and global ids.

The arrays are written and read by :mod:`pipeline.store` (packs, appended record arrays,
checksums); which groups are done, by :mod:`workflows.store.marks`.
"""

#: Point roles: what a point is used for.
ROLE_TRAIN, ROLE_TEST, ROLE_PREDICT = 0, 1, 2

#: The arrays of a chunk's ``points`` pack, assembled from the parts, and their empty forms.
CORE = ("xyz", "gid", "label", "role")
HALO = ("xyz", "gid")
#: Each point's LAS return number and number of returns (uint8), stored beside the core and
#: halo arrays when the features use them (``features.echoes``).
RETURNS = ("return_number", "number_of_returns")
POINTS = "points"
POINT_ARRAYS = (CORE + tuple(f"halo_{name}" for name in HALO) + RETURNS
                + tuple(f"halo_{name}" for name in RETURNS))  # the members of the pack


#: Between a scene's name and the density of a thinned copy of it.
COPY_MARK = "@"


def copy_scene(scene: str, density: float) -> str:
    """The name of the copy of ``scene`` thinned to ``density`` points per m²:
    ``train@5ppm``."""
    return f"{scene}{COPY_MARK}{density:g}ppm"


def is_copy(scene: str) -> bool:
    """Whether ``scene`` is a thinned copy of another (:func:`copy_scene`)."""
    return COPY_MARK in scene


def chunk_path(scene: str, chunk_name: str) -> str:
    return f"scenes/{scene}/chunks/{chunk_name}"


def unit_path(scene: str, key) -> str:
    """The marker of an ingest read unit (a tile, a group's first tile, "i.k" a range of
    tile i), which holds its parts."""
    return f"scenes/{scene}/parts/{key}"


def part_path(scene: str, tile_index: int, chunk_name: str) -> str:
    return f"{unit_path(scene, tile_index)}/{chunk_name}"


#: The chunk's core points on seen ground of the terrain model (the ground rule,
#: ``terrain.ground_tolerance``): computed once with the features, read by every stage.
ON_GROUND = "on_ground"


def proba_array(stage: int) -> str:
    """Name of the probabilities array of cascade stage ``stage`` (0-based; named from 1)."""
    return f"stage{stage + 1}_proba"


def labels_array(stage: int) -> str:
    """Name of the predicted labels of cascade stage ``stage`` where its probabilities are
    not kept (the earlier stages of a chunk classified in one pass)."""
    return f"stage{stage + 1}_labels"


def context_array(stage: int) -> str:
    """Name of the context array that feeds cascade stage ``stage`` (0-based; named from 1)."""
    return f"stage{stage + 1}_context"
