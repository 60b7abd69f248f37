"""Every vertex attribute of glTF read and written back (issue 12, items 1-3).

On ../shared/meshes/scenes (Fox: skinned, non-indexed; RiggedSimple; AnimatedMorphCube:
tangents and two morph targets; BoxAnimated; SimpleMorph when its buffers are there) and
on a small scene built here whose two primitives have different attributes (so the
neutral defaults show), with normalized integers, a VEC3 colour, a custom scalar and a
matrix one: every attribute read equals its accessor's values; a load -> write (full
level) -> load round trip gives the same attributes; the Khronos validator finds no
error in what is written; the CLI's levels of Fox keep the skin and animations with
valid joints and weights at every level, AnimatedMorphCube keeps its targets.
"""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from lodserver import build
from lodserver.cli import main
from lodserver.io import load_mesh
from lodserver.io.glb import render_attributes, skin_influences, unit_tangents
from lodserver.io.scene import load_scene
from lodserver.io.scene_glb import encode_scene
from lodserver.mesh import MeshError

from ..conftest import glb_chunks
from ..test_scene_export import accessor_values
from . import test_gltf
from .test_gltf import assert_valid

gltf_validator = test_gltf.gltf_validator    # the session fixture, shared

SHARED = ["Fox.glb", "RiggedSimple.glb", "AnimatedMorphCube.glb", "BoxAnimated.glb",
          "SimpleMorph.gltf"]


# --- a scene built here ---------------------------------------------------------------------

class _Builder:
    """A GLB document and its binary chunk, grown accessor by accessor."""

    def __init__(self):
        self.document = {"asset": {"version": "2.0"}, "bufferViews": [], "accessors": []}
        self.binary = bytearray()

    def add(self, values, kind: str, dtype: str = "<f4", *, normalized=False,
            bounds=False, target=None) -> int:
        values = np.ascontiguousarray(values, dtype=dtype)
        self.binary.extend(b"\0" * (-len(self.binary) % 4))
        view = {"buffer": 0, "byteOffset": len(self.binary), "byteLength": values.nbytes}
        if target:
            view["target"] = target
        self.document["bufferViews"].append(view)
        self.binary.extend(values.tobytes())
        component = {"<f4": 5126, "<u4": 5125, "<u2": 5123, "|u1": 5121, "<u1": 5121}[
            np.dtype(dtype).str]
        accessor = {"bufferView": len(self.document["bufferViews"]) - 1,
                    "componentType": component, "count": len(values), "type": kind}
        if normalized:
            accessor["normalized"] = True
        if bounds:
            flat = values.reshape(len(values), -1).astype(np.float64)
            accessor["min"], accessor["max"] = flat.min(0).tolist(), flat.max(0).tolist()
        self.document["accessors"].append(accessor)
        return len(self.document["accessors"]) - 1

    def glb(self) -> bytes:
        self.binary.extend(b"\0" * (-len(self.binary) % 4))
        document = {**self.document, "buffers": [{"byteLength": len(self.binary)}]}
        header = json.dumps(document).encode()
        header += b" " * (-len(header) % 4)
        return b"".join([struct.pack("<4sII", b"glTF", 2, 28 + len(header) + len(self.binary)),
                         struct.pack("<I4s", len(header), b"JSON"), header,
                         struct.pack("<I4s", len(self.binary), b"BIN\x00"),
                         bytes(self.binary)])


QUAD = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float64)
QUAD_FACES = np.array([[0, 1, 2], [0, 2, 3]])

# primitive A: every kind of attribute, some stored as normalized integers
A = {
    "NORMAL": np.tile([0.0, 0.0, 1.0], (4, 1)),
    "TEXCOORD_0": np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64),
    "TEXCOORD_1": np.array([[0, 0], [0.5, 0], [0.5, 0.5], [0, 0.5]], np.float64),
    "COLOR_0": np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [51, 51, 51]], np.uint8),
    "TANGENT": np.array([[1, 0, 0, 1], [1, 0, 0, 1], [1, 0, 0, -1], [1, 0, 0, -1]], np.float64),
    "JOINTS_0": np.array([[0, 1, 0, 0], [1, 0, 0, 0], [2, 1, 0, 0], [2, 0, 0, 0]], np.uint8),
    # sums of exactly 65535: the weights are 1 in float64 as stored
    "WEIGHTS_0": np.array([[32768, 32767, 0, 0], [65535, 0, 0, 0], [40000, 25535, 0, 0],
                           [65535, 0, 0, 0]], np.uint16),
    "_TEMPERATURE": np.array([[20.0], [21.5], [-3.0], [0.25]]),
    "_FRAME": np.tile(np.eye(4).ravel(), (4, 1)),
}
A_TARGETS = [{"POSITION": np.array([[0, 0, 1], [0, 0, 2], [0, 0, 3], [0, 0, 4]], np.float64)},
             {"NORMAL": np.tile([0.0, 0.5, 0.0], (4, 1))}]
# primitive B: normals and a float skin only; both targets move positions only
B = {"NORMAL": np.tile([0.0, 0.0, 1.0], (4, 1)),
     "JOINTS_0": np.array([[1, 2, 0, 0]] * 4, np.uint16),
     "WEIGHTS_0": np.array([[0.75, 0.25, 0, 0]] * 4, np.float64)}
B_TARGETS = [{"POSITION": np.full((4, 3), 0.5)}, {"POSITION": np.full((4, 3), -0.5)}]

_KINDS = {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4", 16: "MAT4"}


def attribute_scene(edit=None) -> bytes:
    """A skinned, morphed mesh of two quads (primitives A and B above) on node 0, its
    skin's three joints nodes 1-3, an animation of target weights."""
    builder = _Builder()
    primitives = []
    for offset, attributes, targets in ((0.0, A, A_TARGETS), (2.0, B, B_TARGETS)):
        ids = {"POSITION": builder.add(QUAD + [offset, 0, 0], "VEC3", bounds=True,
                                       target=34962)}
        for name, values in attributes.items():
            dtype = values.dtype.str if values.dtype != np.float64 else "<f4"
            normalized = name in ("COLOR_0", "WEIGHTS_0") and values.dtype != np.float64
            ids[name] = builder.add(values, _KINDS[values.shape[1]], dtype,
                                    normalized=normalized, target=34962)
        primitive = {"attributes": ids, "mode": 4,
                     "indices": builder.add(QUAD_FACES.ravel(), "SCALAR", "<u4", target=34963),
                     "targets": [{key: builder.add(value, "VEC3", bounds=key == "POSITION")
                                  for key, value in target.items()} for target in targets]}
        primitives.append(primitive)
    matrices = builder.add(np.tile(np.eye(4).ravel(), (3, 1)), "MAT4")
    times = builder.add(np.array([[0.0], [1.0]]), "SCALAR", bounds=True)
    weights = builder.add(np.array([[0.0], [0.0], [1.0], [0.5]]), "SCALAR")
    builder.document.update(
        scene=0, scenes=[{"nodes": [0, 1]}],
        nodes=[{"name": "body", "mesh": 0, "skin": 0},
               {"name": "hip", "children": [2, 3]}, {"name": "knee"}, {"name": "toe"}],
        meshes=[{"name": "quads", "primitives": primitives, "weights": [0.0, 0.0],
                 "extras": {"targetNames": ["up", "tilt"]}}],
        skins=[{"joints": [1, 2, 3], "inverseBindMatrices": matrices}],
        animations=[{"samplers": [{"input": times, "output": weights}],
                     "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}]}])
    if edit is not None:
        edit(builder)
    return builder.glb()


def mesh_rows(mesh) -> np.ndarray:
    """(w, 3 + d) float64: each wedge's position and attribute vector, sorted."""
    rows = np.hstack([mesh.positions[mesh.wedge_vertices()], mesh.attributes.values])
    return rows[np.lexsort(rows.T[::-1])]


def unique_rows(rows) -> np.ndarray:
    rows = np.unique(np.asarray(rows, dtype=np.float64), axis=0)
    return rows[np.lexsort(rows.T[::-1])]


# --- reading --------------------------------------------------------------------------------

def test_every_attribute_of_the_built_scene_with_defaults(tmp_path):
    path = tmp_path / "quads.glb"
    path.write_bytes(attribute_scene())
    scene = load_scene(path)
    mesh = scene.meshes[0]
    assert mesh.attributes.layout == (
        ("NORMAL", 3), ("TEXCOORD_0", 2), ("TEXCOORD_1", 2), ("COLOR_0", 4), ("TANGENT", 4),
        ("JOINTS_0", 4), ("WEIGHTS_0", 4), ("TARGET0_POSITION", 3), ("TARGET1_POSITION", 3),
        ("TARGET1_NORMAL", 3), ("_TEMPERATURE", 1))
    # the matrix-typed custom attribute is dropped, and said
    assert scene.reports[0].dropped_attributes == ["_FRAME"]
    assert any("_FRAME" in note for note in scene.notes)
    assert not scene.as_is
    def f32(values):        # a float attribute as float32 stored it
        return np.asarray(values, np.float32).astype(np.float64)

    colour = np.column_stack([A["COLOR_0"] / 255.0, np.ones(4)])     # VEC3: alpha 1
    expected_a = np.hstack([QUAD, A["NORMAL"], f32(A["TEXCOORD_0"]), f32(A["TEXCOORD_1"]),
                            colour, A["TANGENT"], A["JOINTS_0"], A["WEIGHTS_0"] / 65535.0,
                            A_TARGETS[0]["POSITION"], np.zeros((4, 3)),
                            A_TARGETS[1]["NORMAL"], f32(A["_TEMPERATURE"])])
    # B lacks them: UVs 0, white, a tangent in the surface (+Y for normal +Z) with w +1,
    # zero deltas for target 1's normal, zero custom values
    expected_b = np.hstack([QUAD + [2, 0, 0], B["NORMAL"], np.zeros((4, 4)), np.ones((4, 4)),
                            np.tile([0, 1, 0, 1], (4, 1)), B["JOINTS_0"], B["WEIGHTS_0"],
                            B_TARGETS[0]["POSITION"], B_TARGETS[1]["POSITION"],
                            np.zeros((4, 3)), np.zeros((4, 1))])
    expected = unique_rows(np.vstack([expected_a, expected_b]))
    np.testing.assert_array_equal(mesh_rows(mesh), expected)


def test_joints_outside_the_skin_are_refused(tmp_path):
    def short_skin(builder):
        builder.document["skins"][0]["joints"] = [1, 2]     # joint 2 is used

    path = tmp_path / "quads.glb"
    path.write_bytes(attribute_scene(short_skin))
    with pytest.raises(MeshError, match=r"^cannot load quads.glb: mesh 0 uses joint 2, but "
                                        r"skin 0 of node 0 has 2 joints$"):
        load_scene(path)


def test_a_wrongly_typed_attribute_is_one_sentence(tmp_path):
    def vec2_normals(builder):
        attributes = builder.document["meshes"][0]["primitives"][0]["attributes"]
        attributes["NORMAL"] = attributes["TEXCOORD_0"]

    path = tmp_path / "quads.glb"
    path.write_bytes(attribute_scene(vec2_normals))
    with pytest.raises(MeshError, match="its NORMAL accessor is VEC2, not VEC3"):
        load_scene(path)


def _input_rows(path, document, binary, mesh_index: int, layout) -> np.ndarray:
    """Unique (position, attribute vector) rows of mesh ``mesh_index`` straight from its
    accessors (read by the test's own accessor_values), for the vertices triangles use."""
    rows = []
    for primitive in document["meshes"][mesh_index]["primitives"]:
        def values(index):
            accessor = document["accessors"][index]
            data = accessor_values(document, binary, index).astype(np.float64)
            if accessor.get("normalized"):
                data = data / {5121: 255.0, 5123: 65535.0}[accessor["componentType"]]
            return data

        positions = values(primitive["attributes"]["POSITION"])
        if "indices" in primitive:
            used = np.unique(accessor_values(document, binary, primitive["indices"]))
        else:
            used = np.arange(len(positions))
        columns = [positions]
        for name, width in layout:
            if name.startswith("TARGET"):
                t, kind = name[6:].split("_", 1)
                source = primitive["targets"][int(t)].get(kind)
            else:
                source = primitive["attributes"].get(name)
            assert source is not None, f"{path.name}: no {name} in a primitive (no default here)"
            data = values(source)
            if name.startswith("COLOR_") and data.shape[1] == 3:
                data = np.column_stack([data, np.ones(len(data))])
            columns.append(data)
        rows.append(np.hstack(columns)[used])
    return unique_rows(np.vstack(rows))


@pytest.mark.parametrize("name", SHARED)
def test_every_attribute_read_equals_its_accessor(shared_meshes, name):
    path = shared_meshes / "scenes" / name
    if name.endswith(".gltf"):
        document = json.loads(path.read_text())
        missing = [b["uri"] for b in document["buffers"] if not (path.parent / b["uri"]).exists()]
        if missing:
            pytest.skip(f"{name}'s buffers {missing} are not in ../shared/meshes/scenes")
        # one binary of all its buffer files, the bufferViews moved to match
        blobs = [(path.parent / b["uri"]).read_bytes() for b in document["buffers"]]
        starts = np.cumsum([0] + [len(b) for b in blobs])
        for view in document["bufferViews"]:
            view["byteOffset"] = view.get("byteOffset", 0) + int(starts[view["buffer"]])
        binary = b"".join(blobs)
    else:
        document, binary = glb_chunks(path.read_bytes())
    scene = load_scene(path)
    assert scene.meshes and not scene.as_is
    for index, mesh in scene.meshes.items():
        layout = mesh.attributes.layout
        names = {n for p in document["meshes"][index]["primitives"] for n in p["attributes"]}
        names |= {f"TARGET{t}_{k}" for p in document["meshes"][index]["primitives"]
                  for t, target in enumerate(p.get("targets", ())) for k in target}
        assert {n for n, _ in layout} == names - {"POSITION"}, name
        np.testing.assert_array_equal(mesh_rows(mesh),
                                      _input_rows(path, document, binary, index, layout))


def test_flattened_loading_keeps_uvs_colours_tangents_and_drops_the_skin(tmp_path):
    def mirrored(builder):
        builder.document["nodes"][0]["scale"] = [-1.0, 2.0, 1.0]

    path = tmp_path / "quads.glb"
    path.write_bytes(attribute_scene(mirrored))
    mesh, report = load_mesh(path)
    assert [n for n, _ in mesh.attributes.layout] == [
        "NORMAL", "TEXCOORD_0", "TEXCOORD_1", "COLOR_0", "TANGENT", "_TEMPERATURE"]
    assert report.dropped_attributes == ["JOINTS_0", "TARGET0_POSITION", "TARGET1_NORMAL",
                                         "TARGET1_POSITION", "WEIGHTS_0", "_FRAME"]
    tangent = mesh.attributes.values[:, mesh.attributes.columns("TANGENT")]
    world = mesh.positions[mesh.wedge_vertices()]
    # the node maps (x, y, z) to (-x, 2y, z): A's +X tangents become -X, unit, with w
    # negated (the mirror turned the winding); B (no tangents, at x -2..-3) gets one in
    # its surface, +Y for its normal +Z, w +1
    for i, corner in enumerate(QUAD):
        at = np.flatnonzero((world == corner * [-1, 2, 1]).all(axis=1))
        assert len(at) == 1
        np.testing.assert_array_equal(tangent[at[0]], [-1, 0, 0, -A["TANGENT"][i, 3]])
    b = world[:, 0] <= -2
    assert b.sum() == 4
    np.testing.assert_array_equal(tangent[b], np.tile([0, 1, 0, 1], (4, 1)))


# --- writing --------------------------------------------------------------------------------

def test_skin_influences_are_valid_for_gltf():
    joints = np.array([[3, 3, 0, 0, 1, 0, 0, 0],      # joint 3 twice: merged
                       [5, 6, 0, 0, 0, 0, 0, 0],      # zero weights everywhere
                       [2, 300, 0, 0, 0, 0, 0, 0]], np.float64)  # a joint past 255
    weights = np.array([[0.2, 0.2, 0, 0, 0.4, 0, 0, 0],
                        [0, 0, 0, 0, 0, 0, 0, 0],
                        [0.1, 0.5, 0, 0, -0.5, 0, 0, 0.3]], np.float64)
    out_joints, out_weights = skin_influences(joints, weights)
    assert out_joints.dtype == np.uint16 and out_weights.dtype == np.float32
    np.testing.assert_allclose(out_weights.astype(np.float64).sum(axis=1), 1.0, atol=1e-7)
    np.testing.assert_allclose(out_weights[0], [0.5, 0, 0, 0, 0.5, 0, 0, 0], atol=1e-7)
    assert out_joints[0].tolist() == [3, 0, 0, 0, 1, 0, 0, 0]
    assert out_joints[1].tolist() == [0] * 8 and out_weights[1].tolist() == [1] + [0] * 7
    assert (out_weights >= 0).all() and out_joints[2, 1] == 300
    assert out_weights[2, 4] == 0 and out_joints[2, 4] == 0       # a negative weight: 0
    small, _ = skin_influences(joints[:2], weights[:2])
    assert small.dtype == np.uint8


def test_tangents_are_unit_with_a_sign():
    tangents = np.array([[2.0, 0, 0, 0.3], [0, 0, 0, -0.7], [0, 3, 4, -1]])
    normals = np.array([[0, 0, 1.0], [0, 0, 1.0], [1.0, 0, 0]])
    out = unit_tangents(tangents, normals)
    np.testing.assert_allclose(out, [[1, 0, 0, 1], [0, 1, 0, -1], [0, 0.6, 0.8, -1]])


def test_render_attributes_write_every_column():
    layout = (("NORMAL", 3), ("COLOR_1", 4), ("JOINTS_0", 4), ("WEIGHTS_0", 4),
              ("TARGET0_POSITION", 3), ("_ID", 1))
    values = np.array([[0, 0, 1, 2, -1, 0.5, 1, 4, 4, 0, 0, 1, 1, 0, 0, 1, 2, 3, 7]] * 3,
                      np.float64)
    out = render_attributes(layout, values, QUAD[:3], np.array([[0, 1, 2]]))
    assert list(out) == [name for name, _ in layout]
    np.testing.assert_array_equal(out["COLOR_1"], [[1, 0, 0.5, 1]] * 3)
    assert out["JOINTS_0"].dtype == np.uint8 and out["JOINTS_0"][0].tolist() == [4, 0, 0, 0]
    np.testing.assert_allclose(out["WEIGHTS_0"], [[1, 0, 0, 0]] * 3)
    np.testing.assert_array_equal(out["TARGET0_POSITION"], [[1, 2, 3]] * 3)
    assert out["_ID"].dtype == np.float32 and out["_ID"].tolist() == [[7]] * 3


def _round_trip(path, tmp_path):
    """Load ``path``, write every mesh at its full level (through its progressive
    mesh), load that: (scene, written GLB bytes, the scene read back)."""
    scene = load_scene(path)
    levels = {}
    for index, mesh in scene.meshes.items():
        pm = build(mesh)
        levels[index] = [pm.at(pm.vertex_count)]
    data = encode_scene(scene, levels, [0.0])
    out = tmp_path / f"again_{path.stem}.glb"
    out.write_bytes(data)
    return scene, data, load_scene(out)


def _same_attributes(scene, again, what: str):
    for index, mesh in scene.meshes.items():
        back = again.meshes[index]
        assert back.attributes.layout == mesh.attributes.layout, what
        assert (back.vertex_count, back.face_count) == (mesh.vertex_count, mesh.face_count)
        # float32 as written; normals and weights renormalised in float32
        np.testing.assert_allclose(mesh_rows(back), mesh_rows(mesh), rtol=0, atol=4e-7,
                                   err_msg=what)


@pytest.mark.parametrize("name", SHARED[:4])
def test_round_trip_of_shared_scenes(shared_meshes, tmp_path, gltf_validator, name):
    scene, data, again = _round_trip(shared_meshes / "scenes" / name, tmp_path)
    _same_attributes(scene, again, name)
    assert_valid(gltf_validator, data, f"{name} written at full level")


def test_round_trip_of_the_built_scene(tmp_path, gltf_validator):
    path = tmp_path / "quads.glb"
    path.write_bytes(attribute_scene())
    scene, data, again = _round_trip(path, tmp_path)
    _same_attributes(scene, again, "the built scene")
    assert_valid(gltf_validator, data, "the built scene written")
    document, _ = glb_chunks(data)
    mesh = document["meshes"][0]
    assert mesh["weights"] == [0.0, 0.0] and mesh["extras"]["targetNames"] == ["up", "tilt"]
    for primitive in mesh["primitives"]:
        assert [sorted(t) for t in primitive["targets"]] == [["POSITION"],
                                                             ["NORMAL", "POSITION"]]
        assert all("min" in document["accessors"][t["POSITION"]] for t in primitive["targets"])
        assert document["accessors"][primitive["attributes"]["JOINTS_0"]]["componentType"] == 5121


# --- the command line -------------------------------------------------------------------------

def _levels_of(document: dict, node: dict) -> list[dict]:
    ids = node.get("extensions", {}).get("MSFT_lod", {}).get("ids", [])
    return [node, *(document["nodes"][i] for i in ids)]


def _exported_chain(source, tmp_path, gltf_validator, what: str, *flags: str):
    """``lodserver export`` of ``source`` at 1, 0.5 and 0.2 with ``flags`` (an exit code of 0, and
    no validator error in the file): the source's JSON chunk, the chain's JSON and
    binary chunks, and the chain's node carrying MSFT_lod."""
    out = tmp_path / "out.glb"
    assert main(["export", str(source), "-o", str(out), "--lods", "1,0.5,0.2", *flags]) == 0
    before, _ = glb_chunks(source.read_bytes())
    document, binary = glb_chunks(out.read_bytes())
    assert_valid(gltf_validator, out.read_bytes(), what)
    chained = next(n for n in document["nodes"] if "mesh" in n and "MSFT_lod" in
                   n.get("extensions", {}))
    return before, document, binary, chained


def test_export_of_fox_keeps_skin_and_animations(shared_meshes, tmp_path, gltf_validator):
    before, document, binary, fox = _exported_chain(
        shared_meshes / "scenes" / "Fox.glb", tmp_path, gltf_validator, "Fox's chain")
    assert len(document["animations"]) == len(before["animations"]) == 3
    assert document["skins"][0]["joints"] == before["skins"][0]["joints"]
    joints = len(before["skins"][0]["joints"])
    levels = _levels_of(document, fox)
    faces = []
    for node in levels:
        assert node["skin"] == 0
        (primitive,) = document["meshes"][node["mesh"]]["primitives"]
        used = accessor_values(document, binary, primitive["attributes"]["JOINTS_0"])
        weights = accessor_values(document, binary, primitive["attributes"]["WEIGHTS_0"])
        assert used.max() < joints
        np.testing.assert_allclose(weights.astype(np.float64).sum(axis=1), 1.0, atol=2e-7)
        assert (weights >= 0).all()
        faces.append(document["accessors"][primitive["indices"]]["count"] // 3)
    assert len(levels) == 3 and faces[0] == 576 and faces[0] > faces[1] > faces[2]


def test_export_of_the_morph_cube_keeps_its_targets(shared_meshes, tmp_path, gltf_validator):
    source = shared_meshes / "scenes" / "AnimatedMorphCube.glb"
    # float32 attributes, read below as stored (the default quantizes them)
    before, document, binary, cube = _exported_chain(source, tmp_path, gltf_validator,
                                                     "the morph cube's chain",
                                                     "--compress", "none")
    assert document["animations"][0]["channels"] == before["animations"][0]["channels"]
    for node in _levels_of(document, cube):
        mesh = document["meshes"][node["mesh"]]
        assert mesh["weights"] == before["meshes"][0]["weights"]
        for primitive in mesh["primitives"]:
            assert [sorted(t) for t in primitive["targets"]] == [
                ["NORMAL", "POSITION", "TANGENT"]] * 2
            assert "TANGENT" in primitive["attributes"]
            tangent = accessor_values(document, binary, primitive["attributes"]["TANGENT"])
            np.testing.assert_allclose(np.linalg.norm(tangent[:, :3], axis=1), 1.0, atol=1e-6)
            assert set(np.abs(tangent[:, 3]).tolist()) == {1.0}
    # the finest level's deltas are the input's (one delta per input vertex, as a set)
    (primitive,) = document["meshes"][cube["mesh"]]["primitives"]
    (source_primitive,) = before["meshes"][0]["primitives"]
    _, source_binary = glb_chunks(source.read_bytes())
    for t in range(2):
        got = accessor_values(document, binary, primitive["targets"][t]["POSITION"])
        want = accessor_values(before, source_binary, source_primitive["targets"][t]["POSITION"])
        assert unique_rows(got).tolist() == unique_rows(want).tolist()


def test_attribute_values_are_bounded_by_the_limits(tmp_path):
    """4 triangles of 33 attribute floats per corner: 396 values, over the 16 per corner
    of an 8-triangle limit (384), though the triangles themselves are within it."""
    from lodserver.io.limits import LimitError, LoadLimits
    path = tmp_path / "quads.glb"
    path.write_bytes(attribute_scene())
    with pytest.raises(LimitError, match="vertex attributes hold 396 values"):
        load_scene(path, limits=LoadLimits(max_triangles=8))
    assert load_scene(path, limits=LoadLimits(max_triangles=9)).meshes


def test_chain_of_the_built_scene(tmp_path, gltf_validator):
    """export_lods of the built scene: the checks of test_scene_export (document kept
    apart from the meshes, every level exact), skin and morph weights on the LOD nodes,
    the validator clean."""
    from ..test_scene_export import check_scene_export
    path = tmp_path / "quads.glb"
    path.write_bytes(attribute_scene())
    _, after = check_scene_export(path, tmp_path / "out" / "quads.glb", gltf_validator)
    body = after["nodes"][0]
    for node in _levels_of(after, body):
        assert node["skin"] == 0
        mesh = after["meshes"][node["mesh"]]
        assert mesh["weights"] == [0.0, 0.0] and mesh["extras"]["targetNames"] == ["up", "tilt"]


def test_welding_keeps_a_wedge_per_distinct_carried_value():
    """Two corners of one vertex that differ only in a joint, a weight, a tangent sign
    or a morph delta stay two wedges: no carried column is merged by welding."""
    from lodserver.io import clean_mesh
    positions = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float64)
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    base = np.zeros((2, 3, 4))
    for name in ("JOINTS_0", "WEIGHTS_0", "TANGENT", "TARGET0_POSITION", "_SPEED"):
        width = 3 if name.startswith("TARGET") else 4
        values = base[..., :width].copy()
        values[1, 0, width - 1] = 1.0       # vertex 1 in face 1 differs in one column
        _, report = clean_mesh(positions, faces, corner_values=values,
                                  layout=((name, width),))
        assert report.wedges == 5 and report.seam_vertices == 1, name


def test_a_sparse_morph_target_is_read(tmp_path):
    """A target given as a sparse accessor with no bufferView: zeros but where it says."""
    def sparse(builder):
        index = builder.add(np.array([2], np.uint32), "SCALAR", "<u4")
        values = builder.add(np.array([[0.0, 0.0, 9.0]]), "VEC3")
        indices, data = (builder.document["accessors"][i] for i in (index, values))
        builder.document["accessors"].append({
            "componentType": 5126, "count": 4, "type": "VEC3",
            "sparse": {"count": 1,
                       "indices": {"bufferView": indices["bufferView"], "componentType": 5125},
                       "values": {"bufferView": data["bufferView"]}}})
        target = builder.document["meshes"][0]["primitives"][0]["targets"][0]
        target["POSITION"] = len(builder.document["accessors"]) - 1

    path = tmp_path / "quads.glb"
    path.write_bytes(attribute_scene(sparse))
    mesh = load_scene(path).meshes[0]
    delta = mesh.attributes.values[:, mesh.attributes.columns("TARGET0_POSITION")]
    world = mesh.positions[mesh.wedge_vertices()]
    a = world[:, 0] < 1.5
    expected = np.where((world[a] == QUAD[2]).all(axis=1)[:, None], [0, 0, 9.0], 0.0)
    np.testing.assert_array_equal(delta[a], expected)


@pytest.mark.parametrize("which", ["JOINTS_0", "TARGET1_NORMAL", "_TEMPERATURE"])
def test_an_attribute_declaring_a_billion_values_is_refused_unread(tmp_path, which):
    def huge(builder):
        primitive = builder.document["meshes"][0]["primitives"][0]
        index = (primitive["targets"][1]["NORMAL"] if which.startswith("TARGET")
                 else primitive["attributes"][which])
        builder.document["accessors"][index]["count"] = 10 ** 9

    path = tmp_path / "quads.glb"
    path.write_bytes(attribute_scene(huge))
    said = "morph target 1's NORMAL" if which.startswith("TARGET") else which
    with pytest.raises(MeshError, match=f"^cannot load quads.glb: a primitive's {said} has "
                                        "1000000000 values for 4 vertices$"):
        load_scene(path, root=tmp_path)


def test_a_target_of_dropped_attributes_still_counts(tmp_path, gltf_validator):
    """Target 1 holds only a TEXCOORD_0 delta, which is not kept: it stays a target of
    zero POSITION deltas, so the mesh's two weights and the animation still match."""
    def uv_target(builder):
        for primitive in builder.document["meshes"][0]["primitives"]:
            uv = builder.add(np.zeros((4, 2)), "VEC2")
            primitive["targets"][1] = {"TEXCOORD_0": uv}

    path = tmp_path / "quads.glb"
    path.write_bytes(attribute_scene(uv_target))
    scene = load_scene(path)
    names = [name for name, _ in scene.meshes[0].attributes.layout]
    assert [n for n in names if n.startswith("TARGET")] == ["TARGET0_POSITION",
                                                            "TARGET1_POSITION"]
    assert scene.reports[0].dropped_attributes == ["TARGET1_TEXCOORD_0", "_FRAME"]
    data = encode_scene(scene, {0: [scene.meshes[0]]}, [0.0])
    document, _ = glb_chunks(data)
    assert all(len(p["targets"]) == 2 for p in document["meshes"][0]["primitives"])
    assert document["meshes"][0]["weights"] == [0.0, 0.0]
    assert_valid(gltf_validator, data, "the scene with a dropped target")
