"""Perform: one collapse on the corner lists, and its record in the log.

The removed vertex's faces on the edge die, its other faces move to the
survivor (Hoppe 1996's ecol); quadrics and wedges merge (Garland & Heckbert
1997, Hoppe 1999); the record is what the vertex split that undoes the
collapse needs (``simplify.log``).
"""

from __future__ import annotations

from numba import njit

from .quadrics import quadric_error
from .log import COLLAPSES, KILLED, MERGED, MOVED
from .state import NO_REFCOUNT
from .wedges import merge_wedges, vertex_fixed


@njit(inline="always", **NO_REFCOUNT)
def _move_corners(s, r, n_pairs, topo, wedges, pairs, log):
    """r's faces on the edge die; its other faces move to s (corners relabelled,
    wedges of the removed vertex to the survivor's partner). Logs the killed
    faces and the moved corners (``log.moved_corners`` must have room for r's
    faces)."""
    faces = topo.faces
    vhead = topo.vhead
    cnext = topo.cnext
    face_count = topo.face_count
    face_alive = topo.face_alive
    cw = wedges.corner
    moved = log.moved_corners
    killed = log.killed_faces
    nkilled = log.count[KILLED]
    nmoved = log.count[MOVED]
    c = vhead[r]
    while c >= 0:
        nxt = cnext[c]
        f = c // 3
        if face_alive[f]:
            on_edge = False
            for t in range(3):
                if faces[f, t] == s:
                    on_edge = True
            if on_edge:
                face_alive[f] = False
                killed[nkilled] = f
                nkilled += 1
                for t in range(3):
                    face_count[faces[f, t]] -= 1
            else:
                faces[f, c - 3 * f] = s
                for g in range(n_pairs):
                    if cw[c] == pairs[g, 1]:
                        cw[c] = pairs[g, 0]
                moved[nmoved] = c
                nmoved += 1
                cnext[c] = vhead[s]
                vhead[s] = c
        c = nxt
    vhead[r] = -1
    face_count[s] += face_count[r]
    face_count[r] = 0
    # Drop the dead corners from s's list now, while it is short.
    c = vhead[s]
    vhead[s] = -1
    while c >= 0:
        nxt = cnext[c]
        if face_alive[c // 3]:
            cnext[c] = vhead[s]
            vhead[s] = c
        c = nxt
    log.count[KILLED] = nkilled
    log.count[MOVED] = nmoved


@njit(inline="always", **NO_REFCOUNT)
def _move_survivor(s, r, p, verts):
    """s takes r's place in the hierarchy: position p, kind, versions."""
    pos = verts.pos
    world = verts.world
    # Placements at an endpoint copy its mesh-unit position bit for bit
    # (locked vertices must not drift by a rounding).
    if p[0] == pos[r, 0] and p[1] == pos[r, 1] and p[2] == pos[r, 2]:
        for j in range(3):
            world[s, j] = world[r, j]
    elif not (p[0] == pos[s, 0] and p[1] == pos[s, 1] and p[2] == pos[s, 2]):
        origin = verts.origin
        scale = verts.scale
        for j in range(3):
            world[s, j] = origin[j] + scale * p[j]
    pos[s, 0] = p[0]; pos[s, 1] = p[1]; pos[s, 2] = p[2]
    # CAN_COLLAPSE only lets a vertex go onto one of its kind or a stronger one
    verts.kind[s] = max(verts.kind[s], verts.kind[r])
    verts.version[s] += 1
    verts.version[r] += 1


@njit(**NO_REFCOUNT)
def perform_collapse(s, r, n_pairs, o0, o1, verts, topo, wedges, scratch, log):
    """Collapse r into s at ``scratch.p`` and append the record to ``log``
    (``log.moved_corners`` must have room for r's faces). ``scratch.pairs``
    holds the wedge pairs as (survivor's, removed's)."""
    p = scratch.p
    quadrics = verts.quadrics
    gq = scratch.gq
    _move_corners(s, r, n_pairs, topo, wedges, scratch.pairs, log)
    # the logged error is geometric: distance to the planes, not attribute terms
    for j in range(11):
        gq[j] = quadrics[s, j] + quadrics[r, j]
    geometric = max(quadric_error(gq, p[0], p[1], p[2]), 0.0)
    area = quadrics[s, 10] + quadrics[r, 10]
    for j in range(11):
        quadrics[s, j] += quadrics[r, j]
    log.count[MERGED] = merge_wedges(p, n_pairs, scratch.pairs, wedges, log.merge_value,
                                     log.merge_survivor, log.merge_removed, log.count[MERGED])
    _move_survivor(s, r, p, verts)
    topo.vertex_alive[r] = False

    nk = log.count[COLLAPSES]
    log.survivor[nk] = s
    log.removed[nk] = r
    position = log.position
    world = verts.world
    for j in range(3):
        position[nk, j] = world[s, j]
    log.cost[nk] = geometric
    log.area[nk] = area
    nk += 1
    log.count[COLLAPSES] = nk
    log.killed_offsets[nk] = log.count[KILLED]
    log.moved_offsets[nk] = log.count[MOVED]
    log.merge_offsets[nk] = log.count[MERGED]
    if wedges.quadric.shape[0] > 0:
        # s's wedges changed; an opposite vertex may have lost a wedge with its face
        vertex_fixed(s, topo, wedges)
        for o in (o0, o1):
            if o >= 0:
                vertex_fixed(o, topo, wedges)
