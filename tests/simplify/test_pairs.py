"""Close-pair contraction: parts join, the record stays exact, no far pair is contracted."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lodserver import build
from lodserver.io import clean_mesh
from lodserver.mesh import MeshError

from ..meshes import SHARED, canonical_faces, mesh
from .test_fuzz import triangle_sets


def components(faces, n):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    rows = np.concatenate([faces[:, 0], faces[:, 1]])
    cols = np.concatenate([faces[:, 1], faces[:, 2]])
    labels = connected_components(coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)),
                                  directed=False)[1]
    return len(np.unique(labels[np.unique(faces)]))


def check_pair_build(original, threshold):
    pm = build(original, pair_threshold=threshold)
    # exact: the full level is the input, replay and direct extraction agree
    full = pm.at(pm.vertex_count)
    assert np.array_equal(canonical_faces(full.positions, full.faces),
                          canonical_faces(original.positions, original.faces))
    for level in np.linspace(pm.base_vertices, pm.vertex_count, 7).astype(int):
        direct = pm.arrays_at(level)
        for start in (pm.base_vertices, pm.vertex_count):
            replay = pm.cursor(start).seek(level).arrays()
            assert np.array_equal(replay[0], direct[0]) and np.array_equal(replay[1], direct[1])
    # a split that adds no face undoes a close-pair contraction: its two
    # vertices were at most `threshold` apart when contracted
    adds = np.diff(pm.face_counts)
    pair = np.nonzero(adds == 0)[0]
    gap = np.linalg.norm(pm.fine_position[pair] - pm.new_position[pair], axis=1)
    assert np.all(gap <= threshold * (1 + 1e-9) + 1e-12)
    return pm, len(pair)


def test_two_boxes_join():
    original = mesh("two_boxes")            # unit cubes 3 apart: faces 2 apart
    pm, pairs = check_pair_build(original, 2.5)
    assert pairs > 0
    base = pm.at(pm.base_vertices)
    assert components(original.faces, original.vertex_count) == 2
    assert components(base.faces, base.vertex_count) == 1
    pm, pairs = check_pair_build(original, 1.5)  # too far apart to join
    assert pairs == 0


@pytest.mark.skipif(not SHARED.is_dir(), reason=f"shared meshes not found at {SHARED}")
@pytest.mark.parametrize("name", ["office_chair.obj", "2CylinderEngine.glb"])
def test_parts_merge_at_coarse_levels(name):
    original = mesh(name)
    threshold = 0.03 * original.bounding_box_diagonal
    plain = build(original)
    pm, pairs = check_pair_build(original, threshold)
    assert pairs > 0
    for ratio in (0.02, 0.005):
        a, b = plain.at(ratio=ratio), pm.at(ratio=ratio)
        assert components(b.faces, b.vertex_count) < components(a.faces, a.vertex_count)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(triangle_sets(), st.floats(0.5, 2.5))
def test_random_triangle_sets_with_pairs(arrays, threshold):
    positions, faces = arrays
    try:
        original, _ = clean_mesh(positions, faces)
    except MeshError:
        return
    pm, _ = check_pair_build(original, threshold)
    for level in range(pm.base_vertices, pm.vertex_count + 1):
        f = pm.arrays_at(level)[1]
        assert np.all((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2]))
        assert len(np.unique(f)) == level


def test_pair_threshold_from_cli_and_api(tmp_path):
    from lodserver.cli import main
    from lodserver.io import save_mesh

    from ..api.test_api import _client, _upload, _wait_ready

    path = tmp_path / "boxes.obj"
    save_mesh(mesh("two_boxes"), path)
    asset = tmp_path / "boxes.pm"
    assert main(["build", str(path), "--pair-threshold", "60%", "-o", str(asset)]) == 0
    from lodserver import ProgressiveMesh
    pm = ProgressiveMesh.load(asset)
    base = pm.at(pm.base_vertices)
    assert components(base.faces, base.vertex_count) == 1
    assert main(["build", str(path), "--pair-threshold", "x%", "-o", str(asset)]) == 1

    with _client(tmp_path) as client:
        created = _upload(client, content=path.read_bytes(), filename="boxes.obj",
                          pair_threshold="60%")
        assert created.status_code == 202, created.text
        body = _wait_ready(client, created.json()["id"])
        assert body["status"] == "ready" and body["options"]["pair_threshold"] == "60%"
        assert _upload(client, content=path.read_bytes(), filename="boxes.obj",
                       pair_threshold="-1").status_code == 422
