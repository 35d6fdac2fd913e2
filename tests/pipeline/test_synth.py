"""The synthetic forest plot: determinism, content, TLS-like sampling and the LAZ tiles."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from pipeline.errors import ConfigError
from pipeline.synth import (
    CRS_WKT,
    DEFAULT_ORIGIN,
    DEFAULT_SIZE,
    REAL_STAND,
    SYNTH_CLASSES,
    Stand,
    Stem,
    synthetic_plot,
    synthetic_scene,
    write_synthetic_plot,
)
from pipeline.synth.layout import random_layout
from pipeline.synth.scanner import occluded

TERRAIN, TREE = SYNTH_CLASSES["terrain"], SYNTH_CLASSES["tree"]
DEAD_WOOD, MISC = SYNTH_CLASSES["dead_wood"], SYNTH_CLASSES["misc"]


@pytest.fixture(scope="module")
def scene():
    """The default plot (seed 0, DEFAULT_SIZE)."""
    return synthetic_scene(0)


@pytest.fixture(scope="module")
def height(scene):
    """Height of every point above the true ground (m)."""
    xyz = scene.xyz
    return xyz[:, 2] - scene.ground_height(xyz[:, 0], xyz[:, 1])


def test_same_seed_same_plot_different_seed_different_plot():
    xyz, labels = synthetic_plot(seed=5, size=12.0)
    again_xyz, again_labels = synthetic_plot(seed=5, size=12.0)
    assert np.array_equal(xyz, again_xyz)
    assert np.array_equal(labels, again_labels)
    other_xyz, _ = synthetic_plot(seed=6, size=12.0)
    assert other_xyz.shape != xyz.shape or not np.allclose(other_xyz, xyz)
    # Not merely a permutation: the point sets differ.
    assert not np.allclose(np.sort(other_xyz[:, 2])[:1000], np.sort(xyz[:, 2])[:1000])


def test_types_coordinates_and_point_budget(scene):
    xyz, labels = scene.xyz, scene.labels
    assert xyz.dtype == np.float64 and xyz.shape[1] == 3
    assert labels.dtype == np.uint8 and labels.shape == (len(xyz),)
    assert 150_000 <= len(xyz) <= 250_000
    assert set(np.unique(labels)) == set(SYNTH_CLASSES.values())
    # Inside the half-open square at UTM-like coordinates, ground near the origin's z.
    local = xyz[:, :2] - np.asarray(DEFAULT_ORIGIN[:2])
    assert local.min() >= 0.0 and local.max() < DEFAULT_SIZE
    assert np.ptp(local[:, 0]) > 0.95 * DEFAULT_SIZE and np.ptp(local[:, 1]) > 0.95 * DEFAULT_SIZE
    assert abs(np.median(xyz[labels == TERRAIN, 2]) - DEFAULT_ORIGIN[2]) < 5.0


@pytest.mark.parametrize("seed, size", [(0, DEFAULT_SIZE), (1, 14.0), (2, 14.0), (3, 8.0)])
def test_every_class_with_plausible_shares(seed, size):
    _, labels = synthetic_plot(seed, size)
    share = {name: np.mean(labels == code) for name, code in SYNTH_CLASSES.items()}
    assert 0.2 <= share["terrain"] <= 0.7, share
    assert 0.2 <= share["tree"] <= 0.7, share
    assert 0.01 <= share["dead_wood"] <= 0.15, share
    assert 0.01 <= share["misc"] <= 0.15, share


def test_terrain_is_the_lowest_surface(scene, height):
    labels = scene.labels
    local = scene.xyz[:, :2] - np.asarray(scene.origin[:2])
    cell = np.floor(local[:, 0]).astype(np.int64) * 1000 + np.floor(local[:, 1]).astype(np.int64)
    order = np.lexsort((scene.xyz[:, 2], cell))
    lowest = order[np.r_[True, np.diff(cell[order]) != 0]]  # lowest point of each 1 m cell
    assert len(lowest) > 0.95 * DEFAULT_SIZE**2
    assert np.mean(labels[lowest] == TERRAIN) > 0.95
    # Terrain points lie on the ground (roughness and noise of a few cm only) ...
    assert np.percentile(np.abs(height[labels == TERRAIN]), 99) < 0.05
    # ... and the ground is uneven: a slope or relief of more than a metre over the plot.
    assert np.ptp(scene.xyz[labels == TERRAIN, 2]) > 1.0


def test_trees_are_tall_and_dead_wood_and_misc_lie_low(scene, height):
    labels = scene.labels
    tree_h = height[labels == TREE]
    assert tree_h.max() > 15.0
    assert np.mean(tree_h > 8.0) > 0.2  # crowns, not only stems and low branches
    dead_h = height[labels == DEAD_WOOD]
    assert np.mean(dead_h < 2.0) > 0.8  # logs and fallen branches; snags are the rest
    assert dead_h.max() < 6.0
    assert np.mean(dead_h < 0.1) > 0.02  # lying wood in contact with the ground
    assert np.percentile(height[labels == MISC], 99) < 3.0
    # Nothing but noise below the ground.
    assert np.percentile(height[labels != TERRAIN], 0.1) > -0.05


def test_density_falls_with_distance_from_the_scanners(scene):
    terrain = scene.xyz[scene.labels == TERRAIN]
    dist = cKDTree(scene.scanners[:, :2]).query(terrain[:, :2])[0]
    near = np.sum(dist < 2.0) / (len(scene.scanners) * np.pi * 2.0**2)
    # Area farther than 10 m from every scanner, on a fine grid of the plot.
    step = 0.1
    g = np.arange(step / 2, scene.size, step)
    grid = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2) + np.asarray(scene.origin[:2])
    far_area = np.mean(cKDTree(scene.scanners[:, :2]).query(grid)[0] > 10.0) * scene.size**2
    assert far_area > 10.0
    far = np.sum(dist > 10.0) / far_area
    assert near > 2.5 * far, (near, far)
    assert near < 3000.0  # capped like a real TLS point cloud
    assert far > 15.0  # still enough points for 0.5 m neighbourhoods


def test_scanners_are_inside_the_plot_above_the_ground(scene):
    sc = scene.scanners
    assert 3 <= len(sc) <= 5
    local = sc[:, :2] - np.asarray(scene.origin[:2])
    assert np.all((local > 0) & (local < scene.size))
    above = sc[:, 2] - scene.ground_height(sc[:, 0], sc[:, 1])
    assert np.allclose(above, 1.5)


def test_stem_hides_what_is_behind_it():
    stem = Stem(base=np.array([5.0, 0.0, 0.0]), lean=np.zeros(2),
                knots_z=np.array([0.0, 10.0]), knots_r=np.array([0.3, 0.3]))
    scanner = np.array([0.0, 0.0, 1.5])
    points = np.array([
        [10.0, 0.0, 0.0],  # behind the stem
        [10.0, 3.0, 0.0],  # beside it
        [4.71, 0.0, 1.5],  # its near side
        [5.29, 0.0, 1.5],  # its far side
        [10.0, 0.0, 30.0],  # behind, but the ray passes over the top
        [3.0, 0.0, 0.0],  # between scanner and stem
        [-10.0, 0.0, 0.0],  # the other way
    ])
    assert occluded(scanner, points, stem).tolist() == [
        True, False, False, True, False, False, False]


def test_stems_cast_shadows_on_the_ground(scene):
    """Ground 1 m behind a stem, on the ray from its nearest scanner, is sparser than ground
    at the same range 1 m to either side (other scans fill the shadow only in part)."""
    terrain = cKDTree(scene.xyz[scene.labels == TERRAIN][:, :2])
    behind = beside = 0.0
    for x, y, _, _ in scene.stems:
        dist = np.linalg.norm(scene.scanners[:, :2] - [x, y], axis=1)
        k = int(np.argmin(dist))
        if not 2.0 < dist[k] < 7.0:
            continue
        scanner = scene.scanners[k, :2]
        u = ([x, y] - scanner) / dist[k]
        reach = dist[k] + 1.0
        behind += len(terrain.query_ball_point(scanner + reach * u, 0.2))
        for angle in (-1.0 / reach, 1.0 / reach):
            c, s = np.cos(angle), np.sin(angle)
            side = scanner + reach * np.array([c * u[0] - s * u[1], s * u[0] + c * u[1]])
            beside += len(terrain.query_ball_point(side, 0.2)) / 2
    assert beside > 50
    assert behind < 0.6 * beside, (behind, beside)


@pytest.mark.parametrize("kwargs, name", [
    ({"size": -1.0}, "size"), ({"size": 2.0}, "size"), ({"size": float("nan")}, "size"),
    ({"seed": -1}, "seed"), ({"seed": 1.5}, "seed"), ({"origin": (0.0, 1.0)}, "origin"),
])
def test_invalid_arguments_are_refused(kwargs, name):
    with pytest.raises(ConfigError, match=name):
        synthetic_plot(**kwargs)


def test_tiles_hold_every_point_once(tmp_path):
    from pipeline.io import read_info, read_points

    seed, size, tile = 4, 12.0, 5.0
    xyz, labels = synthetic_plot(seed, size)
    paths = write_synthetic_plot(tmp_path / "plot", seed=seed, size=size, tile_size=tile)
    assert [p.name for p in paths] == [f"plot_s{seed}_{ix}_{iy}.laz"
                                       for ix in range(3) for iy in range(3)]
    got_xyz, got_labels, lengths = [], [], []
    for path in paths:
        info = read_info(path)
        assert path.suffix == ".laz" and info.version == "1.4" and info.point_format == 6
        assert info.scale == pytest.approx((0.001, 0.001, 0.001))
        assert info.crs_wkt is not None and "25832" in info.crs_wkt
        assert info.crs_wkt.replace(" ", "") == CRS_WKT.replace(" ", "")
        batch = read_points(path, fields=("classification",))
        ix, iy = (int(v) for v in path.stem.split("_")[-2:])
        corner = np.asarray(DEFAULT_ORIGIN[:2]) + tile * np.array([ix, iy])
        local = batch.xyz[:, :2] - corner
        assert local.min() >= -0.0005 and local.max() <= tile + 0.0005  # its own cell
        got_xyz.append(batch.xyz)
        got_labels.append(batch.fields["classification"])
        lengths.append(len(batch.xyz))
    got_xyz, got_labels = np.concatenate(got_xyz), np.concatenate(got_labels)
    assert len(got_xyz) == len(xyz)
    # A one-to-one match within half a millimetre per axis, with the same labels.
    dist, idx = cKDTree(xyz).query(got_xyz)
    assert dist.max() <= 0.0005 * np.sqrt(3) + 1e-9
    assert len(np.unique(idx)) == len(xyz)
    assert np.array_equal(got_labels, labels[idx])
    # each tile holds its points in the plot's order (tiles are cut from the one plot)
    assert all(np.all(np.diff(part) > 0) for part in np.split(idx, np.cumsum(lengths)[:-1]))
    with open(paths[0], "rb") as f:
        assert f.read(4) == b"LASF"


def test_writing_again_overwrites_and_another_tiling_is_refused(tmp_path):
    first = write_synthetic_plot(tmp_path, seed=7, size=8.0, tile_size=4.0)
    again = write_synthetic_plot(tmp_path, seed=7, size=8.0, tile_size=4.0)
    assert first == again
    assert sorted(tmp_path.glob("*.laz")) == sorted(first)
    with pytest.raises(ConfigError, match="another tiling"):
        write_synthetic_plot(tmp_path, seed=7, size=8.0, tile_size=8.0)
    with pytest.raises(ConfigError, match="tile_size"):
        write_synthetic_plot(tmp_path / "x", seed=7, size=8.0, tile_size=0.0)


def test_every_tree_point_and_only_those_carry_a_tree_id(scene):
    is_tree = scene.labels == TREE
    assert scene.tree_ids.dtype == np.uint32 and scene.tree_ids.shape == scene.labels.shape
    assert np.all(scene.tree_ids[is_tree] > 0)
    assert np.all(scene.tree_ids[~is_tree] == 0)  # snags are dead wood, in no tree
    assert np.array_equal(np.unique(scene.tree_ids[is_tree]), scene.trees["tree_id"])
    assert len(scene.trees) >= 5


def test_true_dbh_is_the_bark_circle_at_breast_height(scene):
    """Each tree's DBH equals the circle fitted to its bark points 1.15-1.45 m above the
    ground under its base (a least-squares circle, independent of the stem model)."""
    checked = 0
    for tree in scene.trees:
        xyz = scene.xyz[scene.tree_ids == tree["tree_id"]]
        rel = xyz[:, 2] - (tree["z"] - tree["height"])  # above the ground under the stem
        near = np.hypot(xyz[:, 0] - tree["x"], xyz[:, 1] - tree["y"]) < tree["dbh"]
        ring = xyz[(np.abs(rel - 1.3) < 0.15) & near, :2] - [tree["x"], tree["y"]]
        if len(ring) < 20:
            continue  # a tree standing outside the plot shows only its crown
        # x^2 + y^2 = 2 a x + 2 b y + c, r^2 = c + a^2 + b^2
        design = np.column_stack((2 * ring, np.ones(len(ring))))
        (a, b, c), *_ = np.linalg.lstsq(design, (ring**2).sum(axis=1), rcond=None)
        assert np.sqrt(c + a * a + b * b) * 2 == pytest.approx(tree["dbh"], abs=0.006)
        assert tree["height"] > 7.5 and tree["dbh"] < 0.5
        checked += 1
    assert checked >= 5


def test_a_trees_z_is_its_tops_elevation_as_in_silvas_tree_tables(scene):
    """z is the elevation of the tree's top (as the trees tables give it: their z is the
    highest point's), z - height the ground under its stem."""
    gaps = []
    for tree in scene.trees:
        top = scene.xyz[scene.tree_ids == tree["tree_id"], 2].max()
        assert top <= tree["z"] + 0.3  # a twig may stand a little above the stem's apex
        gaps.append(abs(tree["z"] - top))
        ground = float(scene.ground_height(np.array([tree["x"]]), np.array([tree["y"]]))[0])
        assert tree["z"] - tree["height"] == pytest.approx(ground, abs=1e-6)
    assert np.median(gaps) < 0.3  # the scanner sees most tops


def test_trees_standing_outside_the_plot_are_marked_with_their_share_inside(scene):
    """A tree whose stem stands outside the plot has ``inside`` 0 and only part of its
    surface in the plot; one standing inside has ``inside`` 1 and most of it there. The share
    follows the points: a tree with little of its surface inside has few points."""
    trees = scene.trees
    ox, oy, _ = scene.origin
    stands_in = ((trees["x"] >= ox) & (trees["x"] < ox + scene.size)
                 & (trees["y"] >= oy) & (trees["y"] < oy + scene.size))
    assert np.array_equal(trees["inside"], stands_in.astype(np.uint8))
    assert 0 < np.count_nonzero(~stands_in) < len(trees)  # the default plot has both kinds
    assert np.all((trees["share"] > 0) & (trees["share"] <= 1))
    assert np.all(trees["share"][~stands_in] < 1)  # a crown cut by the edge
    assert np.median(trees["share"][stands_in]) > np.median(trees["share"][~stands_in])
    counts = np.array([np.count_nonzero(scene.tree_ids == t) for t in trees["tree_id"]])
    cut = trees["share"] < 0.2
    assert counts[cut].max() < np.median(counts[~cut])


def test_tiles_carry_the_tree_ids_and_trees_csv_their_truth(tmp_path):
    from pipeline.io import read_points

    seed, size = 5, 12.0
    scene = synthetic_scene(seed, size)
    paths = write_synthetic_plot(tmp_path, seed=seed, size=size, tile_size=6.0)
    batches = [read_points(p, fields=("classification", "TreeID")) for p in paths]
    xyz = np.concatenate([b.xyz for b in batches])
    ids = np.concatenate([b.fields["TreeID"] for b in batches])
    _, idx = cKDTree(scene.xyz).query(xyz)
    assert np.array_equal(ids, scene.tree_ids[idx])
    table = np.genfromtxt(tmp_path / "trees.csv", delimiter=",", names=True)
    assert table.dtype.names == ("tree_id", "x", "y", "z", "height", "dbh", "inside", "share")
    assert np.array_equal(table["tree_id"].astype(np.uint32), np.unique(ids[ids > 0]))
    for name in table.dtype.names[1:]:
        assert np.allclose(table[name], scene.trees[name], rtol=0, atol=5.1e-5)


def test_writing_leaves_no_temporary_file_nor_a_new_folder_when_it_fails(tmp_path,
                                                                          monkeypatch):
    import pipeline.io

    write_synthetic_plot(tmp_path / "a", seed=7, size=8.0, tile_size=4.0)
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == [
        "plot_s7_0_0.laz", "plot_s7_0_1.laz", "plot_s7_1_0.laz", "plot_s7_1_1.laz", "trees.csv"]
    with pytest.raises(ConfigError, match="another tiling"):
        write_synthetic_plot(tmp_path / "a", seed=7, size=8.0, tile_size=8.0)
    assert len(list((tmp_path / "a").iterdir())) == 5  # the earlier tiles, nothing else

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(pipeline.io, "write_las", full_disk)
    with pytest.raises(OSError, match="No space"):
        write_synthetic_plot(tmp_path / "b" / "c", seed=7, size=8.0, tile_size=4.0)
    assert not (tmp_path / "b" / "c").exists()


# --- a stand closer to real ones --------------------------------------------------------------
def layout_of(seed: int, stand: Stand, size: float = DEFAULT_SIZE):
    return random_layout(np.random.default_rng(seed), size, stand)


def interlocked(trees) -> np.ndarray:
    """Whether each tree's crown reaches 5 % of the two radii into a neighbour's: (T,) bool."""
    xy = np.array([t.stem.base[:2] for t in trees])
    r = np.array([t.crown_radius for t in trees])
    d = np.linalg.norm(xy[:, None] - xy[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    return np.any(d <= 0.95 * (r[:, None] + r[None]), axis=1)


def test_the_default_stand_is_the_plain_plot(scene):
    plain = synthetic_scene(0, stand=Stand())
    assert np.array_equal(plain.xyz, scene.xyz) and np.array_equal(plain.tree_ids,
                                                                   scene.tree_ids)


def test_leaning_stems_lean_by_the_angle_asked_and_their_points_follow():
    """Every stem leans by 2.5-5 degrees, and the bark 3-6 m above the base lies on the
    leaning stem (median distance to its axis within 1 cm of the radius), not on a vertical
    one (10 cm and more off, the lean's drift there)."""
    trees = layout_of(0, Stand(lean=5.0)).trees
    angle = np.degrees(np.arctan([np.hypot(*t.stem.lean) for t in trees]))
    assert angle.min() >= 2.5 and angle.max() <= 5.0
    plain = np.degrees(np.arctan([np.hypot(*t.stem.lean) for t in layout_of(0, Stand()).trees]))
    assert np.median(plain) < 2.5 and np.median(angle) > 3.5
    scene = synthetic_scene(0, stand=Stand(lean=5.0))
    checked = 0
    for row in scene.trees[scene.trees["inside"] == 1]:
        stem = trees[row["tree_id"] - 1].stem  # IDs are 1.. in placement order
        xyz = scene.xyz[scene.tree_ids == row["tree_id"]] - (stem.base + scene.origin)
        z = xyz[:, 2]
        leaning = np.hypot(*(xyz[:, :2] - stem.lean * z[:, None]).T)
        bark = (z > 3.0) & (z < 6.0) & (leaning < stem.radius(z) + 0.05)
        if np.count_nonzero(bark) < 20:
            continue  # hidden, or a crown's branches there
        assert np.median(np.abs(leaning[bark] - stem.radius(z[bark]))) < 0.01
        vertical = np.hypot(*xyz[bark, :2].T)
        assert np.median(np.abs(vertical - stem.radius(z[bark]))) > 0.1
        checked += 1
    assert checked >= 5


def test_touching_crowns_interlock_more_often():
    plain = [interlocked(layout_of(seed, Stand()).trees).mean() for seed in range(4)]
    touching = [interlocked(layout_of(seed, Stand(touching=0.8)).trees).mean()
                for seed in range(4)]
    assert np.mean(touching) > np.mean(plain) + 0.1
    assert min(touching) > 0.7


def test_suppressed_trees_stand_under_a_dominant_crown_and_are_scanned():
    """Each suppressed tree's top is below the crown base of a tree whose crown covers its
    stem; the plain plot has none such. Their points carry their own IDs."""
    def under(trees):
        count = 0
        for t in trees:
            for other in trees:
                d = np.hypot(*(t.stem.base[:2] - other.stem.base[:2]))
                if other is not t and d < other.crown_radius and \
                        t.stem.height < other.crown_base:
                    count += 1
                    break
        return count
    plain = layout_of(1, Stand()).trees
    trees = layout_of(1, Stand(suppressed=0.3)).trees
    assert under(plain) == 0
    assert under(trees) >= 0.2 * len(plain) and len(trees) - len(plain) == under(trees)
    scene = synthetic_scene(1, stand=Stand(suppressed=0.3))
    small = scene.trees[(scene.trees["height"] < 8.0) & (scene.trees["inside"] == 1)]
    assert len(small) >= 3  # the plain plot's trees are 8-25 m
    assert all(np.count_nonzero(scene.tree_ids == i) > 200 for i in small["tree_id"])


def test_real_stand_tiles_are_the_scene(tmp_path):
    from pipeline.io import read_points

    scene = synthetic_scene(4, 12.0, stand=REAL_STAND)
    paths = write_synthetic_plot(tmp_path, seed=4, size=12.0, tile_size=6.0, stand=REAL_STAND)
    xyz = np.concatenate([read_points(p).xyz for p in paths])
    assert len(xyz) == len(scene.xyz)
    assert np.allclose(np.sort(xyz[:, 2]), np.sort(scene.xyz[:, 2]), atol=5e-4)


def _fitted_grade(terrain, size: float) -> tuple[np.ndarray, np.ndarray]:
    """The true ground's heights on a 1 m grid of the plot and its gradient there."""
    x, y = np.meshgrid(np.arange(0.5, size), np.arange(0.5, size))
    z = terrain.height(x, y)
    return z, np.hypot(*np.gradient(z, 1.0))


def test_a_hillside_slopes_at_the_angle_asked_and_a_ridge_falls_both_ways():
    """The median gradient of a 40 degree hillside is tan(40) (the undulations add a
    little); the plain plot's is a gentle grade; a ridge's highest line runs along the
    plot's middle, its edges lower on both sides; the placement draws are unchanged."""
    size = 20.0
    plain, hill, ridge = (layout_of(3, Stand(**kw), size)
                          for kw in ({}, {"slope": 40.0}, {"slope": 40.0, "ridge": True}))
    _, grade = _fitted_grade(hill.terrain, size)
    assert abs(np.median(grade) - np.tan(np.radians(40))) < 0.1
    assert np.median(_fitted_grade(plain.terrain, size)[1]) < 0.3
    z, grade = _fitted_grade(ridge.terrain, size)
    assert abs(np.median(grade) - np.tan(np.radians(40))) < 0.1
    middle = ridge.terrain.height(np.array([size / 2]), np.array([size / 2]))[0]
    assert middle > np.percentile(z, 90)
    for other in (hill, ridge):
        assert np.array_equal(other.terrain.waves, plain.terrain.waves)
        assert np.array_equal([t.stem.base[:2] for t in other.trees],
                              [t.stem.base[:2] for t in plain.trees])


@pytest.mark.parametrize("stand, name", [(Stand(touching=1.5), "stand.touching"),
                                         (Stand(suppressed=-0.1), "stand.suppressed"),
                                         (Stand(lean=20.0), "stand.lean"),
                                         (Stand(lean="a"), "stand.lean"),
                                         (Stand(slope=61.0), "stand.slope"),
                                         (Stand(ridge="yes"), "stand.ridge"),
                                         ({"lean": 5}, "stand must be")])
def test_invalid_stands_are_refused(stand, name):
    with pytest.raises(ConfigError, match=name):
        synthetic_scene(0, 8.0, stand=stand)
