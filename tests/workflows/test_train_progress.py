"""While the forests grow, a quiet run still says how far the training got."""

import pytest

from tests.workflows.conftest import silva, write_config

pytestmark = pytest.mark.slow


def test_quiet_training_prints_the_forests_progress(survey, tmp_path, monkeypatch):
    from workflows.steps import cascade

    monkeypatch.setattr(cascade, "FIT_LINE_SECONDS", 0.0)  # every round, not once a minute
    config = write_config(tmp_path / "c.yaml", survey,
                          cascade={"stages": 1, "out_of_fold": True, "folds": 2})
    result = silva("train", config, "--out", tmp_path / "out", "--in-process", "-q")
    assert result.exit_code == 0, result.output
    lines = [line for line in result.output.splitlines() if line.startswith("train: stage")]
    assert "train: stage 1 of 1, its forest: 6 of 6 trees" in lines
    assert "train: stage 1 of 1, out-of-fold forest 2 of 2: 6 of 6 trees" in lines
    log = (tmp_path / "out" / "silva.log").read_text()
    assert "out-of-fold forest 1 of 2" in log
