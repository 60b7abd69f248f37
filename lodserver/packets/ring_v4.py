"""Version 4's ring prediction of the split edge (flag ``RING_POSITIONS``).

docs/packets.md, "Version 4", "Positions from the ring". After a split's faces
are in place (its step 6) and before its positions are read, the decoder knows
every position around the split but the two it is about to read: ``vs``'s fine
position and the new vertex's. The rings of the two, each without the other,
lean apart along the split edge, so a fraction of the difference of their
centroids predicts the edge ``E`` (the new vertex less vs's fine position):

    P = floor((St / nt - Ss / ns) * 0.625 + 0.5)     per axis, float64

with ``Ss``, ``ns`` the sum of the grid positions and the number of the
vertices of vs's ring, ``St``, ``nt`` those of the new vertex's, in the state
after the split's faces, before its positions. A vertex's ring counts, for
every corner it holds, the vertices of the face's two other corners, but the
vertex itself and the split's other vertex: every neighbour inside a closed
surface twice, with no set to keep. ``P = 0`` when either ring is empty. Every
term is an exact float64 integer and each of the two divisions, the
subtraction, the product by 0.625 (``format.RING_SCALE``) and the sum are single
IEEE operations, so every decoder gets the same ``P``. The packet then codes
``E - P`` in place of ``E``.

The prediction is a function of the level alone (the state of a level is the
same whichever way a client reached it), so the encoder computes it for a
range of splits in one pass over their records (:func:`ring_predictions`); the
reference decoder computes it per split from its state
(``reference.ring_prediction``, the rule written to be read).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numba import njit

from .corners import add_corner, corner_lists, remove_corner
from .encode import index_dtype
from .format import RING_SCALE
from .grids import Grid

if TYPE_CHECKING:
    from ..progressive.mesh import ProgressiveMesh


def ring_predictions(pm: ProgressiveMesh, start: int, stop: int, grid: Grid) -> np.ndarray:
    """(stop - start, 3) int64: the predicted split edge ``P`` of splits ``start ..
    stop-1`` (vertex counts, ``start < stop``) on ``grid``."""
    n0 = pm.base_vertices
    positions, faces = pm.arrays_at(start)
    face_capacity = pm.faces_at_level(stop)
    work_positions = np.zeros((stop, 3), dtype=np.int64)
    work_positions[:start] = grid.quantize(positions)
    work_faces = np.zeros(3 * face_capacity, dtype=index_dtype(3 * face_capacity, stop))
    work_faces[:faces.size] = faces.ravel()
    a, b = start - n0, stop - n0
    return _ring_predictions(work_positions, work_faces, len(faces), start, stop, n0, pm.parent,
                             pm.face_counts, pm.birth_faces, pm.moved_offsets, pm.moved_corners,
                             grid.quantize(pm.fine_position[a:b]),
                             grid.quantize(pm.new_position[a:b]))


@njit(cache=True, nogil=True)
def predicted_edge(ss, ns, st, nt, out):
    """``out`` (3,) = ``P`` from the ring sums ``ss``, ``st`` (3,) and counts."""
    for a in range(3):
        if ns == 0 or nt == 0:
            out[a] = 0
        else:
            out[a] = np.int64(math.floor((st[a] / nt - ss[a] / ns) * RING_SCALE + 0.5))


@njit(cache=True, nogil=True)
def _ring_sum(state, pool, v, other, total):
    """Sum into ``total`` (3,) the positions of the two other corners' vertices of
    every corner of ``v``, but ``v`` and ``other``; returns how many were summed."""
    faces, positions = state.faces, state.positions
    first, d = state.blocks[v, 0], state.blocks[v, 1]
    total[:] = 0
    n = 0
    for i in range(d):
        c = pool[first + i]
        f3 = c - c % 3
        for step in (1, 2):
            u = faces[f3 + (c - f3 + step) % 3]
            if u != v and u != other:
                for a in range(3):
                    total[a] += positions[u, a]
                n += 1
    return n


@njit(cache=True, nogil=True)
def _ring_predictions(positions, faces, face_count, start, stop, base, parent, face_counts,
                      birth_faces, moved_offsets, moved_corners, fine, new):
    state, pool = corner_lists(positions, faces, face_count)
    out = np.zeros((stop - start, 3), dtype=np.int64)
    ss = np.zeros(3, dtype=np.int64)
    st = np.zeros(3, dtype=np.int64)
    for t in range(start, stop):
        j, i = t - base, t - start
        s = parent[t]
        for x in range(moved_offsets[j], moved_offsets[j + 1]):
            c = moved_corners[x]
            remove_corner(state, pool, faces[c], c)
            faces[c] = t
            pool = add_corner(state, pool, t, c)
        for f in range(face_counts[j], face_counts[j + 1]):
            for k in range(3):
                c = 3 * face_count + k
                faces[c] = birth_faces[f, k]
                pool = add_corner(state, pool, faces[c], c)
            face_count += 1
        ns = _ring_sum(state, pool, s, t, ss)
        nt = _ring_sum(state, pool, t, s, st)
        predicted_edge(ss.astype(np.float64), ns, st.astype(np.float64), nt, out[i])
        for a in range(3):
            positions[s, a] = fine[i, a]
            positions[t, a] = new[i, a]
    return out

