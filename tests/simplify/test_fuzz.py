"""Random meshes, clean and broken, through the whole build: no crash, exact replay.

Hypothesis draws small triangle sets over a few vertices (open sheets, fans,
non-manifold edges, bow ties, several components), plus noisy spheres whose
optimal placements land anywhere.
"""

import numpy as np
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lodserver import build
from lodserver.io import clean_mesh
from lodserver.mesh import MeshError

from ..meshes import canonical_faces

FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _check_exact(mesh):
    pm = build(mesh)
    full = pm.at(pm.vertex_count)
    assert np.array_equal(canonical_faces(full.positions, full.faces),
                          canonical_faces(mesh.positions, mesh.faces))
    replayed = pm.cursor(pm.base_vertices).seek(pm.vertex_count).arrays()
    assert np.array_equal(replayed[0], full.positions) and np.array_equal(replayed[1], full.faces)
    for level in range(pm.base_vertices, pm.vertex_count + 1):
        positions, faces = pm.arrays_at(level)
        assert len(np.unique(faces)) == level           # every vertex in use
        assert np.all((faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2])
                      & (faces[:, 0] != faces[:, 2]))
    down = pm.cursor(pm.vertex_count).seek(pm.base_vertices).arrays()
    base = pm.arrays_at(pm.base_vertices)
    assert np.array_equal(down[0], base[0]) and np.array_equal(down[1], base[1])
    return pm


@st.composite
def triangle_sets(draw):
    n = draw(st.integers(4, 14))
    grid = draw(st.lists(st.tuples(*[st.integers(0, 3)] * 3), min_size=n, max_size=n, unique=True))
    triple = st.lists(st.integers(0, n - 1), min_size=3, max_size=3, unique=True)
    faces = draw(st.lists(triple, min_size=1, max_size=24))
    return np.array(grid, float), np.array(faces, np.int64)


@FUZZ
@given(triangle_sets())
def test_random_triangle_sets(arrays):
    positions, faces = arrays
    try:
        mesh, _ = clean_mesh(positions, faces)
    except MeshError:
        return      # every face degenerate or duplicate: nothing to build
    _check_exact(mesh)


@FUZZ
@given(seed=st.integers(0, 2**32 - 1), noise=st.floats(0, 0.3), keep=st.floats(0.6, 1.0))
def test_noisy_sphere_with_holes(seed, noise, keep):
    rng = np.random.default_rng(seed)
    sphere = trimesh.creation.icosphere(2)
    positions = sphere.vertices + rng.normal(scale=noise * 0.1, size=sphere.vertices.shape)
    faces = sphere.faces[rng.random(len(sphere.faces)) < keep]
    try:
        mesh, _ = clean_mesh(positions, faces)
    except MeshError:
        return
    _check_exact(mesh)
