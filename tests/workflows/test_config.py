"""Configuration: defaults, validation errors naming the key, overrides, round trips, fingerprints."""

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from pipeline.errors import ConfigError, InputError, MissingFileError
from pipeline.features.density import capped_halo
from workflows.config import (
    SilvaConfig,
    dump_config,
    expand_inputs,
    load_config,
    validate_config,
)
from workflows.steps.table import STEPS as TABLE

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
CLASSES = {"terrain": [2], "tree": [5], "dead_wood": [64], "misc": [1]}
STEPS = ("ingest", "features", "stage", "export", "evaluate")
fingerprint = TABLE.fingerprint


def write(path: Path, mapping) -> Path:
    path.write_text(yaml.safe_dump(mapping, sort_keys=False))
    return path


def config_error(raw=None, overrides=(), tmp_path=None) -> str:
    """The message of the ConfigError that ``raw`` + ``overrides`` raise."""
    with pytest.raises(ConfigError) as info:
        if overrides:
            load_config(write(tmp_path / "c.yaml", raw or {}), overrides)
        else:
            validate_config(raw)
    message = str(info.value)
    assert "\n" not in message and message.startswith("config error: ")
    return message


# -- ready configs and defaults --------------------------------------------------------------
@pytest.mark.parametrize("name, feature_set, stages", [
    ("demo.yaml", "paper", 3), ("forest.yaml", "default", 2), ("oakland.yaml", "paper", 3)])
def test_ready_configs_validate(name, feature_set, stages):
    cfg = load_config(CONFIGS / name)
    assert cfg.features.set == feature_set and cfg.cascade.stages == stages
    assert load_config(CONFIGS / name) == cfg


def test_demo_config_choices():
    cfg = load_config(CONFIGS / "demo.yaml")
    assert cfg.data.train == [] and cfg.data.test == []
    assert cfg.data.classes == CLASSES and cfg.data.background == ["misc"]
    assert cfg.features.r1 == 0.5 and cfg.cascade.n_estimators == 20
    assert cfg.cascade.min_samples_leaf == 15


def test_oakland_config_uses_the_benchmark_mapping(shared_data):
    cfg = load_config(CONFIGS / "oakland.yaml")
    oakland = shared_data / "oakland"
    assert expand_inputs(cfg.data.train) == [oakland / "oakland_part3_an.xyz_label_conf"]
    assert expand_inputs(cfg.data.test) == [oakland / "oakland_part3_am.xyz_label_conf"]
    assert cfg.data.label_field == "label"
    assert cfg.data.class_names == ["vegetation", "wire", "pole", "ground", "facade"]
    assert cfg.data.code_to_class == {
        1300: 0, 1101: 1, 1102: 1, 1103: 2, 1110: 2, 1302: 2, 1303: 2,
        1200: 3, 1202: 3, 1203: 3, 1400: 4, 1401: 4,
    }


def test_defaults():
    cfg = load_config(None)
    assert cfg == SilvaConfig()
    d = cfg.model_dump()
    assert d["data"] == {"train": [], "test": [], "predict": [], "label_field": "classification",
                         "classes": {}, "ignore": [], "background": [], "split": None,
                         "exclude_codes": [], "exclude_withheld": False,
                         "drop_unlisted": False, "allow_overlap": False, "densities": []}
    assert d["tiling"] == {"chunk_size": "auto", "layout": "balanced",
                           "target_points": 1_000_000, "halo": 1.685, "read_batch": 1_000_000}
    assert d["features"] == {"set": "paper", "r1": 0.5, "r2": 0.25, "max_neighbors": 64,
                             "context_max_neighbors": None, "plane": "pca",
                             "scales": [0.5, 1.0, 2.0, 4.0], "column": 3.0, "cell": 0.5,
                                 "voxel": None, "echoes": False, "version": 2}
    assert d["cascade"] == {"stages": 3, "n_estimators": 20, "min_samples_leaf": 15,
                            "max_features": "sqrt", "context": "hard", "out_of_fold": False,
                            "folds": 5, "max_train_points": 200_000, "balanced": False,
                            "seed": 0}
    assert d["cluster"]["kind"] == "local" and d["cluster"]["n_workers"] is None
    assert d["cluster"]["memory_limit"] == "auto" and d["cluster"]["dashboard"] is True
    # unset SLURM settings are left to the site's dask-jobqueue config
    assert d["cluster"]["slurm"] == {"queue": None, "account": None, "cores": None,
                                     "processes": None, "memory": None, "walltime": None,
                                     "jobs": 2, "job_extra_directives": None,
                                     "local_directory": None}
    assert d["cluster"]["adapt"] is None
    assert d["output"] == {"format": "laz", "write_classification": False,
                           "probabilities": True, "keep_store": True, "keep_features": "auto",
                           "feature_dims": [], "point_format": "auto", "rasters": [],
                           "raster_resolution": 1.0, "canopy_classes": None, "dim_prefix": "",
                           "trees": False}
    assert d["trees"]["method"] == "auto" and d["trees"]["min_height"] == 2.0
    assert d["terrain"] == {"cell": 1.0, "slope": 0.15, "window": 18.0, "threshold": 0.5,
                            "scalar": 1.25, "block": "auto", "ground_tolerance": None}


def test_derived_radii_and_halo():
    cfg = validate_config({"features": {"r1": 0.8}})
    assert cfg.features.r2 == cfg.features.radius2 == 0.4
    # the features' reach (for the paper set r1 and the diagonal of the density voxels,
    # r1 / 16, rounded up to the mm: 0.887) and that + 1 cm for each of 2 later stages
    assert cfg.tiling.halo == cfg.halo == 2.681
    cfg = validate_config({"features": {"r1": 0.8}, "cascade": {"stages": 1}})
    assert cfg.halo == 0.887
    cfg = validate_config({"features": {"r1": 0.8, "r2": 0.3}, "tiling": {"halo": 2.0}})
    assert cfg.features.radius2 == 0.3 and cfg.halo == 2.0


def test_empty_values_mean_defaults(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("data:\ntiling:\n  chunk_size:\ncascade:\n  stages:\ncluster:\n  slurm:\n")
    assert load_config(path) == SilvaConfig()
    (tmp_path / "empty.yaml").write_text("")
    assert load_config(tmp_path / "empty.yaml") == SilvaConfig()


def test_chunk_size_is_auto_or_a_number():
    assert validate_config({"tiling": {"chunk_size": "auto"}}).tiling.chunk_size == "auto"
    cfg = validate_config({"tiling": {"chunk_size": 20, "target_points": 500_000}})
    assert cfg.tiling.chunk_size == 20.0 and isinstance(cfg.tiling.chunk_size, float)
    assert cfg.tiling.target_points == 500_000
    # "key:" left empty is the default, auto
    assert validate_config({"tiling": {"chunk_size": None}}).tiling.chunk_size == "auto"


def test_config_is_frozen():
    cfg = SilvaConfig()
    with pytest.raises(ValidationError, match="chunk_size\n  Instance is frozen"):
        cfg.tiling.chunk_size = 3.0
    with pytest.raises(ValidationError, match="tiling\n  Instance is frozen"):
        cfg.tiling = cfg.tiling.model_copy(update={"chunk_size": 3.0})
    assert cfg.tiling.chunk_size == "auto"


def test_class_helpers():
    cfg = validate_config({"data": {
        "classes": {"ground": [2, 11], "low": [3], "tree": [4, 5], "noise": [7], "misc": [1]},
        "ignore": ["noise", 11], "background": ["misc"],
    }})
    data = cfg.data
    assert data.class_names == ["ground", "low", "tree", "misc"]
    assert data.class_codes == [2, 3, 4, 1]
    assert data.code_to_class == {2: 0, 3: 1, 4: 2, 5: 2, 1: 3}
    assert data.background_indices == [3]


def test_a_single_code_or_path_is_a_list():
    cfg = validate_config({"data": {"train": "a.laz", "classes": {"tree": 5}}})
    assert cfg.data.train == ["a.laz"] and cfg.data.classes == {"tree": [5]}


# -- validation errors -----------------------------------------------------------------------
@pytest.mark.parametrize("raw, expected", [
    ({"tiling": {"chunksize": 3}}, "unknown key 'tiling.chunksize' (did you mean 'chunk_size'?)"),
    ({"tiling": {"chunk_size": 0}}, "tiling.chunk_size must be 'auto' or a number of metres > 0, "
                                    "got 0"),
    ({"tiling": {"chunk_size": -2.5}}, "tiling.chunk_size must be 'auto' or a number of metres "
                                       "> 0, got -2.5"),
    ({"tiling": {"chunk_size": "big"}}, "tiling.chunk_size must be 'auto' or a number of metres "
                                        "> 0, got 'big'"),
    ({"tiling": {"chunk_size": "AUTO"}}, "tiling.chunk_size must be 'auto' or a number"),
    ({"tiling": {"chunk_size": True}}, "tiling.chunk_size must be 'auto' or a number"),
    ({"tiling": {"chunk_size": float("inf")}}, "tiling.chunk_size must be 'auto' or a number"),
    ({"tiling": {"chunk_size": [20]}}, "tiling.chunk_size must be 'auto' or a number"),
    ({"tiling": {"target_points": 0}}, "tiling.target_points must be >= 1, got 0"),
    ({"tiling": {"target_points": -5}}, "tiling.target_points must be >= 1, got -5"),
    ({"tiling": {"target_points": 2.5}}, "tiling.target_points must be an integer, got 2.5"),
    ({"tiling": {"target_points": "big"}}, "tiling.target_points must be an integer, got 'big'"),
    ({"tiling": {"target_points": "auto"}}, "tiling.target_points must be an integer"),
    ({"features": {"r1": -1}}, "features.r1 must be 'auto' or a number of metres > 0, got -1"),
    ({"features": {"r1": float("inf")}}, "features.r1 must be 'auto' or a number of metres > 0, got inf"),
    ({"features": {"r1": float("nan")}}, "features.r1 must be 'auto' or a number of metres > 0, got nan"),
    ({"tiling": {"halo": 0.2}},
     "tiling.halo 0.2 is smaller than the features' reach 0.555; use a halo >= 0.555 or leave "
     "it unset"),
    ({"features": {"r1": 1.0, "r2": 1.5}}, "features.r2 must be > 0 and <= features.r1 (1.0), "
                                           "got 1.5"),
    ({"features": {"set": "enhanced"}}, "features.set must be one of the feature sets 'paper', "
                                        "'covariance', 'default', got 'enhanced'"),
    ({"features": {"scales": [1, 1]}}, "features.scales must be distinct numbers > 0"),
    ({"features": {"cell": 4}}, "features.cell (4.0) must not exceed features.column (3.0)"),
    ({"features": {"plane": "xz"}}, "features.plane"),
    ({"features": {"max_neighbors": 2}}, "features.max_neighbors must be >= 3, got 2"),
    ({"features": {"context_max_neighbors": 0}}, "features.context_max_neighbors must be >= 1"),
    ({"cascade": {"stages": 0}}, "cascade.stages must be >= 1, got 0"),
    ({"cascade": {"stages": True}}, "cascade.stages must be an integer, got true"),
    ({"cascade": {"n_estimators": 2.5}}, "cascade.n_estimators must be an integer, got 2.5"),
    ({"cascade": {"folds": 1}}, "cascade.folds must be >= 2, got 1"),
    ({"cascade": {"context": "fuzzy"}}, "cascade.context must be 'hard' or 'soft', got 'fuzzy'"),
    ({"cascade": {"max_features": "all"}}, "cascade.max_features must be 'sqrt', 'log2', an "
                                           "integer >= 1 or a number in (0, 1], got 'all'"),
    ({"cascade": {"max_features": 1.5}}, "cascade.max_features must be"),
    ({"cascade": {"max_features": 0}}, "cascade.max_features must be"),
    ({"cascade": {"seed": -1}}, "cascade.seed must be >= 0, got -1"),
    ({"cluster": {"kind": "cloud"}}, "cluster.kind must be 'local', 'address' or 'slurm', "
                                     "got 'cloud'"),
    ({"cluster": {"kind": "address"}}, "cluster.address is required when cluster.kind is "
                                       "'address'"),
    ({"cluster": {"n_workers": 0}}, "cluster.n_workers must be >= 1, got 0"),
    ({"cluster": {"memory_limit": "lots"}}, "cluster.memory_limit must be 'auto', a size such "
                                            "as '4GiB' or a number of bytes, got 'lots'"),
    ({"cluster": {"dashboard": "maybe"}}, "cluster.dashboard must be true or false"),
    ({"cluster": {"slurm": {"walltime": 43200}}}, "cluster.slurm.walltime must be a SLURM time"),
    ({"cluster": {"slurm": {"memory": "much"}}}, "cluster.slurm.memory must be 'auto', a size"),
    ({"cluster": {"slurm": {"cores": 2, "processes": 4}}},
     "cluster.slurm.processes (4) is more than cluster.slurm.cores (2)"),
    ({"output": {"format": "ply"}}, "output.format must be 'laz' or 'las', got 'ply'"),
    ({"data": {"train": ["a.laz"]}}, "data.classes is empty but data.train is given"),
    ({"data": {"test": ["a.laz"]}}, "data.classes is empty but data.test is given"),
    ({"data": {"train": 3}}, "data.train must be a list, got 3"),
    ({"data": {"label_field": ""}}, "data.label_field must not be empty"),
    ({"data": {"classes": {"a": [1], "b": [2, 1]}}},
     "data.classes: label code 1 is listed under both 'a' and 'b'"),
    ({"data": {"classes": {"a": [1, 1]}}}, "data.classes: label code 1 is listed twice under 'a'"),
    ({"data": {"classes": {"a": []}}}, "data.classes.a has no label codes"),
    ({"data": {"classes": {"a": ["two"]}}}, "data.classes.a[0] must be an integer, got 'two'"),
    ({"data": {"classes": {"a": [1]}, "ignore": ["b"]}},
     "data.ignore[0] 'b' is not a class in data.classes (classes: a)"),
    ({"data": {"classes": {"a": [1]}, "ignore": [1.5]}},
     "data.ignore[0] must be a class name or an integer label code, got 1.5"),
    ({"data": {"classes": {"a": [1], "b": [2]}, "background": ["a", "c"]}},
     "data.background[1] 'c' is not a class in data.classes (classes: a, b)"),
    ({"data": {"classes": {"a": [1], "b": [2]}, "background": ["a"], "ignore": ["a"]}},
     "data.background 'a' is also in data.ignore"),
    ({"data": {"classes": {"a": [1, 3], "b": [2]}, "ignore": [1, 3]}},
     "data.ignore drops every code of class 'a'"),
    ({"data": {"classes": {"a": [1]}, "ignore": ["a"]}}, "data.ignore drops every class"),
    ({"data": {"split": {"axis": "y", "at": 528.0}}}, "data.split cuts the data.train cloud"),
    ({"data": {"train": ["a"], "classes": {"a": [1]}, "split": {"axis": "w", "at": 1}}},
     "data.split.axis must be 'x', 'y' or 'z', got 'w'"),
    ({"data": {"train": ["a"], "classes": {"a": [1]}, "split": {"axis": "y"}}},
     "data.split.at is required"),
    ({"features": 3}, "features must be a mapping of keys to values, got 3"),
])
def test_errors_name_the_key(raw, expected):
    assert expected in config_error(raw)


def test_several_errors_are_counted():
    message = config_error({"features": {"r1": -1}, "cascade": {"stages": 0, "folds": 1}})
    assert message.endswith("(and 2 more)")
    assert "features.r1 must be 'auto' or a number of metres > 0, got -1" in message


@pytest.mark.parametrize("loc, valid", [
    ((), "tiling"), (("data",), "classes"), (("tiling",), "halo"), (("features",), "r2"),
    (("cascade",), "seed"), (("cluster",), "slurm"), (("cluster", "slurm"), "queue"),
    (("output",), "format"),
])
def test_unknown_keys_at_every_level(loc, valid):
    raw = node = {}
    for part in loc:
        node = node.setdefault(part, {})
    node["zebra"] = "striped"
    message = config_error(raw)
    key = ".".join((*loc, "zebra"))
    assert f"unknown key '{key}'" in message
    assert valid in message  # no close match: the valid keys are listed


def test_unknown_key_in_the_split():
    raw = {"data": {"train": ["a"], "classes": {"a": [1]},
                    "split": {"axis": "y", "at": 1, "att": 2}}}
    assert "unknown key 'data.split.att' (did you mean 'at'?)" in config_error(raw)


def test_yaml_syntax_error_names_file_and_line(tmp_path):
    path = tmp_path / "broken.yaml"
    path.write_text("data:\n  train: [a.laz\n  test: b\n")
    with pytest.raises(ConfigError, match=r"broken\.yaml line 3: "):
        load_config(path)


def test_duplicate_yaml_key_is_refused(tmp_path):
    path = tmp_path / "dup.yaml"
    path.write_text("data:\n  classes:\n    tree: [5]\n    tree: [6]\n")
    with pytest.raises(ConfigError, match=r"dup\.yaml line 4: duplicate key 'tree'"):
        load_config(path)


def test_config_that_is_not_a_mapping(tmp_path):
    path = tmp_path / "list.yaml"
    path.write_text("- data\n- tiling\n")
    with pytest.raises(ConfigError, match="must hold a mapping of sections"):
        load_config(path)


def test_missing_config_file(tmp_path):
    with pytest.raises(MissingFileError, match="nope.yaml"):
        load_config(tmp_path / "nope.yaml")


# -- overrides -------------------------------------------------------------------------------
def test_overrides_scalars_lists_and_nested_keys(tmp_path):
    path = write(tmp_path / "c.yaml", {"data": {"train": ["/t/*.laz"], "classes": CLASSES},
                                       "tiling": {"chunk_size": 9}})
    cfg = load_config(path, [
        "tiling.chunk_size=20",
        "cascade.context=soft",
        "cascade.max_features=0.5",
        "cluster.slurm.queue=short",
        "cluster.slurm.job_extra_directives=[--exclusive, '--gres=gpu:1']",
        "data.classes.tree=[5, 6]",
        "data.background=[misc]",
        "data.split={axis: y, at: 528}",
        "output.write_classification=true",
        "features.r1=0.6",
    ])
    assert cfg.tiling.chunk_size == 20.0 and cfg.cascade.context == "soft"
    assert cfg.cascade.max_features == 0.5
    assert cfg.cluster.slurm.queue == "short"
    assert cfg.cluster.slurm.job_extra_directives == ["--exclusive", "--gres=gpu:1"]
    assert cfg.data.classes["tree"] == [5, 6] and cfg.data.background == ["misc"]
    assert cfg.data.split.axis == "y" and cfg.data.split.at == 528.0
    assert cfg.output.write_classification is True
    # derived values follow the overridden radius
    assert cfg.features.r2 == 0.3 and cfg.halo == 2.015  # 0.665 + 2 x 0.675


def test_later_override_wins(tmp_path):
    cfg = load_config(None, ["cascade.stages=2", "cascade.stages=5"])
    assert cfg.cascade.stages == 5


def test_paths_from_the_file_and_from_overrides(tmp_path, monkeypatch):
    conf_dir = tmp_path / "conf"
    conf_dir.mkdir()
    path = write(conf_dir / "c.yaml", {"data": {
        "train": ["tiles/*.laz", "/abs/x.laz", "../up/y.laz"], "classes": CLASSES}})
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    cfg = load_config(path, ["data.test=[a.laz, b/*.laz]", "data.predict=c/**/*.laz"])
    assert cfg.data.train == [str(conf_dir / "tiles/*.laz"), "/abs/x.laz", str(tmp_path / "up/y.laz")]
    assert cfg.data.test == [str(work / "a.laz"), str(work / "b/*.laz")]
    assert cfg.data.predict == [str(work / "c/**/*.laz")]
    # base_dir replaces the file's directory
    other = load_config(path, base_dir=tmp_path)
    assert other.data.train[0] == str(tmp_path / "tiles/*.laz")
    # without a file, relative paths are taken from the current directory
    assert load_config(None, ["data.predict=[p.laz]"]).data.predict == [str(work / "p.laz")]


@pytest.mark.parametrize("override, expected", [
    ("tiling.chunk_size", "--set 'tiling.chunk_size' has no '='; use KEY=VALUE"),
    ("=3", "--set '=3' has an empty key or key part; use KEY=VALUE"),
    ("tiling..halo=1", "has an empty key or key part; use KEY=VALUE"),
    ("tiling.chunk_size.x=1", "'tiling.chunk_size' is a value, not a section, so it has no "
                              "key 'x'; use KEY=VALUE"),
    ("data.classes.tree.x=1", "'data.classes.tree' holds [5], not a mapping"),
    ("data.test=[*.laz]", "the value of --set 'data.test=[*.laz]' is not valid YAML"),
    ("tiling.chunksize=3", "unknown key 'tiling.chunksize' (did you mean 'chunk_size'?)"),
    ("features.r1=-1", "features.r1 must be 'auto' or a number of metres > 0, got -1"),
    ("colour=green", "unknown key 'colour'"),
])
def test_malformed_or_invalid_overrides(tmp_path, override, expected):
    raw = {"data": {"classes": {"tree": [5]}}}
    assert expected in config_error(raw, [override], tmp_path)


def test_chunk_size_overrides(tmp_path):
    path = write(tmp_path / "c.yaml", {"tiling": {"chunk_size": 9, "target_points": 10}})
    assert load_config(path).tiling.chunk_size == 9.0
    cfg = load_config(path, ["tiling.chunk_size=auto", "tiling.target_points=3_000_000"])
    assert cfg.tiling.chunk_size == "auto" and cfg.tiling.target_points == 3_000_000
    assert load_config(None, ["tiling.chunk_size=20"]).tiling.chunk_size == 20.0
    assert load_config(None, ["tiling.chunk_size=2.5e+1"]).tiling.chunk_size == 25.0
    for value, got in (("0", "0"), ("-1", "-1"), ("big", "'big'")):
        assert config_error(None, [f"tiling.chunk_size={value}"], tmp_path).endswith(
            f"tiling.chunk_size must be 'auto' or a number of metres > 0, got {got}")
    assert config_error(None, ["tiling.target_points=0"], tmp_path).endswith(
        "tiling.target_points must be >= 1, got 0")


# -- dump and load ---------------------------------------------------------------------------
def test_dump_load_round_trip(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    cfg = load_config(None, [
        "data.train=[train dir/*.laz, 'x: y.laz']",
        f"data.classes={CLASSES}",
        "data.ignore=[7, dead_wood]",
        "data.background=[misc]",
        "data.split={axis: x, at: -1.5}",
        "tiling.chunk_size=12.5",
        "features.r1=0.3",
        "cascade.max_features=3",
        "cluster.kind=address",
        "cluster.address=tcp://10.0.0.1:8786",
        "cluster.memory_limit=4GiB",
        "cluster.slurm.walltime='12:00:00'",
        "cluster.slurm.job_extra_directives=['--constraint=a&b']",
        "output.format=las",
    ])
    text = dump_config(cfg)
    assert "r2: 0.15" in text and "halo: 1.019" in text  # derived values written out
    saved = tmp_path / "elsewhere" / "config.yaml"
    saved.parent.mkdir()
    saved.write_text(text)
    again = load_config(saved)
    assert again == cfg
    assert dump_config(again) == text


def test_auto_chunk_size_round_trips(tmp_path):
    cfg = load_config(None, ["tiling.chunk_size=auto", "tiling.target_points=123456"])
    text = dump_config(cfg)
    assert "chunk_size: auto" in text and "target_points: 123456" in text
    assert validate_config(yaml.safe_load(text)) == cfg


@settings(max_examples=30, deadline=None)
@given(
    r1=st.floats(1e-3, 10.0), extra_halo=st.floats(0.0, 5.0),
    chunk=st.one_of(st.just("auto"), st.floats(15.0, 1e4)), stages=st.integers(1, 9),
    fraction=st.floats(1e-6, 1.0), seed=st.integers(0, 2**32 - 1),
)
def test_dump_load_round_trip_property(r1, extra_halo, chunk, stages, fraction, seed):
    cfg = validate_config({
        "tiling": {"chunk_size": chunk, "halo": capped_halo(r1) + extra_halo},
        "features": {"r1": r1},
        "cascade": {"stages": stages, "max_features": fraction, "seed": seed},
    })
    assert validate_config(yaml.safe_load(dump_config(cfg))) == cfg


# -- fingerprints ----------------------------------------------------------------------------
BASE = {"data": {"train": ["/d/train/*.laz"], "test": ["/d/test/*.laz"], "classes": CLASSES,
                 "background": ["misc"]},
        "tiling": {"halo": 1.0}}


def changed_steps(**sections) -> set[str]:
    """The steps whose fingerprint changes when ``sections`` update BASE."""
    a = validate_config(BASE)
    raw = {k: dict(v) for k, v in BASE.items()}
    for section, values in sections.items():
        raw[section] = {**raw.get(section, {}), **values}
    b = validate_config(raw)
    return {step for step in STEPS if fingerprint(a, step) != fingerprint(b, step)}


@pytest.mark.parametrize("sections, expected", [
    ({"features": {"r1": 0.6}}, {"features", "stage", "export", "evaluate"}),
    ({"features": {"max_neighbors": 32}}, {"features", "stage", "export", "evaluate"}),
    ({"features": {"r2": 0.2}}, {"stage", "export", "evaluate"}),
    ({"features": {"context_max_neighbors": 100}}, {"stage", "export", "evaluate"}),
    ({"cascade": {"n_estimators": 30}}, {"stage", "export", "evaluate"}),
    ({"cascade": {"context": "soft"}}, {"stage", "export", "evaluate"}),
    ({"cascade": {"stages": 5}}, set()),
    ({"cluster": {"n_workers": 7}}, set()),
    ({"cluster": {"kind": "slurm"}}, set()),
    ({"tiling": {"read_batch": 1000}}, set()),
    ({"output": {"format": "las"}}, {"export"}),
    ({"output": {"probabilities": False}}, {"export"}),
    ({"output": {"keep_store": False}}, set()),
    ({"output": {"keep_features": "auto"}}, set()),  # the default
    ({"output": {"keep_features": False}}, set(STEPS)),  # it chooses each scene's halo
    ({"output": {"keep_features": True}}, set(STEPS)),
    ({"data": {"background": []}}, {"evaluate"}),
    ({"tiling": {"chunk_size": 20}}, set(STEPS)),
    ({"tiling": {"target_points": 2_000_000}}, set(STEPS)),  # BASE sizes chunks automatically
    ({"tiling": {"layout": "grid"}}, set(STEPS)),
    ({"tiling": {"halo": 2.0}}, set(STEPS)),
    ({"data": {"label_field": "label"}}, set(STEPS)),
    ({"data": {"ignore": [7]}}, set(STEPS)),
    ({"data": {"exclude_codes": [7, 18]}}, set(STEPS)),
    ({"data": {"exclude_withheld": True}}, set(STEPS)),
    ({"output": {"feature_dims": "all"}}, {"export"}),
    ({"output": {"point_format": "keep"}}, {"export"}),
    ({"data": {"predict": ["/d/more.laz"]}}, set(STEPS)),
    ({"data": {"train": ["/d/test/*.laz"], "test": ["/d/train/*.laz"]}}, set(STEPS)),
    ({"data": {"classes": dict(reversed(CLASSES.items()))}}, set(STEPS)),  # class order
    ({"data": {"train": ["/d/train/*.laz", "/d/train/*.laz"]}}, set()),
])
def test_fingerprints_change_with_exactly_what_they_cover(sections, expected):
    assert changed_steps(**sections) == expected


def test_target_points_matters_only_with_auto_chunks():
    def ingest(**tiling):
        return fingerprint(validate_config({**BASE, "tiling": {"halo": 1.0, **tiling}}), "ingest")

    assert ingest() == ingest(chunk_size="auto")
    assert ingest(target_points=10**6) != ingest(target_points=10**7)
    assert ingest(chunk_size=20, target_points=10**6) == ingest(chunk_size=20,
                                                               target_points=10**7)
    assert ingest(chunk_size=20) != ingest(chunk_size=30) != ingest()
    assert ingest(layout="grid") != ingest()
    assert ingest(chunk_size=20, layout="grid") == ingest(chunk_size=20)


def test_unset_halo_follows_r1_into_ingest():
    a = validate_config({"features": {"r1": 0.5}})
    b = validate_config({"features": {"r1": 0.6}})
    assert fingerprint(a, "ingest") != fingerprint(b, "ingest")
    # the same halo written out or left to its default is the same ingest
    c = validate_config({"features": {"r1": 0.5}, "tiling": {"halo": 1.685}})
    assert all(fingerprint(a, step) == fingerprint(c, step) for step in STEPS)


def test_fingerprint_is_short_and_stable_across_processes(tmp_path):
    cfg = validate_config(BASE)
    values = [fingerprint(cfg, step) for step in STEPS]
    assert len(set(values)) == len(STEPS)
    assert all(len(v) == 16 and int(v, 16) >= 0 for v in values)
    path = write(tmp_path / "c.yaml", BASE)
    code = ("import sys; from workflows.config import load_config; "
            "from workflows.steps.table import STEPS; fingerprint = STEPS.fingerprint; "
            f"c = load_config(sys.argv[1]); print(*(fingerprint(c, s) for s in {STEPS!r}))")
    env = {**os.environ, "PYTHONHASHSEED": "12345"}
    out = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True,
                         text=True, check=True, env=env,
                         cwd=Path(__file__).resolve().parents[2]).stdout.split()
    assert out == values


def test_unknown_step():
    with pytest.raises(ConfigError, match="unknown step 'train'"):
        fingerprint(SilvaConfig(), "train")


# -- inputs ----------------------------------------------------------------------------------
def test_expand_inputs(tmp_path):
    for name in ("a/t2.laz", "a/t1.laz", "a/notes.txt", "b/deep/t3.las", "b/t4.laz"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_bytes(b"")
    (tmp_path / "a" / "dir.laz").mkdir()  # a directory is never an input
    found = expand_inputs([str(tmp_path / "b/**/*.la?"), str(tmp_path / "a/*.laz"),
                           str(tmp_path / "a/t1.laz"), tmp_path / "a" / ".." / "a" / "t2.laz"])
    assert [p.relative_to(tmp_path).as_posix() for p in found] == [
        "a/t1.laz", "a/t2.laz", "b/deep/t3.las", "b/t4.laz"]


def test_expand_inputs_refuses_what_matches_nothing(tmp_path):
    (tmp_path / "a.laz").write_bytes(b"")
    pattern = str(tmp_path / "none" / "*.laz")
    with pytest.raises(MissingFileError) as info:
        expand_inputs([str(tmp_path / "a.laz"), pattern])
    assert pattern in str(info.value)
    with pytest.raises(MissingFileError, match=r"missing\.laz' in data\.test"):
        expand_inputs([str(tmp_path / "missing.laz")], key="data.test")
    with pytest.raises(InputError, match="is a directory"):
        expand_inputs([str(tmp_path)])


@pytest.mark.parametrize("chunk, halo", [(0.001, None), (0.5, None), (1.0, 3.0)])
def test_a_chunk_smaller_than_its_halo_is_refused(chunk, halo):
    tiling = {"chunk_size": chunk, **({"halo": halo} if halo else {})}
    with pytest.raises(ConfigError) as err:
        validate_config({"features": {"r1": 0.5}, "tiling": tiling})
    assert f"tiling.chunk_size {chunk} m is less than half the halo of" in str(err.value)
