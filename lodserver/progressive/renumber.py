"""Compiled steps of turning a collapse log into the prefix layout, and of
deriving the split records from it: each is one pass over flat arrays.

``mesh.from_collapse_log`` and ``ProgressiveMesh`` call these instead of
numpy fancy indexing, argsort and temporaries, which would make several
passes and allocate as much again on a large mesh. Every function returns
exactly what that numpy formulation would.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ..mesh import read_only


@njit(cache=True, nogil=True)
def reverse_blocks(values, offsets):
    """Concatenate the blocks ``values[offsets[i]:offsets[i+1]]`` last block
    first, each block keeping its inner order (collapse order -> split order).

    values : (c, ...) any dtype; offsets : (k + 1,) int64, non-decreasing,
    ``offsets[0] == 0`` and ``offsets[k] == len(values)``. Returns (c, ...).
    """
    out = np.empty_like(values)
    k = offsets.shape[0] - 1
    j = 0
    for i in range(k - 1, -1, -1):
        for x in range(offsets[i], offsets[i + 1]):
            out[j] = values[x]
            j += 1
    return out


@njit(cache=True, nogil=True)
def reversed_corners(corners, offsets, new_face):
    """``reverse_blocks(corners, offsets)`` with each corner ``3 * face + slot``
    renumbered to ``3 * new_face[face] + slot``: (c,) int64."""
    out = np.empty_like(corners)
    k = offsets.shape[0] - 1
    j = 0
    for i in range(k - 1, -1, -1):
        for x in range(offsets[i], offsets[i + 1]):
            c = corners[x]
            out[j] = 3 * new_face[c // 3] + c % 3
            j += 1
    return out


def renumbered_faces(faces, face_order, new_id):
    """(m, 3) int64: row ``i`` is ``new_id[faces[face_order[i]]]``, for
    (m, 3) ``faces`` and (m,) ``face_order``, (n,) ``new_id``, all int64."""
    return _renumbered_faces(read_only(faces, np.int64), read_only(face_order, np.int64),
                             read_only(new_id, np.int64))


@njit(cache=True, nogil=True)
def _renumbered_faces(faces, face_order, new_id):
    """``renumbered_faces``'s compiled pass."""
    out = np.empty((face_order.shape[0], 3), dtype=np.int64)
    for i in range(face_order.shape[0]):
        f = face_order[i]
        for k in range(3):
            out[i, k] = new_id[faces[f, k]]
    return out


@njit(cache=True, nogil=True)
def split_face_order(killed_faces, killed_offsets, m):
    """The prefix layout's face order: (m,) int64 input face ids, faces never
    killed first (in input order), then the faces each split brings back
    (``reverse_blocks`` of the killed faces); and ``new_face``, its inverse."""
    alive = np.ones(m, dtype=np.bool_)
    for x in range(killed_faces.shape[0]):
        alive[killed_faces[x]] = False
    order = np.empty(m, dtype=np.int64)
    j = 0
    for f in range(m):
        if alive[f]:
            order[j] = f
            j += 1
    k = killed_offsets.shape[0] - 1
    for i in range(k - 1, -1, -1):
        for x in range(killed_offsets[i], killed_offsets[i + 1]):
            order[j] = killed_faces[x]
            j += 1
    new_face = np.empty(m, dtype=np.int64)
    for i in range(m):
        new_face[order[i]] = i
    return order, new_face


def hierarchy(parent, n0, full, coarse):
    """``_hierarchy`` on read-only views of its inputs (one compiled signature
    for a mesh just built and one loaded from its artefact)."""
    return _hierarchy(read_only(parent, np.int64), int(n0), read_only(full),
                      read_only(coarse))


@njit(cache=True, nogil=True)
def _hierarchy(parent, n0, full, coarse):
    """The values a split writes going forward, from the vertex (or wedge)
    hierarchy, in one pass from the last split down.

    Parameters
    ----------
    parent : (n,) int64, -1 for the first ``n0``; ``parent[t] < t``
    full : (n, d) float64, values at full detail
    coarse : (n - n0, d) float64, the parent's value after collapsing ``t``

    Returns
    -------
    fine : (n - n0, d)
        The parent's value just after split ``t``: the value left by its next
        collapse above ``t`` (its next child), else its full-detail value.
    new : (n - n0, d)
        ``t``'s own value at level ``t + 1``: left by its first child, else
        its full-detail value.
    """
    n, d = parent.shape[0], full.shape[1]
    fine = np.empty((n - n0, d), dtype=full.dtype)
    new = np.empty((n - n0, d), dtype=full.dtype)
    # going down, earliest[x] is the smallest child of x seen so far: for split
    # t it is t's next sibling, and once every child of t is seen, t's first
    earliest = np.full(n, -1, dtype=np.int64)
    for t in range(n - 1, n0 - 1, -1):
        first = earliest[t]   # all of t's children (> t) are already seen
        for j in range(d):
            new[t - n0, j] = coarse[first - n0, j] if first >= 0 else full[t, j]
        s = parent[t]
        sibling = earliest[s]
        for j in range(d):
            fine[t - n0, j] = coarse[sibling - n0, j] if sibling >= 0 else full[s, j]
        earliest[s] = t
    return fine, new
