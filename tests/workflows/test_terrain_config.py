"""The terrain and raster keys of the configuration: validation, defaults, fingerprints."""

import pytest

from pipeline.errors import ConfigError
from workflows.config import load_config
from workflows.steps.table import STEPS as TABLE

STEPS, fingerprint = TABLE.fingerprinted, TABLE.fingerprint

FOREST = "configs/forest.yaml"


def load(*overrides):
    from pathlib import Path

    return load_config(Path(__file__).resolve().parents[2] / FOREST, overrides=list(overrides))


@pytest.mark.parametrize("override, message", [
    ("output.rasters=[dtm,foo]", "output.rasters[1] must be 'dtm', 'dsm' or 'chm'"),
    ("output.canopy_classes=[bush]", "output.canopy_classes: 'bush' is not a class"),
    ("terrain.window=0.5", "terrain.window (0.5 m) must be at least terrain.cell (1.0 m)"),
    ("terrain.slope=0", "terrain.slope"),
    ("output.raster_resolution=-1", "output.raster_resolution"),
])
def test_bad_terrain_and_raster_keys_are_one_line_naming_the_key(override, message):
    with pytest.raises(ConfigError) as err:
        load(override)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_canopy_classes_default_to_the_vegetation_codes_else_all_but_ground():
    assert load().canopy_classes == [1]  # tree: codes 4, 5
    assert load("output.canopy_classes=[tree,misc]").canopy_classes == [1, 3]
    urban = load("data.classes={ground: [2], building: [6], other: [1]}", "data.background=[]")
    assert urban.canopy_classes == [1, 2]  # no vegetation class: every class but ground


def test_a_tree_may_hold_every_class_but_ground_buildings_noise_and_water():
    # forest.yaml: terrain [2], tree [4, 5], dead_wood [64], misc [1]
    assert load().tree_point_classes == [1, 2, 3]
    assert load().stem_classes == [1, 2, 3]  # a stem called dead wood is still found
    assert load("trees.stem_classes=[tree]").stem_classes == [1]
    urban = load("data.classes={ground: [2], building: [6], other: [1], water: [9]}",
                 "data.background=[]")
    assert urban.tree_point_classes == [2]


def test_terrain_keys_change_every_step_but_ingest():
    resolved = ("features.r1=1", "features.voxel=0.2", "features.echoes=false")
    base = load(*resolved)
    changed = load(*resolved, "terrain.cell=2")
    differ = {step for step in STEPS if fingerprint(base, step) != fingerprint(changed, step)}
    assert differ == set(STEPS) - {"ingest"}
    rasters = load(*resolved, "output.rasters=[chm]")
    assert {step for step in STEPS if fingerprint(base, step) != fingerprint(rasters, step)} \
        == {"export"}
