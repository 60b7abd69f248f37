"""glTF animation sampling and skin joint matrices (lodserver.io.animation): samplers
against hand-computed values, a small document by hand, and Fox against TRS composed by hand."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import CubicHermiteSpline
from scipy.spatial.transform import Rotation

from lodserver.io.animation import (
    clip_range,
    joint_matrices,
    node_weights,
    node_worlds,
    sample,
    sample_times,
    slerp,
    trs_matrix,
)
from lodserver.mesh import MeshError


def z_quaternion(degrees):
    return Rotation.from_euler("z", degrees, degrees=True).as_quat()    # x y z w


# --------------------------------------------------------------------------
# Samplers by hand
# --------------------------------------------------------------------------

def test_linear_interpolates_and_clamps_outside_the_keyframes():
    times, values = [0.0, 2.0], [[0.0, 0.0, 0.0], [2.0, 4.0, 6.0]]
    assert np.allclose(sample(times, values, 0.5), [0.5, 1.0, 1.5])
    assert np.allclose(sample(times, values, -1.0), [0, 0, 0])
    assert np.allclose(sample(times, values, 5.0), [2, 4, 6])


def test_step_holds_the_previous_keyframe():
    times, values = [0.0, 1.0, 2.0], [[1.0], [5.0], [9.0]]
    assert sample(times, values, 0.99, "STEP")[0] == 1.0
    assert sample(times, values, 1.0, "STEP")[0] == 5.0
    assert sample(times, values, 1.5, "STEP")[0] == 5.0
    assert sample(times, values, 7.0, "STEP")[0] == 9.0


def test_cubic_spline_by_hand_with_tangents_scaled_by_the_interval():
    # keys (in, value, out): v0 = 0 leaving at 1.5/s, v1 = 1 arriving at -0.5/s, dt = 2
    values = [[9.0], [0.0], [1.5], [-0.5], [1.0], [9.0]]
    # s = 1/2: h00 = h01 = 1/2, h10 = 1/8, h11 = -1/8
    # p = 0 + (1/8) 2 (1.5) + (1/2) 1 + (-1/8) 2 (-0.5) = 0.375 + 0.5 + 0.125
    assert sample([0.0, 2.0], values, 1.0, "CUBICSPLINE")[0] == pytest.approx(1.0)
    assert sample([0.0, 2.0], values, -3.0, "CUBICSPLINE")[0] == 0.0
    assert sample([0.0, 2.0], values, 3.0, "CUBICSPLINE")[0] == 1.0


def test_cubic_spline_matches_a_hermite_spline_when_in_and_out_tangents_agree():
    times = np.array([0.0, 0.5, 2.0, 2.25])
    keys = np.array([1.0, -2.0, 0.5, 3.0])
    slopes = np.array([0.3, 4.0, -1.0, 2.0])
    values = np.stack([slopes, keys, slopes], 1).reshape(-1, 1)
    reference = CubicHermiteSpline(times, keys, slopes)
    for t in np.linspace(0.0, 2.25, 23):
        assert sample(times, values, t, "CUBICSPLINE")[0] == pytest.approx(float(reference(t)))


def test_slerp_turns_at_a_constant_rate_along_the_shorter_arc():
    q0, q1 = z_quaternion(0), z_quaternion(90)
    assert np.allclose(slerp(q0, q1, 0.5), z_quaternion(45))
    # a linear blend of the two would turn 26.6 degrees at s = 1/4, slerp turns 22.5
    got = sample([0.0, 1.0], [q0, q1], 0.25, rotation=True)
    assert np.allclose(got, z_quaternion(22.5))
    # -q1 is the same rotation: still the 90-degree arc, not the 270-degree one
    assert np.allclose(slerp(q0, -q1, 0.5), z_quaternion(45))
    assert np.linalg.norm(got) == pytest.approx(1.0)


def test_cubic_spline_rotations_come_out_unit():
    q0, q1 = z_quaternion(0), z_quaternion(120)
    zero = np.zeros(4)
    got = sample([0.0, 1.0], [zero, q0, zero, zero, q1, zero], 0.3, "CUBICSPLINE", rotation=True)
    assert np.linalg.norm(got) == pytest.approx(1.0)
    assert got[3] > 0 and got[2] > 0                   # between the two about +z


def test_bad_samplers_are_refused_in_one_sentence():
    with pytest.raises(MeshError, match="interpolation"):
        sample([0.0, 1.0], [[0.0], [1.0]], 0.5, "BEZIER")
    with pytest.raises(MeshError, match="keyframes"):
        sample([0.0, 1.0], [[0.0], [1.0]], 0.5, "CUBICSPLINE")


# --------------------------------------------------------------------------
# A small document by hand
# --------------------------------------------------------------------------

def carried_of(arrays: dict) -> dict:
    """{accessor: (values, record, role)} as Scene.carried holds them, float32."""
    return {index: (np.asarray(values, np.float32).reshape(len(values), -1),
                    {"componentType": 5126}, "other") for index, values in arrays.items()}


def arm_document():
    """root (translated) -> joint (rotated about z by the animation) -> tip; a mesh node
    with two morph targets whose weights are animated; a skin of joint and tip."""
    document = {
        "nodes": [
            {"name": "root", "translation": [1.0, 0.0, 0.0], "children": [1, 3]},
            {"name": "joint", "translation": [0.0, 2.0, 0.0], "children": [2]},
            {"name": "tip", "translation": [0.0, 1.0, 0.0], "scale": [2.0, 2.0, 2.0]},
            {"name": "body", "mesh": 0, "skin": 0, "translation": [0.0, 0.0, 5.0]},
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 9},
                                    "targets": [{"POSITION": 9}, {"POSITION": 9}]}],
                    "weights": [0.25, 0.0]}],
        "skins": [{"joints": [1, 2], "inverseBindMatrices": 4}],
        "animations": [{
            "samplers": [{"input": 0, "output": 1},
                         {"input": 0, "output": 2, "interpolation": "STEP"}],
            "channels": [{"sampler": 0, "target": {"node": 1, "path": "rotation"}},
                         {"sampler": 1, "target": {"node": 3, "path": "weights"}}]}],
    }
    rest_joint = trs_matrix((1.0, 2.0, 0.0))
    rest_tip = rest_joint @ trs_matrix((0.0, 1.0, 0.0), scale=(2, 2, 2))
    inverse_bind = np.stack([np.linalg.inv(rest_joint), np.linalg.inv(rest_tip)])
    carried = carried_of({
        0: [0.0, 1.0],
        1: [z_quaternion(0), z_quaternion(90)],
        2: [1.0, 0.0, 0.0, 1.0],                       # per keyframe: 2 target weights
        4: inverse_bind.transpose(0, 2, 1).reshape(2, 16),   # column-major
    })
    return document, carried


def test_rest_pose_worlds_compose_parents_first():
    document, carried = arm_document()
    worlds = node_worlds(document, carried)
    assert np.allclose(worlds[2][:3, 3], [1.0, 3.0, 0.0])
    assert np.allclose(worlds[2][:3, :3], 2 * np.eye(3))
    assert np.allclose(worlds[3][:3, 3], [1.0, 0.0, 5.0])


def test_an_animated_rotation_turns_the_subtree():
    document, carried = arm_document()
    worlds = node_worlds(document, carried, 0.5, 0)
    turn = Rotation.from_euler("z", 45, degrees=True).as_matrix()
    assert np.allclose(worlds[1][:3, :3], turn)
    # the tip sits 1 up the joint's turned y axis
    assert np.allclose(worlds[2][:3, 3], [1.0, 2.0, 0.0] + turn @ [0.0, 1.0, 0.0])
    assert np.allclose(worlds[0], node_worlds(document, carried)[0])


def test_morph_weights_animated_defaulted_and_checked():
    document, carried = arm_document()
    assert np.allclose(node_weights(document, carried, 3), [0.25, 0.0])      # the mesh's
    assert np.allclose(node_weights(document, carried, 3, 0.5, 0), [1.0, 0.0])   # STEP
    assert np.allclose(node_weights(document, carried, 3, 1.0, 0), [0.0, 1.0])
    document["nodes"][3]["weights"] = [0.5]
    with pytest.raises(MeshError, match="2 targets"):
        node_weights(document, carried, 3)


def test_joint_matrices_in_the_mesh_nodes_space():
    document, carried = arm_document()
    rest = node_worlds(document, carried)
    matrices = joint_matrices(document, carried, 0, 3, rest)
    # at rest each joint matrix undoes its inverse bind: only the mesh node's inverse is left
    assert np.allclose(matrices, np.linalg.inv(rest[3]))
    posed = node_worlds(document, carried, 1.0, 0)
    matrices = joint_matrices(document, carried, 0, 3, posed)
    expected = np.linalg.inv(posed[3]) @ posed[2] @ np.linalg.inv(rest[2])
    assert np.allclose(matrices[1], expected)
    del document["skins"][0]["inverseBindMatrices"]
    assert np.allclose(joint_matrices(document, carried, 0, 3, posed)[0],
                       np.linalg.inv(posed[3]) @ posed[1])


def test_sample_times_spread_over_every_clip():
    document, carried = arm_document()
    document["animations"].append({"samplers": [{"input": 5, "output": 6}], "channels": [
        {"sampler": 0, "target": {"node": 2, "path": "translation"}}]})
    carried.update(carried_of({5: [2.0, 6.0], 6: [[0, 0, 0], [0, 1, 0]]}))
    found = sample_times(document, carried, 5)
    assert [clip for clip, _ in found] == [0, 0, 0, 1, 1]
    assert np.allclose([t for _, t in found], [1 / 6, 0.5, 5 / 6, 3.0, 5.0])
    assert [clip for clip, _ in sample_times(document, carried, 1)] == [0]
    assert sample_times({"nodes": []}, {}, 8) == []


def test_a_cycle_or_a_missing_clip_is_refused():
    document, carried = arm_document()
    with pytest.raises(MeshError, match="animation 3"):
        node_worlds(document, carried, 0.0, 3)
    document["nodes"][2]["children"] = [1]
    with pytest.raises(MeshError):
        node_worlds(document, carried)


# --------------------------------------------------------------------------
# Fox (shared asset): a joint's world at a keyframe equals TRS composed by hand
# --------------------------------------------------------------------------

def test_fox_joint_world_at_a_keyframe_is_trs_composed_by_hand(shared_meshes):
    from lodserver.io.scene import load_scene
    scene = load_scene(shared_meshes / "scenes" / "Fox.glb")
    document, carried = scene.document, scene.carried
    nodes = document["nodes"]
    clip = 2                                         # "Run"
    animation = document["animations"][clip]
    head = next(i for i, node in enumerate(nodes) if node["name"] == "b_Head_05")
    first_sampler = animation["samplers"][0]
    times = carried[first_sampler["input"]][0].ravel().astype(np.float64)
    k = len(times) // 3
    time = float(times[k])

    def value(node, path, default):
        for channel in animation["channels"]:
            if channel["target"] == {"node": node, "path": path}:
                sampler = animation["samplers"][channel["sampler"]]
                keys = carried[sampler["input"]][0].ravel().astype(np.float64)
                (index,) = np.flatnonzero(keys == time)   # a keyframe of this sampler too
                return carried[sampler["output"]][0][index].astype(np.float64)
        return np.asarray(nodes[node].get(path, default), dtype=np.float64)

    parent = {child: i for i, node in enumerate(nodes) for child in node.get("children", ())}
    chain, node = [], head
    while node is not None:
        chain.append(node)
        node = parent.get(node)
    world = np.eye(4)
    for node in reversed(chain):
        local = np.eye(4)
        rotation = Rotation.from_quat(value(node, "rotation", (0, 0, 0, 1))).as_matrix()
        local[:3, :3] = rotation * value(node, "scale", (1, 1, 1))
        local[:3, 3] = value(node, "translation", (0, 0, 0))
        world = world @ local
    got = node_worlds(document, carried, time, clip)[head]
    assert np.allclose(got, world, atol=1e-6)
    assert not np.allclose(got, node_worlds(document, carried)[head], atol=1e-3)
    first, last = clip_range(document, carried, clip)
    assert first <= time <= last
    skin = nodes[1]["skin"]
    assert joint_matrices(document, carried, skin, 1, node_worlds(document, carried)).shape == \
        (len(document["skins"][skin]["joints"]), 4, 4)
