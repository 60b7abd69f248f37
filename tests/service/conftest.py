"""The fixtures the service tests share."""

import pytest

from lodserver.service.catalog import PostgresCatalog
from lodserver.service.store import LocalStore

from ..services.postgres import postgres_server, postgres_url  # noqa: F401 (fixtures)

# Parametrize ``catalog_url`` (indirect) over these: every queue test runs on both.
DIALECTS = ["sqlite", "postgresql"]


@pytest.fixture
def store(tmp_path):
    """An empty store in tmp_path/data, closed after the test."""
    store = LocalStore(tmp_path / "data")
    yield store
    store.close()


@pytest.fixture
def catalog_url(request, tmp_path):
    """A catalogue URL of the kind ``request.param`` names ("sqlite": a file under
    tmp_path/shared; "postgresql": the module's database), its table empty."""
    if request.param == "sqlite":
        return f"sqlite://{tmp_path}/shared/catalogue.sqlite3"
    url = request.getfixturevalue("postgres_url")
    catalog = PostgresCatalog(url)
    catalog._run("DELETE FROM meshes")
    catalog.close()
    return url


@pytest.fixture
def two_stores(catalog_url, tmp_path):
    """Two stores, as two servers see them: data directories of their own
    (tmp_path/one, tmp_path/two), one catalogue (``catalog_url``), one folder of
    blobs (tmp_path/blobs); closed after the test."""
    stores = [LocalStore(tmp_path / name, catalog=catalog_url, blobs=str(tmp_path / "blobs"))
              for name in ("one", "two")]
    yield stores
    for store in stores:
        store.close()
