"""New faces turned to start at the split vertex, so a codec need not say where they start.

A face's corners can be listed from any of its three (the turn keeps the
orientation), and the input's choice is arbitrary: a split record that names
the corners of its new faces in order then pays for that choice (about
``log2 3`` bits a face). The prefix layout instead starts every face a split
``t`` creates at its corner on ``vs`` (``parent[t]``) at level ``t + 1``, or, for a
face without ``vs``, at its corner on ``t``; base faces keep the input's order.
Every per-corner array turns with its face: the face rows, the corner wedges,
and the moved corners (``3 * face + slot``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .replay import ancestor_below

__all__ = ["new_face_turns", "turned_rows", "turned_corners"]


def new_face_turns(faces, parent, face_counts, base_vertices: int) -> np.ndarray:
    """(m,) int64: how many places each face's corners move left, 0 to 2.

    ``faces`` (m, 3) full-detail vertex ids of the prefix layout, ``parent`` (n,),
    ``face_counts`` (n - n0 + 1,): as :class:`~.mesh.ProgressiveMesh` holds them.
    """
    return _turns(np.ascontiguousarray(faces, dtype=np.int64),
                  np.ascontiguousarray(parent, dtype=np.int64),
                  np.ascontiguousarray(face_counts, dtype=np.int64), int(base_vertices))


@njit(cache=True, nogil=True)
def _turns(faces, parent, face_counts, n0):
    turn = np.zeros(faces.shape[0], dtype=np.int64)
    for i in range(face_counts.shape[0] - 1):
        t = n0 + i
        s = parent[t]
        for f in range(face_counts[i], face_counts[i + 1]):
            on_s = on_t = -1
            for k in range(3):
                v = ancestor_below(parent, faces[f, k], t + 1)
                if v == s and on_s < 0:
                    on_s = k
                elif v == t and on_t < 0:
                    on_t = k
            turn[f] = on_s if on_s >= 0 else max(on_t, 0)
    return turn


def turned_rows(rows: np.ndarray, turn: np.ndarray) -> np.ndarray:
    """(m, 3) ``rows`` (faces or corner wedges), row ``f`` turned left by ``turn[f]``."""
    return _turned_rows(np.ascontiguousarray(rows), np.ascontiguousarray(turn, dtype=np.int64))


@njit(cache=True, nogil=True)
def _turned_rows(rows, turn):
    out = rows.copy()
    for f in range(rows.shape[0]):
        r = turn[f]
        if r:
            for k in range(3):
                out[f, k] = rows[f, (k + r) % 3]
    return out


def turned_corners(corners: np.ndarray, turn: np.ndarray) -> np.ndarray:
    """Corner ids ``3 * face + slot`` after :func:`turned_rows`: slot ``j`` of face
    ``f`` is now slot ``(j - turn[f]) % 3``."""
    return _turned_corners(np.ascontiguousarray(corners, dtype=np.int64),
                           np.ascontiguousarray(turn, dtype=np.int64))


@njit(cache=True, nogil=True)
def _turned_corners(corners, turn):
    out = np.empty_like(corners)
    for i in range(corners.shape[0]):
        face, slot = corners[i] // 3, corners[i] % 3
        out[i] = 3 * face + (slot - turn[face]) % 3
    return out
