"""Appearance attributes through decimation and the progressive mesh: wedges
stay exact at every level, seams stay seams, volume is preserved."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lodserver import build
from lodserver.progressive import decode_progressive, encode_progressive
from lodserver.simplify.collapse import decimate
from lodserver.mesh import Attributes, Materials, Mesh
from lodserver.simplify.quadrics import seam_edges, wedge_quadrics

from ..meshes import mesh, progressive

TEXTURED = ["textured_sphere", "hard_sphere"]


def corner_rows(m: Mesh) -> np.ndarray:
    """Every face as its three (position, attribute vector) corners, rotated to
    start at the smallest corner and sorted: equal for equal meshes whatever
    the vertex, wedge and face numbering."""
    a = m.attributes
    corners = np.concatenate([m.positions[m.faces], a.values[a.corners]], axis=2)  # (f, 3, 3+d)
    # rotate each face so its lexicographically smallest corner comes first (winding kept)
    keys = [tuple(row) for row in corners.reshape(-1, corners.shape[2])]
    rank = np.empty(len(keys), dtype=np.int64)
    rank[sorted(range(len(keys)), key=keys.__getitem__)] = np.arange(len(keys))
    first = np.argmin(rank.reshape(-1, 3), axis=1)
    roll = (first[:, None] + np.arange(3)) % 3
    rotated = np.take_along_axis(corners, roll[:, :, None], axis=1).reshape(len(corners), -1)
    return rotated[np.lexsort(rotated.T[::-1])]


def same_level(x: Mesh, y: Mesh) -> bool:
    return (np.array_equal(x.positions, y.positions) and np.array_equal(x.faces, y.faces)
            and np.array_equal(x.attributes.values, y.attributes.values)
            and np.array_equal(x.attributes.corners, y.attributes.corners))


def charts(m: Mesh) -> np.ndarray:
    """Chart id of every face: faces joined across edges that are not seams."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    faces, corners = m.faces, m.attributes.corners
    u, v = faces.ravel(), faces[:, [1, 2, 0]].ravel()
    wu, wv = corners.ravel(), corners[:, [1, 2, 0]].ravel()
    face = np.repeat(np.arange(len(faces)), 3)
    # a half-edge and its twin join their faces if the wedges agree on both ends
    key = {}
    rows, cols = [], []
    for i in range(len(u)):
        twin = key.get((v[i], u[i]))
        if twin is not None and wu[i] == wv[twin] and wv[i] == wu[twin]:
            rows.append(face[i])
            cols.append(face[twin])
        key[(u[i], v[i])] = i
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(faces), len(faces)))
    return connected_components(graph, directed=False)[1]


@pytest.mark.parametrize("name", TEXTURED)
def test_all_splits_give_back_the_input_with_its_attributes(name):
    m, pm = mesh(name), progressive(name)
    assert pm.has_attributes and pm.split_count > 0.9 * m.vertex_count
    full = pm.at(pm.vertex_count)
    np.testing.assert_array_equal(corner_rows(full), corner_rows(m))
    replayed = pm.cursor(pm.base_vertices).seek(pm.vertex_count).mesh()
    assert same_level(replayed, full)


@pytest.mark.parametrize("name", TEXTURED)
def test_forward_then_backward_is_the_identity_with_attributes(name):
    pm = progressive(name)
    cursor = pm.cursor(pm.base_vertices)
    start = cursor.mesh()
    cursor.seek(pm.vertex_count).seek(pm.base_vertices)
    assert same_level(cursor.mesh(), start)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
@pytest.mark.parametrize("name", TEXTURED)
def test_a_level_is_the_same_from_every_direction(name, data):
    pm = progressive(name)
    levels = st.integers(pm.base_vertices, pm.vertex_count)
    start, target = data.draw(levels), data.draw(levels)
    reached = pm.cursor(start).seek(target).mesh()
    assert same_level(reached, pm.at(target))
    assert same_level(pm.cursor(pm.vertex_count).seek(target).mesh(), reached)


@pytest.mark.parametrize("name", TEXTURED)
def test_wedges_merge_only_within_their_chart(name):
    """No wedge's attributes move across a seam: a wedge only ever merges into
    a wedge of the same chart, so every corner at every level reads a wedge of
    its own face's chart."""
    pm = progressive(name)
    full = pm.at(pm.vertex_count)
    chart = charts(full)
    wedge_chart = np.full(len(pm.wedge_values), -1)
    wedge_chart[full.attributes.corners.ravel()] = np.repeat(chart, 3)
    merged = np.nonzero(pm.wedge_parent >= 0)[0]
    assert len(merged) > 0
    known = wedge_chart[merged] >= 0
    assert np.array_equal(wedge_chart[merged][known], wedge_chart[pm.wedge_parent[merged]][known])
    for level in np.linspace(pm.base_vertices, pm.vertex_count, 7).astype(int):
        lod = pm.at(level)
        corners_chart = wedge_chart[lod.attributes.corners]
        assert np.all(corners_chart == chart[:lod.face_count, None])


def test_seams_survive_to_coarse_levels():
    pm = progressive("hard_sphere")
    lod = pm.at(ratio=0.1)
    edges, _ = seam_edges(lod.faces, lod.attributes.corners)
    assert len(edges) > 0
    # the hard edge runs round the equator: the seam vertices there stay at z = 0
    normals = lod.attributes.values[:, 2]
    assert normals.min() < -0.3 and normals.max() > 0.3


def test_merged_normals_are_unit_length():
    pm = progressive("textured_sphere")
    values, _ = pm.wedges_at(pm.level_for(ratio=0.05))
    np.testing.assert_allclose(np.linalg.norm(values[:, :3], axis=1), 1.0, rtol=1e-9)


def test_uvs_follow_the_surface():
    """On the sphere u, v are functions of the position (away from the seam
    and the poles), so a coarse level's UVs must still match its positions."""
    lod = progressive("textured_sphere").at(ratio=0.2)
    a = lod.attributes
    position = lod.positions[lod.faces]            # (f, 3, 3)
    uv = a.values[a.corners][:, :, 3:]
    v_expected = np.arccos(np.clip(position[:, :, 2] / np.linalg.norm(position, axis=2), -1, 1)) / np.pi
    assert np.abs(uv[:, :, 1] - v_expected).mean() < 0.02


def volume(m: Mesh) -> float:
    p = m.positions[m.faces]
    return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6)


@pytest.mark.parametrize("name", ["icosphere", "torus"])
def test_volume_preservation_keeps_the_volume(name):
    m = mesh(name)
    kept = build(m).at(ratio=0.1)
    free = build(m, preserve_volume=False).at(ratio=0.1)
    assert abs(volume(kept) / volume(m) - 1) < 0.01
    assert abs(volume(kept) - volume(m)) < abs(volume(free) - volume(m))


def test_a_constant_attribute_costs_nothing():
    """A wedge quadric measures deviation from the attribute field: a constant
    field fits every face exactly, so only the geometric terms remain."""
    m = mesh("icosphere")
    # jittered, so that no two collapses tie and rounding cannot reorder them
    jitter = np.random.default_rng(1).normal(scale=1e-3, size=m.positions.shape)
    m = Mesh(m.positions + jitter, m.faces)
    values = np.ones((m.vertex_count, 2))
    q = wedge_quadrics(m.positions, m.faces, m.faces, values)
    np.testing.assert_allclose(q[:, :9], 0, atol=1e-12)      # no gradient: A = 0, b = 0
    # ... and the best value (D_j / area = 1) leaves no residual: c = sum_j D_j^2 / area
    np.testing.assert_allclose(q[:, 9], (q[:, 14] ** 2 + q[:, 18] ** 2) / q[:, 10], rtol=1e-12)
    painted = Mesh(m.positions, m.faces, Attributes((("TEXCOORD_0", 2),), values, m.faces))
    with_attributes = decimate(painted)
    np.testing.assert_allclose(with_attributes.merge_value, 1.0)
    geometric = decimate(m)
    np.testing.assert_array_equal(geometric.survivor, with_attributes.survivor)
    np.testing.assert_allclose(geometric.position, with_attributes.position, rtol=1e-9)


def test_attributes_and_materials_survive_the_artefact():
    m = mesh("textured_sphere")
    material = np.zeros(m.face_count, dtype=np.int32)
    material[::2] = -1
    materials = Materials({"materials": [{"name": "paint"}], "textures": [], "images": [],
                           "samplers": []}, (b"\x89PNG fake",))
    pm = build(Mesh(m.positions, m.faces, m.attributes, material, materials))
    again = decode_progressive(encode_progressive(pm))
    for level in (pm.base_vertices, pm.level_for(ratio=0.3), pm.vertex_count):
        x, y = pm.at(level), again.at(level)
        assert same_level(x, y)
        assert np.array_equal(x.face_material, y.face_material)
    assert again.materials.gltf == materials.gltf and again.materials.images == materials.images
    np.testing.assert_array_equal(np.sort(pm.at(pm.vertex_count).face_material), np.sort(material))


def test_attribute_weights_are_checked():
    with pytest.raises(ValueError, match="positive"):
        build(mesh("textured_sphere"), attribute_weights={"NORMAL": 0})
    with pytest.raises(ValueError, match="no attribute named"):
        build(mesh("textured_sphere"), attribute_weights={"TANGENT": 1})


@pytest.mark.parametrize("name", ["Duck.glb", "bunny10k_textured/bunny10k_textured.obj",
                                  "Avocado/Avocado.gltf"])
def test_shared_textured_meshes_are_exact_at_every_level(shared_meshes, name):
    """The core's properties with real wedges, seams and materials: all splits
    give back the input, forward then backward is the identity, and a level
    is the same from either end; two wedges of one vertex never merge."""
    m = mesh(name)
    pm = build(m)
    assert pm.has_attributes and pm.materials is not None
    full = pm.at(pm.vertex_count)
    np.testing.assert_array_equal(corner_rows(full), corner_rows(m))
    assert np.array_equal(np.sort(full.face_material), np.sort(m.face_material))
    cursor = pm.cursor(pm.base_vertices)
    base = cursor.mesh()
    for level in np.linspace(pm.base_vertices, pm.vertex_count, 6).astype(int)[::-1]:
        assert same_level(pm.cursor(pm.vertex_count).seek(int(level)).mesh(), pm.at(int(level)))
        assert same_level(cursor.seek(int(level)).mesh(), pm.at(int(level)))
    assert same_level(cursor.seek(pm.base_vertices).mesh(), base)
    # a seam stays a seam: a split re-creates a wedge of its new vertex out of
    # a wedge of the vertex it splits, never two wedges of one vertex
    owner = np.full(len(pm.wedge_values), -1)
    owner[pm.corner_wedges.ravel()] = pm.faces.ravel()

    def owner_at(wedge, level):
        v = owner[wedge]
        while v >= level:
            v = pm.parent[v]
        return v

    split_of = np.repeat(np.arange(pm.base_vertices, pm.vertex_count), np.diff(pm.wedge_counts))
    for x, t in zip(range(int(pm.wedge_counts[0]), len(pm.wedge_values)), split_of):
        if owner[x] >= 0 and owner[pm.wedge_parent[x]] >= 0:
            assert owner_at(x, t + 1) == t
            assert owner_at(pm.wedge_parent[x], t + 1) == pm.parent[t]
