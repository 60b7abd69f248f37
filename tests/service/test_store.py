"""The embedded store: catalogue rows, atomic artefacts, ids, and recovery after a restart."""

import numpy as np
import pytest

from lodserver.service.store import (
    ID_PATTERN,
    LocalStore,
    NotReadyError,
    Status,
    UnknownMeshError,
    check_id,
)

from lodserver.io.scene import Scene
from lodserver.packets import encode_records
from lodserver.service.loaded import fixed_nbytes, loaded_nbytes, records_nbytes
from lodserver.scene.asset import SceneAsset, ScenePart

from ..conftest import record_calls
from ..meshes import progressive


def _grid() -> SceneAsset:
    """The grid as the store keeps it: a scene of one part."""
    return SceneAsset.of_mesh(progressive("grid"))


def _source(tmp_path, name="cube.obj"):
    path = tmp_path / name
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    return path


def test_create_get_list_delete(store, tmp_path):
    record = store.create(name="cube", source=_source(tmp_path), file_type="OBJ",
                          options={"boundary_weight": 1.0})
    assert ID_PATTERN.match(record.id) and record.status is Status.QUEUED
    assert record.file_type == "obj" and record.options == {"boundary_weight": 1.0}
    assert store.source_path(mesh_id=record.id).is_file()
    assert not (tmp_path / "cube.obj").exists()  # moved into the store
    assert store.get(mesh_id=record.id) == record
    second = store.create(name="two", source=_source(tmp_path), file_type="obj", options={})
    assert [r.id for r in store.list()] == [second.id, record.id]
    assert [r.id for r in store.list(limit=1, offset=1)] == [record.id]
    store.delete(mesh_id=record.id)
    with pytest.raises(UnknownMeshError):
        store.get(mesh_id=record.id)
    assert not list(store.sources.glob(f"{record.id}*"))


@pytest.mark.parametrize("bad", ["../../etc/passwd", "a" * 21, "a" * 23, "abc/def" + "a" * 15,
                                 "", "a" * 21 + ".", "a" * 21 + "\n"])
def test_malformed_ids_never_reach_the_filesystem(store, bad):
    with pytest.raises(UnknownMeshError):
        check_id(bad)
    with pytest.raises(UnknownMeshError):
        store.get(mesh_id=bad)
    with pytest.raises(UnknownMeshError):
        store.delete(mesh_id=bad)


def test_ready_artefact_is_served_after_reopening(tmp_path):
    pm = progressive("grid")
    store = LocalStore(tmp_path / "data")
    record = store.create(name="grid", source=_source(tmp_path), file_type="obj", options={})
    with pytest.raises(NotReadyError, match="not built yet"):
        store.load(mesh_id=record.id)
    store.mark_building(mesh_id=record.id)
    store.set_progress(mesh_id=record.id, progress=0.5)
    assert store.get(mesh_id=record.id).progress == 0.5
    ready = store.put_artefact(mesh_id=record.id, asset=SceneAsset.of_mesh(pm))
    assert ready.status is Status.READY and ready.progress == 1.0 and len(ready.digest) == 64
    assert ready.summary["vertices"] == pm.vertex_count and ready.summary["error_curve"]
    assert not store.source_path(mesh_id=record.id).exists()  # the source goes once built
    assert not list(store.artefacts.glob(".*.tmp"))
    store.close()

    reopened = LocalStore(tmp_path / "data")
    assert reopened.recover() == []
    loaded = reopened.load(mesh_id=record.id).single
    assert np.array_equal(loaded.arrays_at(loaded.base_vertices + 5)[1],
                          pm.arrays_at(pm.base_vertices + 5)[1])
    reopened.close()


def test_interrupted_builds_are_requeued_or_failed(tmp_path):
    store = LocalStore(tmp_path / "data")
    building = store.create(name="a", source=_source(tmp_path), file_type="obj", options={})
    queued = store.create(name="b", source=_source(tmp_path), file_type="obj", options={})
    lost = store.create(name="c", source=_source(tmp_path), file_type="obj", options={})
    for record in (building, lost):
        store.mark_building(mesh_id=record.id)
    store.source_path(mesh_id=lost.id).unlink()
    # a crash in the middle of an atomic write leaves a temporary file
    (store.artefacts / f".{building.id}.pm.xyz.tmp").write_bytes(b"half")
    store.close()

    reopened = LocalStore(tmp_path / "data")
    assert not list(reopened.artefacts.glob(".*.tmp"))
    assert sorted(reopened.recover()) == sorted([building.id, queued.id])
    assert reopened.get(mesh_id=building.id).status is Status.QUEUED
    failed = reopened.get(mesh_id=lost.id)
    assert failed.status is Status.FAILED and "upload it again" in failed.failure
    with pytest.raises(NotReadyError, match="failed to build"):
        reopened.load(mesh_id=lost.id)
    reopened.close()


def test_artefact_of_a_mesh_deleted_while_building_is_dropped(store, tmp_path):
    record = store.create(name="a", source=_source(tmp_path), file_type="obj", options={})
    store.delete(mesh_id=record.id)
    with pytest.raises(UnknownMeshError):
        store.put_artefact(mesh_id=record.id, asset=_grid())
    assert not list(store.artefacts.iterdir())


def test_racing_loads_of_one_mesh_share_one_object(tmp_path, monkeypatch):
    """Requests racing for a mesh just built (and its job preparing its packets)
    get the same object: what is cached on it is not built twice."""
    import threading

    from lodserver.service import store as store_module

    store = LocalStore(tmp_path / "data")
    record = store.create(name="grid", source=_source(tmp_path), file_type="obj", options={})
    store.put_artefact(mesh_id=record.id, asset=_grid())
    reads = record_calls(monkeypatch, store_module, "load_artefact")
    start, found = threading.Barrier(6), []

    def load():
        start.wait()
        found.append(store.load(mesh_id=record.id))

    threads = [threading.Thread(target=load) for _ in range(6)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(found) == 6 and all(pm is found[0] for pm in found)
    assert len(reads) == 1
    store.close()


def test_loaded_meshes_are_bounded(tmp_path):
    with pytest.raises(ValueError, match="at least 1"):
        LocalStore(tmp_path / "x", loaded_meshes=0)
    store = LocalStore(tmp_path / "data", loaded_meshes=1)
    ids = []
    for name in ("a", "b"):
        record = store.create(name=name, source=_source(tmp_path, f"{name}.obj"), file_type="obj",
                              options={})
        store.put_artefact(mesh_id=record.id, asset=_grid())
        ids.append(record.id)
    first = store.load(mesh_id=ids[0])
    assert store.load(mesh_id=ids[0]) is first
    store.load(mesh_id=ids[1])                  # drops the first from memory
    assert store.load(mesh_id=ids[0]) is not first
    store.close()


def _two_meshes(store, tmp_path, pms):
    ids = []
    for name, pm in zip("ab", pms):
        record = store.create(name=name, source=_source(tmp_path, f"{name}.obj"), file_type="obj",
                              options={})
        store.put_artefact(mesh_id=record.id, asset=SceneAsset.of_mesh(pm))
        ids.append(record.id)
    return ids


def test_loaded_meshes_are_bounded_by_bytes(tmp_path):
    size = loaded_nbytes(_grid())
    # room for one grid and a half: the second load drops the first
    store = LocalStore(tmp_path / "data", loaded_meshes=8, loaded_bytes=size * 3 // 2)
    ids = _two_meshes(store, tmp_path, [progressive("grid"), progressive("grid")])
    first = store.load(mesh_id=ids[0])
    assert loaded_nbytes(first) == size and store._loaded.held == size
    assert store.load(mesh_id=ids[0]) is first
    store.load(mesh_id=ids[1])
    assert ids[0] not in store._loaded and store._loaded.held == size
    assert store.load(mesh_id=ids[0]) is not first
    store.close()
    # one mesh past the bound alone is still kept: it is the one in use
    store = LocalStore(tmp_path / "data", loaded_bytes=size // 2)
    assert store.load(mesh_id=ids[1]) is store.load(mesh_id=ids[1])
    store.close()


def test_packet_records_count_once_encoded(tmp_path):
    """Records encoded after a mesh is kept are measured when it is used next: the
    bytes then pass the bound and the least recently used mesh is dropped."""
    size = loaded_nbytes(_grid())
    store = LocalStore(tmp_path / "data", loaded_bytes=2 * size + 1)
    ids = _two_meshes(store, tmp_path, [progressive("grid"), progressive("grid")])
    first = store.load(mesh_id=ids[0])
    store.load(mesh_id=ids[1])
    assert len(store._loaded) == 2 and store._loaded.held == 2 * size
    encode_records(first.single)
    assert records_nbytes(first) > 1
    assert store.load(mesh_id=ids[0]) is first          # measured again: too many bytes
    assert ids[1] not in store._loaded
    assert store._loaded.held == size + records_nbytes(first)
    store.close()


def test_a_scene_counts_its_carried_bytes_once_however_aliased():
    pm = progressive("grid")
    values = np.zeros((250_000, 4), np.float32)         # 4 MB
    carried = {0: (values, {}, "OTHER"), 1: (values, {}, "OTHER"),
               2: (values[:10], {}, "OTHER")}          # a view inside the first
    asset = SceneAsset(Scene({"asset": {"version": "2.0"}}, carried=carried),
                       [ScenePart(0, 0, "grid", [0], pm)])
    alone = fixed_nbytes(SceneAsset.of_mesh(pm))
    assert fixed_nbytes(asset) - alone - values.nbytes < 1000     # the document's JSON
    asset.scene.carried[3] = (values.copy(), {}, "OTHER")
    assert fixed_nbytes(asset) - alone - 2 * values.nbytes < 1000


def test_an_artefact_stored_before_keys_named_digests_is_renamed_and_served(tmp_path):
    store = LocalStore(tmp_path / "data")
    record = store.create(name="grid", source=_source(tmp_path), file_type="obj", options={})
    ready = store.put_artefact(mesh_id=record.id, asset=_grid())
    current = store.artefacts / f"{record.id}.{ready.digest}.pm"
    current.rename(store.artefacts / f"{record.id}.pm")       # the layout of older versions
    stray = store.artefacts / f"{record.id}.{'0' * 64}.pm"      # a build that lost its claim
    stray.write_bytes(b"not the row's")
    store.close()
    reopened = LocalStore(tmp_path / "data")
    assert sorted(p.name for p in reopened.artefacts.iterdir()) == [current.name]
    assert reopened.load(mesh_id=record.id).single.vertex_count == progressive("grid").vertex_count
    reopened.close()
