"""Dense copies of a part (``simplify.submesh``): a copy holds every face and
vertex a collapse of its part touches, writing it back changes only the
part's rows, and the kernel's log on a copy, mapped back, is a log of the
mesh; and the prefetch hints (``simplify.prefetch``) compile and change no
result."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit

from lodserver.simplify import collapse
from lodserver.simplify.options import DecimateOptions
from lodserver.simplify.parts import FROZEN, partition
from lodserver.simplify.prefetch import prefetch, prefetch2
from lodserver.simplify.state import new_scratch
from lodserver.simplify.submesh import extract, group_faces, map_log, write_back

from ..meshes import mesh


def _kernel_inputs(name):
    m = mesh(name)
    verts, faces, wedges, options, _, _ = collapse._prepare(m, DecimateOptions())
    faces = faces.astype(np.int32)
    n = len(verts.pos)
    alive = np.bincount(faces.ravel(), minlength=n) > 0
    return verts, faces, wedges, options, alive


@pytest.mark.parametrize("name", ["spot", "textured_sphere"])
def test_a_copy_holds_the_part_and_its_ring(name):
    verts, faces, wedges, _, alive = _kernel_inputs(name)
    n = len(verts.pos)
    label = partition(verts.pos, faces, alive, 4)
    face_alive = np.ones(len(faces), bool)
    ids, offsets = group_faces(faces, face_alive, label, 4)
    count = np.bincount(faces.ravel(), minlength=n)
    seen = np.full(n, -1)
    held = []
    for part in range(4):
        own = ids[offsets[part]:offsets[part + 1]]
        sub = extract(verts, faces, face_alive, count, wedges, label, part, own, seen)
        assert (seen == -1).all()       # the scratch is handed back clean
        # exactly the faces with a vertex of the part, renumbered, in the
        # order of their first vertex
        expected = np.flatnonzero((label[faces] == part).any(axis=1))
        np.testing.assert_array_equal(np.sort(sub.face_ids), expected)
        expected = sub.face_ids
        assert (np.diff(sub.topo.faces.min(axis=1)) >= 0).all()
        np.testing.assert_array_equal(sub.vertex_ids[sub.topo.faces], faces[expected])
        assert (np.diff(sub.vertex_ids) > 0).all()
        np.testing.assert_array_equal(sub.label == 0, label[sub.vertex_ids] == part)
        np.testing.assert_array_equal(sub.verts.quadrics, verts.quadrics[sub.vertex_ids])
        # a part's vertex has all its faces in the copy; a frozen one keeps the mesh's count
        np.testing.assert_array_equal(sub.topo.face_count, count[sub.vertex_ids])
        if wedges.quadric.shape[0]:
            np.testing.assert_array_equal(sub.wedges.corner.reshape(-1, 3),
                                          wedges.corner.reshape(-1, 3)[expected])
        held.append(set(sub.face_ids))
    # no face is in two copies, and every face not in one is a frozen strip's
    assert sum(map(len, held)) == len(set().union(*held))
    missing = np.setdiff1d(np.arange(len(faces)), list(set().union(*held)))
    assert (label[faces[missing]] == FROZEN).all()


@pytest.mark.parametrize("name", ["spot", "textured_sphere"])
def test_a_decimated_copy_maps_back_to_a_log_of_the_mesh(name):
    verts, faces, wedges, options, alive = _kernel_inputs(name)
    n = len(verts.pos)
    before_faces, before_pos = faces.copy(), verts.pos.copy()
    label = partition(verts.pos, faces, alive, 2)
    face_alive = np.ones(len(faces), bool)
    ids, offsets = group_faces(faces, face_alive, label, 2)
    count = np.bincount(faces.ravel(), minlength=n)
    sub = extract(verts, faces, face_alive, count, wedges, label, 0, ids[offsets[0]:offsets[1]],
                  np.full(n, -1))
    own = int((sub.label == 0).sum())
    columns, _, _, _ = collapse._decimate_kernel(
        sub.verts, sub.topo, sub.wedges, new_scratch(len(sub.vertex_ids)),
        options._replace(min_vertices=own // 2), sub.label, 0, np.zeros(2, np.int64))
    vertex_alive = alive.copy()
    write_back(sub, verts, faces, face_alive, vertex_alive, wedges)
    s, r, p, _, _, killed_offsets, killed, moved_offsets, moved = map_log(columns, sub)[:9]
    assert len(r) == own - own // 2
    # both ends of every collapse are the part's; the removed ones are dead now
    assert (label[s] == 0).all() and (label[r] == 0).all()
    assert not vertex_alive[r].any() and vertex_alive[label == 1].all()
    # the other part's faces and vertices are untouched
    other = (label[before_faces] == 1).any(axis=1)
    np.testing.assert_array_equal(faces[other], before_faces[other])
    np.testing.assert_array_equal(verts.pos[label != 0], before_pos[label != 0])
    # the log replayed on the mesh's own ids gives the written-back faces
    replay = before_faces.astype(np.int64).copy()
    dead = np.zeros(len(faces), bool)
    for i in range(len(r)):
        dead[killed[killed_offsets[i]:killed_offsets[i + 1]]] = True
        for c in moved[moved_offsets[i]:moved_offsets[i + 1]]:
            assert replay[c // 3, c % 3] == r[i]
            replay[c // 3, c % 3] = s[i]
    np.testing.assert_array_equal(dead, ~face_alive)
    np.testing.assert_array_equal(replay[face_alive], faces[face_alive])


@njit(cache=True)
def _hinted_sum(values, rows, index):
    total = 0.0
    for i in range(index.shape[0]):
        if i + 4 < index.shape[0]:
            prefetch(values, index[i + 4])
            prefetch2(rows, index[i + 4], 1)
        total += values[index[i]] + rows[index[i], 1]
    return total


def test_prefetch_hints_change_no_result():
    rng = np.random.default_rng(0)
    values, rows = rng.random(1000), rng.random((1000, 11))
    index = rng.integers(0, 1000, 5000)
    expected = values[index].sum() + rows[index, 1].sum()
    assert _hinted_sum(values, rows, index) == pytest.approx(expected, rel=1e-12)
    assert _hinted_sum(values, rows, index.astype(np.int32)) == pytest.approx(expected, rel=1e-12)
