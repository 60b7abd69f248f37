"""Pose quadrics (lodserver.simplify.poses): skin and morph maps, the pull-back of posed
planes to bind space against identities and a naive sum, a bent two-bone strip, the
poses of a scene's mesh, and decimate(poses=) on Fox."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lodserver.io.animation import joint_matrices, node_worlds, sample_times, trs_matrix
from lodserver.io.scene import Scene
from lodserver.mesh import Attributes, Mesh, MeshError
from lodserver.simplify import poses as poses_module
from lodserver.simplify.collapse import decimate
from lodserver.simplify.options import DecimateOptions
from lodserver.simplify.poses import (
    compose_maps,
    morph_pose_maps,
    pose_quadrics,
    poses_to_unit_box,
    scene_poses,
    skin_pose_maps,
)
from lodserver.simplify.quadrics import optimal_position, quadric_error, vertex_quadrics

from .. import meshes


def apply(maps, positions):
    """(P, n, 3): every pose's map applied to bind ``positions`` (n, 3)."""
    return np.einsum("pnij,nj->pni", maps[..., :3], positions) + maps[..., 3]


def rigid(angle_deg=37.0, axis=(1.0, 2.0, 0.5), shift=(0.3, -1.0, 2.0)):
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_rotvec(np.radians(angle_deg) * np.asarray(axis)
                                          / np.linalg.norm(axis)).as_matrix()
    matrix[:3, 3] = shift
    return matrix


# --------------------------------------------------------------------------
# Maps
# --------------------------------------------------------------------------

def test_a_vertex_bound_to_one_joint_takes_that_joints_matrix():
    matrices = np.stack([np.stack([np.eye(4), rigid(), rigid(80, (0, 0, 1), (1, 1, 1))])] * 2)
    matrices[1, 2] = rigid(-20, (1, 0, 0), (0, 3, 0))
    joints = np.array([[2, 0, 0, 0], [1, 2, 0, 0], [0, 0, 0, 0]], dtype=np.float64)
    weights = np.array([[1, 0, 0, 0], [0.25, 0.75, 0, 0], [0, 0, 0, 0]], dtype=np.float64)
    maps = skin_pose_maps(joints, weights, matrices)
    assert maps.shape == (2, 3, 3, 4)
    assert np.allclose(maps[0, 0], matrices[0, 2, :3])
    assert np.allclose(maps[1, 0], matrices[1, 2, :3])
    assert np.allclose(maps[1, 1], 0.25 * matrices[1, 1, :3] + 0.75 * matrices[1, 2, :3])
    assert np.allclose(maps[:, 2], np.eye(3, 4))            # no weight: stays where it is
    with pytest.raises(MeshError, match="joint outside"):
        skin_pose_maps(joints + 3 * (weights > 0), weights, matrices)


def test_morph_maps_translate_by_the_weighted_deltas_and_compose_before_the_skin():
    rng = np.random.default_rng(0)
    deltas = rng.normal(size=(2, 5, 3))
    weights = np.array([[1.0, 0.0], [0.5, -2.0]])
    maps = morph_pose_maps(deltas, weights)
    x = rng.normal(size=(5, 3))
    assert np.allclose(apply(maps, x)[1], x + 0.5 * deltas[0] - 2.0 * deltas[1])
    skin = skin_pose_maps(np.zeros((5, 4)), np.tile([1.0, 0, 0, 0], (5, 1)),
                          np.stack([rigid()[None]] * 2))
    both = compose_maps(skin, maps)
    expected = (rigid()[:3, :3] @ (x + deltas[0]).T).T + rigid()[:3, 3]
    assert np.allclose(apply(both, x)[0], expected)


def test_maps_in_the_unit_box_move_unit_points_where_the_mesh_units_map_goes():
    rng = np.random.default_rng(1)
    maps = rng.normal(size=(3, 6, 3, 4))
    x = rng.normal(size=(6, 3))
    lo, scale = np.array([-2.0, 0.5, 3.0]), 7.5
    unit_maps = poses_to_unit_box(maps, lo, scale)
    assert np.allclose(apply(unit_maps, (x - lo) / scale), (apply(maps, x) - lo) / scale)


# --------------------------------------------------------------------------
# Pose quadrics
# --------------------------------------------------------------------------

def identity_maps(count, n):
    return np.broadcast_to(np.eye(3, 4), (count, n, 3, 4)).copy()


@pytest.mark.parametrize("name", ["spot", "grid"])
def test_an_identity_pose_is_the_bind_quadric(name):
    m = meshes.mesh(name)
    bind = vertex_quadrics(m.positions, m.faces, boundary_weight=0)
    posed = pose_quadrics(m.positions, m.faces, identity_maps(1, m.vertex_count))
    assert np.abs(posed - bind).max() <= 1e-12 * max(1.0, np.abs(bind).max())
    three = pose_quadrics(m.positions, m.faces, identity_maps(3, m.vertex_count))
    assert np.allclose(three, 3 * bind, rtol=1e-12, atol=1e-15)


def test_a_rigid_pose_keeps_every_distance_so_the_bind_positions_cost_nothing():
    m = meshes.mesh("spot")
    bind = vertex_quadrics(m.positions, m.faces, boundary_weight=0)
    maps = np.broadcast_to(rigid()[:3], (1, m.vertex_count, 3, 4))
    posed = pose_quadrics(m.positions, m.faces, maps)
    assert np.allclose(posed, bind, rtol=1e-9, atol=1e-12)
    for v in range(0, m.vertex_count, 97):
        assert abs(quadric_error(posed[v], *m.positions[v])) <= 1e-12 * max(1.0, posed[v, 10])


def test_pose_quadrics_are_the_naive_sum_of_pulled_back_posed_planes():
    rng = np.random.default_rng(2)
    m = meshes.mesh("grid")
    n = m.vertex_count
    maps = identity_maps(2, n) + rng.normal(scale=0.2, size=(2, n, 3, 4))
    q = pose_quadrics(m.positions, m.faces, maps)
    posed = apply(maps, m.positions)
    for v in rng.choice(n, 6, replace=False):
        x = m.positions[v] + rng.normal(scale=0.05, size=3)
        expected, area = 0.0, 0.0
        for p in range(2):
            for face in m.faces[(m.faces == v).any(axis=1)]:
                a, b, c = posed[p][face]
                normal = np.cross(b - a, c - a)
                twice = np.linalg.norm(normal)
                y = maps[p, v, :, :3] @ x + maps[p, v, :, 3]
                expected += 0.5 * twice * ((normal / twice) @ (y - a)) ** 2
                area += 0.5 * twice
        assert quadric_error(q[v], *x) == pytest.approx(expected, rel=1e-9, abs=1e-14)
        assert q[v, 10] == pytest.approx(area)
        # the vertex at its own bind position is posed onto its posed planes
        assert abs(quadric_error(q[v], *m.positions[v])) <= 1e-12 * max(1.0, q[v, 10])


def test_bad_pose_shapes_are_refused():
    m = meshes.mesh("grid")
    with pytest.raises(MeshError, match="poses must have shape"):
        pose_quadrics(m.positions, m.faces, identity_maps(1, m.vertex_count - 1))
    with pytest.raises(MeshError, match="poses must have shape"):
        poses_to_unit_box(np.zeros((2, 3, 4)), np.zeros(3), 1.0)


# --------------------------------------------------------------------------
# A strip bent at a joint
# --------------------------------------------------------------------------

def bent_strip(nx=17, ny=5, bend_deg=70.0):
    """A flat strip x in [0, 4], y in [0, 1] (z = 0), bone 0 up to x = 1.5 and bone 1
    from x = 2.5, blended between; bone 1 turned ``bend_deg`` about the y axis at
    x = 2, lifting the strip's far half out of its plane. Returns (mesh, joints,
    weights, joint matrices (2, 2, 4, 4): the bind pose and the bent one)."""
    xs, ys = np.linspace(0, 4, nx), np.linspace(0, 1, ny)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    positions = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)
    index = np.arange(nx * ny).reshape(nx, ny)
    a, b = index[:-1, :-1].ravel(), index[1:, :-1].ravel()
    c, d = index[1:, 1:].ravel(), index[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    far = np.clip(positions[:, 0] - 1.5, 0.0, 1.0)
    joints = np.tile([0.0, 1.0, 0.0, 0.0], (len(positions), 1))
    weights = np.stack([1 - far, far, 0 * far, 0 * far], 1)
    pivot = np.array([2.0, 0.0, 0.0])
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("y", -bend_deg, degrees=True).as_matrix()
    bend = trs_matrix(pivot) @ turn @ trs_matrix(-pivot)
    matrices = np.array([[np.eye(4), np.eye(4)], [np.eye(4), bend]])
    return Mesh(positions, faces), joints, weights, matrices


def collapse_cost(q, a, b, positions):
    """The cost of collapsing vertex ``a`` onto ``b`` at its best place: Q(p) of the summed rows."""
    row = q[a] + q[b]
    out = np.empty(3)
    optimal_position(row, positions[a], positions[b], out)
    return quadric_error(row, *out)


def test_a_collapse_across_the_bending_joint_costs_more_with_poses():
    strip, joints, weights, matrices = bent_strip()
    maps = skin_pose_maps(joints, weights, matrices[1:])
    bind = vertex_quadrics(strip.positions, strip.faces, boundary_weight=0)
    mean = (bind + pose_quadrics(strip.positions, strip.faces, maps)) / 2
    p = strip.positions

    def vertex(x, y):
        return int(np.flatnonzero((np.abs(p[:, 0] - x) < 1e-9) & (np.abs(p[:, 1] - y) < 1e-9))[0])

    across = vertex(2.0, 0.5), vertex(2.25, 0.5)          # in the bend
    away = vertex(0.5, 0.5), vertex(0.75, 0.5)            # on bone 0 alone
    scale = mean[across[0], 10]                           # ~ area around a vertex
    assert collapse_cost(bind, *across, p) < 1e-20        # flat at rest: free
    assert collapse_cost(mean, *across, p) > 1e-4 * scale
    assert collapse_cost(mean, *away, p) < 1e-20          # rigid there: still free


def level_of(mesh: Mesh, log, vertices: int):
    """(positions (n, 3), faces (f, 3), kept vertex ids (n,)) after the log's collapses
    down to ``vertices``: removed vertices relabelled to their survivors, degenerate
    faces dropped; each kept vertex keeps its input id's skin (see kept ids)."""
    k = mesh.vertex_count - vertices
    label = np.arange(mesh.vertex_count)
    positions = mesh.positions.copy()
    for i in range(k):
        label[log.removed[i]] = log.survivor[i]
        positions[log.survivor[i]] = log.position[i]
    while not np.array_equal(label, label[label]):
        label = label[label]
    faces = label[mesh.faces]
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2])
                  & (faces[:, 0] != faces[:, 2])]
    kept = np.unique(faces)
    renumber = np.full(mesh.vertex_count, -1)
    renumber[kept] = np.arange(len(kept))
    return positions[kept], renumber[faces], kept


def posed_rms(mesh, log, vertices, joints, weights, matrices, samples=20_000):
    """Mean over poses of the two-sided RMS surface distance between the full mesh
    and its level of ``vertices``, both skinned in each pose (each kept vertex with
    its own joints and weights), relative to the posed full mesh's diagonal."""
    from lodserver.metrics.surface import surface_distance
    positions, faces, kept = level_of(mesh, log, vertices)
    full = apply(skin_pose_maps(joints, weights, matrices), mesh.positions)
    coarse = apply(skin_pose_maps(joints[kept], weights[kept], matrices), positions)
    return float(np.mean([surface_distance((full[p], mesh.faces), (coarse[p], faces),
                                           samples=samples)["rms"]
                          for p in range(len(matrices))]))


def test_decimating_the_bent_strip_with_poses_keeps_the_bend():
    strip, joints, weights, matrices = bent_strip()
    maps = skin_pose_maps(joints, weights, matrices[1:])
    plain = decimate(strip, DecimateOptions(boundary_weight=1.0))
    posed = decimate(strip, DecimateOptions(boundary_weight=1.0), poses=maps)
    target = 20
    bent = matrices[1:]
    with_poses = posed_rms(strip, posed, target, joints, weights, bent)
    without = posed_rms(strip, plain, target, joints, weights, bent)
    assert with_poses < 0.5 * without


# --------------------------------------------------------------------------
# The poses of a scene's mesh
# --------------------------------------------------------------------------

def tiny_scene(with_skin=True, targets=1):
    """Two triangles bound to two joints (STEP-animated rotation of joint 1 by 90
    degrees about z at t >= 1), ``targets`` morph targets (target t lifts by t + 1)."""
    nodes = [{"name": "body", "mesh": 0}, {"name": "j0", "children": [2]},
             {"name": "j1", "translation": [1.0, 0.0, 0.0]}]
    if with_skin:
        nodes[0]["skin"] = 0
    document = {"nodes": nodes, "meshes": [{"primitives": [{"attributes": {}}]}],
                "skins": [{"joints": [1, 2]}],
                "animations": [{"samplers": [{"input": 0, "output": 1,
                                              "interpolation": "STEP"}],
                                "channels": [{"sampler": 0,
                                              "target": {"node": 2, "path": "rotation"}}]}]}
    if targets:
        document["meshes"][0]["primitives"][0]["targets"] = [{}] * targets
    turn = Rotation.from_euler("z", 90, degrees=True).as_quat()
    carried = {0: (np.array([[0.0], [1.0], [2.0]], np.float32), {"componentType": 5126}, "other"),
               1: (np.array([[0, 0, 0, 1], turn, turn], np.float32),
                   {"componentType": 5126}, "other")}
    positions = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    layout = [("JOINTS_0", 4), ("WEIGHTS_0", 4)]
    columns = [np.tile([0.0, 1, 0, 0], (4, 1)),
               np.array([[1.0, 0, 0, 0], [0, 1, 0, 0], [1, 0, 0, 0], [0, 1, 0, 0]])]
    for t in range(targets):
        layout.append((f"TARGET{t}_POSITION", 3))
        columns.append(np.tile([0.0, 0.0, t + 1.0], (4, 1)))
    mesh = Mesh(positions, faces, Attributes(tuple(layout), np.concatenate(columns, 1),
                                             faces.copy()))
    return Scene(document, carried=carried), mesh


def test_scene_poses_of_a_skinned_mesh_follow_the_animation():
    scene, mesh = tiny_scene(targets=0)
    maps = scene_poses(scene, 0, mesh, count=4)
    assert maps.shape == (4, 4, 3, 4)
    times = [t for _, t in sample_times(scene.document, scene.carried, 4)]
    posed = apply(maps, mesh.positions)
    for p, t in enumerate(times):
        # vertex 1 hangs on joint 1 (at x = 1): it turns 90 degrees about z once t >= 1,
        # but the joint has no inverse bind matrix, so at rest it sits at 1 + 1 = 2 on x
        expected = [1.0, 1.0, 0.0] if t >= 1 else [2.0, 0.0, 0.0]
        assert np.allclose(posed[p, 1], expected)
        assert np.allclose(posed[p, 0], mesh.positions[0])   # joint 0: at rest always


def test_scene_poses_of_a_morphed_mesh_are_each_target_alone():
    scene, mesh = tiny_scene(with_skin=False, targets=2)
    maps = scene_poses(scene, 0, mesh)
    assert maps.shape == (2, 4, 3, 4)                 # no weights channel: targets only
    assert np.allclose(maps[1, :, :, 3], [0.0, 0.0, 2.0])
    skinned, mesh = tiny_scene(with_skin=True, targets=2)
    both = scene_poses(skinned, 0, mesh, count=3)
    assert both.shape == (3 + 2, 4, 3, 4)
    # the last two: a target alone at weight 1, skinned in the rest pose
    # vertex 1, (1, 0, 0), lifted by 2 then moved 1 along x by joint 1 at rest
    assert np.allclose(apply(both, mesh.positions)[-1, 1], [2.0, 0.0, 2.0])
    assert scene_poses(Scene(scene.document), 0, Mesh(mesh.positions, mesh.faces)) is None


def test_scene_poses_cap_poses_times_vertices(monkeypatch):
    scene, mesh = tiny_scene(targets=0)
    monkeypatch.setattr(poses_module, "MAX_POSE_VERTICES", 4 * 3)
    assert scene_poses(scene, 0, mesh, count=8).shape[0] == 3


# --------------------------------------------------------------------------
# Fox (shared asset): decimate(poses=) on a real skinned mesh
# --------------------------------------------------------------------------

def fox_mesh(path: Path, scene):
    """Fox's mesh as load_scene gives it, or read and cleaned here while skinned meshes
    are still kept as they are."""
    if 0 in scene.meshes:
        return scene.meshes[0]
    from lodserver.io.clean import clean_mesh
    from lodserver.io.gltf import read_gltf_meshes
    from lodserver.io.limits import LoadLimits
    from lodserver.io.scene import HONOURED_REQUIRED
    parts = read_gltf_meshes(path, "glb", root=None, limits=LoadLimits.unbounded(),
                             honoured=HONOURED_REQUIRED)
    arrays = dict(parts["meshes"][0])
    arrays.pop("dropped_attributes", None)
    arrays.pop("missing_files", None)
    return clean_mesh(**arrays)[0]


def subdivided(positions, faces, joints, weights, levels):
    """Midpoint subdivision ``levels`` times, each new vertex's skin the mean of its edge
    ends' influences (summed per joint), the 4 largest kept and renormalised."""
    count = int(joints.max()) + 1
    dense = np.zeros((len(positions), count))
    np.add.at(dense, (np.repeat(np.arange(len(positions)), joints.shape[1]),
                      joints.astype(np.int64).ravel()), weights.ravel())
    for _ in range(levels):
        edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        ab, bc, ca = (len(positions) + inverse.ravel()).reshape(3, -1)
        positions = np.concatenate([positions, positions[unique].mean(1)])
        dense = np.concatenate([dense, dense[unique].mean(1)])
        a, b, c = faces.T
        faces = np.concatenate([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1),
                                np.stack([ca, bc, c], 1), np.stack([ab, bc, ca], 1)])
    order = np.argsort(-dense, axis=1)[:, :4]
    kept = np.take_along_axis(dense, order, 1)
    return Mesh(positions, faces), order.astype(np.float64), kept / kept.sum(1, keepdims=True)


def held_out_matrices(document, carried, skin, node, per_clip=8):
    """Joint matrices at times the poses were not sampled at: a quarter into each of
    ``per_clip`` equal slices of every clip (sample_times takes their middles)."""
    from lodserver.io.animation import clip_range
    found = []
    for clip in range(len(document["animations"])):
        first, last = clip_range(document, carried, clip)
        for j in range(per_clip):
            time = first + (j + 0.25) / per_clip * (last - first)
            found.append(joint_matrices(document, carried, skin, node,
                                        node_worlds(document, carried, time, clip)))
    return np.array(found)


def skinned_rms(full: Mesh, level: Mesh, matrices, samples=5000):
    """Mean over poses of the two-sided RMS surface distance (relative to the diagonal)
    between ``full`` and ``level``, each skinned with its own JOINTS_0/WEIGHTS_0."""
    from lodserver.metrics.surface import surface_distance
    from lodserver.simplify.poses import vertex_columns
    posed = []
    for m in (full, level):
        skin = vertex_columns(m, ["JOINTS_0", "WEIGHTS_0"])
        posed.append(apply(skin_pose_maps(skin[:, :4], skin[:, 4:], matrices), m.positions))
    return float(np.mean([surface_distance((posed[0][p], full.faces), (posed[1][p], level.faces),
                                           samples=samples)["rms"]
                          for p in range(len(matrices))]))


def test_fox_decimates_with_its_animation_poses(shared_meshes):
    from lodserver import build
    from lodserver.io.scene import load_scene
    from lodserver.simplify.poses import vertex_columns
    path = shared_meshes / "scenes" / "Fox.glb"
    scene = load_scene(path)
    fox = fox_mesh(path, scene)
    maps = scene_poses(scene, 0, fox, count=8)
    assert maps.shape == (8, fox.vertex_count, 3, 4)
    document, carried = scene.document, scene.carried
    times = sample_times(document, carried, 8)
    sampled = np.array([joint_matrices(document, carried, 0, 1,
                                       node_worlds(document, carried, t, c)) for c, t in times])
    skin = vertex_columns(fox, ["JOINTS_0", "WEIGHTS_0"])
    assert np.allclose(maps, skin_pose_maps(skin[:, :4], skin[:, 4:], sampled))
    from lodserver.simplify.carried import solved_part
    log = decimate(solved_part(fox), poses=maps)  # the kernel ranks the UVs; the skin is carried
    assert len(log.survivor) > 0.7 * fox.vertex_count
    assert np.isfinite(log.error).all()
    level = build(fox, poses=maps).at(ratio=0.2)
    assert level.attributes.layout == fox.attributes.layout

    # Fox has 290 vertices: at 20% its bends cannot be kept either way (the report has
    # the figures). Subdivided twice (4610 vertices, skin interpolated), its 20% level
    # built with the poses, skin carried by simplify.carried, is much closer to the
    # full mesh in animation poses it was not built from.
    dense, joints, weights = subdivided(fox.positions, fox.faces, skin[:, :4], skin[:, 4:], 2)
    dense = Mesh(dense.positions, dense.faces,
                 Attributes((("JOINTS_0", 4), ("WEIGHTS_0", 4)),
                            np.concatenate([joints, weights], 1), dense.faces))
    held = held_out_matrices(document, carried, 0, 1, per_clip=3)
    posed = build(dense, poses=skin_pose_maps(joints, weights, sampled)).at(ratio=0.2)
    plain = build(dense).at(ratio=0.2)
    assert posed.vertex_count == plain.vertex_count
    assert skinned_rms(dense, posed, held) < 0.5 * skinned_rms(dense, plain, held)


def test_the_shared_scenes_poses_and_builds(shared_meshes):
    from lodserver import build
    from lodserver.io.animation import node_weights
    from lodserver.io.scene import load_scene
    from lodserver.simplify.poses import vertex_columns
    cube = load_scene(shared_meshes / "scenes" / "AnimatedMorphCube.glb")
    mesh = cube.meshes[0]
    maps = scene_poses(cube, 0, mesh, count=8)
    # two targets alone, then the 8 animated weight sets (the cube is not skinned)
    assert maps.shape == (2 + 8, mesh.vertex_count, 3, 4)
    deltas = vertex_columns(mesh, ["TARGET0_POSITION", "TARGET1_POSITION"]).reshape(-1, 2, 3)
    assert np.allclose(maps[0, :, :, 3], deltas[:, 0])
    assert np.allclose(maps[1, :, :, 3], deltas[:, 1])
    node = cube.mesh_nodes[0][0]
    for p, (clip, time) in enumerate(sample_times(cube.document, cube.carried, 8)):
        weights = node_weights(cube.document, cube.carried, node, time, clip)
        assert np.allclose(maps[2 + p, :, :, 3], np.einsum("ntc,t->nc", deltas, weights))
    assert np.allclose(maps[..., :3], np.eye(3))
    for name in ("AnimatedMorphCube.glb", "RiggedSimple.glb", "BoxAnimated.glb"):
        scene = load_scene(shared_meshes / "scenes" / name)
        for index, mesh in scene.meshes.items():
            maps = scene_poses(scene, index, mesh)
            if name == "BoxAnimated.glb":
                assert maps is None                   # node animation only: rigid, no poses
                continue
            level = build(mesh, poses=maps).at(ratio=0.5)
            assert level.attributes.layout == mesh.attributes.layout
