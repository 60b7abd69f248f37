"""Sub-meshes: a part of the mesh being decimated, copied out dense, and back.

A greedy collapse order visits the mesh at random, so the kernel's speed is
the speed of its cache misses: a collapse is cheapest on a mesh whose rows
fit in cache, dearer on a large mesh's arrays, and dearest near the end of a
decimation, when the survivors are scattered thinly through rows sized for
the input. So a part (``simplify.parts``)
is not decimated in place: its faces, and the vertices on them, are copied
into small dense arrays (``extract``; vertices keep their relative order, so
the Morton locality of ``parts.memory_order`` carries over), the unchanged
kernel runs on the copy, and the copy's state is written back (``write_back``)
and its log mapped to the mesh's ids (``map_log``).

Which faces a part's copy holds: every live face with a vertex of the part.
Its other vertices are frozen (``parts.partition``), so every face, vertex
and wedge a collapse of the part reads or writes is in the copy, and no two
copies share one: the copies of one phase can be decimated at once, in any
order, with the same result. A frozen vertex's face count is the mesh's, not
the copy's (the rule that keeps a vertex's last face reads it).

Wedge ids are not renumbered: the wedge quadric and value arrays are shared,
and a part only writes the rows of its own vertices' wedges.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

from ..mesh import read_only
from .log import LogColumns
from .state import Vertices, new_topology
from .wedges import fill_fixed

# A part copied out: verts (``state.Vertices``), topo (``state.Topology``),
# wedges (``wedges.Wedges`` with its own marks), label (k,) int32 (0: the
# part's own vertices, parts.FROZEN: the others), vertex_ids (k,) and
# face_ids (j,) int64: the mesh's id of each copied vertex and face.
SubMesh = namedtuple("SubMesh", "verts topo wedges label vertex_ids face_ids")


@njit(cache=True, nogil=True)
def group_faces(faces, face_alive, label, parts):
    """The live faces of each part, grouped: (face ids (j,) int64, offsets
    (parts + 1,)); part ``k``'s faces are ``ids[offsets[k]:offsets[k+1]]``,
    ascending. A face belongs to the part of its vertices that are not
    frozen (a face with vertices of two parts has only frozen ones, and
    belongs to none)."""
    m = faces.shape[0]
    owner = np.full(m, -1, np.int64)
    offsets = np.zeros(parts + 1, np.int64)
    for f in range(m):
        if face_alive[f]:
            k = max(label[faces[f, 0]], label[faces[f, 1]], label[faces[f, 2]])
            if k >= 0:
                owner[f] = k
                offsets[k + 1] += 1
    for k in range(parts):
        offsets[k + 1] += offsets[k]
    fill = offsets[:-1].copy()
    ids = np.empty(offsets[parts], np.int64)
    for f in range(m):
        k = owner[f]
        if k >= 0:
            ids[fill[k]] = f
            fill[k] += 1
    return ids, offsets


@njit(cache=True, nogil=True)
def _dense_faces(faces, face_ids, seen):
    """The vertices on ``face_ids`` in ascending id order, the faces in the
    copy's order (ids of the mesh) and renumbered onto the vertices. ``seen``
    (n,) int64 must hold -1 on entry and holds it again on return (it is the
    caller's, reused between parts)."""
    k = face_ids.shape[0]
    count = 0
    for i in range(k):
        for t in range(3):
            v = faces[face_ids[i], t]
            if seen[v] < 0:
                seen[v] = 0
                count += 1
    vertex_ids = np.empty(count, np.int64)
    count = 0
    for i in range(k):
        for t in range(3):
            v = faces[face_ids[i], t]
            if seen[v] == 0:
                seen[v] = 1
                vertex_ids[count] = v
                count += 1
    vertex_ids.sort()
    for j in range(count):
        seen[vertex_ids[j]] = j
    # The faces in the order of their first vertex (a counting sort, stable),
    # so that the faces around a vertex lie together as its neighbours do:
    # the mesh's own face order need not be spatial (Loop subdivision writes
    # a face's four children a quarter of the array apart).
    start = np.zeros(count + 1, np.int64)
    for i in range(k):
        f = face_ids[i]
        start[min(seen[faces[f, 0]], seen[faces[f, 1]], seen[faces[f, 2]]) + 1] += 1
    for j in range(count):
        start[j + 1] += start[j]
    order = np.empty(k, np.int64)
    local = np.empty((k, 3), np.int64)
    for i in range(k):
        f = face_ids[i]
        a, b, c = seen[faces[f, 0]], seen[faces[f, 1]], seen[faces[f, 2]]
        at = start[min(a, b, c)]
        start[min(a, b, c)] += 1
        order[at] = f
        local[at, 0] = a
        local[at, 1] = b
        local[at, 2] = c
    for j in range(count):
        seen[vertex_ids[j]] = -1
    return vertex_ids, order, local


@njit(cache=True, nogil=True)
def _copy_corners(corner, face_ids):
    """The wedge of every corner of ``face_ids``, in the copy's corner order."""
    out = np.empty(3 * face_ids.shape[0], np.int32)
    for i in range(face_ids.shape[0]):
        for t in range(3):
            out[3 * i + t] = corner[3 * face_ids[i] + t]
    return out


@njit(cache=True, nogil=True)
def _own_counts(topo, local_label, vertex_ids, face_count):
    """Give the copy's frozen vertices the mesh's face counts."""
    for j in range(vertex_ids.shape[0]):
        if local_label[j] < 0:
            topo.face_count[j] = face_count[vertex_ids[j]]


def extract(verts, faces, face_alive, face_count, wedges, label, part, face_ids, seen):
    """Copy part ``part`` of the mesh out dense.

    Parameters
    ----------
    verts : state.Vertices
        The mesh's vertices (rows copied, never written).
    faces : (m, 3) int32, face_alive : (m,) bool, face_count : (n,) int64
        The mesh's faces as decimated so far, and every vertex's live faces.
    wedges : wedges.Wedges
        The mesh's wedges (corner ids copied; quadrics and values shared).
    label : (n,) int32
        The part of every vertex, or parts.FROZEN; None copies every live
        face, all as one part.
    part : int
        The part to copy.
    face_ids : (j,) int64
        Its faces (``group_faces``); the copy holds them in another order
        (``SubMesh.face_ids``).
    seen : (n,) int64
        Scratch holding -1 (left so).

    Returns
    -------
    SubMesh
    """
    vertex_ids, face_ids, local = _dense_faces(faces, face_ids, seen)
    k = len(vertex_ids)
    if label is None:
        local_label = np.zeros(k, np.int32)
    else:
        local_label = np.where(label[vertex_ids] == part, 0, -1).astype(np.int32)
    sub_verts = Vertices(verts.pos[vertex_ids], verts.world[vertex_ids],
                         verts.quadrics[vertex_ids], verts.kind[vertex_ids],
                         np.zeros(k, np.int64), verts.origin, verts.scale)
    has_wedges = wedges.quadric.shape[0] > 0
    sub_wedges = wedges._replace(
        corner=_copy_corners(wedges.corner, face_ids) if has_wedges else wedges.corner,
        fixed=np.zeros((k if has_wedges else 0, 11)), mark=np.zeros_like(wedges.mark),
        stamp=np.zeros(1, np.int64), merged=np.empty_like(wedges.merged))
    # read-only, as the whole-mesh kernel's input faces are: one compiled signature
    topo = new_topology(read_only(local), k)
    fill_fixed(topo, sub_wedges)
    if label is not None:
        _own_counts(topo, local_label, vertex_ids, face_count)
    return SubMesh(sub_verts, topo, sub_wedges, local_label, vertex_ids, face_ids)


@njit(cache=True, nogil=True)
def _write_faces(faces, face_alive, corner, sub_faces, sub_alive, sub_corner, vertex_ids,
                 face_ids, has_wedges):
    for i in range(face_ids.shape[0]):
        f = face_ids[i]
        face_alive[f] = sub_alive[i]
        for t in range(3):
            faces[f, t] = vertex_ids[sub_faces[i, t]]
            if has_wedges:
                corner[3 * f + t] = sub_corner[3 * i + t]


def write_back(sub: SubMesh, verts, faces, face_alive, vertex_alive, wedges):
    """Copy the decimated part back into the mesh's arrays: its own vertices'
    rows (position, quadric, kind, alive) and its faces (corners, alive,
    wedges). Touches no row another part's copy holds."""
    own = sub.vertex_ids[sub.label == 0]
    rows = np.flatnonzero(sub.label == 0)
    for name in ("pos", "world", "quadrics", "kind"):
        getattr(verts, name)[own] = getattr(sub.verts, name)[rows]
    vertex_alive[own] = sub.topo.vertex_alive[rows]
    _write_faces(faces, face_alive, wedges.corner, sub.topo.faces, sub.topo.face_alive,
                 sub.wedges.corner, sub.vertex_ids, sub.face_ids, wedges.quadric.shape[0] > 0)


def map_log(columns: LogColumns, sub: SubMesh) -> LogColumns:
    """The kernel's log of a copy (``simplify.log.filled``) with the copy's
    vertex, face and corner ids replaced by the mesh's (wedge ids are the
    mesh's already), every column an array of its own."""
    vertex_ids, face_ids = sub.vertex_ids, sub.face_ids
    moved = 3 * face_ids[columns.moved_corners // 3] + columns.moved_corners % 3
    mapped = columns._replace(survivor=vertex_ids[columns.survivor],
                              removed=vertex_ids[columns.removed],
                              killed_faces=face_ids[columns.killed_faces],
                              moved_corners=moved)
    # The kernel's columns are views of arrays sized for every vertex of the
    # part to go; the phases' logs wait for the merge, so each keeps only its
    # filled rows and the kernel's arrays are freed now.
    return LogColumns(*(column.copy() if column.base is not None else column
                        for column in mapped))
