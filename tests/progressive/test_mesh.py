"""Exactness of the progressive mesh, as properties over real and generated meshes."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lodserver import build
from lodserver.progressive.mesh import _faces_at_kernel, ancestor_below

from ..meshes import SHARED, canonical_faces, mesh, progressive

GENERATED = ["spot", "icosphere", "torus", "grid", "two_boxes"]
SHARED_NAMES = ["fertility.off", "camelhead.off", "stanford-bunny.obj", "mountain.obj",
                "non_manif_hole.ply", "joined_tetrahedra.obj", "conrod.stl", "soup.stl",
                "office_chair.obj", "brain.ply", "Duck.glb", "2CylinderEngine.glb"]


def _params():
    shared = [pytest.param(name, marks=pytest.mark.skipif(
        not SHARED.is_dir(), reason=f"shared meshes not found at {SHARED}")) for name in SHARED_NAMES]
    return GENERATED + shared


ALL = _params()
HYPOTHESIS = settings(max_examples=25, deadline=None,
                      suppress_health_check=[HealthCheck.function_scoped_fixture])


def _edge_face_counts(faces):
    e = np.sort(np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2), axis=1)
    return np.unique(e, axis=0, return_counts=True)[1]


def _every_mesh_drawing_levels(test):
    """``test(name, data)`` over every mesh, as a Hypothesis test (HYPOTHESIS) whose
    ``data`` draws its levels (``_drawn_levels``)."""
    return pytest.mark.parametrize("name", ALL)(HYPOTHESIS(given(data=st.data())(test)))


def _drawn_levels(name, data, *labels):
    """``name``'s progressive mesh and a level (base to full detail) drawn from
    ``data`` for each label, in order."""
    pm = progressive(name)
    return pm, [data.draw(st.integers(pm.base_vertices, pm.vertex_count), label=label)
                for label in labels]


@pytest.mark.parametrize("name", ALL)
def test_full_level_is_the_input(name):
    original, pm = mesh(name), progressive(name)
    full = pm.at(pm.vertex_count)
    assert full.vertex_count == original.vertex_count
    assert full.face_count == original.face_count
    # same vertices (as a multiset of positions) and same faces up to order
    assert np.array_equal(np.sort(full.positions, axis=0), np.sort(original.positions, axis=0))
    assert np.array_equal(canonical_faces(full.positions, full.faces),
                          canonical_faces(original.positions, original.faces))


@pytest.mark.parametrize("name", ALL)
def test_replaying_every_split_gives_the_input(name):
    original, pm = mesh(name), progressive(name)
    cursor = pm.cursor(pm.base_vertices).seek(pm.vertex_count)
    positions, faces = cursor.arrays()
    assert np.array_equal(positions, pm.positions)
    assert np.array_equal(canonical_faces(positions, faces),
                          canonical_faces(original.positions, original.faces))


@_every_mesh_drawing_levels
def test_forward_then_backward_is_identity(name, data):
    pm, (a, b) = _drawn_levels(name, data, "from", "to")
    cursor = pm.cursor(a)
    before = cursor.arrays()
    cursor.seek(b).seek(a)
    after = cursor.arrays()
    assert np.array_equal(before[0], after[0]) and np.array_equal(before[1], after[1])


@_every_mesh_drawing_levels
def test_level_is_the_same_from_any_direction(name, data):
    pm, (level, start) = _drawn_levels(name, data, "level", "start")
    direct = pm.arrays_at(level)
    from_base = pm.cursor(pm.base_vertices).seek(level).arrays()
    from_full = pm.cursor(pm.vertex_count).seek(level).arrays()
    from_start = pm.cursor(start).seek(level).arrays()
    for positions, faces in (from_base, from_full, from_start):
        assert np.array_equal(positions, direct[0])
        assert np.array_equal(faces, direct[1])


def _sample_levels(pm, count=12):
    """Up to ``count`` levels below full detail, the base included (none if there are no splits)."""
    if pm.split_count == 0:
        return []
    return sorted({int(x) for x in np.linspace(pm.base_vertices, pm.vertex_count - 1, count)})


@pytest.mark.parametrize("name", ALL)
def test_levels_stay_manifold_and_clean(name):
    original, pm = mesh(name), progressive(name)
    input_manifold = _edge_face_counts(original.faces).max() <= 2
    for level in _sample_levels(pm):
        lod = pm.at(level)
        f = lod.faces
        # no face repeats a vertex, and every vertex is used
        assert np.all((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2]))
        assert len(np.unique(f)) == lod.vertex_count
        # no duplicate faces appear
        assert len(np.unique(np.sort(f, axis=1), axis=0)) == len(f)
        if input_manifold:
            assert _edge_face_counts(f).max() <= 2, f"non-manifold edge at level {level}"


@pytest.mark.parametrize("name", ALL)
def test_no_face_flips_relative_to_the_level_above(name):
    pm = progressive(name)
    for level in _sample_levels(pm, 20):
        coarse, fine = pm.arrays_at(level), pm.arrays_at(level + 1)
        count = len(coarse[1])

        def normals(positions, faces):
            tri = positions[faces[:count]]
            return np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])

        a, b = normals(*coarse), normals(*fine)
        la, lb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
        ok = (la > 0) & (lb > 0)
        cos = np.einsum("ij,ij->i", a[ok], b[ok]) / (la[ok] * lb[ok])
        assert cos.min() > 0, f"a face flips between levels {level} and {level + 1}"


@pytest.mark.parametrize("name", GENERATED)
def test_counts_and_error_curve_are_monotone(name):
    pm = progressive(name)
    assert np.all(np.diff(pm.face_counts) >= 0)
    assert np.all(np.diff(pm.level_error) <= 0)
    assert pm.error_at_level(pm.vertex_count) == 0
    assert pm.base_vertices < 0.05 * pm.vertex_count + 8


def test_level_selection():
    pm = progressive("spot")
    assert pm.level_for(vertices=10**9) == pm.vertex_count
    assert pm.level_for(vertices=1) == pm.base_vertices
    level = pm.level_for(faces=1000)
    assert pm.faces_at_level(level) <= 1000 < pm.faces_at_level(level + 1)
    assert pm.at(ratio=0.1).face_count == pm.at(faces=round(0.1 * pm.face_count)).face_count
    e = pm.error_at_level(pm.level_for(ratio=0.2))
    level = pm.level_for(error=e)
    assert pm.error_at_level(level) <= e
    assert level == pm.base_vertices or pm.error_at_level(level - 1) > e
    for bad in ({"vertices": 0}, {"ratio": 0}, {"ratio": 1.5}, {"error": -1}, {"faces": 0}, {}):
        with pytest.raises(ValueError):
            pm.level_for(**bad)
    with pytest.raises(ValueError):
        pm.at(pm.vertex_count + 1)
    # check_level is public: the packet encoder checks its levels with it
    assert pm.check_level(np.int64(pm.base_vertices)) == pm.base_vertices
    for bad in (pm.base_vertices - 1, pm.vertex_count + 1):
        with pytest.raises(ValueError, match="outside"):
            pm.check_level(bad)


def test_ancestor_below_is_the_level_a_corner_reads():
    """The public kernel the packet encoder shares: a full-detail corner at a level
    reads its first ancestor below that level, as the level's faces say."""
    pm = progressive("torus")
    level = (pm.base_vertices + pm.vertex_count) // 2
    faces = pm.arrays_at(level)[1]
    expected = np.array([[ancestor_below(pm.parent, int(x), level) for x in row]
                         for row in pm.faces[:len(faces)]])
    assert np.array_equal(faces, expected)


def _climbed(parent, faces, level):
    """``faces`` read at ``level`` by climbing the hierarchy, vectorized (the reference)."""
    x = faces.copy()
    while np.any(x >= level):
        x = np.where(x >= level, parent[np.minimum(x, len(parent) - 1)], x)
    return x


@pytest.mark.parametrize("name", ["torus", "spot"])
def test_every_level_matches_climbing_and_replaying(name):
    """``arrays_at`` and ``wedges_at`` (branch-free table kernels) at every level,
    against climbing the hierarchy from each corner and against a cursor that
    collapses one split at a time from full detail; the table kernel gives the
    same with the int64 table a mesh of over 2**31 vertices would use, and
    ``write_level`` the same into uint32 arrays."""
    pm = progressive(name)
    cursor = pm.cursor(pm.vertex_count)
    for level in range(pm.vertex_count, pm.base_vertices - 1, -1):
        positions, faces = pm.arrays_at(level)
        cursor.seek(level)
        assert np.array_equal(positions, cursor.positions[:level])
        assert np.array_equal(faces, cursor.arrays()[1])
        assert np.array_equal(faces, _climbed(pm.parent, pm.faces[:len(faces)], level))
        wide = np.empty_like(faces)
        below = np.empty(pm.vertex_count - level + 1, dtype=np.int64)
        _faces_at_kernel(pm.faces, pm.parent, len(faces), level, below, wide)
        assert np.array_equal(wide, faces)
        if pm.has_attributes:
            values, corners = pm.wedges_at(level)
            expected_values, expected_corners = cursor.wedges()
            assert np.array_equal(values, expected_values)
            assert np.array_equal(corners, expected_corners)
    level = (pm.base_vertices + pm.vertex_count) // 3
    expected = pm.arrays_at(level)
    positions = np.empty((level, 3), dtype=np.float32)
    faces = np.empty((pm.faces_at_level(level), 3), dtype=np.uint32)
    pm.write_level(level, positions, faces)
    assert np.array_equal(faces, expected[1])
    assert np.array_equal(positions, expected[0].astype(np.float32))


def test_locked_vertices_never_move_or_vanish():
    original = mesh("grid")
    from lodserver.simplify.topology import census
    locked = np.zeros(original.vertex_count, bool)
    locked[census(original.faces, original.vertex_count).on_boundary] = True
    pm = build(original, locked=locked)
    # locked input vertices, by position (the progressive mesh renumbers them)
    keys = {tuple(p) for p in original.positions[locked]}
    base = pm.at(pm.base_vertices)
    assert keys <= {tuple(p) for p in base.positions}
    for level in _sample_levels(pm):
        assert keys <= {tuple(p) for p in pm.at(level).positions}


def test_bad_lock_mask_is_refused():
    with pytest.raises(ValueError, match="locked"):
        build(mesh("spot"), locked=np.zeros(3, bool))


def test_simplification_stays_close_to_the_surface():
    from lodserver.metrics import surface_distance
    original, pm = mesh("spot"), progressive("spot")
    for ratio, bound in ((0.5, 2e-3), (0.1, 6e-3)):
        d = surface_distance(original, pm.at(ratio=ratio), samples=20_000)
        assert d["rms"] < bound, (ratio, d)


def test_two_parts_are_decimated_separately():
    pm = progressive("two_boxes")
    base = pm.at(pm.base_vertices)
    # each box ends as a tetrahedron at worst; nothing joins them
    assert base.face_count >= 8
    # no face spans the gap between the boxes (x < 1.5 and x > 1.5)
    side = base.positions[base.faces][:, :, 0] > 1.5
    assert np.all(side.all(axis=1) | ~side.any(axis=1))
    assert side.any() and not side.all()


@pytest.mark.parametrize("name", ["spot", "torus"])
def test_a_level_needs_no_second_scan_and_equals_the_checked_mesh(name, tmp_path):
    pm = progressive(name)
    pm.save(tmp_path / "a.pm")
    loaded = type(pm).load(tmp_path / "a.pm")
    assert pm.levels_finite and loaded.levels_finite
    rng = np.random.default_rng(3)
    for level in [pm.base_vertices, pm.vertex_count, *rng.integers(pm.base_vertices,
                                                                   pm.vertex_count, 8)]:
        fast = loaded.at(int(level))
        checked = pm.mesh_of(*pm.arrays_at(int(level)), *pm.wedges_at(int(level)))
        assert not fast.positions.flags.writeable and not fast.faces.flags.writeable
        np.testing.assert_array_equal(fast.positions, checked.positions)
        np.testing.assert_array_equal(fast.faces, checked.faces)
        assert (fast.attributes is None) == (checked.attributes is None)
        if fast.attributes is not None:
            np.testing.assert_array_equal(fast.attributes.values, checked.attributes.values)
            np.testing.assert_array_equal(fast.attributes.corners, checked.attributes.corners)


def test_a_non_finite_coarse_position_still_fails_its_levels():
    import dataclasses

    from lodserver.mesh import MeshError

    pm = progressive("torus")
    coarse = pm.coarse_position.copy()
    coarse[-1] = np.nan        # the last split's: the level just below full detail reads it
    broken = dataclasses.replace(pm, coarse_position=coarse)
    assert not broken.levels_finite
    with pytest.raises(MeshError, match="NaN or infinite"):
        broken.at(broken.vertex_count - 1)
    broken.at(broken.vertex_count)


def test_a_mesh_of_checked_arrays_still_checks_shapes():
    from lodserver.mesh import Mesh, MeshError

    with pytest.raises(MeshError, match="no faces"):
        Mesh.of_checked_arrays(np.zeros((3, 3)), np.zeros((0, 3), dtype=np.int64))
    with pytest.raises(MeshError, match="shape"):
        Mesh.of_checked_arrays(np.zeros((3, 2)), np.zeros((1, 3), dtype=np.int64))
