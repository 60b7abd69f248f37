"""Hostile scenes: glTF files built in memory to break the scene reader
(``io.scene.load_scene``), the animation sampler (``io.animation``) and the pose
maps (``simplify.poses.scene_poses``) each answer with one sentence naming no
server path (a MeshError or LimitError), or with a correct result, in bounded
time and memory.

:func:`skinned_document` is a 5 x 5 grid of two triangles a cell, skinned to two
joints (a root and a child one unit up, each vertex bound by its height), with an
animation bending the child joint; tests edit its JSON (and append accessors) to
make it hostile. ``tests/api/test_hostile_scenes.py`` uploads the same files.
"""

from __future__ import annotations

import re
import resource
import time

import numpy as np
import pytest

from lodserver.io.limits import LimitError, LoadLimits
from lodserver.io.scene import load_scene
from lodserver.mesh import MeshError
from lodserver.simplify.poses import scene_poses

from ..hostile_files import GlbWriter

# The in-memory GLB builder the scene abuse tests and bench share.
Glb = GlbWriter


def grid(size: int = 5):
    """(size^2, 3) positions of a unit grid in the XY plane and its (2 (size-1)^2, 3) faces."""
    u, v = np.meshgrid(np.linspace(0, 1, size), np.linspace(0, 1, size))
    positions = np.column_stack([u.ravel(), v.ravel(), np.zeros(size * size)])
    cells = np.array([(i * size + j, i * size + j + 1, (i + 1) * size + j + 1, (i + 1) * size + j)
                      for i in range(size - 1) for j in range(size - 1)])
    faces = np.concatenate([cells[:, [0, 1, 2]], cells[:, [0, 2, 3]]])
    return positions, faces


def skinned_document(*, skin: bool = True, animation: bool = True) -> Glb:
    """The skinned grid (module docstring): accessors 0 POSITION, 1 indices,
    2 JOINTS_0, 3 WEIGHTS_0, 4 inverse bind matrices, 5 times, 6 rotations."""
    glb = Glb()
    positions, faces = grid()
    position = glb.add(positions, "VEC3", min=positions.min(0).tolist(),
                       max=positions.max(0).tolist())
    indices = glb.add(faces.ravel(), "SCALAR", 5125)
    primitive = {"attributes": {"POSITION": position}, "indices": indices, "mode": 4}
    nodes = [{"name": "grid", "mesh": 0}, {"name": "root", "children": [2]},
             {"name": "bend", "translation": [0.0, 0.5, 0.0]}]
    document = glb.document
    document.update(scene=0, scenes=[{"nodes": [0, 1]}], nodes=nodes,
                    meshes=[{"name": "grid", "primitives": [primitive]}])
    if skin:
        height = positions[:, 1]
        joints = np.zeros((len(positions), 4))
        joints[:, 1] = 1
        weights = np.zeros((len(positions), 4))
        weights[:, 0], weights[:, 1] = 1.0 - height, height
        primitive["attributes"]["JOINTS_0"] = glb.add(joints, "VEC4", 5123)
        primitive["attributes"]["WEIGHTS_0"] = glb.add(weights, "VEC4")
        inverse = np.stack([np.eye(4), np.eye(4)])
        inverse[1, 1, 3] = -0.5                                  # the child's bind place
        ibm = glb.add(inverse.transpose(0, 2, 1).reshape(2, 16), "MAT4")
        document["skins"] = [{"joints": [1, 2], "inverseBindMatrices": ibm}]
        nodes[0]["skin"] = 0
    if animation:
        times = glb.add(np.array([0.0, 1.0, 2.0]), "SCALAR", min=[0.0], max=[2.0])
        half = np.sin(np.pi / 8)
        rotations = glb.add(np.array([[0, 0, 0, 1], [0, 0, half, np.cos(np.pi / 8)],
                                      [0, 0, 0, 1]]), "VEC4")
        document["animations"] = [{"name": "bend", "samplers": [
            {"input": times, "output": rotations}],
            "channels": [{"sampler": 0, "target": {"node": 2, "path": "rotation"}}]}]
    return glb


def write(tmp_path, glb: Glb, name: str = "hostile.glb"):
    path = tmp_path / name
    path.write_bytes(glb.glb())
    return path


def one_sentence(message: str, *paths) -> None:
    """``message`` is one sentence (no line break, one final full stop at most) naming
    none of ``paths`` nor any absolute path."""
    assert "\n" not in message and message.strip(), message
    assert message.rstrip(".").count(". ") == 0, message
    for path in paths:
        assert str(path) not in message, message
    assert "/tmp/" not in message and "/work/" not in message, message


def poses_of(path, **kwargs):
    """Load ``path`` as a scene and make mesh 0's poses, as a build does."""
    scene = load_scene(path, **kwargs)
    return scene, scene_poses(scene, 0, scene.meshes[0])


def refused(path, match: str, error=MeshError, **kwargs) -> str:
    """Loading ``path`` and making its poses raises ``error`` matching ``match``: its message."""
    with pytest.raises(error, match=match) as caught:
        poses_of(path, **kwargs)
    message = str(caught.value)
    one_sentence(message, path.parent)
    return message


@pytest.fixture(autouse=True)
def bounded_time():
    """Every case answers within a few seconds (generous for a loaded 2-core machine)."""
    start = time.monotonic()
    yield
    assert time.monotonic() - start < 60


def test_the_skinned_grid_itself_poses(tmp_path):
    _scene, poses = poses_of(write(tmp_path, skinned_document()))
    assert poses.shape[1:] == (25, 3, 4) and np.isfinite(poses).all()
    # the child joint bends: some pose moves the top row, none moves the bottom row's root
    assert np.abs(poses[:, :, :, :3] - np.eye(3)).max() > 0.1


# ---- the node tree -------------------------------------------------------------------
@pytest.mark.parametrize("children, match", [
    ({1: [2], 2: [1]}, "cycle|child twice"),        # 1 -> 2 -> 1
    ({2: [2]}, "child twice, of itself"),            # its own parent
    ({1: [2, 2]}, "child twice"),                    # one child listed twice
    ({1: [2, 7]}, "does not exist"),                 # a child that is no node
    ({1: [2, "x"]}, "does not exist"),
])
def test_node_cycles_and_bad_children_are_refused(tmp_path, children, match):
    glb = skinned_document()
    for node, kids in children.items():
        glb.document["nodes"][node]["children"] = kids
    refused(write(tmp_path, glb), match)


def test_a_100k_deep_node_chain_is_walked_without_recursion(tmp_path):
    glb = skinned_document(animation=False)
    nodes = glb.document["nodes"]
    depth = 100_000
    # root -> chain of depth nodes -> bend: the skin's child joint hangs at the bottom
    first = len(nodes)
    nodes[1]["children"] = [first]
    nodes.extend({"children": [first + i + 1]} for i in range(depth - 1))
    nodes.append({"children": [2]})
    _scene, poses = poses_of(write(tmp_path, glb))
    assert np.isfinite(poses).all()


def test_a_skin_joint_that_is_not_a_node_is_refused(tmp_path):
    for joints in ([1, 99], [1, -1], [1, "two"]):
        glb = skinned_document()
        glb.document["skins"][0]["joints"] = joints
        refused(write(tmp_path, glb), "joint")


def test_a_skin_with_100k_joints_is_bounded(tmp_path):
    glb = skinned_document(animation=False)
    nodes = glb.document["nodes"]
    count = 100_000
    first = len(nodes)
    nodes.extend({"translation": [0.0, 0.0, 0.0]} for _ in range(count - 2))
    nodes[1]["children"] = [2, *range(first, first + count - 2)]
    glb.document["skins"][0]["joints"] = [1, 2, *range(first, first + count - 2)]
    del glb.document["skins"][0]["inverseBindMatrices"]
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    _scene, poses = poses_of(write(tmp_path, glb))
    grown = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before    # KiB
    assert np.isfinite(poses).all() and grown < 1_000_000


@pytest.mark.parametrize("matrices, match", [
    (np.tile(np.eye(4).ravel(), (3, 1)), "3 inverse bind matrices for 2 joints"),
    (np.tile(np.eye(4).ravel(), (1, 1)), "1 inverse bind matrices for 2 joints"),
    (np.array([np.eye(4).ravel(), [np.nan] * 16]), "not finite"),
    (np.array([np.eye(4).ravel(), [np.inf] + [0] * 15]), "not finite"),
])
def test_inverse_bind_matrices_of_the_wrong_count_or_not_finite(tmp_path, matrices, match):
    glb = skinned_document()
    glb.document["skins"][0]["inverseBindMatrices"] = glb.add(matrices, "MAT4")
    refused(write(tmp_path, glb), match)


def test_a_joint_out_of_the_skin_is_refused_at_load(tmp_path):
    glb = skinned_document()
    joints = np.zeros((25, 4))
    joints[7, 2] = 5                                    # the skin has 2 joints
    glb.document["meshes"][0]["primitives"][0]["attributes"]["JOINTS_0"] = \
        glb.add(joints, "VEC4", 5123)
    path = write(tmp_path, glb)
    with pytest.raises(MeshError, match="uses joint 5, but skin 0 of node 0 has 2 joints") as e:
        load_scene(path)
    one_sentence(str(e.value), tmp_path)


@pytest.mark.parametrize("fill", ["zero", "negative", "nan"])
def test_weights_all_zero_negative_or_nan(tmp_path, fill):
    glb = skinned_document()
    weights = np.zeros((25, 4))
    if fill == "negative":
        weights[:, 0], weights[:, 1] = 1.5, -0.5
    elif fill == "nan":
        weights[:, 0] = np.nan
    glb.document["meshes"][0]["primitives"][0]["attributes"]["WEIGHTS_0"] = \
        glb.add(weights, "VEC4")
    path = write(tmp_path, glb)
    if fill == "zero":
        # a vertex bound to nothing stays where it is: the identity in every pose
        _scene, poses = poses_of(path)
        assert np.allclose(poses, np.eye(4)[:3])
    elif fill == "negative":
        refused(path, "mesh 0 has negative skin weights")
    else:
        refused(path, "NaN or infinite attribute values")


# ---- animations ----------------------------------------------------------------------
def _sampler(glb: Glb, times, values, kind="VEC4", interpolation=None, path="rotation"):
    sampler = {"input": glb.add(np.asarray(times, dtype=float), "SCALAR"),
               "output": glb.add(np.asarray(values, dtype=float), kind)}
    if interpolation:
        sampler["interpolation"] = interpolation
    glb.document["animations"] = [{"samplers": [sampler], "channels": [
        {"sampler": 0, "target": {"node": 2, "path": path}}]}]
    return glb


def test_ten_million_keyframes_declared_over_a_tiny_buffer(tmp_path):
    glb = skinned_document()
    glb.document["accessors"][5]["count"] = 10_000_000
    glb.document["accessors"][6]["count"] = 10_000_000
    refused(write(tmp_path, glb), "runs past the end")


def test_ten_million_keyframes_without_a_buffer_are_refused(tmp_path):
    # an accessor without a bufferView reads as zeros: nothing in the file backs them
    glb = skinned_document()
    for index in (5, 6):
        del glb.document["accessors"][index]["bufferView"]
        glb.document["accessors"][index]["count"] = 10_000_000
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    refused(write(tmp_path, glb), "accessor 5 has 10000000 values without a bufferView",
            limits=LoadLimits())
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 200_000


@pytest.mark.parametrize("times, match", [
    ([0.0, 2.0, 1.0], "increasing"),
    ([0.0, np.nan, 2.0], "finite|increasing"),
    ([np.inf, 1.0, 2.0], "finite|increasing"),
])
def test_input_times_not_increasing_or_not_finite(tmp_path, times, match):
    glb = _sampler(skinned_document(), times, [[0, 0, 0, 1]] * 3)
    refused(write(tmp_path, glb), match)


def test_cubicspline_output_of_the_wrong_count(tmp_path):
    glb = _sampler(skinned_document(), [0.0, 1.0, 2.0], [[0, 0, 0, 1]] * 7,
                   interpolation="CUBICSPLINE")
    refused(write(tmp_path, glb), "3 keyframes but 7 outputs")


def test_an_unknown_interpolation_is_refused(tmp_path):
    glb = _sampler(skinned_document(), [0.0, 1.0, 2.0], [[0, 0, 0, 1]] * 3,
                   interpolation="BEZIER")
    refused(write(tmp_path, glb), "interpolation")


@pytest.mark.parametrize("target, match", [
    ({"node": 999, "path": "rotation"}, "node 999"),
    ({"node": -1, "path": "rotation"}, "node -1"),
    ({"node": "bend", "path": "rotation"}, "node 'bend'"),
])
def test_a_channel_targeting_a_missing_node(tmp_path, target, match):
    glb = skinned_document()
    glb.document["animations"][0]["channels"][0]["target"] = target
    refused(write(tmp_path, glb), match)


@pytest.mark.parametrize("sampler", [5, -1, "0", None])
def test_a_channel_naming_a_missing_sampler(tmp_path, sampler):
    glb = skinned_document()
    glb.document["animations"][0]["channels"][0]["sampler"] = sampler
    refused(write(tmp_path, glb), "sampler")


def test_a_sampler_naming_a_missing_accessor(tmp_path):
    glb = skinned_document()
    glb.document["animations"][0]["samplers"][0]["output"] = 99
    path = write(tmp_path, glb)
    with pytest.raises(MeshError, match="accessor 99") as e:
        load_scene(path)
    one_sentence(str(e.value), tmp_path)


def test_a_weights_channel_for_a_mesh_without_targets_is_ignored(tmp_path):
    glb = skinned_document()
    glb.document["animations"][0]["channels"].append(
        {"sampler": 0, "target": {"node": 0, "path": "weights"}})
    _scene, poses = poses_of(write(tmp_path, glb))
    assert np.isfinite(poses).all()


def test_a_rotation_sampler_with_three_components_is_refused(tmp_path):
    glb = _sampler(skinned_document(), [0.0, 1.0, 2.0], [[0, 0, 0]] * 3, kind="VEC3")
    refused(write(tmp_path, glb), "rotation sampler has outputs of 3 components")


def test_ten_thousand_animations_are_bounded(tmp_path):
    glb = skinned_document()
    animation = glb.document["animations"][0]
    glb.document["animations"] = [animation] * 10_000
    start = time.monotonic()
    _scene, poses = poses_of(write(tmp_path, glb))
    assert len(poses) == 8 and np.isfinite(poses).all()
    assert time.monotonic() - start < 30


# ---- morph targets -------------------------------------------------------------------
def _morphed(targets_per_primitive, *, size: int = 5):
    """A ``size`` x ``size`` grid for each entry, side by side, each one primitive with
    that many POSITION targets (all sharing one accessor of deltas (0, 0, 0.1))."""
    glb = skinned_document(skin=False, animation=False)
    positions, faces = grid(size)
    indices = glb.add(faces.ravel(), "SCALAR", 5125)
    deltas = glb.add(np.tile([0.0, 0.0, 0.1], (len(positions), 1)), "VEC3")
    primitives = []
    for number, count in enumerate(targets_per_primitive):
        placed = positions + [2.0 * number, 0.0, 0.0]
        position = glb.add(placed, "VEC3", min=placed.min(0).tolist(),
                           max=placed.max(0).tolist())
        primitives.append({"attributes": {"POSITION": position}, "indices": indices,
                           "targets": [{"POSITION": deltas}] * count})
    glb.document["meshes"][0]["primitives"] = primitives
    return glb


def test_a_thousand_morph_targets_are_refused_before_allocating(tmp_path):
    # 19602 triangles x 3 corners x 3000 floats: 1.4 GB of corner values if allocated
    path = write(tmp_path, _morphed([1000], size=100))
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    # the server's limits: past the carried-data budget, from the declarations
    with pytest.raises(MeshError, match="240000000 for the morph targets of mesh 0") as e:
        load_scene(path, limits=LoadLimits())
    one_sentence(str(e.value), tmp_path)
    with pytest.raises(MeshError, match="at most 255"):
        load_scene(path)                            # unbounded (the trusted command line)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 200_000


def test_targets_of_different_counts_per_primitive(tmp_path):
    scene, poses = poses_of(write(tmp_path, _morphed([2, 5])))
    # five targets; the first grid (x < 1.5) is not moved by targets 2..4 (zero deltas)
    assert len(poses) == 5 and np.isfinite(poses).all()
    first = scene.meshes[0].positions[:, 0] < 1.5
    moved = poses[:, :, 2, 3]
    assert np.allclose(moved[:2], 0.1)
    assert np.allclose(moved[2:, first], 0.0) and np.allclose(moved[2:, ~first], 0.1)


@pytest.mark.parametrize("count", [24, 26, 10_000_000])
def test_target_accessors_shorter_or_longer_than_position(tmp_path, count):
    glb = _morphed([1])
    deltas = glb.add(np.zeros((min(count, 30), 3)), "VEC3")
    glb.document["accessors"][deltas]["count"] = count
    glb.document["meshes"][0]["primitives"][0]["targets"] = [{"POSITION": deltas}]
    path = write(tmp_path, glb)
    with pytest.raises(MeshError, match=f"{count} values for 25 vertices") as e:
        load_scene(path)
    one_sentence(str(e.value), tmp_path)


def _weights_channel(glb: Glb, per_key: int) -> Glb:
    times = glb.add(np.array([0.0, 1.0]), "SCALAR")
    values = glb.add(np.linspace(0, 1, 2 * per_key), "SCALAR")
    glb.document["animations"] = [{"samplers": [{"input": times, "output": values}],
                                   "channels": [{"sampler": 0,
                                                 "target": {"node": 0, "path": "weights"}}]}]
    return glb


def test_an_animated_weights_channel_poses_each_target(tmp_path):
    _scene, poses = poses_of(write(tmp_path, _weights_channel(_morphed([2]), 2)))
    # 2 targets alone + 8 sampled times; at each, the deltas' blend of the two weights
    assert len(poses) == 10 and np.isfinite(poses).all()


@pytest.mark.parametrize("edit, match", [
    (lambda glb: glb.document["meshes"][0].update(weights=[0.5, 0.5, 0.5]),
     "mesh 0 has 3 morph weights for 2 targets"),
    (lambda glb: glb.document["nodes"][0].update(weights=[0.5]),
     "node 0 has 1 morph weights for 2 targets"),
    (lambda glb: glb.document["nodes"][0].update(weights="heavy"),
     "node 0 has no list of morph weights"),
    (lambda glb: _weights_channel(glb, 3), "animation 0 gives node 0 3 morph weights for 2"),
])
def test_morph_weights_of_the_wrong_count_are_refused_at_load(tmp_path, edit, match):
    glb = _morphed([2])
    edit(glb)
    path = write(tmp_path, glb)
    with pytest.raises(MeshError, match=match) as e:
        load_scene(path)
    one_sentence(str(e.value), tmp_path)


# ---- custom attributes ---------------------------------------------------------------
def _custom(names_kinds):
    glb = skinned_document(skin=False, animation=False)
    attributes = glb.document["meshes"][0]["primitives"][0]["attributes"]
    widths = {"SCALAR": 1, "VEC2": 2, "MAT4": 16}
    for name, kind in names_kinds:
        attributes[name] = glb.add(np.ones((25, widths[kind])), kind)
    return glb


def test_three_hundred_custom_attributes_are_refused(tmp_path):
    path = write(tmp_path, _custom([(f"_X{i}", "SCALAR") for i in range(300)]))
    with pytest.raises(MeshError, match="it has 300 vertex attributes; at most 255") as e:
        load_scene(path)
    one_sentence(str(e.value), tmp_path)


def test_a_custom_attribute_named_by_ten_kilobytes_is_dropped_not_echoed(tmp_path):
    name = "_" + "N" * 10_000
    scene = load_scene(write(tmp_path, _custom([(name, "VEC2"), ("_OK", "SCALAR")])))
    layout = scene.meshes[0].attributes.layout
    assert [n for n, _ in layout] == ["_OK"]
    assert all(len(note) < 500 for note in scene.notes), [len(n) for n in scene.notes]
    assert all(len(n) < 100 for n in scene.reports[0].dropped_attributes)


def test_a_mat4_custom_attribute_is_dropped_and_named(tmp_path):
    scene = load_scene(write(tmp_path, _custom([("_MATRIX", "MAT4"), ("_OK", "VEC2")])))
    assert [n for n, _ in scene.meshes[0].attributes.layout] == ["_OK"]
    assert scene.reports[0].dropped_attributes == ["_MATRIX"]


def test_a_known_semantic_with_a_ten_kilobyte_number_is_dropped(tmp_path):
    scene = load_scene(write(tmp_path, _custom([("TEXCOORD_" + "0" * 10_000 + "1", "VEC2")])))
    assert scene.meshes[0].attributes is None or not scene.meshes[0].attributes.layout
    assert all(len(n) < 100 for n in scene.reports[0].dropped_attributes)


@pytest.mark.parametrize("edit", [
    lambda d: d["nodes"].append("node"),
    lambda d: d["nodes"][1].update(children="2"),
    lambda d: d["nodes"][2].update(translation=[0, "up", 0]),
    lambda d: d["nodes"][2].update(matrix=[1, 0, 0]),
    lambda d: d["skins"].append("skin"),
    lambda d: d["animations"].append("clip"),
    lambda d: d["animations"][0]["channels"].append("channel"),
    lambda d: d["animations"][0]["channels"][0].update(target="bend"),
    lambda d: d["animations"][0]["samplers"].append({"input": 5}),
    lambda d: d["animations"][0]["samplers"][0].update(input=[5]),
], ids=["node", "children", "translation", "matrix", "skin", "animation", "channel",
        "target", "sampler", "input"])
def test_strings_where_objects_or_numbers_belong(tmp_path, edit):
    glb = skinned_document()
    edit(glb.document)
    path = write(tmp_path, glb)
    with pytest.raises(MeshError) as e:
        poses_of(path)
    one_sentence(str(e.value), tmp_path)


# ---- the command line ----------------------------------------------------------------
def _cycle(glb):
    glb.document["nodes"][1]["children"] = [2]
    glb.document["nodes"][2]["children"] = [1]
    return glb


@pytest.mark.parametrize("glb, match", [
    (_cycle(skinned_document()), "cycle|child twice"),
    (_morphed([1000]), "1000 vertex attributes"),
    (_custom([(f"_X{i}", "SCALAR") for i in range(300)]), "300 vertex attributes"),
], ids=["node cycle", "1000 targets", "300 customs"])
def test_lodserver_export_of_a_hostile_scene_is_one_sentence_and_writes_nothing(
        tmp_path, capsys, glb, match):
    from lodserver.cli import main
    source, output = write(tmp_path, glb), tmp_path / "out" / "levels.glb"
    capsys.readouterr()
    assert main(["export", str(source), "-o", str(output)]) == 1
    message = capsys.readouterr().err.strip().splitlines()[-1]
    assert re.search(match, message), message
    one_sentence(message.replace(str(source), "hostile.glb"))
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_lodserver_export_of_odd_but_valid_scenes_writes_levels(tmp_path, capsys):
    from lodserver.cli import main
    glb = _morphed([2, 5])
    glb.document["meshes"][0]["primitives"][0]["attributes"]["_" + "N" * 10_000] = \
        glb.add(np.ones((25, 2)), "VEC2")
    source, output = write(tmp_path, glb), tmp_path / "levels.glb"
    assert main(["export", str(source), "--lods", "1,0.5", "-o", str(output)]) == 0
    scene = load_scene(output)
    assert len(scene.document["meshes"]) >= 2 and np.isfinite(
        scene.meshes[0].positions).all()


# ---- what a small file may cost: GPU instances, aliased bytes, expanded targets --------
def instanced(count: int, *, scale: bool = False) -> Glb:
    """The plain grid (32 triangles) drawn by one node with ``count`` EXT_mesh_gpu_instancing
    translations (and scales 1, 2, 3, ... with ``scale``)."""
    glb = skinned_document(skin=False, animation=False)
    steps = np.arange(count, dtype=np.float64)
    attributes = {"TRANSLATION": glb.add(np.column_stack([2 * steps, 0 * steps, 0 * steps]),
                                         "VEC3")}
    if scale:
        attributes["SCALE"] = glb.add(np.repeat(1 + steps[:, None], 3, axis=1), "VEC3")
    glb.document["nodes"][0]["extensions"] = {
        "EXT_mesh_gpu_instancing": {"attributes": attributes}}
    glb.document["extensionsUsed"] = ["EXT_mesh_gpu_instancing"]
    return glb


def aliased_clips(samplers: int, keys: int, *, distinct: bool = False) -> Glb:
    """The plain grid and ``samplers`` nodes, each animated by its own sampler whose
    output accessor reads the same bufferView of ``keys`` translations: the same
    bytes (one accessor identity), or with ``distinct`` each one key further in."""
    glb = skinned_document(skin=False, animation=False)
    times = glb.add(np.arange(keys, dtype=np.float64), "SCALAR", min=[0.0],
                    max=[float(keys - 1)])
    first = glb.add(np.random.default_rng(0).normal(size=(keys + samplers, 3)), "VEC3")
    record = dict(glb.document["accessors"][first], count=keys)
    glb.document["accessors"][first] = record
    nodes = glb.document["nodes"]
    outputs = [first]
    for k in range(1, samplers):
        glb.document["accessors"].append({**record, "byteOffset": 12 * k if distinct else 0})
        outputs.append(len(glb.document["accessors"]) - 1)
    start = len(nodes)
    nodes.extend({"name": f"moved {k}"} for k in range(samplers))
    glb.document["scenes"][0]["nodes"].extend(range(start, start + samplers))
    glb.document["animations"] = [{"samplers": [{"input": times, "output": o} for o in outputs],
                                   "channels": [{"sampler": k, "target": {
                                       "node": start + k, "path": "translation"}}
                                       for k in range(samplers)]}]
    return glb


@pytest.mark.parametrize("in_the_scene", [True, False])
def test_gpu_instances_count_against_the_instance_limit(tmp_path, in_the_scene):
    glb = instanced(70_000)
    if not in_the_scene:        # drawn by no scene, its instances are still derived
        glb.document["scenes"][0]["nodes"].remove(0)
    path = write(tmp_path, glb)
    with pytest.raises(LimitError, match="69999 GPU instances") as e:
        load_scene(path, root=tmp_path, limits=LoadLimits())
    one_sentence(str(e.value), tmp_path)
    # within the limit: loaded, translations alone (12 bytes an instance)
    assert load_scene(write(tmp_path, instanced(65_000), "within.glb"),
                      limits=LoadLimits()).meshes[0].face_count == 32


def test_gpu_instances_count_against_the_triangle_total(tmp_path):
    # 5000 instances of 32 triangles: 160,000 placed
    path = write(tmp_path, instanced(5000))
    with pytest.raises(LimitError, match="160000 triangles after placing every mesh instance"):
        load_scene(path, limits=LoadLimits(max_triangles=100_000))
    assert load_scene(path, limits=LoadLimits(max_triangles=200_000)).meshes[0].face_count == 32


def test_instance_scales_are_one_array_per_part_and_match_each_matrix(tmp_path):
    from lodserver.scene.budget import scene_instances
    from lodserver.io.gltf import _local_matrix

    count = 60_000
    scene = load_scene(write(tmp_path, instanced(count, scale=True)), limits=LoadLimits())
    instances, diagonal = scene_instances(scene)
    assert isinstance(instances[0], np.ndarray) and instances[0].shape == (count,)
    assert np.array_equal(instances[0], 1.0 + np.arange(count))
    # the vectorised transforms are the ones a node's own TRS gives, to the bit
    chosen = [0, 1, 12_345, count - 1]
    columns = {name: scene.carried[index][0].astype(np.float64) for name, index in
               scene.document["nodes"][0]["extensions"]["EXT_mesh_gpu_instancing"][
                   "attributes"].items()}
    from lodserver.scene.budget import _instancing_matrices
    ours = _instancing_matrices(columns, count)[chosen]
    theirs = np.stack([_local_matrix({n.lower(): columns[n][i].tolist() for n in columns})
                       for i in chosen])
    assert np.array_equal(ours, theirs)
    # the last instance sits at x = 2 (count - 1), scaled by count
    assert diagonal > 2 * (count - 1)


def test_aliased_sampler_outputs_are_read_once(tmp_path):
    scene = load_scene(write(tmp_path, aliased_clips(60, 20_000)), limits=LoadLimits())
    outputs = [s["output"] for s in scene.document["animations"][0]["samplers"]]
    arrays = [scene.carried[o][0] for o in outputs]
    assert len(set(outputs)) == 60 and all(a is arrays[0] for a in arrays)


def test_sixty_outputs_over_distinct_ranges_of_one_view_are_refused(tmp_path):
    # 60 x 20,000 keys x 12 bytes once read, from a file of 0.5 MB
    path = write(tmp_path, aliased_clips(60, 20_000, distinct=True))
    with pytest.raises(LimitError, match="for the animations, skins and instancing accessors"
                       ) as e:
        load_scene(path, limits=LoadLimits())
    one_sentence(str(e.value), tmp_path)
    assert load_scene(path).carried                 # unbounded: the trusted command line


def test_255_targets_naming_one_accessor_are_refused_before_reading(tmp_path):
    # 10,000 vertices x 255 targets x 3 float64: 61 MB from a file of about 480 KB
    path = write(tmp_path, _morphed([255], size=100))
    assert path.stat().st_size < 600_000
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(LimitError, match="61200000 for the morph targets of mesh 0") as e:
        load_scene(path, limits=LoadLimits())
    one_sentence(str(e.value), tmp_path)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 100_000     # KiB


def test_every_shared_scene_loads_within_the_carried_budget(shared_meshes):
    files = sorted([*shared_meshes.rglob("*.glb"), *shared_meshes.rglob("*.gltf")])
    assert len(files) >= 7
    for path in files:
        try:
            load_scene(path, root=path.parent, limits=LoadLimits())
        except LimitError as exc:
            pytest.fail(f"{path.name}: {exc}")
        except MeshError as exc:            # SimpleMorph.gltf ships without its buffer
            assert "is missing" in str(exc), f"{path.name}: {exc}"


def test_joints_times_gpu_instances_are_counted(tmp_path):
    # a skinned node of 65,000 instances: 130,000 joint transforms to derive
    glb = skinned_document(animation=False)
    translations = glb.add(np.zeros((65_000, 3)), "VEC3")
    glb.document["nodes"][0]["extensions"] = {
        "EXT_mesh_gpu_instancing": {"attributes": {"TRANSLATION": translations}}}
    path = write(tmp_path, glb)
    with pytest.raises(LimitError, match="16640000 for the joint transforms of skinned nodes"):
        load_scene(path, limits=LoadLimits())
