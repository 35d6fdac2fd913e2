"""A survey, not a plot: the same points over 49 times the area cost no more memory, since
the terrain is modelled in fixed blocks on the workers and no step holds an array as large
as the survey's area."""

import json
import subprocess
import sys

import laspy
import numpy as np
import pytest
import yaml

pytestmark = pytest.mark.slow

#: Runs the command given and prints the peak resident bytes of the process.
PEAK = """
import json, resource, runpy, sys
sys.argv = ["silva", *sys.argv[1:]]
try:
    runpy.run_module("workflows", run_name="__main__")
except SystemExit as end:
    code = end.code
print(json.dumps({"peak": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
                  "code": code}))
"""


def write_sparse_survey(root, side: float, per_tile: int = 400, n: int = 7, seed: int = 0):
    """``n`` x ``n`` LAS tiles over a square of ``side`` metres, ``per_tile`` points each on
    a gently sloping ground, a third of them in low vegetation: the same points whatever
    the side."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True)
    tile = side / n
    for i in range(n):
        for j in range(n):
            u = rng.random((per_tile, 2))
            xy = 500_000.0 + (np.array([i, j]) + u) * tile
            z = 200.0 + 0.01 * (xy[:, 0] - 500_000.0) + 3.0 * (rng.random(per_tile) < 0.3)
            header = laspy.LasHeader(point_format=6, version="1.4")
            header.scales, header.offsets = [0.01] * 3, [500_000.0, 0.0, 0.0]
            las = laspy.LasData(header)
            las.x, las.y, las.z = xy[:, 0], xy[:, 1], z
            las.classification = np.full(per_tile, 2, np.uint8)
            las.write(root / f"t{i}_{j}.las")


def peak_of_features(tmp_path, name: str, side: float) -> int:
    survey = tmp_path / name
    write_sparse_survey(survey, side)
    config = tmp_path / f"{name}.yaml"
    config.write_text(yaml.safe_dump({
        "data": {"predict": [str(survey / "*.las")], "classes": {"ground": [2], "other": [1]}},
        "features": {"set": "paper", "r1": 2.0},
        # 5 m cells: the larger survey's points stay one group of cells near each other (25 m
        # apart, tiles of 30 m), modelled in 49 blocks of 500 m instead of one raster
        "terrain": {"cell": 5.0, "block": 500.0},
        "cluster": {"kind": "local", "n_workers": 1, "dashboard": False},
    }))
    done = subprocess.run([sys.executable, "-c", PEAK, "features", str(config), "--out",
                           str(tmp_path / f"{name}-out"), "--in-process", "-q"],
                          capture_output=True, text=True, timeout=900)
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["code"] in (0, None), done.stderr
    return result["peak"]


def test_the_same_points_over_49_times_the_area_take_no_more_memory(tmp_path):
    """19,600 points over 0.25 km² and over 12.25 km² (49 tiles each), ingest, terrain and
    features in one process: the larger survey's peak stays within 64 MiB of the smaller's
    (a terrain model of the whole 12.25 km² at 5 m, 490,000 cells, took some 230 MB)."""
    small = peak_of_features(tmp_path, "small", 500.0)
    large = peak_of_features(tmp_path, "large", 3500.0)
    assert large < small + 64 * 2**20, (small / 2**20, large / 2**20)
