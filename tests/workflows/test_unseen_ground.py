"""A scene whose terrain model is mostly interpolated says so in one plain sentence."""

import laspy
import numpy as np

from tests.workflows.conftest import silva, write_config


def _canopy_tile(path, seed):
    """A 20 m plot under a closed canopy: ground points at about 1 per 4 m², canopy points
    15 m up at 10 per m², so most 1 m cells see no ground."""
    rng = np.random.default_rng(seed)
    ground = np.column_stack([rng.uniform(0, 20, (100, 2)), rng.normal(0, 0.02, 100)])
    crown = np.column_stack([rng.uniform(0, 20, (4000, 2)), rng.uniform(14, 16, 4000)])
    xyz = np.vstack([ground, crown])
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = [0.001] * 3, [0.0] * 3
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    las.classification = np.r_[np.full(100, 2), np.full(4000, 5)].astype(np.uint8)
    path.parent.mkdir(parents=True)
    las.write(path)


def test_a_mostly_interpolated_terrain_model_is_said_plainly(tmp_path):
    survey = {scene: tmp_path / scene for scene in ("train", "test")}
    for seed, folder in enumerate(survey.values()):
        _canopy_tile(folder / f"plot{seed}.laz", seed)
    config = write_config(tmp_path / "c.yaml", survey,
                          data={"classes": {"terrain": [2], "tree": [5]}, "background": []},
                          features={"set": "covariance", "r1": 1.0})
    result = silva("features", config, "--out", tmp_path / "out", "--in-process")
    assert result.exit_code == 0, result.output
    lines = [line for line in result.output.splitlines() if "no ground was seen" in line]
    assert len(lines) == 2, result.output
    share = lines[0].split("no ground was seen in ")[1].split("%")[0]
    assert 50 < int(share) <= 100
    assert lines[0] == (
        f"warning: scene 'train': no ground was seen in {share}% of the 1 m cells that hold "
        "its points (dense canopy, roofs, or no ground in the scan); the terrain model is "
        "interpolated there and heights above it are less certain")
