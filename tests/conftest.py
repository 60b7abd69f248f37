import os
from pathlib import Path

import pytest

SHARED_MESHES = Path(__file__).resolve().parents[1].parent / "shared" / "meshes"

# Under CI=true (as .ci/run is run) a test whose browser, tool or service is
# missing fails instead of skipping: a green CI then proves those tests ran.
IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")


def need(reason: str):
    """Skip the calling test for a missing browser, tool or service; fail under CI=true."""
    if IN_CI:
        pytest.fail(f"{reason} (CI=true: .ci/run must provide it)", pytrace=False)
    pytest.skip(reason)


@pytest.fixture
def shared_meshes() -> Path:
    """The shared test meshes beside the repo (../shared/meshes); skips when absent."""
    if not SHARED_MESHES.is_dir():
        pytest.skip(f"shared meshes not found at {SHARED_MESHES}")
    return SHARED_MESHES
