"""Connectivity facts of a triangle mesh, from its face array alone.

- vertex -> faces adjacency as CSR (``offsets`` (n+1,), ``faces`` (3m,)),
- boundary edges (used by one face) in their face's winding,
- non-manifold edges (used by more than two faces),
- fans: the number of edge-connected triangle fans around each vertex
  (1 for a manifold vertex, 2 or more for a bow tie).

Computed per vertex from its faces with compiled loops: sorting the 3m edges
of a million-face mesh with ``np.unique`` costs about ten times more here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from ..mesh import read_only


@njit(cache=True, nogil=True)
def link_corners(faces, head, nxt, face_count):
    """Thread every corner ``c = 3 f + k`` onto its vertex's list, in corner order:
    ``head[v] -> c -> nxt[c] -> ... -> -1``, and count each vertex's faces into
    ``face_count``. ``head`` (n,) and ``nxt`` (3m,) come filled with -1 and
    ``face_count`` with 0, in the caller's integer type. The decimation kernels
    edit these lists in place as faces move and die."""
    m = faces.shape[0]
    for c in range(3 * m - 1, -1, -1):
        v = faces[c // 3, c % 3]
        nxt[c] = head[v]
        head[v] = c
        face_count[v] += 1


@njit(cache=True, nogil=True)
def _vertex_faces(faces, n):
    """CSR of the faces around each vertex, in ascending face order (counting sort)."""
    offsets = np.zeros(n + 1, np.int64)
    m = faces.shape[0]
    for f in range(m):
        for k in range(3):
            offsets[faces[f, k] + 1] += 1
    for v in range(n):
        offsets[v + 1] += offsets[v]
    fill = offsets[:-1].copy()
    out = np.empty(3 * m, np.int64)
    for f in range(m):
        for k in range(3):
            v = faces[f, k]
            out[fill[v]] = f
            fill[v] += 1
    return offsets, out


@njit(cache=True, nogil=True)
def _census(faces, offsets, vfaces, n):
    """Per-vertex fan counts and flags, and the directed boundary edges.

    Returns (fans (n,), on_boundary (n,) bool, on_nonmanifold_edge (n,) bool,
    boundary (k, 2), boundary_face (k,)).
    """
    fans = np.zeros(n, np.int64)
    on_boundary = np.zeros(n, np.bool_)
    on_nonmanifold = np.zeros(n, np.bool_)
    count = np.zeros(n, np.int64)       # faces at v that contain neighbour w
    local = np.full(n, -1, np.int64)    # neighbour w -> slot in the union-find
    parent = np.empty(n, np.int64)
    bnd = np.empty((16, 2), np.int64)
    bnd_face = np.empty(16, np.int64)
    nb = 0
    for v in range(n):
        start, end = offsets[v], offsets[v + 1]
        used = 0
        for i in range(start, end):
            f = vfaces[i]
            for k in range(3):
                w = faces[f, k]
                if w != v:
                    count[w] += 1
                    if local[w] < 0:
                        local[w] = used
                        parent[used] = used
                        used += 1
        # Faces at v sharing an edge (v, w) share the link vertex w, so the
        # connected components of the link graph are v's fans.
        components = used
        for i in range(start, end):
            f = vfaces[i]
            x = -1
            y = -1
            for k in range(3):
                w = faces[f, k]
                if w != v:
                    if x < 0:
                        x = local[w]
                    else:
                        y = local[w]
            while parent[x] != x:
                x = parent[x]
            while parent[y] != y:
                y = parent[y]
            if x != y:
                parent[x] = y
                components -= 1
        fans[v] = components
        for i in range(start, end):
            f = vfaces[i]
            for k in range(3):
                w = faces[f, k]
                if w == v:
                    continue
                c = count[w]
                if c == 1:
                    on_boundary[v] = True
                    # record each boundary edge once, from the face where v comes first
                    if faces[f, (k + 2) % 3] == v:
                        if nb == bnd.shape[0]:
                            grown = np.empty((2 * nb, 2), np.int64)
                            grown[:nb] = bnd
                            bnd = grown
                            grown_face = np.empty(2 * nb, np.int64)
                            grown_face[:nb] = bnd_face
                            bnd_face = grown_face
                        bnd[nb, 0] = v
                        bnd[nb, 1] = w
                        bnd_face[nb] = f
                        nb += 1
                elif c > 2:
                    on_nonmanifold[v] = True
        for i in range(start, end):
            f = vfaces[i]
            for k in range(3):
                count[faces[f, k]] = 0
                local[faces[f, k]] = -1
    return fans, on_boundary, on_nonmanifold, bnd[:nb].copy(), bnd_face[:nb].copy()


@dataclass(frozen=True)
class Census:
    """What ``census`` finds; arrays indexed by vertex unless said otherwise.

    fans : (n,) int64             edge-connected fans around each vertex (0 if unused)
    on_boundary : (n,) bool       vertex has an edge used by one face
    on_nonmanifold_edge : (n,) bool  vertex has an edge used by three or more faces
    boundary_edges : (k, 2) int64 boundary edges, oriented as in their face
    boundary_faces : (k,) int64   the face of each boundary edge
    """

    fans: np.ndarray
    on_boundary: np.ndarray
    on_nonmanifold_edge: np.ndarray
    boundary_edges: np.ndarray
    boundary_faces: np.ndarray


def vertex_faces(faces, n):
    """Faces around each vertex as CSR: ``faces_csr[offsets[v]:offsets[v+1]]``.

    Returns (offsets (n+1,) int64, faces_csr (3m,) int64).
    """
    return _vertex_faces(read_only(faces, np.int64), int(n))


def census(faces, n) -> Census:
    """Boundary, non-manifold edges and fans of the mesh with ``faces`` (m, 3) over ``n`` vertices."""
    faces = read_only(faces, np.int64)
    offsets, vfaces = _vertex_faces(faces, int(n))
    return Census(*_census(faces, offsets, vfaces, int(n)))
