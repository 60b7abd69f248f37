"""The catalogue and its build queue, on SQLite and on a real PostgreSQL: schema
creation (idempotent, concurrent, migrating an old file), claims (oldest first,
each row to one claimer however many race), leases (renewal, expiry, takeover),
fencing (a superseded claim records nothing), recovery and abandonment; then
the store on top of it: two data directories sharing one catalogue and one
folder of blobs."""

import sqlite3
import threading
import time
from pathlib import Path

import pytest

from lodserver.scene.asset import SceneAsset
from lodserver.service import store as store_module
from lodserver.service.catalog import (
    MAX_LOST,
    CatalogUnavailable,
    MeshRecord,
    PostgresCatalog,
    SqliteCatalog,
    Status,
    open_catalog,
    redact_url,
)
from lodserver.service.store import (
    LeaseLostError,
    LocalStore,
    NotReadyError,
    StoreError,
    UnknownMeshError,
)

from ..meshes import progressive
from .conftest import DIALECTS


def _grid() -> SceneAsset:
    """The grid as the store keeps it: a scene of one part."""
    return SceneAsset.of_mesh(progressive("grid"))


def _open(url, tmp_path):
    return open_catalog(url, data_dir=tmp_path)


def _row(mesh_id, created, status=Status.QUEUED):
    return MeshRecord(id=mesh_id, name=mesh_id, status=status, progress=0.0, file_type="obj",
                      source_bytes=10, options={"min_vertices": 4}, created=created,
                      updated=created)


def _ids(n):
    return [f"{chr(ord('A') + i)}" * 22 for i in range(n)]


@pytest.fixture
def catalog(catalog_url, tmp_path):
    """The catalogue at ``catalog_url``, closed after the test."""
    catalog = _open(catalog_url, tmp_path)
    yield catalog
    catalog.close()


@pytest.mark.parametrize("catalog_url", DIALECTS, indirect=True)
def test_rows_round_trip(catalog):
    a, b = _ids(2)
    catalog.insert(_row(a, 1.0))
    catalog.insert(_row(b, 2.0))
    got = catalog.get(mesh_id=a)
    assert got == _row(a, 1.0) and got.options == {"min_vertices": 4}
    assert [r.id for r in catalog.list(limit=10, offset=0)] == [b, a]
    assert [r.id for r in catalog.list(limit=1, offset=1)] == [a]
    updated = catalog.update(mesh_id=a, values={"summary": {"vertices": 5}, "progress": 0.5},
                             updated=3.0)
    assert updated.summary == {"vertices": 5} and updated.progress == 0.5
    assert updated.updated == 3.0
    assert catalog.delete(mesh_id=a).id == a
    assert catalog.get(mesh_id=a) is None and catalog.delete(mesh_id=a) is None
    assert catalog.update(mesh_id=a, values={"progress": 1.0}, updated=4.0) is None


@pytest.mark.parametrize("catalog_url", DIALECTS, indirect=True)
def test_claims_take_the_oldest_and_each_row_once(catalog_url, tmp_path):
    first = _open(catalog_url, tmp_path)
    ids = _ids(6)
    for n, mesh_id in enumerate(ids):
        first.insert(_row(mesh_id, 10.0 + n))
    claim = first.claim(owner="n1/a", lease_seconds=30, updated=20.0)
    assert claim.mesh_id == ids[0] and claim.attempt == 1 and claim.owner == "n1/a"
    assert claim.record.status is Status.BUILDING
    assert first.claim(owner="n1/a", lease_seconds=30, updated=20.0,
                       mesh_id=ids[0]) is None            # held: not claimable
    assert first.queued_before(first.get(mesh_id=ids[3])) == 2

    # Eight claimers, each on its own connection, race for the five left.
    catalogs = [_open(catalog_url, tmp_path) for _ in range(8)]
    start, won = threading.Barrier(len(catalogs)), []

    def claim_all(catalog, n):
        start.wait()
        while (got := catalog.claim(owner=f"n{n}/x", lease_seconds=30, updated=21.0)):
            won.append(got.mesh_id)

    threads = [threading.Thread(target=claim_all, args=(c, n)) for n, c in enumerate(catalogs)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(won) == sorted(ids[1:])              # every row, each exactly once
    for catalog in catalogs + [first]:
        catalog.close()


@pytest.mark.parametrize("catalog_url", DIALECTS, indirect=True)
def test_an_expired_lease_is_taken_over_and_the_old_claim_is_fenced(catalog):
    mesh_id, = _ids(1)
    catalog.insert(_row(mesh_id, 1.0))
    old = catalog.claim(owner="dead/1", lease_seconds=0.6, updated=2.0)
    assert catalog.renew(claim=old, lease_seconds=0.6)
    assert catalog.claim(owner="live/1", lease_seconds=30, updated=2.0) is None
    time.sleep(0.8)                                     # the holder stopped renewing
    new = catalog.claim(owner="live/1", lease_seconds=30, updated=3.0)
    assert new.mesh_id == mesh_id and new.attempt == 2
    # the first holder comes back: nothing it writes counts, not even completion
    assert not catalog.renew(claim=old, lease_seconds=30)
    assert catalog.update(mesh_id=mesh_id, values={"status": "ready", "digest": "0" * 64},
                          updated=4.0, attempt=old.attempt) is None
    assert catalog.get(mesh_id=mesh_id).status is Status.BUILDING
    done = catalog.update(mesh_id=mesh_id, values={"status": "ready", "digest": "1" * 64},
                          updated=5.0, attempt=new.attempt)
    assert done.status is Status.READY and done.digest == "1" * 64
    # settled: neither claim may write again, and nobody can claim it
    assert catalog.update(mesh_id=mesh_id, values={"progress": 0.5}, updated=6.0,
                          attempt=new.attempt) is None
    assert not catalog.renew(claim=new, lease_seconds=30)
    assert catalog.claim(owner="x/1", lease_seconds=30, updated=7.0) is None


@pytest.mark.parametrize("catalog_url", DIALECTS, indirect=True)
def test_a_build_whose_builders_keep_vanishing_is_failed(catalog):
    mesh_id, = _ids(1)
    catalog.insert(_row(mesh_id, 1.0))
    for lost in range(MAX_LOST):
        assert catalog.abandon(max_lost=MAX_LOST, reason="r", updated=2.0) == []
        claim = catalog.claim(owner=f"n{lost}/1", lease_seconds=0.2, updated=2.0)
        assert claim.attempt == lost + 1
        time.sleep(0.3)                                 # ... and its builder dies
    failed, = catalog.abandon(max_lost=MAX_LOST, reason="killed them all", updated=3.0)
    assert failed.id == mesh_id and failed.status is Status.FAILED
    assert catalog.get(mesh_id=mesh_id).failure == "killed them all"
    assert catalog.claim(owner="n9/1", lease_seconds=30, updated=4.0) is None


@pytest.mark.parametrize("catalog_url", DIALECTS, indirect=True)
def test_recover_takes_back_only_its_own_nodes_builds(catalog):
    mine, other, legacy = _ids(3)
    for n, mesh_id in enumerate((mine, other, legacy)):
        catalog.insert(_row(mesh_id, 1.0 + n))
    catalog.claim(owner="node_a/old", lease_seconds=300, updated=2.0, mesh_id=mine)
    catalog.claim(owner="node_ab/1", lease_seconds=300, updated=2.0, mesh_id=other)
    catalog.update(mesh_id=legacy, values={"status": "building"}, updated=2.0)  # no lease
    requeued = catalog.recover(node="node_a", updated=3.0)
    assert sorted(r.id for r in requeued) == sorted([mine, legacy])
    assert catalog.get(mesh_id=other).status is Status.BUILDING   # a live node's lease holds
    assert [r.id for r in catalog.pending()] == [mine, legacy]


def _open_at_once(url, tmp_path, openers: int = 6):
    """``openers`` threads opening the catalogue ``url`` at one barrier:
    (the catalogues opened, the exceptions raised)."""
    start, opened, errors = threading.Barrier(openers), [], []

    def open_one():
        start.wait()
        try:
            opened.append(_open(url, tmp_path))
        except Exception as exc:      # noqa: BLE001 - the caller's assertion names it
            errors.append(exc)

    threads = [threading.Thread(target=open_one) for _ in range(openers)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return opened, errors


@pytest.mark.parametrize("catalog_url", DIALECTS, indirect=True)
def test_schema_is_created_once_by_concurrent_openers(catalog_url, tmp_path, request):
    if catalog_url.startswith("postgresql"):
        # a database of its own, with no table yet
        import psycopg

        server = request.getfixturevalue("postgres_server")
        with psycopg.connect(server, autocommit=True) as admin:
            admin.execute('DROP DATABASE IF EXISTS "lodserver_schema_race" WITH (FORCE)')
            admin.execute('CREATE DATABASE "lodserver_schema_race"')
        catalog_url = server.rpartition("/")[0] + "/lodserver_schema_race"
    else:
        catalog_url += ".race"
    opened, errors = _open_at_once(catalog_url, tmp_path)
    assert errors == [] and len(opened) == 6
    opened[0].insert(_row(_ids(1)[0], 1.0))
    assert opened[5].get(mesh_id=_ids(1)[0]) is not None
    for catalog in opened:
        catalog.close()
    _open(catalog_url, tmp_path).close()              # and again, idempotent


def test_fresh_sqlite_files_opened_at_once_never_report_locked(tmp_path):
    """Switching a new file to WAL mode takes its exclusive lock and is refused at
    once (no busy handler) while another opener holds any lock: many rounds of six
    openers racing on a new file each, so that the race is met, not hoped for."""
    for round_ in range(100):
        url = f"sqlite://{tmp_path}/round-{round_}/catalogue.sqlite3"
        opened, errors = _open_at_once(url, tmp_path)
        for catalog in opened:
            catalog.close()
        assert errors == [], f"round {round_}: {errors}"
        with sqlite3.connect(tmp_path / f"round-{round_}" / "catalogue.sqlite3") as check:
            assert check.execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_an_old_sqlite_catalogue_gains_the_queue_columns(tmp_path):
    """A data directory written before leases: its rows stay, and are claimable."""
    path = tmp_path / "catalogue.sqlite3"
    old = sqlite3.connect(path)
    old.executescript("""CREATE TABLE meshes (id TEXT PRIMARY KEY, name TEXT NOT NULL,
        status TEXT NOT NULL, progress REAL NOT NULL, file_type TEXT NOT NULL,
        source_bytes INTEGER NOT NULL, options TEXT NOT NULL, summary TEXT NOT NULL,
        failure TEXT, digest TEXT, created REAL NOT NULL, updated REAL NOT NULL);""")
    old.execute("INSERT INTO meshes VALUES (?, 'a', 'building', 0.3, 'obj', 5, '{}', '{}', "
                "NULL, NULL, 1.0, 1.0)", ("A" * 22,))
    old.commit()
    old.close()
    catalog = SqliteCatalog(path)
    assert catalog.get(mesh_id="A" * 22).attempt == 0
    claim = catalog.claim(owner="n/1", lease_seconds=30, updated=2.0)
    assert claim.mesh_id == "A" * 22 and claim.attempt == 1
    catalog.close()


def test_catalogue_urls_are_checked_and_never_echo_a_password(tmp_path):
    with pytest.raises(ValueError, match="postgresql:// or sqlite://") as caught:
        open_catalog("mysql://user:hunter2@db/x", data_dir=tmp_path)
    assert "hunter2" not in str(caught.value)
    assert redact_url("postgresql://u:hunter2@h:5/db") == "postgresql://u:***@h:5/db"
    assert redact_url("postgresql://h/db") == "postgresql://h/db"
    with pytest.raises(CatalogUnavailable) as caught:
        PostgresCatalog("postgresql://u:hunter2@127.0.0.1:1/db", connect_seconds=2)
    assert "cannot reach the catalogue" in str(caught.value)
    assert "hunter2" not in str(caught.value)
    assert isinstance(caught.value, ConnectionError)        # the API's 503
    assert isinstance(open_catalog(None, data_dir=tmp_path), SqliteCatalog)
    assert (tmp_path / "catalogue.sqlite3").is_file()


# ---- the store on a shared catalogue -------------------------------------------------------
def _source(tmp_path, name="a.obj"):
    path = tmp_path / name
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    return path


@pytest.mark.parametrize("catalog_url", DIALECTS, indirect=True)
def test_two_stores_share_rows_artefacts_and_deletes(two_stores, tmp_path, monkeypatch):
    one, two = two_stores
    record = one.create(name="a", source=_source(tmp_path), file_type="obj", options={})
    assert [r.id for r in two.list()] == [record.id]
    claim = two.claim(lease_seconds=30)
    assert claim.mesh_id == record.id and claim.owner.startswith(two.node + "/")
    staged = two.stage_source(mesh_id=record.id, folder=two.scratch(prefix="t-"))
    assert staged.read_text().startswith("v 0 0 0")
    two.set_progress(mesh_id=record.id, progress=0.5, attempt=claim.attempt)
    assert one.get(mesh_id=record.id).progress == 0.5
    ready = two.put_artefact(mesh_id=record.id, asset=_grid(), attempt=claim.attempt)
    artefact = tmp_path / "blobs" / "artefacts" / f"{record.id}.{ready.digest}.pm"
    assert artefact.is_file()
    assert not (tmp_path / "blobs" / "sources" / f"{record.id}.obj").exists()

    reads = []
    real_load = store_module.load_artefact
    monkeypatch.setattr(store_module, "load_artefact",
                        lambda path: reads.append(path) or real_load(path))
    pm = one.load(mesh_id=record.id)
    assert one.load(mesh_id=record.id) is pm and len(reads) == 1   # kept in memory
    two.delete(mesh_id=record.id)
    # one's memory holds the mesh, but the row says it is gone
    with pytest.raises(UnknownMeshError):
        one.load(mesh_id=record.id)
    assert not artefact.exists()


@pytest.mark.parametrize("catalog_url", DIALECTS, indirect=True)
def test_a_store_whose_claim_was_taken_over_records_nothing(two_stores, tmp_path):
    one, two = two_stores
    record = one.create(name="a", source=_source(tmp_path), file_type="obj", options={})
    stalled = one.claim(lease_seconds=0.5)
    time.sleep(0.7)
    taker = two.claim(lease_seconds=30)
    assert taker.mesh_id == record.id and taker.attempt == stalled.attempt + 1
    with pytest.raises(LeaseLostError):
        one.set_progress(mesh_id=record.id, progress=0.9, attempt=stalled.attempt)
    with pytest.raises(LeaseLostError):
        one.put_artefact(mesh_id=record.id, asset=_grid(), attempt=stalled.attempt)
    with pytest.raises(LeaseLostError):
        one.mark_failed(mesh_id=record.id, reason="no", attempt=stalled.attempt)
    assert one.get(mesh_id=record.id).status is Status.BUILDING
    two.put_artefact(mesh_id=record.id, asset=_grid(), attempt=taker.attempt)
    assert two.get(mesh_id=record.id).status is Status.READY
    assert one.load(mesh_id=record.id).single.vertex_count == progressive("grid").vertex_count
    # deleted while building: the builder's write is refused as an unknown mesh
    other = one.create(name="b", source=_source(tmp_path, "b.obj"), file_type="obj", options={})
    held = two.claim(lease_seconds=30)
    one.delete(mesh_id=other.id)
    assert not two.renew(claim=held, lease_seconds=30)
    with pytest.raises(UnknownMeshError):
        two.put_artefact(mesh_id=other.id, asset=_grid(), attempt=held.attempt)
    assert list((tmp_path / "blobs" / "artefacts").glob(f"{other.id}*")) == []


@pytest.mark.parametrize("catalog_url", DIALECTS, indirect=True)
def test_a_mesh_that_keeps_killing_its_builders_is_failed_and_its_source_dropped(
        two_stores, tmp_path):
    one, two = two_stores
    record = one.create(name="a", source=_source(tmp_path), file_type="obj", options={})
    for n in range(MAX_LOST):
        assert (one, two)[n % 2].claim(lease_seconds=0.2).mesh_id == record.id
        time.sleep(0.3)
    assert one.claim(lease_seconds=30) is None
    failed = two.get(mesh_id=record.id)
    assert failed.status is Status.FAILED and "not tried again" in failed.failure
    assert not (tmp_path / "blobs" / "sources" / f"{record.id}.obj").exists()
    with pytest.raises(NotReadyError, match="failed to build"):
        two.load(mesh_id=record.id)


def test_a_data_directory_is_one_processs(tmp_path):
    store = LocalStore(tmp_path / "data")
    with pytest.raises(StoreError, match="its own LODSERVER_DATA_DIR"):
        LocalStore(tmp_path / "data")
    store.close()
    LocalStore(tmp_path / "data").close()                 # free again once closed


def test_a_restart_takes_back_its_own_builds_at_once(tmp_path):
    """A node's builds are requeued when it starts again (its previous process is
    dead: one process per data directory), without waiting for the lease."""
    store = LocalStore(tmp_path / "data")
    record = store.create(name="a", source=_source(tmp_path), file_type="obj", options={})
    claim = store.claim(lease_seconds=300)
    assert claim.mesh_id == record.id
    store.close()                                         # a crash: the lease is still held
    again = LocalStore(tmp_path / "data")
    assert again.node == store.node and again.owner != store.owner
    assert again.recover() == [record.id]
    assert again.claim(lease_seconds=30).attempt == claim.attempt + 1
    again.close()


def test_stores_sharing_a_remote_store_fetch_once_and_quarantine_a_bad_copy(tmp_path):
    """The object-store path (fsspec's memory:// stands in for S3 here; the S3
    tests run it against moto): sources staged by download, artefacts read
    through each server's bounded local cache, a corrupt copy set aside."""
    import secrets

    url = f"memory://lodserver-test-{secrets.token_hex(4)}/lods"
    catalog = f"sqlite://{tmp_path}/shared/catalogue.sqlite3"
    one, two = (LocalStore(tmp_path / name, catalog=catalog, blobs=url)
                for name in ("one", "two"))
    try:
        record = one.create(name="a", source=_source(tmp_path), file_type="obj", options={})
        assert not (tmp_path / "a.obj").exists() and not one.local_files
        claim = two.claim(lease_seconds=30)
        staged = two.stage_source(mesh_id=record.id, folder=two.scratch(prefix="t-"))
        assert staged.read_text().startswith("v 0 0 0")
        ready = two.put_artefact(mesh_id=record.id, asset=_grid(),
                                 attempt=claim.attempt)
        key = f"artefacts/{record.id}.{ready.digest}.pm"
        assert one.blobs.exists(key) and not one.blobs.exists(f"sources/{record.id}.obj")
        assert one.load(mesh_id=record.id).single.vertex_count == progressive("grid").vertex_count
        cached = list((tmp_path / "one" / "cache").iterdir())
        assert len(cached) == 1 and cached[0].stat().st_size == one.blobs.size(key)

        # this server's copy goes bad: the mesh fails once, with the reason, for all
        one._loaded.clear()
        cached[0].write_bytes(b"garbage")
        with pytest.raises(NotReadyError, match="corrupt"):
            one.load(mesh_id=record.id)
        assert (tmp_path / "one" / "quarantine" / Path(key).name).read_bytes() == b"garbage"
        assert two.get(mesh_id=record.id).status is Status.FAILED
        two.delete(mesh_id=record.id)
        assert not one.blobs.exists(key)
    finally:
        one.close()
        two.close()


@pytest.mark.parametrize("catalog_url", ["postgresql"], indirect=True)
def test_connections_the_server_dropped_are_replaced(catalog_url, postgres_server):
    """A PostgreSQL restart (or an idle timeout) kills pooled connections: the next
    statement runs on a new one instead of failing."""
    import psycopg

    catalog = PostgresCatalog(catalog_url)
    catalog.insert(_row(_ids(1)[0], 1.0))
    assert catalog.get(mesh_id=_ids(1)[0]) is not None       # a pooled connection now
    database = catalog_url.rpartition("/")[2]
    with psycopg.connect(postgres_server, autocommit=True) as admin:
        killed = admin.execute("SELECT count(pg_terminate_backend(pid)) FROM pg_stat_activity "
                               "WHERE datname = %s", (database,)).fetchone()[0]
    assert killed >= 1
    assert catalog.get(mesh_id=_ids(1)[0]).id == _ids(1)[0]
    catalog.close()
