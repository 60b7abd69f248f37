"""A partly animated scene's far level (issue 28): the meshes whose nodes do not move
relative to each other merged into one each, animated parts kept, skinned meshes
merged only within one skeleton (``scene.groups``).

The scene is assembled here: three static nodes (a "building"), a carrier node
moved by an animation with two meshes under it (they move together), and a
spinning node with a mesh of its own; every mesh is separate small spheres,
which edge collapse cannot join.
"""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from lodserver.chains import REACH_SLACK
from lodserver.io.animation import node_worlds
from lodserver.io.scene import load_scene
from lodserver.pipeline import export_lods
from lodserver.scene.groups import rigid_groups

from ..io import test_gltf
from ..meshes import GlbBuilder
from ..io.test_gltf import assert_valid

gltf_validator = test_gltf.gltf_validator    # the session fixture, shared


def _balls(count: int, seed: int) -> trimesh.Trimesh:
    rng = np.random.default_rng(seed)
    return trimesh.util.concatenate([trimesh.creation.icosphere(1).apply_scale(0.3)
                                     .apply_translation(rng.random(3) * 4) for _ in range(count)])


def assembled_scene() -> bytes:
    """The GLB described in the module docstring: nodes 1-3 static (mesh 0 twice,
    mesh 1), node 4 the carrier (animated translation) of nodes 5 (mesh 1) and 6
    (mesh 2), node 7 spinning (animated rotation, mesh 2)."""
    builder = GlbBuilder()
    add = builder.add

    meshes = []
    for number, (count, seed) in enumerate(((20, 1), (15, 2), (10, 3))):
        shape = _balls(count, seed)
        position = add(shape.vertices.astype("<f4"), "VEC3", 5126, 34962, bounds=True)
        normal = add(shape.vertex_normals.astype("<f4"), "VEC3", 5126, 34962)
        indices = add(shape.faces.astype("<u4").ravel(), "SCALAR", 5125, 34963)
        meshes.append({"name": f"balls{number}", "primitives": [{
            "attributes": {"POSITION": position, "NORMAL": normal}, "indices": indices}]})
    times = add(np.array([0.0, 1.0, 2.0], "<f4"), "SCALAR", 5126, bounds=True)
    moves = add(np.array([[0, 0, 0], [0, 3, 0], [0, 0, 0]], "<f4"), "VEC3", 5126)
    turns = add(np.array([[0, 0, 0, 1], [0, 0.7071068, 0, 0.7071068], [0, 0, 0, 1]], "<f4"),
                "VEC4", 5126)
    document = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"name": "root", "children": [1, 2, 3, 4, 7]},
                  {"name": "wall A", "mesh": 0, "translation": [-6.0, 0.0, 0.0]},
                  {"name": "wall B", "mesh": 1, "translation": [0.0, 0.0, -6.0]},
                  {"name": "wall C", "mesh": 0, "translation": [6.0, 0.0, 0.0],
                   "rotation": [0.0, 0.7071068, 0.0, 0.7071068]},
                  {"name": "carrier", "translation": [0.0, 2.0, 6.0], "children": [5, 6]},
                  {"name": "cargo A", "mesh": 1, "translation": [-3.0, 0.0, 0.0]},
                  {"name": "cargo B", "mesh": 2, "translation": [3.0, 0.0, 0.0],
                   "scale": [0.5, 0.5, 0.5]},
                  {"name": "spinner", "mesh": 2, "translation": [0.0, 8.0, 0.0]}],
        "meshes": meshes,
        "animations": [{"name": "go", "channels": [
            {"sampler": 0, "target": {"node": 4, "path": "translation"}},
            {"sampler": 1, "target": {"node": 7, "path": "rotation"}}], "samplers": [
            {"input": times, "output": moves, "interpolation": "LINEAR"},
            {"input": times, "output": turns, "interpolation": "LINEAR"}]}],
    }
    return builder.glb(document)


def _document(glb: bytes) -> dict:
    length, _ = struct.unpack_from("<I4s", glb, 12)
    return json.loads(glb[20:20 + length])


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("groups") / "assembled.glb"
    path.write_bytes(assembled_scene())
    return path


def test_groups_follow_the_animation(scene_file):
    groups = rigid_groups(load_scene(scene_file))
    found = {group.anchor: sorted(node for node, _ in group.members) for group in groups}
    # the static world and the carrier's cargo; the spinner moves alone, a part
    assert found == {None: [1, 2, 3], 4: [5, 6]}
    carrier = next(group for group in groups if group.anchor == 4)
    # each member placed in the carrier's frame: its own local transform
    assert np.allclose(carrier.matrices[0][:3, 3], [-3.0, 0.0, 0.0])


def test_the_far_level_merges_each_group_and_keeps_the_parts(scene_file, tmp_path,
                                                              gltf_validator):
    lods = (1, 0.02)
    done = export_lods(scene_file, tmp_path / "out.glb", lods=lods, separate=True)
    full = done.drawn[0]
    budget = lods[1] * full
    assert abs(done.drawn[1] - budget) <= 0.1 * budget, (done.drawn, budget)
    stuck = export_lods(scene_file, tmp_path / "stuck.glb", lods=lods, separate=True,
                        reach="none")
    assert stuck.drawn[1] > REACH_SLACK * budget       # edge collapse alone stops above it
    far = done.outputs[1].read_bytes()
    assert_valid(gltf_validator, far, "a partly animated scene's far level")
    document = _document(far)
    nodes = document["nodes"]
    merged = [n for n, node in enumerate(nodes) if node.get("name") == "merged"]
    assert len(merged) == 2
    # the static group's node is a root of the scene, the cargo's a child of the carrier
    roots = document["scenes"][0]["nodes"]
    assert sum(n in roots for n in merged) == 1
    assert any(n in nodes[4].get("children", ()) for n in merged)
    # the grouped nodes draw nothing; the spinner keeps its mesh and its animation
    assert all("mesh" not in nodes[n] for n in (1, 2, 3, 5, 6)) and "mesh" in nodes[7]
    targets = sorted(c["target"]["node"] for c in document["animations"][0]["channels"])
    assert targets == [4, 7]
    # three draw calls: two merged groups and the spinner
    drawn = [n for n, node in enumerate(nodes) if "mesh" in node]
    assert sum(len(document["meshes"][nodes[n]["mesh"]]["primitives"]) for n in drawn) == 3


def test_the_merged_cargo_moves_with_its_carrier(scene_file, tmp_path):
    """At rest the merged cargo lies where its meshes lay: every vertex of it, placed
    through the carrier's transform, within a sphere's size of the cargo nodes'
    surface (the carrier's own move is 6 units)."""
    done = export_lods(scene_file, tmp_path / "out.glb", lods=(1, 0.02), separate=True)
    source, far = load_scene(scene_file), load_scene(done.outputs[1])
    before, after = node_worlds(source.document, source.carried), \
        node_worlds(far.document, far.carried)
    placed = np.concatenate([source.meshes[source.document["nodes"][n]["mesh"]].positions
                             @ before[n][:3, :3].T + before[n][:3, 3] for n in (5, 6)])
    node = next(n for n in far.document["nodes"][4]["children"]
                if far.document["nodes"][n].get("name") == "merged")
    mesh = far.meshes[far.document["nodes"][node]["mesh"]]
    moved = mesh.positions @ after[node][:3, :3].T + after[node][:3, 3]
    distance, _ = cKDTree(placed).query(moved)
    assert distance.max() < 0.6, distance.max()


def test_skinned_meshes_group_only_within_their_skeleton(shared_meshes):
    """Fox's one skinned mesh placed by a second node with the same skin groups with
    it; a third node with another skin does not."""
    scene = load_scene(shared_meshes / "scenes" / "Fox.glb")
    document = scene.document
    nodes = document["nodes"]
    skinned = next(n for n, node in enumerate(nodes) if "skin" in node)
    skins = document["skins"]
    scene.document = {**document, "skins": [*skins, dict(skins[0])],
                      "nodes": [*nodes, dict(nodes[skinned]),
                                {**nodes[skinned], "skin": len(skins)}],
                      "scenes": [{"nodes": [*document["scenes"][0]["nodes"],
                                            len(nodes), len(nodes) + 1]}]}
    groups = rigid_groups(scene)
    assert [(group.skin, sorted(n for n, _ in group.members)) for group in groups] == [
        (nodes[skinned]["skin"], [skinned, len(nodes)])]


def test_one_file_chain_bakes_its_merged_parts_once(scene_file, tmp_path, gltf_validator):
    """In one file (``MSFT_lod`` per node, so every part keeps its own levels) the
    parts a level merges share one atlas and one material: one bake, not one each."""
    done = export_lods(scene_file, tmp_path / "one.glb", lods=(1, 0.02))
    budget = 0.02 * done.drawn[0]
    assert done.drawn[1] <= (1 + 0.1) * budget, (done.drawn, budget)
    data = done.outputs[0].read_bytes()
    assert_valid(gltf_validator, data, "a one-file chain with parts baked together")
    document = _document(data)
    coarse = [mesh for mesh in document["meshes"] if mesh.get("name", "").endswith("LOD1")]
    assert len(coarse) == 3
    used = {primitive.get("material") for mesh in coarse for primitive in mesh["primitives"]}
    assert len(used) == 1 and len(document["materials"]) == 1
    assert len(document["images"]) == 2        # base colour and normal map, once
