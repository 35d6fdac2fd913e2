"""Groups of input tiles read by one task: many small tiles cost about what one tile of all
their points costs."""

import numpy as np

#: Small tiles are grouped up to this share of a chunk's target points: a chunk then draws
#: on a few groups' parts, and a group writes the few chunks around its own.
GROUP_SHARE = 1 / 4


def group_tiles(n_points, keys, budget: int) -> list[list[int]]:
    """The tiles (positions in ``n_points``) each task reads, in groups.

    Tiles with the same key (the chunk holding a tile's centre) are taken in order and
    packed greedily: a group is closed when the next tile would take it above ``budget``
    points. A tile of ``budget`` points or more is a group of its own, so large tiles are
    read one per task as before. Groups are listed by their first tile, tiles in order
    within a group.

    Parameters
    ----------
    n_points : array_like of int, shape (n,)
        Points of each tile (from its header), >= 0.
    keys : array_like of int, shape (n,)
        The group key of each tile: only tiles of one key share a group.
    budget : int
        Points a group of several tiles holds at most, >= 1.

    Raises
    ------
    ValueError
        ``budget`` below 1, or ``n_points`` and ``keys`` of different lengths.
    """
    n_points = np.asarray(n_points, dtype=np.int64).reshape(-1)
    keys = np.asarray(keys, dtype=np.int64).reshape(-1)
    if len(keys) != len(n_points):
        raise ValueError(f"keys has {len(keys)} entries for {len(n_points)} tiles; give one "
                         "key per tile")
    if not budget >= 1:
        raise ValueError(f"budget must be an integer >= 1, got {budget!r}")
    groups: list[list[int]] = []
    open_group: dict[int, tuple[list[int], int]] = {}  # key -> (group, its points)
    for tile, (n, key) in enumerate(zip(n_points.tolist(), keys.tolist())):
        if n >= budget:
            groups.append([tile])
            continue
        members, held = open_group.get(key, (None, 0))
        if members is None or held + n > budget:
            members, held = [], 0
            groups.append(members)
        members.append(tile)
        open_group[key] = (members, held + n)
    return groups
