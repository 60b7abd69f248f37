"""What every viewer test module shares: one headless Chromium and one server each."""

from __future__ import annotations

import pytest

from ..conftest import headless_chromium
from ..server import serve


@pytest.fixture(scope="module")
def chromium():
    """A launched headless Chromium (Playwright over Debian's binary); missing, a skip
    (a failure under CI=true)."""
    with headless_chromium() as browser:
        yield browser


@pytest.fixture(scope="module")
def server(request, tmp_path_factory):
    """A ``lodserver serve`` process of the module's own, with a fresh data directory
    (``client.data_dir``)."""
    data = tmp_path_factory.mktemp(request.module.__name__.rsplit(".", 1)[-1]) / "data"
    with serve(data) as client:
        client.data_dir = data
        yield client
