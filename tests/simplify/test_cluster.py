"""Vertex clustering: targets, placement inside cells, merging parts."""

import numpy as np
import pytest
import trimesh

from lodserver.simplify.cluster import cluster
from lodserver.io import clean_mesh
from lodserver.mesh import MeshError
from lodserver.metrics import surface_distance

from ..meshes import mesh


@pytest.mark.parametrize("ratio", [0.5, 0.1, 0.02])
def test_reaches_the_face_target_from_below(ratio):
    original = mesh("spot")
    target = round(ratio * original.face_count)
    lod = cluster(original, target_faces=target)
    assert 0.6 * target <= lod.face_count <= target
    assert surface_distance(original, lod, samples=20_000)["rms"] < 0.02


def test_a_fine_grid_changes_nothing():
    original = mesh("icosphere")
    lod = cluster(original, cells=100_000)
    assert lod.face_count == original.face_count
    assert np.allclose(np.sort(lod.positions, axis=0), np.sort(original.positions, axis=0),
                       atol=1e-9)


def test_representatives_stay_in_their_cells():
    original = mesh("torus")
    cells = 8
    lod = cluster(original, cells=cells)
    lo = original.positions.min(axis=0)
    size = (original.positions.max(axis=0) - lo).max() / cells
    # every representative lies in the cell of some input vertex
    input_cells = {tuple(c) for c in np.minimum(((original.positions - lo) / size).astype(int), cells - 1)}
    for p in lod.positions:
        cell = np.floor((p - lo) / size - 1e-9).astype(int)
        near = {tuple(cell + d) for d in np.ndindex(2, 2, 2)}
        assert near & input_cells


def _components(m):
    """Connected components of the vertices used by faces."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    f = m.faces
    rows = np.concatenate([f[:, 0], f[:, 1]])
    cols = np.concatenate([f[:, 1], f[:, 2]])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(m.vertex_count,) * 2)
    return connected_components(graph, directed=False)[0]


def test_merges_nearby_parts():
    boxes = trimesh.util.concatenate([trimesh.creation.box(), trimesh.creation.box().apply_translation([1.01, 0, 0])])
    original, _ = clean_mesh(boxes.vertices, boxes.faces)
    lod = cluster(original, cells=3)
    assert _components(original) == 2 and _components(lod) == 1


def test_bad_arguments():
    with pytest.raises(ValueError):
        cluster(mesh("spot"))
    with pytest.raises(ValueError):
        cluster(mesh("spot"), cells=4, target_faces=10)
    with pytest.raises(MeshError, match="no face survives"):
        cluster(mesh("spot"), cells=1)
