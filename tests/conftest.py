"""Shared test fixtures."""

import json
from pathlib import Path

import pytest
from hypothesis import settings

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The real LiDAR of ``../shared/data``; tests that use it skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real LiDAR data not found at {SHARED_DATA}")
    return SHARED_DATA


def edit_model_json(model: Path, change) -> None:
    """Edit a saved model's model.json by hand, as a user might: ``change(description)``."""
    path = model / "model.json"
    description = json.loads(path.read_text())
    change(description)
    path.write_text(json.dumps(description, indent=2))


# The suite is deterministic: each property test draws the same examples on every run, so a
# failure in CI is reproducible and never a matter of luck. To search for new counterexamples,
# run the property tests with fresh random draws: pytest --hypothesis-profile=explore
settings.register_profile("default", derandomize=True, database=None)
settings.register_profile("explore", derandomize=False, database=None)
settings.load_profile("default")
