"""Reading a glTF scene kept whole (lodserver.io.scene): the document, and each glTF mesh
as one Mesh in its local space, instanced or not.

``scene_glb()`` builds the scene the export tests use too: two meshes (a textured
spot with a material and its image, and a plain ball), three nodes instancing
them under a transformed root (the spot twice), a camera, a KHR_lights_punctual
light, unknown extensions, extras and an animation of the first spot's translation.
"""

from __future__ import annotations

import copy
import json
import struct

import numpy as np
import pytest
import trimesh

from lodserver.io import load_mesh
from lodserver.io.limits import LimitError, LoadLimits
from lodserver.io.scene import load_scene
from lodserver.mesh import MeshError

from ..conftest import glb_chunks
from ..meshes import textured_spot


def pack_glb(document: dict, binary: bytes) -> bytes:
    """A GLB of ``document`` and ``binary`` (padded to 4 bytes, buffer 0's length set)."""
    binary = binary + b"\0" * (-len(binary) % 4)
    document = {**document, "buffers": [{"byteLength": len(binary)}]}
    header = json.dumps(document).encode()
    header += b" " * (-len(header) % 4)
    total = 28 + len(header) + len(binary)
    return b"".join([struct.pack("<4sII", b"glTF", 2, total),
                     struct.pack("<I4s", len(header), b"JSON"), header,
                     struct.pack("<I4s", len(binary), b"BIN\x00"), binary])


def _append(document: dict, binary: bytearray, values: np.ndarray, kind: str, *,
            component: int = 5126, target: int | None = None, bounds: bool = False) -> int:
    """Append ``values`` as a new bufferView and accessor; the accessor's index."""
    binary.extend(b"\0" * (-len(binary) % 4))
    data = np.ascontiguousarray(values, dtype="<f4" if component == 5126 else "<u4").tobytes()
    view = {"buffer": 0, "byteOffset": len(binary), "byteLength": len(data)}
    if target:
        view["target"] = target
    document["bufferViews"].append(view)
    binary.extend(data)
    accessor = {"bufferView": len(document["bufferViews"]) - 1, "componentType": component,
                "count": len(values), "type": kind}
    if bounds:
        flat = np.asarray(values, dtype=np.float32).reshape(len(values), -1)
        accessor["min"] = flat.min(axis=0).tolist()
        accessor["max"] = flat.max(axis=0).tolist()
    document["accessors"].append(accessor)
    return len(document["accessors"]) - 1


BALL = trimesh.creation.icosphere(2)


def scene_document() -> tuple[dict, bytearray]:
    """The built scene's JSON and binary chunk (see the module docstring)."""
    from lodserver.io import encode_mesh
    document, binary = glb_chunks(encode_mesh(textured_spot(), "glb"))
    binary = bytearray(binary)
    position = _append(document, binary, BALL.vertices, "VEC3", target=34962, bounds=True)
    indices = _append(document, binary, BALL.faces.ravel(), "SCALAR", component=5125,
                      target=34963)
    document["meshes"][0]["name"] = "spot"
    document["meshes"].append({"name": "ball", "extras": {"kind": "ball"}, "primitives": [
        {"attributes": {"POSITION": position}, "indices": indices, "mode": 4}]})
    times = _append(document, binary, np.array([0.0, 1.0, 2.0]), "SCALAR", bounds=True)
    moves = _append(document, binary, np.array([[0, 0, 0], [0, 1, 0], [0, 0, 0]]), "VEC3")
    document.update(
        scene=0,
        scenes=[{"name": "Stage", "nodes": [0, 4, 5], "extras": {"level": 3}}],
        nodes=[
            {"name": "root", "children": [1, 2, 3], "translation": [1.0, 2.0, 3.0]},
            {"name": "spotA", "mesh": 0, "translation": [-2.0, 0.0, 0.0],
             "extensions": {"VENDOR_node_tag": {"tag": "a"}}},
            {"name": "spotB", "mesh": 0, "rotation": [0.0, 0.7071068, 0.0, 0.7071068],
             "scale": [2.0, 2.0, 2.0], "extras": {"note": "big"}},
            {"name": "ballNode", "mesh": 1,
             "matrix": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 3, 0, 1]},
            {"name": "camNode", "camera": 0, "translation": [0.0, 0.0, 10.0]},
            {"name": "lightNode", "extensions": {"KHR_lights_punctual": {"light": 0}}},
        ],
        cameras=[{"name": "cam", "type": "perspective",
                  "perspective": {"yfov": 0.8, "znear": 0.1, "zfar": 100.0}}],
        animations=[{"name": "bob", "samplers": [{"input": times, "output": moves}],
                     "channels": [{"sampler": 0, "target": {"node": 1, "path": "translation"}}]}],
        extensions={"KHR_lights_punctual": {"lights": [{"type": "point", "color": [1, 0.5, 0],
                                                        "intensity": 3.0}]},
                    "VENDOR_scene_info": {"author": "tests", "values": [1, 2, 3]}},
        extensionsUsed=["KHR_lights_punctual", "VENDOR_node_tag", "VENDOR_scene_info"],
        extras={"project": "lodserver"},
    )
    document["asset"]["copyright"] = "public domain"
    return document, binary


def scene_glb(edit=None) -> bytes:
    """The built scene as GLB bytes, after ``edit(document)`` if given."""
    document, binary = scene_document()
    if edit is not None:
        edit(document)
    return pack_glb(document, bytes(binary))


@pytest.fixture
def scene_file(tmp_path):
    path = tmp_path / "stage.glb"
    path.write_bytes(scene_glb())
    return path


def test_each_mesh_once_in_its_local_space(scene_file):
    scene = load_scene(scene_file)
    assert not scene.as_is
    assert sorted(scene.meshes) == [0, 1]
    assert scene.mesh_nodes == {0: [1, 2], 1: [3]}            # the spot is instanced twice
    spot = textured_spot()
    # local space: the spot as it was encoded, not moved by its nodes' transforms
    np.testing.assert_array_equal(np.unique(scene.meshes[0].positions, axis=0),
                                  np.unique(spot.positions.astype(np.float32), axis=0))
    assert scene.meshes[0].face_count == spot.face_count
    assert scene.meshes[0].attributes.layout == spot.attributes.layout
    assert scene.meshes[0].materials is scene.materials and scene.materials.count == 1
    assert (scene.meshes[0].face_material == 0).all()
    ball = scene.meshes[1]
    assert ball.face_count == len(BALL.faces) and (ball.face_material == -1).all()
    assert ball.attributes is None
    np.testing.assert_array_equal(np.unique(ball.positions, axis=0),
                                  np.unique(BALL.vertices.astype(np.float32), axis=0))
    # the flattened reading places the spot twice and the ball once
    flat, _ = load_mesh(scene_file)
    assert flat.face_count == 2 * spot.face_count + len(BALL.faces)
    assert scene.document["nodes"][1]["name"] == "spotA"
    sampler = scene.document["animations"][0]["samplers"][0]
    assert set(scene.carried) == {sampler["input"], sampler["output"]}
    np.testing.assert_array_equal(scene.carried[sampler["input"]][0].ravel(), [0, 1, 2])


def test_required_extensions(tmp_path):
    def requiring(name):
        def edit(document):
            document["extensionsUsed"].append(name)
            document["extensionsRequired"] = [name]
        return edit

    # (compressed geometry is decoded: tests/io/test_gltf_compressed_*.py)
    for name in ("VENDOR_secret_geometry",):
        path = tmp_path / f"{name}.glb"
        path.write_bytes(scene_glb(requiring(name)))
        with pytest.raises(MeshError) as caught:
            load_scene(path)
        message = str(caught.value)
        assert message == (f"cannot load {path.name}: it requires the glTF extension {name}, "
                           "which lodserver cannot honour")
        assert str(tmp_path) not in message
    # a required extension lodserver carries is no error
    path = tmp_path / "transform.glb"
    path.write_bytes(scene_glb(requiring("KHR_texture_transform")))
    assert sorted(load_scene(path).meshes) == [0, 1]


def test_limits_and_root_as_load_mesh(tmp_path, scene_file):
    with pytest.raises(LimitError, match="triangles in mesh 0"):
        load_scene(scene_file, limits=LoadLimits(max_triangles=100))
    with pytest.raises(LimitError, match="nodes in its default scene"):
        load_scene(scene_file, limits=LoadLimits(max_instances=3))
    # a .gltf naming a buffer outside its folder, loaded under root=
    document, binary = scene_document()
    (tmp_path / "outside.bin").write_bytes(bytes(binary))
    inner = tmp_path / "inner"
    inner.mkdir()
    document["buffers"] = [{"byteLength": len(binary), "uri": "../outside.bin"}]
    (inner / "stage.gltf").write_text(json.dumps(document))
    assert load_scene(inner / "stage.gltf").meshes                # trusted: allowed
    with pytest.raises(MeshError) as caught:
        load_scene(inner / "stage.gltf", root=inner)
    with pytest.raises(MeshError) as flat:
        load_mesh(inner / "stage.gltf", root=inner)
    assert str(caught.value) == str(flat.value)                   # the very same refusal
    with pytest.raises(MeshError, match="only .gltf and .glb"):
        load_scene(tmp_path / "x.obj")
    with pytest.raises(MeshError, match="cannot load nothing.glb: no such file"):
        load_scene(tmp_path / "nothing.glb")


def test_skinned_and_morphed_meshes_are_meshes_and_points_are_kept_as_they_are(tmp_path):
    """A skinned or morphed mesh is a Mesh with its joints, weights and target deltas as
    attributes; only a mesh without triangles is written as it is."""
    def skinned(document):
        document["skins"] = [{"joints": [3]}]
        document["nodes"][1]["skin"] = 0

    def morphed(document):
        primitive = document["meshes"][1]["primitives"][0]
        primitive["targets"] = [{"POSITION": primitive["attributes"]["POSITION"]}]

    def points(document):
        document["meshes"][1]["primitives"][0]["mode"] = 0

    for edit in (skinned, morphed):
        path = tmp_path / "x.glb"
        path.write_bytes(scene_glb(edit))
        scene = load_scene(path)
        assert not scene.as_is and sorted(scene.meshes) == [0, 1]
    names = [name for name, _ in scene.meshes[1].attributes.layout]
    assert "TARGET0_POSITION" in names
    path.write_bytes(scene_glb(points))
    scene = load_scene(path)
    assert list(scene.as_is) == [1] and "no triangles" in scene.as_is[1]
    assert sorted(scene.meshes) == [0]
    primitive = scene.document["meshes"][1]["primitives"][0]
    assert all(scene.carried[a][2] == "vertex" for a in primitive["attributes"].values())
    assert scene.carried[primitive["indices"]][2] == "index"


def test_shared_scenes(shared_meshes):
    engine = load_scene(shared_meshes / "2CylinderEngine.glb")
    document = engine.document
    used = {node["mesh"] for node in document["nodes"] if "mesh" in node}
    assert sorted(engine.meshes) == sorted(used)
    assert len(engine.meshes) == len(document["meshes"])
    per_instance = sum(engine.meshes[node["mesh"]].face_count
                       for node in document["nodes"] if "mesh" in node)
    flat, _ = load_mesh(shared_meshes / "2CylinderEngine.glb")
    # welding across instances in the flattened mesh can only remove faces
    assert per_instance >= flat.face_count > 0.99 * per_instance
    fox = load_scene(shared_meshes / "scenes" / "Fox.glb")
    assert not fox.as_is and [n for n, _ in fox.meshes[0].attributes.layout] == [
        "TEXCOORD_0", "JOINTS_0", "WEIGHTS_0"]
    box = load_scene(shared_meshes / "scenes" / "BoxAnimated.glb")
    assert not box.as_is and box.carried
    duck = load_scene(shared_meshes / "Duck.glb")
    assert list(duck.meshes) == [0] and duck.materials.count == 1


def test_document_is_not_modified(scene_file):
    scene = load_scene(scene_file)
    before = copy.deepcopy(scene.document)
    from lodserver.io.scene_glb import encode_scene
    levels = {index: [mesh] for index, mesh in scene.meshes.items()}
    encode_scene(scene, levels, [0.0])
    assert scene.document == before
