"""export_lods of a glTF scene: the same document out, each mesh replaced by its LOD chain.

Checked on the scene tests/io/test_scene.py builds (instancing, a camera, a light,
unknown extensions, extras, an animation) and on ../shared/meshes: node tree,
names, transforms, cameras, lights, materials and extensions identical apart from
the meshes; instancing kept; each level's glTF mesh exactly the progressive mesh's
level; the Khronos validator clean.
"""

from __future__ import annotations

import copy
import re

import numpy as np
import pytest

from lodserver import build
from lodserver.io.glb import render_primitives
from lodserver.io.scene import load_scene
from lodserver.pipeline import export_lods
from lodserver.simplify.poses import scene_poses

from .conftest import glb_chunks
from .io import test_gltf
from .io.test_gltf import assert_valid
from .io.test_scene import scene_glb

LODS = (1.0, 0.5, 0.2)
gltf_validator = test_gltf.gltf_validator    # the session fixture, shared


def accessor_values(document: dict, binary: bytes, index: int) -> np.ndarray:
    """(count, width) values of a tightly packed accessor of a GLB lodserver wrote."""
    accessor = document["accessors"][index]
    view = document["bufferViews"][accessor["bufferView"]]
    dtype = {5126: "<f4", 5125: "<u4", 5123: "<u2", 5122: "<i2", 5121: "<u1",
             5120: "<i1"}[accessor["componentType"]]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}[accessor["type"]]
    start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    item = np.dtype(dtype).itemsize
    stride = view.get("byteStride", item * width)
    return np.ndarray((accessor["count"], width), dtype, buffer=binary, offset=start,
                      strides=(stride, item))


def without_meshes(document: dict) -> dict:
    """``document`` without what the export rewrites: meshes and their data, the nodes'
    mesh, MSFT_lod and screen coverage, the generator; nodes past the input's are LOD nodes."""
    kept = {key: copy.deepcopy(value) for key, value in document.items()
            if key not in ("meshes", "accessors", "bufferViews", "buffers", "extensionsUsed")}
    kept["asset"].pop("generator", None)
    for node in kept.get("nodes", ()):
        node.pop("mesh", None)
        extensions = node.get("extensions", {})
        extensions.pop("MSFT_lod", None)
        if "EXT_mesh_gpu_instancing" in extensions:   # accessor indices are renumbered
            attributes = extensions["EXT_mesh_gpu_instancing"]["attributes"]
            extensions["EXT_mesh_gpu_instancing"]["attributes"] = sorted(attributes)
        if not extensions:
            node.pop("extensions", None)
        if isinstance(node.get("extras"), dict):
            node["extras"].pop("MSFT_screencoverage", None)
            if not node["extras"]:
                node.pop("extras")
    for image in kept.get("images", ()):
        image.pop("bufferView", None)
        image.pop("uri", None)
    for animation in kept.get("animations", ()):
        for sampler in animation["samplers"]:
            sampler.pop("input"), sampler.pop("output")
    for skin in kept.get("skins", ()):
        skin.pop("inverseBindMatrices", None)
    return kept


def carried_equal(source_doc, scene, document, binary, old: int, new: int):
    """The output accessor ``new`` holds the values of the input's accessor ``old``."""
    assert document["accessors"][new]["componentType"] == source_doc["accessors"][old][
        "componentType"]
    assert document["accessors"][new]["type"] == source_doc["accessors"][old]["type"]
    np.testing.assert_array_equal(accessor_values(document, binary, new), scene.carried[old][0])


def assert_primitives_equal(document: dict, binary: bytes, written: list, expected: list):
    """The glTF primitives ``written`` hold ``expected`` (render_primitives' tuples):
    material, positions, indices, every attribute and morph target delta."""
    assert len(written) == len(expected)
    for record, (material, vertices, attributes, indices) in zip(written, expected):
        assert record.get("material", -1) == material
        np.testing.assert_array_equal(
            accessor_values(document, binary, record["attributes"]["POSITION"]),
            vertices.astype(np.float32))
        np.testing.assert_array_equal(
            accessor_values(document, binary, record["indices"]).reshape(-1, 3), indices)
        targets = record.get("targets", [])
        for name, values in attributes.items():
            morph = re.fullmatch(r"TARGET(\d+)_(\w+)", name)
            index = (targets[int(morph[1])][morph[2]] if morph
                     else record["attributes"][name])
            np.testing.assert_array_equal(accessor_values(document, binary, index), values)
        assert set(record["attributes"]) == {"POSITION", *(
            name for name in attributes if not name.startswith("TARGET"))}


def written_level(pm, document: dict, binary: bytes, mesh: dict) -> int:
    """The level (vertex count) of ``pm`` that glTF mesh ``mesh`` holds exactly; a
    test failure if it is none of the levels with its face count."""
    faces = sum(document["accessors"][p["indices"]]["count"] // 3 for p in mesh["primitives"])
    candidates = np.flatnonzero(pm.face_counts == faces) + pm.base_vertices
    assert len(candidates), f"no level of the mesh has {faces} faces"
    failure = None
    for level in candidates[::-1]:          # finest first: the budget's usual pick
        try:
            assert_primitives_equal(document, binary, mesh["primitives"],
                                    list(render_primitives(pm.at(int(level)))))
            return int(level)
        except AssertionError as exc:
            failure = exc
    raise failure


def check_scene_export(source, out, validate=None) -> tuple[dict, dict]:
    """Export ``source`` as a chain and --separate and check everything the brief asks;
    (input document, output document) of the chain."""
    scene = load_scene(source)
    # every level edge collapse's, so that each is checked against its progressive mesh
    done = export_lods(source, out, lods=LODS, reach="none")
    document, binary = glb_chunks(out.read_bytes())
    source_doc = scene.document
    count, meshes = len(LODS), sorted(scene.meshes)
    n = len(source_doc["nodes"])
    # the document is the input's apart from the meshes
    expected = without_meshes(source_doc)
    got = without_meshes(document)
    got["nodes"] = got["nodes"][:n]
    for key in ("images",):
        expected.pop(key, None), got.pop(key, None)
    assert got == expected
    chained = ["MSFT_lod"] if meshes else []
    assert document.get("extensionsUsed", []) == [
        *[e for e in source_doc.get("extensionsUsed", ())
          if e != "KHR_mesh_quantization" or scene.as_is], *chained]
    # instancing kept: one glTF mesh per level per source mesh
    assert len(document["meshes"]) == count * len(meshes) + len(scene.as_is)
    lod_meshes = {}
    for number, node in enumerate(document["nodes"][:n]):
        if "mesh" not in source_doc["nodes"][number]:
            assert "mesh" not in node
            continue
        old_mesh = source_doc["nodes"][number]["mesh"]
        if old_mesh in scene.as_is:
            # kept as it is: the same primitives, every accessor's values carried
            assert "MSFT_lod" not in node.get("extensions", {})
            for old, new in zip(source_doc["meshes"][old_mesh]["primitives"],
                                document["meshes"][node["mesh"]]["primitives"]):
                assert old.get("material") == new.get("material")
                for before, after in zip((old["attributes"], *old.get("targets", ())),
                                         (new["attributes"], *new.get("targets", ()))):
                    assert before.keys() == after.keys()
                    for name in before:
                        carried_equal(source_doc, scene, document, binary, before[name],
                                      after[name])
                if "indices" in old:
                    carried_equal(source_doc, scene, document, binary, old["indices"],
                                  new["indices"])
            continue
        ids = node["extensions"]["MSFT_lod"]["ids"]
        assert len(ids) == count - 1 and all(i >= n for i in ids)
        assert node["extras"]["MSFT_screencoverage"] == pytest.approx(done.coverage)
        chain = [node["mesh"], *(document["nodes"][i]["mesh"] for i in ids)]
        # every node instancing one source mesh shares its level meshes
        assert lod_meshes.setdefault(source_doc["nodes"][number]["mesh"], chain) == chain
        for i in ids:
            lod = document["nodes"][i]
            assert "children" not in lod
            for key in ("matrix", "translation", "rotation", "scale"):
                assert lod.get(key) == node.get(key)
    roots = {r for s in document["scenes"] for r in s["nodes"]}
    assert roots.isdisjoint(range(n, len(document["nodes"])))
    assert len(document["nodes"]) == n + (count - 1) * sum(
        1 for node in source_doc["nodes"] if "mesh" in node and node["mesh"] in scene.meshes)
    for old, new in zip(source_doc.get("skins", ()), document.get("skins", ())):
        carried_equal(source_doc, scene, document, binary, old["inverseBindMatrices"],
                      new["inverseBindMatrices"])
    for old, new in zip(source_doc.get("animations", ()), document.get("animations", ())):
        for old_sampler, new_sampler in zip(old["samplers"], new["samplers"]):
            for key in ("input", "output"):
                carried_equal(source_doc, scene, document, binary, old_sampler[key],
                              new_sampler[key])
    # each level's mesh is exactly one of the progressive mesh's levels, as
    # render_primitives has it (which level, the scene budget chooses)
    written_faces = [sum(scene.as_is_faces.values())] * count
    for index in meshes:
        pm = build(scene.meshes[index], poses=scene_poses(scene, index, scene.meshes[index]))
        for k, mesh_index in enumerate(lod_meshes[index]):
            level = written_level(pm, document, binary, document["meshes"][mesh_index])
            written_faces[k] += pm.faces_at_level(level)
    assert done.faces == written_faces
    if validate is not None:
        assert_valid(validate, out.read_bytes(), f"chain of {source.name}")
    # --separate: one complete scene per level
    separate = export_lods(source, out.with_name("sep.glb"), lods=LODS, separate=True,
                           reach="none")
    assert [p.name for p in separate.outputs] == [f"sep_lod{k}.glb" for k in range(count)]
    for k, path in enumerate(separate.outputs):
        level_doc, _ = glb_chunks(path.read_bytes())
        assert len(level_doc["meshes"]) == len(meshes) + len(scene.as_is)
        assert "MSFT_lod" not in level_doc.get("extensionsUsed", ())
        level_got = without_meshes(level_doc)
        level_got.pop("images", None)
        assert level_got == expected
        faces = sum(level_doc["accessors"][p.get("indices", p["attributes"]["POSITION"])]
                    ["count"] // 3 for mesh in level_doc["meshes"] for p in mesh["primitives"]
                    if p.get("mode", 4) == 4)
        assert faces == done.faces[k]
        if validate is not None and k in (0, count - 1):
            assert_valid(validate, path.read_bytes(), f"level {k} of {source.name}")
    return source_doc, document


def test_built_scene(tmp_path, gltf_validator):
    source = tmp_path / "stage.glb"
    source.write_bytes(scene_glb())
    assert_valid(gltf_validator, source.read_bytes(), "the built scene")   # a fair input
    before, after = check_scene_export(source, tmp_path / "out" / "stage.glb", gltf_validator)
    # spot instanced twice and the ball once: 2 source meshes, 3 levels
    assert len(after["meshes"]) == 6 and len(after["nodes"]) == 6 + 3 * 2
    assert after["cameras"] == before["cameras"]
    assert after["extensions"] == before["extensions"]          # lights, the unknown one
    assert after["nodes"][1]["extensions"]["VENDOR_node_tag"] == {"tag": "a"}
    assert after["nodes"][2]["extras"]["note"] == "big"
    assert after["nodes"][1]["name"] == "spotA" and after["nodes"][6]["name"] == "spotA LOD1"
    assert after["meshes"][after["nodes"][3]["mesh"]]["extras"] == {"kind": "ball"}
    assert after["materials"] == before["materials"]
    # the animation's keys and values, as they were
    _, source_binary = glb_chunks(source.read_bytes())
    document, binary = glb_chunks((tmp_path / "out" / "stage.glb").read_bytes())
    old, new = before["animations"][0]["samplers"][0], after["animations"][0]["samplers"][0]
    for key in ("input", "output"):
        np.testing.assert_array_equal(accessor_values(document, binary, new[key]),
                                      accessor_values(before, source_binary, old[key]))
    assert after["animations"][0]["channels"] == before["animations"][0]["channels"]


def test_required_unknown_extension_is_refused(tmp_path):
    def edit(document):
        document["extensionsUsed"].append("VENDOR_must_have")
        document["extensionsRequired"] = ["VENDOR_must_have"]

    source = tmp_path / "stage.glb"
    source.write_bytes(scene_glb(edit))
    from lodserver.mesh import MeshError
    with pytest.raises(MeshError, match="requires the glTF extension VENDOR_must_have"):
        export_lods(source, tmp_path / "out.glb")
    assert not (tmp_path / "out.glb").exists()


@pytest.mark.parametrize("name", ["Duck.glb", "2CylinderEngine.glb", "Avocado/Avocado.gltf",
                                  "scenes/BoxAnimated.glb"])
def test_shared_scenes(shared_meshes, tmp_path, gltf_validator, name):
    check_scene_export(shared_meshes / name, tmp_path / "out.glb", gltf_validator)


@pytest.mark.parametrize("name", ["Fox.glb", "RiggedSimple.glb", "AnimatedMorphCube.glb"])
def test_skinned_and_morphed_meshes_get_levels(shared_meshes, tmp_path, gltf_validator, name):
    """Skinned and morphed meshes are simplified like any other: every level keeps its
    joints (valid for the skin), weights summing to 1 and morph targets; the LOD nodes
    carry the node's skin; skins, morph weights and animations survive."""
    source = shared_meshes / "scenes" / name
    before, after = check_scene_export(source, tmp_path / "out.glb", gltf_validator)
    scene = load_scene(source)
    assert scene.meshes and not scene.as_is
    for key in ("skins", "animations"):
        assert len(after.get(key, ())) == len(before.get(key, ()))
    document, binary = glb_chunks((tmp_path / "out.glb").read_bytes())
    n = len(before["nodes"])
    for number, node in enumerate(before["nodes"]):
        if "mesh" not in node:
            continue
        out = document["nodes"][number]
        lods = [out, *(document["nodes"][i] for i in out["extensions"]["MSFT_lod"]["ids"])]
        assert all(i >= n for i in out["extensions"]["MSFT_lod"]["ids"])
        source_mesh = before["meshes"][node["mesh"]]
        targets = len(source_mesh["primitives"][0].get("targets", ()))
        for lod in lods:
            assert lod.get("skin") == node.get("skin")
            mesh = document["meshes"][lod["mesh"]]
            assert mesh.get("weights") == source_mesh.get("weights")
            for primitive in mesh["primitives"]:
                assert len(primitive.get("targets", ())) == targets
                names = primitive["attributes"]
                if "skin" in node:
                    joints = accessor_values(document, binary, names["JOINTS_0"])
                    weights = accessor_values(document, binary, names["WEIGHTS_0"])
                    assert joints.max() < len(before["skins"][node["skin"]]["joints"])
                    np.testing.assert_allclose(weights.astype(np.float64).sum(axis=1), 1.0,
                                               atol=2e-7)


def test_a_morphed_mesh_beside_static_ones(tmp_path, gltf_validator):
    """The ball gets a morph target: it is simplified with its target and weights, and
    the spot gets its chain as before."""
    def morphed(document):
        primitive = document["meshes"][1]["primitives"][0]
        primitive["targets"] = [{"POSITION": primitive["attributes"]["POSITION"]}]
        document["meshes"][1]["weights"] = [0.5]
        document["meshes"][1]["extras"]["targetNames"] = ["grow"]

    source = tmp_path / "stage.glb"
    source.write_bytes(scene_glb(morphed))
    assert_valid(gltf_validator, source.read_bytes(), "the morphed scene")
    _, after = check_scene_export(source, tmp_path / "out.glb", gltf_validator)
    ids = after["nodes"][3]["extensions"]["MSFT_lod"]["ids"]
    for node in (after["nodes"][3], *(after["nodes"][i] for i in ids)):
        ball = after["meshes"][node["mesh"]]
        assert ball["weights"] == [0.5] and len(ball["primitives"][0]["targets"]) == 1
        assert ball["extras"]["targetNames"] == ["grow"]
    assert "MSFT_lod" in after["nodes"][1]["extensions"]
    assert len(after["meshes"]) == 2 * len(LODS)


def test_carried_vertex_data_and_gpu_instancing(tmp_path, gltf_validator):
    """A kept mesh's (points, no triangles) 3-byte colours get a padded stride (vertex data is 4-byte aligned)
    and keep their values; EXT_mesh_gpu_instancing's accessors follow their node."""
    from .io.test_scene import pack_glb, scene_document
    document, binary = scene_document()
    primitive = document["meshes"][1]["primitives"][0]
    count = document["accessors"][primitive["attributes"]["POSITION"]]["count"]
    colours = (np.arange(count * 3) % 251).astype(np.uint8)
    binary.extend(b"\0" * (-len(binary) % 4))
    document["bufferViews"].append({"buffer": 0, "byteOffset": len(binary),
                                    "byteLength": count * 4, "byteStride": 4, "target": 34962})
    binary.extend(np.column_stack([colours.reshape(-1, 3),
                                   np.zeros(count, np.uint8)]).tobytes())
    document["accessors"].append({"bufferView": len(document["bufferViews"]) - 1,
                                  "componentType": 5121, "normalized": True, "count": count,
                                  "type": "VEC3"})
    primitive["attributes"]["COLOR_0"] = len(document["accessors"]) - 1
    primitive["mode"] = 0           # points: no triangles, so the mesh is written as it is
    offsets = np.array([[0, 0, 0], [5, 0, 0]], np.float32)
    binary.extend(offsets.tobytes())
    document["bufferViews"].append({"buffer": 0, "byteOffset": len(binary) - 24,
                                    "byteLength": 24})
    document["accessors"].append({"bufferView": len(document["bufferViews"]) - 1,
                                  "componentType": 5126, "count": 2, "type": "VEC3"})
    document["nodes"][1]["extensions"]["EXT_mesh_gpu_instancing"] = {
        "attributes": {"TRANSLATION": len(document["accessors"]) - 1}}
    document["extensionsUsed"].append("EXT_mesh_gpu_instancing")
    source = tmp_path / "stage.glb"
    source.write_bytes(pack_glb(document, bytes(binary)))
    assert_valid(gltf_validator, source.read_bytes(), "the coloured scene")
    _, after = check_scene_export(source, tmp_path / "out.glb", gltf_validator)
    written, data = glb_chunks((tmp_path / "out.glb").read_bytes())
    colour = written["meshes"][after["nodes"][3]["mesh"]]["primitives"][0]["attributes"]["COLOR_0"]
    assert written["bufferViews"][written["accessors"][colour]["bufferView"]]["byteStride"] == 4
    np.testing.assert_array_equal(accessor_values(written, data, colour), colours.reshape(-1, 3))
    moved = after["nodes"][1]["extensions"]["EXT_mesh_gpu_instancing"]["attributes"]
    np.testing.assert_array_equal(accessor_values(written, data, moved["TRANSLATION"]), offsets)
    # the node's levels are instanced as it is
    for i in after["nodes"][1]["extensions"]["MSFT_lod"]["ids"]:
        assert after["nodes"][i]["extensions"]["EXT_mesh_gpu_instancing"]["attributes"] == moved


def test_untrusted_scene_keeps_to_its_folder(tmp_path):
    from lodserver.mesh import MeshError

    from .io.test_scene import scene_document
    document, binary = scene_document()
    (tmp_path / "outside.bin").write_bytes(bytes(binary))
    inner = tmp_path / "inner"
    inner.mkdir()
    document["buffers"] = [{"byteLength": len(binary), "uri": "../outside.bin"}]
    (inner / "stage.gltf").write_text(__import__("json").dumps(document))
    with pytest.raises(MeshError, match="^cannot load stage.gltf: ") as caught:
        export_lods(inner / "stage.gltf", tmp_path / "out.glb", untrusted=True)
    assert str(tmp_path) not in str(caught.value) and not (tmp_path / "out.glb").exists()
    assert export_lods(inner / "stage.gltf", tmp_path / "out.glb").outputs   # trusted: fine
