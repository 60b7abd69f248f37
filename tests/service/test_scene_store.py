"""Scenes stored as assets with parts: one artefact holding every part's progressive
mesh and the document, atomic, content-addressed, shared by servers."""

import json
import struct

import numpy as np
import pytest
import trimesh

from lodserver.build import build
from lodserver.io.scene import load_scene
from lodserver.service import store as store_module
from lodserver.service.parsing import check_mesh_file
from lodserver.scene.artefact import decode_asset, encode_asset
from lodserver.scene.asset import PartError, SceneAsset, instances_of, part_of, scene_levels_for
from lodserver.scene.build import build_scene
from lodserver.scene.load import scene_reason
from lodserver.scene.write import scene_glb
from lodserver.service.store import LocalStore, NotReadyError, Status

from ..meshes import GlbBuilder


def scene_glb_bytes() -> bytes:
    """A GLB scene: mesh 0 (a ball, 1280 faces) placed by two nodes (one at half
    scale), mesh 1 (a capsule) by one rotated node, a camera node, and an
    animation moving the capsule's node. Positions and normals, indices."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    pill = trimesh.creation.capsule(height=1.0, radius=0.4, count=[24, 24])
    builder = GlbBuilder()
    add = builder.add

    meshes = []
    for name, shape in (("ball", ball), ("pill", pill)):
        position = add(shape.vertices.astype("<f4"), "VEC3", 5126, 34962, bounds=True)
        normal = add(shape.vertex_normals.astype("<f4"), "VEC3", 5126, 34962)
        indices = add(shape.faces.astype("<u4").ravel(), "SCALAR", 5125, 34963)
        meshes.append({"name": name, "primitives": [{
            "attributes": {"POSITION": position, "NORMAL": normal}, "indices": indices}]})
    times = add(np.array([0.0, 1.0, 2.0], "<f4"), "SCALAR", 5126, bounds=True)
    moves = add(np.array([[0, 0, 0], [0, 1, 0], [0, 0, 0]], "<f4"), "VEC3", 5126)
    document = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"name": "root", "children": [1, 2, 3, 4]},
                  {"name": "ball A", "mesh": 0, "translation": [-2.0, 0.0, 0.0]},
                  {"name": "ball B", "mesh": 0, "translation": [2.0, 0.0, 0.0],
                   "scale": [0.5, 0.5, 0.5]},
                  {"name": "pill", "mesh": 1, "rotation": [0.0, 0.0, 0.7071068, 0.7071068]},
                  {"name": "eye", "camera": 0, "translation": [0.0, 0.0, 8.0]}],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.8, "znear": 0.1}}],
        "meshes": meshes,
        "animations": [{"name": "bob", "channels": [{"sampler": 0, "target": {
            "node": 3, "path": "translation"}}], "samplers": [{
                "input": times, "output": moves, "interpolation": "LINEAR"}]}],
    }
    return builder.glb(document)


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("scene") / "two.glb"
    path.write_bytes(scene_glb_bytes())
    return path


@pytest.fixture(scope="module")
def asset(scene_file):
    scene, report = check_mesh_file(scene_file, file_type="glb", max_triangles=10**6,
                                    scenes=True)
    assert report.as_dict()["scene"] is True
    built = build_scene(scene, build=build, options={})
    built.metadata.update(load_report=report.as_dict(), options={})
    return built


def test_which_documents_are_scenes():
    one = {"nodes": [{"mesh": 0, "translation": [1, 2, 3]}], "meshes": [{"primitives": []}]}
    assert scene_reason(one) is None      # one mesh placed once: flattened as before
    assert "more than one mesh" in scene_reason({**one, "nodes": [{"mesh": 0}, {"mesh": 1}]})
    assert "several nodes" in scene_reason({**one, "nodes": [{"mesh": 0}, {"mesh": 0}]})
    assert "skin" in scene_reason({**one, "skins": [{"joints": [0]}]})
    assert "animations" in scene_reason({**one, "animations": [{"channels": []}]})
    assert "cameras" in scene_reason({**one, "cameras": [{"type": "perspective"}]})
    morphed = {**one, "meshes": [{"primitives": [{"targets": [{"POSITION": 1}]}]}]}
    assert "morph" in scene_reason(morphed)


def test_a_single_mesh_glb_is_still_one_mesh(tmp_path):
    path = tmp_path / "ball.glb"
    trimesh.creation.icosphere(subdivisions=2).export(path)
    mesh, _ = check_mesh_file(path, file_type="glb", max_triangles=10**6, scenes=True)
    assert mesh.face_count == 320


def test_parts_are_the_glb_meshes_with_their_nodes(asset):
    assert [(p.index, p.mesh, p.name, p.nodes) for p in asset.parts] == [
        (0, 0, "ball", [1, 2]), (1, 1, "pill", [3])]
    assert all(p.pm.vertex_count > p.pm.base_vertices for p in asset.parts)
    # one scale per instance: the half-size ball counts with its scale
    assert {p: list(scales) for p, scales in instances_of(asset).items()} == {
        0: [pytest.approx(1.0), pytest.approx(0.5)], 1: [pytest.approx(1.0)]}
    with pytest.raises(PartError, match="no part 2"):
        part_of(asset, 2)


def test_the_progress_of_a_scene_build_is_over_all_its_parts(scene_file):
    scene, _ = check_mesh_file(scene_file, file_type="glb", max_triangles=10**6, scenes=True)
    seen = []
    build_scene(scene, build=build, options={}, progress=lambda done, total: seen.append(
        (done, total)))
    faces = [scene.meshes[m].face_count for m in sorted(scene.meshes)]
    assert seen and all(total == sum(faces) for _, total in seen)
    done = [d for d, _ in seen]
    assert done == sorted(done) and done[-1] <= sum(faces)
    assert any(d > faces[0] for d in done)      # the second part adds to the first's


def test_the_stored_form_round_trips_and_is_deterministic(asset):
    data = encode_asset(asset)
    again = decode_asset(data)
    assert encode_asset(again) == data
    for mine, theirs in zip(asset.parts, again.parts):
        assert np.array_equal(mine.pm.positions, theirs.pm.positions)
        assert np.array_equal(mine.pm.wedge_values, theirs.pm.wedge_values)
        assert theirs.pm.materials is again.materials     # stored once, shared
    assert again.scene.document == asset.scene.document
    assert set(again.scene.carried) == set(asset.scene.carried)


def test_the_scene_glb_keeps_nodes_animation_and_camera(asset, tmp_path):
    levels = scene_levels_for(asset, ratio=0.5)
    path = tmp_path / "half.glb"
    path.write_bytes(scene_glb(asset, levels))
    out = load_scene(path)
    nodes = out.document["nodes"]
    assert [n.get("name") for n in nodes] == ["root", "ball A", "ball B", "pill", "eye"]
    assert nodes[0]["children"] == [1, 2, 3, 4] and nodes[2]["scale"] == [0.5, 0.5, 0.5]
    assert out.document["cameras"] == asset.scene.document["cameras"]
    assert out.document["animations"][0]["channels"][0]["target"] == {"node": 3,
                                                                      "path": "translation"}
    assert [m["extras"]["lodserver_part"] for m in out.document["meshes"]] == [0, 1]
    for part in asset.parts:
        assert out.meshes[part.mesh].face_count == part.pm.faces_at_level(levels[part.index])


def _glb_parts(data: bytes) -> dict:
    """lodserver_part -> (vertex count, (f, 3) indices) of each single-primitive glTF
    mesh of a GLB, read straight from its chunks."""
    length = struct.unpack_from("<I", data, 12)[0]
    document = json.loads(data[20:20 + length])
    binary = data[20 + length + 8:]
    out = {}
    for mesh in document["meshes"]:
        [primitive] = mesh["primitives"]
        accessor = document["accessors"][primitive["indices"]]
        view = document["bufferViews"][accessor["bufferView"]]
        indices = np.frombuffer(binary, "<u4", accessor["count"],
                                view["byteOffset"] + accessor.get("byteOffset", 0))
        count = document["accessors"][primitive["attributes"]["POSITION"]]["count"]
        out[mesh["extras"]["lodserver_part"]] = (count, indices.reshape(-1, 3))
    return out


def test_the_scene_glb_vertices_are_in_the_json_levels_order(asset):
    from lodserver.service.levels import encode_level

    levels = scene_levels_for(asset, ratio=0.3)
    written = _glb_parts(scene_glb(asset, levels))
    for part in asset.parts:
        level = json.loads(encode_level(part.pm, levels[part.index], file_type="json"))
        count, indices = written[part.index]
        # one material: render vertex k is the level's wedge k, triangles its corners
        assert count == len(level["wedges"])
        assert np.array_equal(indices, np.array(level["corners"]))


def _stored(tmp_path, name, **shared):
    return LocalStore(tmp_path / name, **shared)


def test_a_stored_scene_is_served_by_another_store_and_after_a_restart(asset, tmp_path,
                                                                       scene_file):
    shared = {"catalog": f"sqlite://{tmp_path}/shared/catalogue.sqlite3",
              "blobs": str(tmp_path / "shared")}
    first = _stored(tmp_path, "a", **shared)
    source = tmp_path / "two.glb"
    source.write_bytes(scene_file.read_bytes())
    record = first.create(name="two", source=source, file_type="glb", options={})
    ready = first.put_artefact(mesh_id=record.id, asset=asset)
    assert ready.status is Status.READY and ready.summary["scene"] is True
    assert [p["nodes"] for p in ready.summary["parts"]] == [[1, 2], [3]]
    second = _stored(tmp_path, "b", **shared)
    for store in (first, second):
        loaded = store.load(mesh_id=record.id)
        assert isinstance(loaded, SceneAsset)
        assert encode_asset(loaded) == encode_asset(asset)
    first.close()
    second.close()
    reopened = _stored(tmp_path, "a", **shared)
    assert encode_asset(reopened.load(mesh_id=record.id)) == encode_asset(asset)
    reopened.close()


def test_a_corrupt_scene_artefact_fails_its_mesh_once(asset, tmp_path):
    store = LocalStore(tmp_path / "data")
    source = tmp_path / "s.glb"
    source.write_bytes(b"x")
    record = store.create(name="s", source=source, file_type="glb", options={})
    ready = store.put_artefact(mesh_id=record.id, asset=asset)
    path = store.artefacts / f"{record.id}.{ready.digest}.pm"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF        # inside a stored member: its CRC-32 no longer matches
    path.write_bytes(bytes(data))
    with pytest.raises(NotReadyError, match="corrupt"):
        store.load(mesh_id=record.id)
    assert store.get(mesh_id=record.id).status is Status.FAILED
    assert not path.exists() and list(store.quarantine.iterdir())
    store.close()


def test_a_failed_scene_write_stores_nothing(asset, tmp_path, monkeypatch):
    store = LocalStore(tmp_path / "data")
    source = tmp_path / "s.glb"
    source.write_bytes(b"x")
    record = store.create(name="s", source=source, file_type="glb", options={})

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(store_module, "save_asset", full)
    with pytest.raises(store_module.StorageFullError):
        store.put_artefact(mesh_id=record.id, asset=asset)
    assert store.get(mesh_id=record.id).status is Status.QUEUED
    assert not list(store.artefacts.iterdir())
    assert not [p for p in store.tmp.iterdir()]
    store.close()
