"""Octree clustering recorded as collapses: a progressive mesh as exact as
edge collapse's, which may join parts."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from lodserver import build
from lodserver.cli import main
from lodserver.mesh import Mesh
from lodserver.progressive.mesh import ProgressiveMesh

from ..meshes import canonical_faces, mesh

NAMES = ["icosphere", "torus", "grid", "two_boxes", "spot"]


def components(m: Mesh) -> int:
    f = m.faces
    rows = np.concatenate([f[:, 0], f[:, 1]])
    cols = np.concatenate([f[:, 1], f[:, 2]])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(m.vertex_count,) * 2)
    used = np.unique(f)
    labels = connected_components(graph, directed=False)[1]
    return len(np.unique(labels[used]))


def same(x: Mesh, y: Mesh) -> bool:
    return np.array_equal(x.positions, y.positions) and np.array_equal(x.faces, y.faces)


@pytest.fixture(scope="module", params=NAMES)
def clustered(request):
    m = mesh(request.param)
    return Mesh(m.positions, m.faces), build(m, method="cluster")


def test_all_splits_give_back_the_input(clustered):
    m, pm = clustered
    assert pm.base_vertices < 0.05 * m.vertex_count + 4
    full = pm.at(pm.vertex_count)
    np.testing.assert_array_equal(canonical_faces(full.positions, full.faces),
                                  canonical_faces(m.positions, m.faces))
    assert same(pm.cursor(pm.base_vertices).seek(pm.vertex_count).mesh(), full)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                  HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_levels_are_the_same_from_every_direction(clustered, data):
    _, pm = clustered
    levels = st.integers(pm.base_vertices, pm.vertex_count)
    start, target = data.draw(levels), data.draw(levels)
    assert same(pm.cursor(start).seek(target).mesh(), pm.at(target))


def test_no_level_holds_a_duplicate_or_degenerate_face(clustered):
    _, pm = clustered
    for level in np.unique(np.geomspace(pm.base_vertices, pm.vertex_count, 12).astype(int)):
        faces = pm.at(int(level)).faces
        assert np.all((faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2])
                      & (faces[:, 0] != faces[:, 2]))
        assert len(np.unique(np.sort(faces, axis=1), axis=0)) == len(faces)


def test_clustering_joins_parts():
    m = mesh("two_boxes")
    pm = build(m, method="cluster")
    assert components(m) == 2
    assert components(pm.at(pm.base_vertices)) == 1


def test_errors_are_distances_within_the_cells(clustered):
    """A representative stays inside its cell, so its RMS distance to the
    planes of the cell's faces is at most the cell's diagonal: positive at the
    base, and never more than the mesh's bounding-box diagonal (mesh units)."""
    m, pm = clustered
    assert 0 < pm.error_at_level(pm.base_vertices) <= m.bounding_box_diagonal
    assert np.all(pm.error >= 0)


def test_cluster_build_from_the_cli(tmp_path):
    source = tmp_path / "sphere.obj"
    from lodserver.io import save_mesh
    save_mesh(mesh("icosphere"), source)
    out = tmp_path / "sphere.pm"
    assert main(["build", str(source), "-o", str(out), "--method", "cluster"]) == 0
    pm = ProgressiveMesh.load(out)
    assert pm.metadata["options"]["method"] == "cluster"
    assert pm.vertex_count == mesh("icosphere").vertex_count


@pytest.mark.parametrize("name", ["2CylinderEngine.glb", "office_chair.obj"])
def test_multi_part_meshes_end_in_few_parts(shared_meshes, name):
    m = mesh(name)
    pm = build(m, method="cluster")
    lod = pm.at(ratio=0.02)
    assert components(lod) < components(m) / 4
    full = pm.at(pm.vertex_count)
    np.testing.assert_array_equal(canonical_faces(full.positions, full.faces),
                                  canonical_faces(m.positions, m.faces))


def test_a_corner_may_move_more_often_than_there_are_corners(shared_meshes):
    """soup.stl (100 scattered triangles) moves 416 corners over the depths:
    more than its 300 corners, since a corner moves each time its vertex
    merges. The log must grow to hold them (it once wrote past its end)."""
    from lodserver.simplify.octree import octree_log
    m = mesh("soup.stl")
    log = octree_log(Mesh(m.positions, m.faces))
    assert len(log.moved_corners) > 3 * m.face_count
    assert log.moved_offsets[-1] == len(log.moved_corners)
    pm = build(m, method="cluster")
    full = pm.at(pm.vertex_count)
    np.testing.assert_array_equal(canonical_faces(full.positions, full.faces),
                                  canonical_faces(m.positions, m.faces))
    for level in range(pm.base_vertices, pm.vertex_count + 1):
        assert same(pm.cursor(pm.vertex_count).seek(level).mesh(), pm.at(level))
