"""New faces start at their split vertex (progressive/face_rotation.py): the rule
holds at every split, every per-corner array turns with its face, and the turn is
a rotation of the input's corners (the same triangle, the same orientation)."""

from __future__ import annotations

import numpy as np
import pytest

from lodserver import build
from lodserver.progressive.face_rotation import new_face_turns, turned_corners, turned_rows

from ..meshes import mesh, textured_sphere


def _rotations(rows):
    """Each row's three rotations, the smallest first: a key equal for turned rows."""
    r = np.stack([np.roll(rows, -k, axis=1) for k in range(3)], axis=1)
    return np.sort(r.view([("", r.dtype)] * 3).reshape(len(rows), 3), axis=1)


@pytest.mark.parametrize("name", ["spot", "torus", "textured"])
def test_every_new_face_starts_at_its_split_vertex(name):
    pm = build(textured_sphere() if name == "textured" else mesh(name))
    n0, n = pm.base_vertices, pm.vertex_count
    starts = 0
    for t in range(n0, n):
        at = pm.at(t + 1).faces
        s = pm.parent[t]
        for f in range(pm.face_counts[t - n0], pm.face_counts[t - n0 + 1]):
            face = list(at[f])
            assert face[0] == (s if s in face else t)
            starts += 1
    assert starts == len(pm.faces) - pm.face_counts[0] > 0
    # the layout already obeys the rule: no face turns again
    assert not new_face_turns(pm.faces, pm.parent, pm.face_counts, n0).any()


def test_per_corner_arrays_turn_with_their_faces():
    rng = np.random.default_rng(0)
    faces = rng.integers(0, 100, (50, 3))
    turn = rng.integers(0, 3, 50)
    turned = turned_rows(faces, turn)
    corners = np.arange(150)
    assert np.array_equal(turned.ravel()[turned_corners(corners, turn)], faces.ravel())
    assert np.array_equal(_rotations(turned), _rotations(faces))
    assert np.array_equal(turned_rows(faces, np.zeros(50, dtype=np.int64)), faces)
