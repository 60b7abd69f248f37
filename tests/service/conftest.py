"""The fixture the service tests share."""

import pytest

from lodserver.service.store import LocalStore


@pytest.fixture
def store(tmp_path):
    """An empty store in tmp_path/data, closed after the test."""
    store = LocalStore(tmp_path / "data")
    yield store
    store.close()
