"""Check: the legality rules of one collapse, each refusal a named reason.

The rules (``simplify.rules``) keep every collapse undoable by one vertex
split (Hoppe 1996) and topology-preserving (Dey et al. 1999), and refuse
fold-overs (Garland & Heckbert 1997, section 3.3). ``check_legality`` tests
them in order of cost and returns the first that refuses.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .rules import (DEGENERATE_AREA, LEGAL, REJECT_DEGENERATE, REJECT_FLIP, REJECT_LAST_FACE,
                    REJECT_LINK, REJECT_NON_MANIFOLD_EDGE, REJECT_NOT_AN_EDGE,
                    REJECT_PAIR_SHARES_NEIGHBOURS, REJECT_PAIR_TOO_FAR, REJECT_PINCH,
                    REJECT_TETRAHEDRON, on_border)
from .quadrics import cross, edge_vectors
from .prefetch import prefetch, prefetch2
from .state import NO_REFCOUNT


@njit(cache=True, nogil=True, inline="always")
def _face_turn(v, x, y, p, pos, flip_cos):
    """Moving corner ``v`` of face (v, x, y) to ``p``: REJECT_DEGENERATE if
    the face is left without area, REJECT_FLIP if its normal turns by more
    than arccos(flip_cos), else LEGAL.

    G&H 1997 section 3.3 refuses fold-overs (normal turned past 90 degrees);
    the stricter angle also keeps the slivers that precede a fold."""
    # normals (v - y) x (x - y) before and after: the edge (x, y) stays put
    ex, ey, ez, ux, uy, uz = edge_vectors(pos, y, x, v)
    ax, ay, az = cross(ux, uy, uz, ex, ey, ez)
    bx, by, bz = cross(p[0] - pos[y, 0], p[1] - pos[y, 1], p[2] - pos[y, 2], ex, ey, ez)
    lb = bx * bx + by * by + bz * bz
    if lb <= DEGENERATE_AREA:
        return REJECT_DEGENERATE
    la = ax * ax + ay * ay + az * az
    if la <= DEGENERATE_AREA:
        return LEGAL    # already degenerate: no orientation to keep
    if ax * bx + ay * by + az * bz <= flip_cos * np.sqrt(la * lb):
        return REJECT_FLIP
    return LEGAL


@njit(inline="always", **NO_REFCOUNT)
def _warm_neighbour(x, verts):
    """Start loading what re-ranking the edge to neighbour ``x`` will read
    (its quadric's two cache lines and its version; ``simplify.prefetch``):
    the scans are the first to meet the collapse's neighbours, and the
    re-rank after the collapse reads them all. Each ring vertex is the ``x``
    of one face of the ring, so every neighbour is met once."""
    prefetch(verts.quadrics, x)
    prefetch2(verts.quadrics, x, 8)
    prefetch(verts.version, x)


@njit(inline="always", **NO_REFCOUNT)
def _scan_survivor(s, r, p, flip_cos, verts, topo, scratch, stamp):
    """Walk s's faces: mark its neighbours with ``stamp``, find the faces on
    the edge (s, r) and the vertex opposite it in each (into
    ``scratch.opposite``), and test s's other faces for turns.
    Returns (faces on the edge, turn reason of the first face that fails or LEGAL)."""
    # namedtuple fields are read once, outside the loops: each read of a field
    # is a reference count taken and dropped
    faces, cnext, face_alive = topo.faces, topo.cnext, topo.face_alive
    pos = verts.pos
    mark = scratch.mark
    opposite = scratch.opposite
    n_shared = 0
    turned = LEGAL
    c = topo.vhead[s]
    while c >= 0:
        f = c // 3
        if face_alive[f]:
            slot = c - 3 * f
            x = faces[f, (slot + 1) % 3]
            y = faces[f, (slot + 2) % 3]
            _warm_neighbour(x, verts)
            mark[x] = stamp
            mark[y] = stamp
            if x == r or y == r:
                if n_shared < 2:
                    opposite[n_shared] = y if x == r else x
                n_shared += 1
            elif turned == LEGAL:
                turned = _face_turn(s, x, y, p, pos, flip_cos)
        c = cnext[c]
    return n_shared, turned


@njit(inline="always", **NO_REFCOUNT)
def _scan_removed(s, r, p, o0, o1, flip_cos, turned, verts, topo, scratch, stamp):
    """Walk r's faces: count the common neighbours of s and r (marked by
    ``_scan_survivor``), look for a face (r, o0, o1) on the opposite vertices,
    test r's faces that move for turns (if none failed yet).
    Returns (common neighbours, r has a face on o0 and o1, turn reason)."""
    faces, cnext, face_alive = topo.faces, topo.cnext, topo.face_alive
    pos = verts.pos
    mark = scratch.mark
    mark2 = scratch.mark2
    common = 0
    on_opposite = False
    c = topo.vhead[r]
    while c >= 0:
        f = c // 3
        if face_alive[f]:
            slot = c - 3 * f
            x = faces[f, (slot + 1) % 3]
            y = faces[f, (slot + 2) % 3]
            _warm_neighbour(x, verts)
            if x != s and y != s:
                if (x == o0 and y == o1) or (x == o1 and y == o0):
                    on_opposite = True
                if turned == LEGAL:
                    turned = _face_turn(r, x, y, p, pos, flip_cos)
            for w in (x, y):
                if w != s and mark[w] == stamp and mark2[w] != stamp:
                    mark2[w] = stamp
                    common += 1
        c = cnext[c]
    return common, on_opposite, turned


@njit(inline="always", **NO_REFCOUNT)
def _has_face_on(v, o0, o1, topo):
    """True if a live face of v has the other two corners o0 and o1."""
    faces, cnext, face_alive = topo.faces, topo.cnext, topo.face_alive
    c = topo.vhead[v]
    while c >= 0:
        f = c // 3
        if face_alive[f]:
            slot = c - 3 * f
            x = faces[f, (slot + 1) % 3]
            y = faces[f, (slot + 2) % 3]
            if (x == o0 and y == o1) or (x == o1 and y == o0):
                return True
        c = cnext[c]
    return False


@njit(**NO_REFCOUNT)
def check_legality(s, r, p, options, verts, topo, scratch, stamp):
    """Every rule a collapse of r into s, placed at ``p``, must pass, in the
    order they are tested. ``stamp`` must be fresh for ``scratch.mark``.

    Returns (reason, o0, o1): LEGAL or the first REJECT_* that refuses, and
    the vertices opposite the edge (-1 where there is none).
    """
    kind = verts.kind
    pos = verts.pos
    n_shared, turned = _scan_survivor(s, r, p, options.flip_cos, verts, topo, scratch, stamp)
    if n_shared == 0:
        if options.pair_radius <= 0.0:
            return REJECT_NOT_AN_EDGE, -1, -1
        # A close pair: never contract one that has drifted apart.
        d0 = pos[s, 0] - pos[r, 0]
        d1 = pos[s, 1] - pos[r, 1]
        d2 = pos[s, 2] - pos[r, 2]
        if d0 * d0 + d1 * d1 + d2 * d2 > options.pair_radius * options.pair_radius:
            return REJECT_PAIR_TOO_FAR, -1, -1
    elif n_shared > 2:
        return REJECT_NON_MANIFOLD_EDGE, -1, -1
    # Only a border edge may join two border vertices; an interior edge
    # between them would leave a vertex with two fans (a bow tie).
    both_border = on_border(kind[s]) and on_border(kind[r])
    if n_shared > 0 and (n_shared == 2) == both_border:
        return REJECT_PINCH, -1, -1
    o0 = scratch.opposite[0] if n_shared > 0 else -1
    o1 = scratch.opposite[1] if n_shared == 2 else -1
    common, r_on_opposite, turned = _scan_removed(s, r, p, o0, o1, options.flip_cos, turned,
                                                  verts, topo, scratch, stamp)
    if n_shared == 0 and common > 0:
        # a shared neighbour could turn into a duplicate face or a pinch
        return REJECT_PAIR_SHARES_NEIGHBOURS, o0, o1
    # Link condition (Dey et al. 1999; Hoppe 1996's "legal move"): the common
    # neighbours of s and r must be exactly the vertices opposite the edge,
    # or the collapse pinches a handle or glues two sheets together.
    if common != n_shared:
        return REJECT_LINK, o0, o1
    # Edges count in the link too: if s and r both have a face on the two
    # opposite vertices, the collapse makes a duplicate face (the last step
    # of squashing a tetrahedron). Rare, so s is rescanned only then.
    if r_on_opposite and _has_face_on(s, o0, o1, topo):
        return REJECT_TETRAHEDRON, o0, o1
    # No vertex may be left without faces: not the survivor, nor an opposite
    # vertex whose only face is the one on the edge (the base mesh keeps one).
    fc = topo.face_count
    if (fc[s] + fc[r] - 2 * n_shared <= 0
            or (o0 >= 0 and fc[o0] <= 1) or (o1 >= 0 and fc[o1] <= 1)):
        return REJECT_LAST_FACE, o0, o1
    # Tested during the scans, reported last (the cheapest rules go first).
    return turned, o0, o1
