"""Rank: the cost and placement of a candidate collapse, and the queue's
ranking steps (``simplify.collapse``'s pass loop calls them).

- ``rank_collapse``: Garland & Heckbert's summed quadric ``Q_a + Q_b`` (plus
  Hoppe 1999's wedge terms, ``simplify.wedges``) at its minimiser;
  ``rank_geometry`` the same for a mesh without attributes, in a leaner call;
- ``place_on_volume_plane``: the placement moved onto the plane that keeps
  the enclosed volume (Lindstrom & Turk 1998);
- ``rank_all``: every edge of a part (and the close pairs) into the queue,
  at the start of a pass;
- ``rerank_around``: the edges at a survivor, after its collapse.

The kernel's state is in ``simplify.state``, the queue in ``simplify.queue``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .pairs import close_pairs
from .quadrics import constrain_to_plane, optimal_position_xyz, quadric_error
from .queue import (
    CAPACITY,
    RESERVOIR,
    pair_key,
    push_reservoir,
    queue_append,
    with_room,
)
from .rules import LEGAL, REJECT_LOCKED, REJECT_SEAM, can_collapse, keeps_position
from .state import NO_REFCOUNT
from .wedges import add_wedge_terms

# A collapse where both endpoints keep a wedge the other has no partner for
# (two seams meeting) must drag one of them; its cost is multiplied by this, so
# such collapses wait until the alternatives cost as much (refusing them
# outright smears less texture at fine levels but ruins coarse ones).
SEAM_PENALTY = 4.0


@njit(inline="always", **NO_REFCOUNT)
def _survivor(a, b, kind):
    """The endpoint the other may vanish into (CAN_COLLAPSE): a border vertex
    outlives an interior one, a locked one anything; a when both ways are
    open; -1 when neither way is."""
    if can_collapse(kind[b], kind[a]):
        return a
    if can_collapse(kind[a], kind[b]):
        return b
    return -1


@njit(inline="always", **NO_REFCOUNT)
def _place(a, b, s, pos, kind, q, p):
    """The placement of the collapse of (a, b) into ``s`` for the summed
    quadric ``q`` (into ``p``): the minimiser, or ``s`` itself when it is
    locked. Returns its cost."""
    if keeps_position(kind[s]):
        p[0] = pos[s, 0]; p[1] = pos[s, 1]; p[2] = pos[s, 2]
        return quadric_error(q, p[0], p[1], p[2])
    return optimal_position_xyz(q, pos[a, 0], pos[a, 1], pos[a, 2], pos[b, 0], pos[b, 1],
                                pos[b, 2], p)


@njit(**NO_REFCOUNT)
def rank_geometry(a, b, pos, quadrics, kind, q, p):
    """``rank_collapse``'s cost of collapsing (a, b) for a mesh without
    attributes, taking only the arrays it reads: a call that passes the
    ``Topology`` and ``Wedges`` namedtuples copies every field of their
    arrays on every call, work this step never needs. Writes ``q`` and ``p``
    as ``rank_collapse`` does. Returns (cost, survivor): inf and
    -1 when the collapse is never legal (both ends locked)."""
    s = _survivor(a, b, kind)
    if s < 0:
        return np.inf, s
    for j in range(11):
        q[j] = quadrics[a, j] + quadrics[b, j]
    return max(_place(a, b, s, pos, kind, q, p), 0.0), s


@njit(**NO_REFCOUNT)
def rank_collapse(a, b, pos, quadrics, kind, q, p, pairs, topo, wedges):
    """Cost of collapsing (a, b): G&H's summed quadric ``Q_a + Q_b`` (plus
    Hoppe's wedge terms), at its minimiser, or at the survivor when that is
    locked. ``pos``, ``quadrics``, ``kind`` are the ``Vertices`` columns;
    writes the summed quadric into ``q`` (11,), the placement into ``p``
    (3,) and the wedge pairs into ``pairs`` (2, 2).

    The hottest step (about ten calls a collapse) takes its arrays one by
    one, because reading them out of the namedtuples here would repeat that
    read on every call. ``topo`` and ``wedges`` are only read for a mesh
    with attributes. Compiled without reference counting
    (``state.NO_REFCOUNT``): with it, taking the two namedtuples as
    arguments would count a reference to each of their arrays on every
    call, most of the step's own work.

    Returns (cost, survivor, wedge pair count, seams meet, reason): cost is
    inf, with the reason, when the collapse is never legal.
    """
    s = _survivor(a, b, kind)
    if s < 0:
        return np.inf, a, 0, False, REJECT_LOCKED
    for j in range(11):
        q[j] = quadrics[a, j] + quadrics[b, j]
    n_pairs = 0
    seams_meet = False
    if wedges.quadric.shape[0] > 0:
        legal, n_pairs, seams_meet = add_wedge_terms(a, b, q, topo, wedges, pairs)
        if not legal:
            return np.inf, a, 0, False, REJECT_SEAM
    cost = _place(a, b, s, pos, kind, q, p)
    if seams_meet:
        cost *= SEAM_PENALTY
    return max(cost, 0.0), s, n_pairs, seams_meet, LEGAL


@njit(inline="always", **NO_REFCOUNT)
def _volume_plane(a, b, pos, faces, vhead, cnext, face_alive, out):
    """The plane ``N . p = h`` on which collapsing (a, b) to ``p`` keeps the
    enclosed volume (signed tetrahedra against ``a``'s position, so a's own
    faces add nothing before the move). Writes (Nx, Ny, Nz, h) into ``out``."""
    ox = pos[a, 0]; oy = pos[a, 1]; oz = pos[a, 2]
    nx = 0.0; ny = 0.0; nz = 0.0; h = 0.0
    for v, other in ((a, b), (b, a)):
        c = vhead[v]
        while c >= 0:
            f = c // 3
            if face_alive[f]:
                slot = c - 3 * f
                x = faces[f, (slot + 1) % 3]
                y = faces[f, (slot + 2) % 3]
                if x != other and y != other:
                    xx = pos[x, 0] - ox; xy = pos[x, 1] - oy; xz = pos[x, 2] - oz
                    yx = pos[y, 0] - ox; yy = pos[y, 1] - oy; yz = pos[y, 2] - oz
                    cx = xy * yz - xz * yy
                    cy = xz * yx - xx * yz
                    cz = xx * yy - xy * yx
                    nx += cx; ny += cy; nz += cz
                    if v == b:
                        h += (pos[b, 0] - ox) * cx + (pos[b, 1] - oy) * cy + (pos[b, 2] - oz) * cz
            c = cnext[c]
    out[0] = nx; out[1] = ny; out[2] = nz
    out[3] = h + nx * ox + ny * oy + nz * oz


@njit(**NO_REFCOUNT)
def place_on_volume_plane(a, b, seams_meet, pos, faces, vhead, cnext, face_alive, q, p, plane):
    """Move the placement ``p`` (3,) of the ranked (a, b), whose summed
    quadric is ``q`` (11,), onto its volume plane (Lindstrom & Turk 1998;
    Hoppe 1999 section 4) along the quadric's metric; ``plane`` (4,) is
    scratch. Takes the arrays of ``Vertices``, ``Topology`` and ``Scratch``
    it reads one by one, as ``rank_geometry`` does. Returns the new cost, or
    -1.0 when there is no such plane (``p`` is then left alone)."""
    _volume_plane(a, b, pos, faces, vhead, cnext, face_alive, plane)
    if not constrain_to_plane(q, plane[0], plane[1], plane[2], plane[3], p):
        return -1.0
    cost = max(quadric_error(q, p[0], p[1], p[2]), 0.0)
    if seams_meet:
        cost *= SEAM_PENALTY
    return cost


@njit(cache=True, nogil=True)
def rank_all(verts, topo, wedges, scratch, queue, stamp, pair_radius, label, me):
    """Rank every live edge of part ``me`` once (both ends labelled ``me`` in
    ``label``, see ``simplify.parts``), and every close pair, into the
    reservoir. Returns (queue, stamp): the queue's arrays may have grown."""
    faces, vhead, cnext, face_alive = topo.faces, topo.vhead, topo.cnext, topo.face_alive
    vertex_alive, face_count = topo.vertex_alive, topo.face_count
    pos, quadrics, kind, version = verts.pos, verts.quadrics, verts.kind, verts.version
    q, p, wedge_pairs, mark = scratch.q, scratch.p, scratch.pairs, scratch.mark
    rk, rab, rvs, size = queue.key, queue.pair, queue.version, queue.size
    # The reservoir's fill and capacity are kept in locals: as array cells,
    # they would be loaded and stored on every edge, a large share of this
    # step's work. Nothing in the reservoir is stale during a ranking, so
    # when it is full it doubles, as ``reservoir_append`` would do.
    rsize, capacity = size[RESERVOIR], size[CAPACITY]
    has_wedges = wedges.quadric.shape[0] > 0
    for a in range(pos.shape[0]):
        if not vertex_alive[a] or label[a] != me:
            continue
        stamp += 1
        if capacity + 2 * face_count[a] > rk.shape[0]:
            size[RESERVOIR], size[CAPACITY] = rsize, capacity
            queue = with_room(queue, np.int64(0), 2 * face_count[a])
            rk, rab, rvs = queue.key, queue.pair, queue.version
        c = vhead[a]
        while c >= 0:
            f = c // 3
            if face_alive[f]:
                slot = c - 3 * f
                for t in range(1, 3):
                    b = np.int64(faces[f, (slot + t) % 3])    # one signature for rank_collapse
                    if b > a and label[b] == me and mark[b] != stamp:
                        mark[b] = stamp
                        if has_wedges:
                            cost = rank_collapse(a, b, pos, quadrics, kind, q, p, wedge_pairs,
                                                 topo, wedges)[0]
                        else:
                            cost = rank_geometry(a, b, pos, quadrics, kind, q, p)[0]
                        if cost < np.inf:
                            if rsize == capacity:
                                capacity = max(rsize + 1, 2 * capacity)
                            rk[rsize] = cost
                            rab[rsize] = pair_key(a, b)
                            rvs[rsize] = version[a] + version[b]
                            rsize += 1
            c = cnext[c]
    size[RESERVOIR], size[CAPACITY] = rsize, capacity
    if pair_radius > 0.0:
        pairs, stamp = close_pairs(pos, topo, pair_radius, mark, stamp)
        queue = with_room(queue, np.int64(0), np.int64(pairs.shape[0]))
        for i in range(pairs.shape[0]):
            a = pairs[i, 0]
            b = pairs[i, 1]
            cost = rank_collapse(a, b, pos, quadrics, kind, q, p, wedge_pairs, topo, wedges)[0]
            if cost < np.inf:
                push_reservoir(queue, cost, pair_key(a, b), version[a] + version[b], version,
                               vertex_alive)
    return queue, stamp


@njit(**NO_REFCOUNT)
def rerank_around(s, verts, topo, wedges, scratch, queue, stamp, label, me):
    """Queue every edge of part ``me`` at s anew: its quadric and position
    changed (the queue must have room for two entries per face of s)."""
    faces, cnext, vertex_alive = topo.faces, topo.cnext, topo.vertex_alive
    pos, quadrics, kind, version = verts.pos, verts.quadrics, verts.kind, verts.version
    q, p, pairs, mark = scratch.q, scratch.p, scratch.pairs, scratch.mark
    hk, hab, hvs = queue.heap_key, queue.heap_pair, queue.heap_version
    rk, rab, rvs, size, tau = queue.key, queue.pair, queue.version, queue.size, queue.tau
    has_wedges = wedges.quadric.shape[0] > 0
    c = topo.vhead[s]
    while c >= 0:
        f = c // 3
        slot = c - 3 * f
        for t in range(1, 3):
            w = np.int64(faces[f, (slot + t) % 3])
            if mark[w] != stamp and label[w] == me:
                mark[w] = stamp
                if has_wedges:
                    cost = rank_collapse(s, w, pos, quadrics, kind, q, p, pairs, topo, wedges)[0]
                else:
                    cost = rank_geometry(s, w, pos, quadrics, kind, q, p)[0]
                if cost < np.inf:
                    e_ab = pair_key(s, w) if s < w else pair_key(w, s)
                    queue_append(hk, hab, hvs, rk, rab, rvs, size, tau, cost, e_ab,
                                 version[s] + version[w], version, vertex_alive)
        c = cnext[c]
