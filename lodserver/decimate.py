"""Greedy quadric-error edge collapse, recording every collapse.

Implements Garland & Heckbert, "Surface Simplification Using Quadric Error
Metrics" (SIGGRAPH 1997) with the topology rules of Hoppe, "Progressive
Meshes" (SIGGRAPH 1996) and Dey et al., "Topology preserving edge contraction"
(1999): a collapse is taken only when it keeps the mesh a manifold and flips
no triangle, so that every collapse, reversed, is a vertex split.

Pipeline, in the order of this file:

1. classify vertices (interior, border, locked) from edge-face counts and fans;
2. build vertex quadrics (``quadrics.vertex_quadrics``);
3. in a compiled kernel: corner lists per vertex, a collapse queue keyed on
   quadric error (a small heap of the cheapest slice over an unsorted
   reservoir, stale entries detected by vertex versions), then pop / check /
   perform / re-rank until no legal collapse is left, in passes (a collapse
   refused now may become legal once its neighbourhood has moved, so each
   pass re-ranks all edges, and finds close pairs anew when they are asked for);
4. return the collapse log as parallel arrays, one row per collapse.

With a pair threshold, vertices closer than it that share no edge are
candidates too (G&H's "valid pairs"): contracting one joins two parts and
removes no face, which the log records like any other collapse.

Positions are rescaled to the unit box inside the kernel so its tolerances
are scale-free; logged positions are kept in mesh units alongside.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
from numba import njit

from .mesh import Mesh, MeshError
from .quadrics import (
    add_fixed,
    add_reduced,
    best_attributes,
    constrain_to_plane,
    optimal_position_xyz,
    quadric_error,
    seam_edges,
    vertex_quadrics,
    wedge_quadrics,
)
from .topology import Census, census, link_corners

# Vertex kinds. The rules, as in meshoptimizer's kCanCollapse table:
#   interior-interior : any collapse, optimal placement;
#   interior-border   : the border vertex survives (the boundary planes keep it on the border);
#   border-border     : only along a border edge (an interior edge joining two
#                       border vertices would pinch the surface into a bow tie);
#   locked            : never removed and never moved; it may absorb an unlocked neighbour.
INTERIOR = 0
BORDER = 1
LOCKED = 2

# A collapse is refused if it turns any surviving triangle's normal by more
# than arccos(DEFAULT_FLIP_COS) (about 78 degrees): larger turns are fold-overs
# in the making, and a strict 90 degree test lets slivers through.
DEFAULT_FLIP_COS = 0.2
# New triangles with twice-area below this (in the unit-box frame) are degenerate.
DEGENERATE_AREA = 1e-20

# How often (in collapses) the kernel reports progress and checks for cancellation.
_PROGRESS_STRIDE = 1024

# Reasons a popped candidate is refused, counted for diagnostics.
REJECT_REASONS = ("stale", "not_an_edge", "non_manifold_edge", "pinch", "link",
                  "tetrahedron", "last_face", "flip", "pair_too_far", "pair_shares_neighbours",
                  "seam", "deferred_by_volume")

_REASON_COUNT = len(REJECT_REASONS)

# Close pairs (G&H's "valid pairs" that share no edge): at most this many
# candidates per vertex and per pass, so a dense cloud cannot blow up memory.
MAX_PAIRS_PER_VERTEX = 8

# Default weight of each attribute's squared error against squared distance in
# the unit box (positions are scaled so the longest box side is 1): with 0.3, a
# UV error of 0.01 costs as much as a geometric error of 0.55% of the model's
# size. Chosen on the textured shared meshes (bench/appearance.py): heavier
# weights bought little texture accuracy for much geometric error. Normals
# weigh least: their field varies with curvature (1/radius per unit length),
# so even a small weight pins vertices against sliding along the surface, and
# normals come out right wherever the geometry does.
DEFAULT_ATTRIBUTE_WEIGHTS = {"NORMAL": 0.003, "TEXCOORD_0": 0.3, "TEXCOORD_1": 0.3, "COLOR_0": 0.3}

# With volume preservation, a collapse popped from the queue is re-placed on
# its volume plane, which can only raise its cost; if the cost rose past this
# factor times the next key in the queue, it goes back into the queue (lazy
# re-ranking keeps the order cheapest-first to within the factor).
VOLUME_SLACK = 1.1

# A collapse where both endpoints keep a wedge the other has no partner for
# (two seams meeting) must drag one of them; its cost is multiplied by this, so
# such collapses wait until the alternatives cost as much (refusing them
# outright smears less texture at fine levels but ruins coarse ones).
SEAM_PENALTY = 4.0


@dataclass(frozen=True)
class CollapseLog:
    """Every collapse, in order; row ``i`` is collapse ``i``. Vertex and face
    ids are those of the input mesh.

    Attributes
    ----------
    survivor : (k,) int64
        The vertex that stays (``vs`` of the split that undoes it).
    removed : (k,) int64
        The vertex that goes (``vt``); it is never used again.
    position : (k, 3) float64
        The survivor's position after the collapse, mesh units.
    error : (k,) float64
        sqrt(Q(p) / area) of the collapse: an RMS distance in mesh units.
    killed_offsets : (k + 1,) int64
        ``killed_faces[killed_offsets[i]:killed_offsets[i+1]]`` are the faces collapse i removes.
    killed_faces : (f,) int64
    moved_offsets : (k + 1,) int64
        ``moved_corners[moved_offsets[i]:moved_offsets[i+1]]`` are the corners
        (``3 * face + slot``) that collapse i relabels from ``removed`` to ``survivor``.
    moved_corners : (c,) int64
    merge_offsets : (k + 1,) int64
        ``merge_*[merge_offsets[i]:merge_offsets[i+1]]`` are the wedge merges of collapse i.
    merge_survivor, merge_removed : (g,) int64
        Wedge ``merge_removed`` (of the removed vertex) merges into
        ``merge_survivor`` (of the survivor); the removed wedge is never used again.
    merge_value : (g, d) float64
        The survivor wedge's attribute vector after the merge (input units).
    rejected : dict
        How many popped candidates were refused, by reason.
    passes : int
    """

    survivor: np.ndarray
    removed: np.ndarray
    position: np.ndarray
    error: np.ndarray
    killed_offsets: np.ndarray
    killed_faces: np.ndarray
    moved_offsets: np.ndarray
    moved_corners: np.ndarray
    rejected: dict
    passes: int
    merge_offsets: np.ndarray | None = None
    merge_survivor: np.ndarray | None = None
    merge_removed: np.ndarray | None = None
    merge_value: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.survivor)


# --------------------------------------------------------------------------
# 1. Vertex classification
# --------------------------------------------------------------------------

def classify_vertices(found: Census, n, locked=None):
    """Kind of every vertex: INTERIOR, BORDER or LOCKED.

    Parameters
    ----------
    found : Census
        The mesh's connectivity facts (``topology.census``).
    n : int
        Vertex count.
    locked : (n,) bool, optional
        Vertices the caller wants kept exactly (e.g. tile borders).

    Returns
    -------
    kind : (n,) int8
    """
    kind = np.zeros(n, dtype=np.int8)
    kind[found.on_boundary] = BORDER
    # Non-manifold edges and bow-tie vertices (two or more fans) cannot be
    # collapsed and split back as a Hoppe vertex split: lock them.
    kind[found.on_nonmanifold_edge | (found.fans > 1)] = LOCKED
    if locked is not None:
        locked = np.asarray(locked, dtype=bool)
        if locked.shape != (n,):
            raise ValueError(f"locked must be a boolean mask of shape ({n},), got {locked.shape}")
        kind[locked] = LOCKED
    return kind


# --------------------------------------------------------------------------
# 2. The kernel: heap, checks, collapses
# --------------------------------------------------------------------------

# The collapse queue. A binary heap of every candidate would hold millions of
# entries, most of them stale (a collapse re-ranks ~10 edges and strands the
# old entries), and each pop would walk ~22 cache-missing levels. So only the
# cheapest slice lives in the heap (keys <= tau); the rest waits unsorted in a
# reservoir and moves over, a slice at a time, when the heap runs dry. The pop
# order is still exactly cheapest-first. An entry is (key, a << 32 | b,
# version[a] + version[b]); versions only grow, so the sum matches iff both do.

_REFILL_SAMPLE = 4096       # reservoir keys sampled to choose the next tau
_REFILL_MIN = 8192          # smallest slice moved into the heap at a refill


@njit(cache=True, nogil=True)
def _sift_down(keys, ab, vs, size, i):
    key = keys[i]
    e_ab = ab[i]
    e_vs = vs[i]
    while True:
        c = 2 * i + 1
        if c >= size:
            break
        if c + 1 < size and keys[c + 1] < keys[c]:
            c += 1
        if key <= keys[c]:
            break
        keys[i] = keys[c]
        ab[i] = ab[c]
        vs[i] = vs[c]
        i = c
    keys[i] = key
    ab[i] = e_ab
    vs[i] = e_vs


@njit(cache=True, nogil=True)
def _heap_push(keys, ab, vs, size, key, e_ab, e_vs):
    i = size
    while i > 0:
        parent = (i - 1) >> 1
        if keys[parent] <= key:
            break
        keys[i] = keys[parent]
        ab[i] = ab[parent]
        vs[i] = vs[parent]
        i = parent
    keys[i] = key
    ab[i] = e_ab
    vs[i] = e_vs
    return size + 1


@njit(cache=True, nogil=True)
def _heap_pop(keys, ab, vs, size):
    """Drop the root (read it first); returns the new size."""
    size -= 1
    if size > 0:
        keys[0] = keys[size]
        ab[0] = ab[size]
        vs[0] = vs[size]
        _sift_down(keys, ab, vs, size, 0)
    return size


@njit(cache=True, nogil=True)
def _refill(hk, hab, hvs, rk, rab, rvs, rsize, version, vertex_alive):
    """Move the cheapest slice of the reservoir into the (empty) heap,
    dropping the stale entries of that slice on the way.

    Returns (hk, hab, hvs, heap size, reservoir size, tau, dropped): the heap
    arrays may have been reallocated; every reservoir key left is > tau.
    """
    want = max(_REFILL_MIN, rsize // 16)
    if rsize <= want:
        tau = np.inf
    else:
        stride = max(1, rsize // _REFILL_SAMPLE)
        sample = np.sort(rk[:rsize:stride])
        tau = sample[min(len(sample) - 1, (want * len(sample)) // rsize)]
    if hk.shape[0] < rsize:
        hk = np.empty(rsize, np.float64)
        hab = np.empty(rsize, np.int64)
        hvs = np.empty(rsize, np.int64)
    hsize = 0
    kept = 0
    dropped = 0
    for i in range(rsize):
        if rk[i] <= tau:
            a = rab[i] >> 32
            b = rab[i] & 0xFFFFFFFF
            if vertex_alive[a] and vertex_alive[b] and version[a] + version[b] == rvs[i]:
                hk[hsize] = rk[i]
                hab[hsize] = rab[i]
                hvs[hsize] = rvs[i]
                hsize += 1
            else:
                dropped += 1
        else:
            rk[kept] = rk[i]
            rab[kept] = rab[i]
            rvs[kept] = rvs[i]
            kept += 1
    for i in range(hsize // 2 - 1, -1, -1):
        _sift_down(hk, hab, hvs, hsize, i)
    return hk, hab, hvs, hsize, kept, tau, dropped


@njit(cache=True, nogil=True)
def _drop_stale(rk, rab, rvs, rsize, version, vertex_alive):
    """Compact the reservoir, dropping entries whose endpoints have changed."""
    kept = 0
    for i in range(rsize):
        a = rab[i] >> 32
        b = rab[i] & 0xFFFFFFFF
        if vertex_alive[a] and vertex_alive[b] and version[a] + version[b] == rvs[i]:
            rk[kept] = rk[i]
            rab[kept] = rab[i]
            rvs[kept] = rvs[i]
            kept += 1
    return kept


@njit(cache=True, nogil=True)
def _reservoir_push(rk, rab, rvs, rsize, key, e_ab, e_vs, version, vertex_alive):
    """Append an entry to the reservoir; returns (rk, rab, rvs, new size).

    When full, stale entries are dropped first and the arrays grow only if
    that freed less than half of them.
    """
    if rsize == rk.shape[0]:
        rsize = _drop_stale(rk, rab, rvs, rsize, version, vertex_alive)
        if rsize > rk.shape[0] // 2:
            rk = _grow(rk, rsize + 1)
            rab = _grow(rab, rsize + 1)
            rvs = _grow(rvs, rsize + 1)
    rk[rsize] = key
    rab[rsize] = e_ab
    rvs[rsize] = e_vs
    return rk, rab, rvs, rsize + 1


@njit(cache=True, nogil=True)
def _grow(a, need):
    if need <= a.shape[0]:
        return a
    b = np.empty(max(need, 2 * a.shape[0]), a.dtype)
    b[:a.shape[0]] = a
    return b


@njit(cache=True, nogil=True)
def _wedge_terms(a, b, q, faces, face_alive, vhead, cnext, cw, wq, wval, fv, groups):
    """Add the attribute terms of collapsing (a, b) to ``q``.

    The faces on the edge pair each wedge of ``a`` with one of ``b``; such a
    pair merges into one wedge whose attributes are solved for (Hoppe's
    reduced quadric). Every other wedge of ``a`` and ``b`` keeps its value
    wherever the vertex goes (its fixed-value quadric, summed per vertex in
    ``fv``). A seam along the edge keeps both sides (two pairs); a collapse
    that would merge two wedges of one vertex, i.e. drag a seam across the
    surface, is refused (returns False). If both endpoints keep an unpaired
    wedge (two seams meeting), one of them is dragged off its seam whatever
    the placement: the caller multiplies the cost by SEAM_PENALTY.

    ``groups`` receives [pair count, a's wedge, b's wedge, a's wedge, b's
    wedge, -2 if both endpoints keep an unpaired wedge else -1].
    """
    groups[5] = -1
    for j in range(10):
        q[j] += fv[a, j] + fv[b, j]
    n = 0
    c = vhead[a]
    while c >= 0:
        f = c // 3
        if face_alive[f]:
            slot = c - 3 * f
            for t in range(1, 3):
                k = (slot + t) % 3
                if faces[f, k] == b:
                    if n == 2:
                        return False        # non-manifold edge
                    groups[1 + 2 * n] = cw[c]
                    groups[2 + 2 * n] = cw[3 * f + k]
                    n += 1
        c = cnext[c]
    if n == 2:
        same_a = groups[1] == groups[3]
        if same_a != (groups[2] == groups[4]):
            return False
        if same_a:
            n = 1
    groups[0] = n
    if n > 0:
        # fv[v, 10] counts v's wedges; the pairs hold n of each endpoint's
        a_keeps = fv[a, 10] > n
        b_keeps = fv[b, 10] > n
        if a_keeps and b_keeps:
            groups[5] = -2
    d = wval.shape[1]
    for g in range(n):
        wa = groups[1 + 2 * g]
        wb = groups[2 + 2 * g]
        add_fixed(q, wq, wa, wval[wa], -1.0)
        add_fixed(q, wq, wb, wval[wb], -1.0)
        add_reduced(q, wq, wa, wb, d)
    return True


@njit(cache=True, nogil=True)
def _vertex_fixed(v, faces, face_alive, vhead, cnext, cw, wq, wval, fv, wmark, stamp):
    """fv[v, :10] = the sum of the fixed-value quadrics of v's wedges, fv[v, 10]
    their number; returns the new stamp."""
    stamp += 1
    for j in range(11):
        fv[v, j] = 0.0
    c = vhead[v]
    while c >= 0:
        if face_alive[c // 3]:
            w = cw[c]
            if wmark[w] != stamp:
                wmark[w] = stamp
                add_fixed(fv[v], wq, w, wval[w], 1.0)
                fv[v, 10] += 1.0
        c = cnext[c]
    return stamp


@njit(cache=True, nogil=True)
def _volume_plane(a, b, pos, faces, face_alive, vhead, cnext, out):
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


@njit(cache=True, nogil=True)
def _plan(a, b, pos, quadrics, kind, q, p, faces, face_alive, vhead, cnext, cw, wq, wval, fv,
          groups):
    """Cost of collapsing edge (a, b); writes the placement into ``p`` and the
    summed quadric into ``q``.

    Returns (cost, survivor); cost is inf when the collapse is never legal.
    """
    if kind[a] == LOCKED and kind[b] == LOCKED:
        return np.inf, a
    for j in range(11):
        q[j] = quadrics[a, j] + quadrics[b, j]
    groups[0] = 0
    groups[5] = -1
    if wq.shape[0] > 0 and not _wedge_terms(a, b, q, faces, face_alive, vhead, cnext, cw, wq,
                                            wval, fv, groups):
        return np.inf, a
    if kind[a] == LOCKED or kind[b] == LOCKED:
        s = a if kind[a] == LOCKED else b
        p[0] = pos[s, 0]; p[1] = pos[s, 1]; p[2] = pos[s, 2]
        cost = quadric_error(q, p[0], p[1], p[2])
    else:
        cost = optimal_position_xyz(q, pos[a, 0], pos[a, 1], pos[a, 2], pos[b, 0], pos[b, 1],
                                    pos[b, 2], p)
        # The border vertex survives an interior-border collapse; otherwise either may.
        s = b if kind[b] > kind[a] else a
    if groups[5] == -2:
        cost *= SEAM_PENALTY
    return max(cost, 0.0), s


@njit(cache=True, nogil=True)
def _face_flips(v, x, y, p, pos, flip_cos):
    """True if moving corner ``v`` of face (v, x, y) to ``p`` flips the face,
    turns its normal by more than arccos(flip_cos), or makes it degenerate."""
    ex = pos[x, 0] - pos[y, 0]
    ey = pos[x, 1] - pos[y, 1]
    ez = pos[x, 2] - pos[y, 2]
    # normals (v - y) x (x - y) before and after: the edge (x, y) stays put
    ux = pos[v, 0] - pos[y, 0]
    uy = pos[v, 1] - pos[y, 1]
    uz = pos[v, 2] - pos[y, 2]
    ax = uy * ez - uz * ey
    ay = uz * ex - ux * ez
    az = ux * ey - uy * ex
    ux = p[0] - pos[y, 0]
    uy = p[1] - pos[y, 1]
    uz = p[2] - pos[y, 2]
    bx = uy * ez - uz * ey
    by = uz * ex - ux * ez
    bz = ux * ey - uy * ex
    lb = bx * bx + by * by + bz * bz
    if lb <= DEGENERATE_AREA:
        return True
    la = ax * ax + ay * ay + az * az
    if la <= DEGENERATE_AREA:
        return False    # already degenerate: no orientation to keep
    return ax * bx + ay * by + az * bz <= flip_cos * np.sqrt(la * lb)


@njit(cache=True, nogil=True)
def _close_pairs(pos, vertex_alive, faces, face_alive, vhead, cnext, radius, mark, stamp):
    """Pairs (a < b) of live vertices at most ``radius`` apart that share no edge.

    A uniform grid of cells ``radius`` wide is the spatial index: rebuilt from
    the current positions at each pass (vertices move as they absorb others),
    every vertex looks at its 27 surrounding cells. At most
    MAX_PAIRS_PER_VERTEX candidates per vertex, nearest cells first.

    Returns (pairs (k, 2) int64, the last stamp used in ``mark``).
    """
    n = pos.shape[0]
    cells = int(np.ceil(1.0 / radius)) + 3
    keys = np.full(n, np.iinfo(np.int64).max, np.int64)
    for v in range(n):
        if vertex_alive[v]:
            keys[v] = ((int(pos[v, 0] / radius) + 1) * cells
                       + int(pos[v, 1] / radius) + 1) * cells + int(pos[v, 2] / radius) + 1
    order = np.argsort(keys)
    sorted_keys = keys[order]
    pairs = np.empty((16, 2), np.int64)
    count = 0
    r2 = radius * radius
    for a in range(n):
        if not vertex_alive[a]:
            continue
        # mark a's neighbours: an existing edge is not a close pair
        stamp += 1
        c = vhead[a]
        while c >= 0:
            f = c // 3
            if face_alive[f]:
                for t in range(3):
                    mark[faces[f, t]] = stamp
            c = cnext[c]
        found = 0
        for dx in (0, -1, 1):
            for dy in (0, -1, 1):
                for dz in (0, -1, 1):
                    key = keys[a] + (dx * cells + dy) * cells + dz
                    i = np.searchsorted(sorted_keys, key)
                    while i < n and sorted_keys[i] == key and found < MAX_PAIRS_PER_VERTEX:
                        b = order[i]
                        i += 1
                        if b <= a or mark[b] == stamp:
                            continue
                        d0 = pos[a, 0] - pos[b, 0]
                        d1 = pos[a, 1] - pos[b, 1]
                        d2 = pos[a, 2] - pos[b, 2]
                        if d0 * d0 + d1 * d1 + d2 * d2 <= r2:
                            if count == pairs.shape[0]:
                                grown = np.empty((2 * count, 2), np.int64)
                                grown[:count] = pairs
                                pairs = grown
                            pairs[count, 0] = a
                            pairs[count, 1] = b
                            count += 1
                            found += 1
    return pairs[:count], stamp


@njit(cache=True, nogil=True)
def _log_arrays(n, m):
    """Room for the log of at most ``n`` collapses of an ``m``-face mesh:
    survivor, removed, position (n, 3), error, then the killed faces and the
    moved corners of each collapse as offsets (n + 1,) and values."""
    return (np.empty(n, np.int64), np.empty(n, np.int64), np.empty((n, 3), np.float64),
            np.empty(n, np.float64), np.zeros(n + 1, np.int64), np.empty(m, np.int64),
            np.zeros(n + 1, np.int64), np.empty(3 * m, np.int64))


@njit(cache=True, nogil=True)
def _decimate_kernel(pos, world, scale, origin, faces, quadrics, kind, min_vertices,
                     max_collapses, flip_cos, pair_radius, progress, corner_wedge, wq, wval,
                     normal_col, normal_len, color_col, color_max, volume):
    """Collapse edges (and close pairs, if ``pair_radius`` > 0) cheapest first
    until none is legal or a limit is hit.

    ``pos`` and ``quadrics`` are updated in place (unit-box frame); ``world``
    holds the same positions in mesh units (``origin + scale * pos``), kept
    bit-exact for vertices that never move, so locked vertices log their input
    position exactly.
    ``progress[0]`` receives the collapse count as it goes; a non-zero
    ``progress[1]`` asks the kernel to stop early.

    Wedges (all empty for a geometry-only mesh): ``corner_wedge`` (3m,) the
    wedge of every corner, ``wq`` (w, 11 + 4d) their attribute quadrics and
    ``wval`` (w, d) their values, scaled by sqrt(weight); both updated in
    place. Columns ``normal_col .. +3`` are renormalised to ``normal_len`` and
    ``color_col .. +4`` clamped to [0, color_max] after a merge (-1: absent).
    ``volume`` keeps interior collapses on their volume-preserving plane.
    """
    n = pos.shape[0]
    m = faces.shape[0]
    # int32 ids halve the memory traffic of the corner walks, which dominate
    faces = faces.astype(np.int32)

    # Corner lists: vhead[v] -> corner -> cnext[corner] ... of the faces at v.
    # Dead faces are unlinked lazily, when the survivor's list is next rebuilt.
    vhead = np.full(n, -1, np.int32)
    cnext = np.full(3 * m, -1, np.int32)
    face_count = np.zeros(n, np.int64)     # live faces at each vertex
    link_corners(faces, vhead, cnext, face_count)
    face_alive = np.ones(m, np.bool_)
    # Wedges: fv[v] caches the fixed-value attribute quadrics of v's wedges
    cw = corner_wedge.astype(np.int32)
    d = wval.shape[1]
    has_wedges = wq.shape[0] > 0
    fv = np.zeros((n if has_wedges else 0, 11), np.float64)
    wmark = np.zeros(wq.shape[0], np.int64)
    wstamp = 0
    if has_wedges:
        for v in range(n):
            wstamp = _vertex_fixed(v, faces, face_alive, vhead, cnext, cw, wq, wval, fv, wmark,
                                   wstamp)
    groups = np.full(6, -1, np.int64)
    value = np.empty(d, np.float64)
    mg_off = np.zeros(n + 1, np.int64)
    mg_s = np.empty(2 * n if has_wedges else 0, np.int64)
    mg_r = np.empty(2 * n if has_wedges else 0, np.int64)
    mg_v = np.empty((2 * n if has_wedges else 0, d), np.float64)
    nmerged = 0
    plane = np.empty(4, np.float64)
    gq = np.empty(11, np.float64)
    vertex_alive = face_count > 0
    alive_count = 0
    for v in range(n):
        if vertex_alive[v]:
            alive_count += 1

    # A heap entry is stale once either endpoint's version has moved on.
    version = np.zeros(n, np.int64)
    mark = np.zeros(n, np.int64)
    mark2 = np.zeros(n, np.int64)
    stamp = 0

    hk = np.empty(_REFILL_MIN, np.float64)
    hab = np.empty(_REFILL_MIN, np.int64)
    hvs = np.empty(_REFILL_MIN, np.int64)
    rk = np.empty(3 * m // 2 + 16, np.float64)
    rab = np.empty(3 * m // 2 + 16, np.int64)
    rvs = np.empty(3 * m // 2 + 16, np.int64)

    log_s, log_r, log_p, log_cost, killed_off, killed, moved_off, moved = _log_arrays(n, m)
    log_area = np.empty(n, np.float64)
    nk = 0
    nkilled = 0
    nmoved = 0

    rejected = np.zeros(_REASON_COUNT, np.int64)
    q = np.empty(11)
    p = np.empty(3)
    shared_opp = np.empty(2, np.int64)
    passes = 0

    while True:
        passes += 1
        collapses_before = nk
        # ---- rank every live edge once, into the reservoir ----
        rsize = 0
        for a in range(n):
            if not vertex_alive[a]:
                continue
            stamp += 1
            c = vhead[a]
            while c >= 0:
                f = c // 3
                if face_alive[f]:
                    slot = c - 3 * f
                    for t in range(1, 3):
                        b = faces[f, (slot + t) % 3]
                        if b > a and mark[b] != stamp:
                            mark[b] = stamp
                            cost, _s = _plan(a, b, pos, quadrics, kind, q, p, faces, face_alive,
                                             vhead, cnext, cw, wq, wval, fv, groups)
                            if cost < np.inf:
                                rk, rab, rvs, rsize = _reservoir_push(
                                    rk, rab, rvs, rsize, cost, (a << 32) | b,
                                    version[a] + version[b], version, vertex_alive)
                c = cnext[c]
        if pair_radius > 0.0:
            pairs, stamp = _close_pairs(pos, vertex_alive, faces, face_alive, vhead, cnext,
                                        pair_radius, mark, stamp)
            for i in range(pairs.shape[0]):
                a = pairs[i, 0]
                b = pairs[i, 1]
                cost, _s = _plan(a, b, pos, quadrics, kind, q, p, faces, face_alive, vhead, cnext,
                                 cw, wq, wval, fv, groups)
                if cost < np.inf:
                    rk, rab, rvs, rsize = _reservoir_push(rk, rab, rvs, rsize, cost, (a << 32) | b,
                                                          version[a] + version[b], version,
                                                          vertex_alive)
        hsize = 0
        tau = -np.inf

        # ---- pop cheapest, check, collapse, re-rank the neighbourhood ----
        stop = False
        while True:
            if alive_count <= min_vertices or nk >= max_collapses or progress[1] != 0:
                stop = True
                break
            if hsize == 0:
                if rsize == 0:
                    break
                hk, hab, hvs, hsize, rsize, tau, dropped = _refill(hk, hab, hvs, rk, rab, rvs, rsize,
                                                                    version, vertex_alive)
                rejected[0] += dropped
                continue
            a = hab[0] >> 32
            b = hab[0] & 0xFFFFFFFF
            entry_version = hvs[0]
            hsize = _heap_pop(hk, hab, hvs, hsize)
            if (not vertex_alive[a] or not vertex_alive[b]
                    or version[a] + version[b] != entry_version):
                rejected[0] += 1
                continue
            cost, s = _plan(a, b, pos, quadrics, kind, q, p, faces, face_alive, vhead, cnext,
                            cw, wq, wval, fv, groups)
            if cost == np.inf:
                rejected[10] += 1
                continue
            if volume and kind[a] == INTERIOR and kind[b] == INTERIOR:
                _volume_plane(a, b, pos, faces, face_alive, vhead, cnext, plane)
                if constrain_to_plane(q, plane[0], plane[1], plane[2], plane[3], p):
                    cost = max(quadric_error(q, p[0], p[1], p[2]), 0.0)
                    if groups[5] == -2:
                        cost *= SEAM_PENALTY
                    next_key = hk[0] if hsize > 0 else tau
                    if cost > VOLUME_SLACK * next_key:
                        # dearer than what waits next: back into the queue at its true cost
                        rejected[11] += 1
                        if cost <= tau:
                            if hsize == hk.shape[0]:
                                hk = _grow(hk, hsize + 1); hab = _grow(hab, hsize + 1)
                                hvs = _grow(hvs, hsize + 1)
                            hsize = _heap_push(hk, hab, hvs, hsize, cost, (a << 32) | b,
                                               entry_version)
                        else:
                            rk, rab, rvs, rsize = _reservoir_push(
                                rk, rab, rvs, rsize, cost, (a << 32) | b, entry_version, version,
                                vertex_alive)
                        continue
            r = b if s == a else a
            # wedge pairs as (survivor's, removed's)
            n_groups = groups[0]
            if s != a:
                for g in range(n_groups):
                    groups[1 + 2 * g], groups[2 + 2 * g] = groups[2 + 2 * g], groups[1 + 2 * g]

            # Scan s: mark its neighbours, find the faces on the edge (s, r)
            # and the vertex opposite it in each, and test s's other faces for flips.
            stamp += 1
            n_shared = 0
            flipped = False
            c = vhead[s]
            while c >= 0:
                f = c // 3
                if face_alive[f]:
                    slot = c - 3 * f
                    x = faces[f, (slot + 1) % 3]
                    y = faces[f, (slot + 2) % 3]
                    mark[x] = stamp
                    mark[y] = stamp
                    if x == r or y == r:
                        if n_shared < 2:
                            shared_opp[n_shared] = y if x == r else x
                        n_shared += 1
                    elif not flipped:
                        flipped = _face_flips(s, x, y, p, pos, flip_cos)
                c = cnext[c]
            if n_shared == 0:
                if pair_radius <= 0.0:
                    rejected[1] += 1
                    continue
                # A close pair: never contract one that has drifted apart.
                d0 = pos[s, 0] - pos[r, 0]
                d1 = pos[s, 1] - pos[r, 1]
                d2 = pos[s, 2] - pos[r, 2]
                if d0 * d0 + d1 * d1 + d2 * d2 > pair_radius * pair_radius:
                    rejected[8] += 1
                    continue
            elif n_shared > 2:
                rejected[2] += 1
                continue
            # Only a border edge may join two border vertices; an interior
            # edge between them would leave a vertex with two fans.
            both_border = kind[s] != INTERIOR and kind[r] != INTERIOR
            if n_shared > 0 and (n_shared == 2) == both_border:
                rejected[3] += 1
                continue

            # Scan r: count the common neighbours of s and r, look for a face
            # (r, x, y) on the two opposite vertices, test r's faces for flips.
            common = 0
            r_on_opposite = False
            o0 = shared_opp[0] if n_shared > 0 else -1
            o1 = shared_opp[1] if n_shared == 2 else -1
            c = vhead[r]
            while c >= 0:
                f = c // 3
                if face_alive[f]:
                    slot = c - 3 * f
                    x = faces[f, (slot + 1) % 3]
                    y = faces[f, (slot + 2) % 3]
                    if x != s and y != s:
                        if (x == o0 and y == o1) or (x == o1 and y == o0):
                            r_on_opposite = True
                        if not flipped:
                            flipped = _face_flips(r, x, y, p, pos, flip_cos)
                    for w in (x, y):
                        if w != s and mark[w] == stamp and mark2[w] != stamp:
                            mark2[w] = stamp
                            common += 1
                c = cnext[c]
            # Link condition: the common neighbours of s and r must be exactly
            # the vertices opposite the edge, or the collapse pinches a handle.
            if n_shared == 0 and common > 0:
                # a shared neighbour could turn into a duplicate face or a pinch
                rejected[9] += 1
                continue
            if common != n_shared:
                rejected[4] += 1
                continue
            # Edges count in the link too: if s and r both have a face on the
            # two opposite vertices, the collapse makes a duplicate face (the
            # last step of squashing a tetrahedron). Rare, so s is rescanned.
            if r_on_opposite:
                s_on_opposite = False
                c = vhead[s]
                while c >= 0:
                    f = c // 3
                    if face_alive[f]:
                        slot = c - 3 * f
                        x = faces[f, (slot + 1) % 3]
                        y = faces[f, (slot + 2) % 3]
                        if (x == o0 and y == o1) or (x == o1 and y == o0):
                            s_on_opposite = True
                    c = cnext[c]
                if s_on_opposite:
                    rejected[5] += 1
                    continue
            # No vertex may be left without faces: not the survivor, nor an
            # opposite vertex whose only face is the one on the edge.
            if (face_count[s] + face_count[r] - 2 * n_shared <= 0
                    or (o0 >= 0 and face_count[o0] <= 1) or (o1 >= 0 and face_count[o1] <= 1)):
                rejected[6] += 1
                continue
            if flipped:
                rejected[7] += 1
                continue

            # ---- perform: r's faces die (if on the edge) or move to s ----
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
                        for g in range(n_groups):
                            if cw[c] == groups[2 + 2 * g]:
                                cw[c] = groups[1 + 2 * g]
                        if nmoved >= moved.shape[0]:
                            moved = _grow(moved, nmoved + 1)
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

            # the logged error is geometric: distance to the planes, not attribute terms
            for j in range(11):
                gq[j] = quadrics[s, j] + quadrics[r, j]
            geometric = max(quadric_error(gq, p[0], p[1], p[2]), 0.0)
            area = quadrics[s, 10] + quadrics[r, 10]
            for j in range(11):
                quadrics[s, j] += quadrics[r, j]
            for g in range(n_groups):
                ws = groups[1 + 2 * g]
                wr = groups[2 + 2 * g]
                for j in range(wq.shape[1]):
                    wq[ws, j] += wq[wr, j]
                if wq[ws, 10] > 0.0:
                    best_attributes(wq, ws, p[0], p[1], p[2], value)
                else:
                    for j in range(d):
                        value[j] = 0.5 * (wval[ws, j] + wval[wr, j])
                if normal_col >= 0:
                    length = np.sqrt(value[normal_col] ** 2 + value[normal_col + 1] ** 2
                                     + value[normal_col + 2] ** 2)
                    if length > 0.0:
                        for j in range(normal_col, normal_col + 3):
                            value[j] *= normal_len / length
                if color_col >= 0:
                    for j in range(color_col, color_col + 4):
                        value[j] = min(max(value[j], 0.0), color_max)
                for j in range(d):
                    wval[ws, j] = value[j]
                    mg_v[nmerged, j] = value[j]
                mg_s[nmerged] = ws
                mg_r[nmerged] = wr
                nmerged += 1
            # Placements at an endpoint copy its mesh-unit position bit for bit
            # (locked vertices must not drift by a rounding).
            if p[0] == pos[r, 0] and p[1] == pos[r, 1] and p[2] == pos[r, 2]:
                for j in range(3):
                    world[s, j] = world[r, j]
            elif not (p[0] == pos[s, 0] and p[1] == pos[s, 1] and p[2] == pos[s, 2]):
                for j in range(3):
                    world[s, j] = origin[j] + scale * p[j]
            pos[s, 0] = p[0]; pos[s, 1] = p[1]; pos[s, 2] = p[2]
            kind[s] = max(kind[s], kind[r])
            vertex_alive[r] = False
            alive_count -= 1
            version[s] += 1
            version[r] += 1

            log_s[nk] = s
            log_r[nk] = r
            log_p[nk, 0] = world[s, 0]; log_p[nk, 1] = world[s, 1]; log_p[nk, 2] = world[s, 2]
            log_cost[nk] = geometric
            log_area[nk] = area
            nk += 1
            killed_off[nk] = nkilled
            moved_off[nk] = nmoved
            mg_off[nk] = nmerged
            if has_wedges:
                # s's wedges changed; an opposite vertex may have lost a wedge with its face
                wstamp = _vertex_fixed(s, faces, face_alive, vhead, cnext, cw, wq, wval, fv,
                                       wmark, wstamp)
                for o in (o0, o1):
                    if o >= 0:
                        wstamp = _vertex_fixed(o, faces, face_alive, vhead, cnext, cw, wq, wval,
                                               fv, wmark, wstamp)
            if nk % _PROGRESS_STRIDE == 0:
                progress[0] = nk

            # Re-rank the edges around s: its quadric and position changed.
            stamp += 1
            c = vhead[s]
            while c >= 0:
                f = c // 3
                slot = c - 3 * f
                for t in range(1, 3):
                    w = faces[f, (slot + t) % 3]
                    if mark[w] != stamp:
                        mark[w] = stamp
                        cost2, _s = _plan(s, w, pos, quadrics, kind, q, p, faces, face_alive,
                                          vhead, cnext, cw, wq, wval, fv, groups)
                        if cost2 < np.inf:
                            e_ab = (s << 32) | w if s < w else (w << 32) | s
                            e_vs = version[s] + version[w]
                            if cost2 <= tau:
                                if hsize == hk.shape[0]:
                                    hk = _grow(hk, hsize + 1); hab = _grow(hab, hsize + 1)
                                    hvs = _grow(hvs, hsize + 1)
                                hsize = _heap_push(hk, hab, hvs, hsize, cost2, e_ab, e_vs)
                            else:
                                rk, rab, rvs, rsize = _reservoir_push(
                                    rk, rab, rvs, rsize, cost2, e_ab, e_vs, version, vertex_alive)
                c = cnext[c]
        if stop or nk == collapses_before:
            break

    progress[0] = nk
    return (log_s[:nk], log_r[:nk], log_p[:nk], log_cost[:nk], log_area[:nk],
            killed_off[:nk + 1], killed[:nkilled], moved_off[:nk + 1], moved[:nmoved],
            rejected, passes, mg_off[:nk + 1], mg_s[:nmerged], mg_r[:nmerged], mg_v[:nmerged])


# --------------------------------------------------------------------------
# 3. Public entry point
# --------------------------------------------------------------------------

def decimate(mesh: Mesh, *, boundary_weight: float = 1.0, locked=None, min_vertices: int = 0,
             max_collapses: int | None = None, flip_cos: float = DEFAULT_FLIP_COS,
             pair_threshold: float = 0.0, attribute_weights: dict | None = None,
             preserve_volume: bool = True, seam_weight: float = 1.0, progress=None,
             cancel: threading.Event | None = None) -> CollapseLog:
    """Collapse edges of ``mesh`` cheapest first and log every collapse.

    Parameters
    ----------
    mesh : Mesh
        Welded, clean input (see ``io.clean_mesh``).
    boundary_weight : float
        Weight of the border constraint planes; 0 lets borders shrink.
    locked : (n,) bool, optional
        Vertices that must neither move nor vanish.
    min_vertices : int
        Stop when this few vertices remain (0: run until no legal collapse is left).
    max_collapses : int, optional
        Stop after this many collapses.
    flip_cos : float
        A collapse that turns a surviving face's normal by more than
        ``arccos(flip_cos)`` is refused.
    pair_threshold : float
        Also contract vertex pairs that share no edge but lie at most this far
        apart (mesh units), joining separate parts and sheets (G&H's close
        pairs). 0 (default) contracts edges only. A pair is contracted only if
        the two vertices share no neighbour and are still that close; the
        joined vertex then has two fans, and the link condition keeps every
        later collapse from making a non-manifold edge.
    attribute_weights : dict, optional
        Weight of each attribute's squared error (by glTF name, e.g.
        ``{"NORMAL": 0.25, "TEXCOORD_0": 1}``) against squared distance in the
        unit box; missing names take :data:`DEFAULT_ATTRIBUTE_WEIGHTS`. Only
        used when the mesh has attributes.
    preserve_volume : bool
        Place every interior collapse on the plane that keeps the enclosed
        volume (default), so thin parts do not shrink away.
    seam_weight : float
        Weight of the constraint planes along attribute seams (as
        ``boundary_weight`` for borders).
    progress : callable(done: int, expected: int), optional
        Called from this thread about ten times a second while the kernel runs.
    cancel : threading.Event, optional
        When set, the kernel stops at the next progress check.

    Returns
    -------
    CollapseLog
    """
    positions = np.asarray(mesh.positions, dtype=np.float64)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    n = len(positions)
    if 3 * len(faces) >= 2**31:
        # the kernel stores vertex and corner ids as int32
        raise MeshError(f"{len(faces)} faces is more than the 715 million decimation supports")
    found = census(faces, n)
    kind = classify_vertices(found, n, locked)

    # Work in the unit box: tolerances become scale-free and quadric
    # coefficients stay in a range where float64 cancellation is harmless.
    lo = positions.min(axis=0)
    scale = float((positions.max(axis=0) - lo).max()) or 1.0
    unit = (positions - lo) / scale
    attributes = mesh.attributes
    seams = _texture_seams(mesh) if attributes is not None else None
    quadrics = vertex_quadrics(unit, faces, boundary_weight=boundary_weight,
                               boundary=(found.boundary_edges, found.boundary_faces),
                               seams=seams, seam_weight=seam_weight)
    corner_wedge, wq, wval, scales, *columns = _wedge_inputs(attributes, unit, faces,
                                                             attribute_weights)

    if not pair_threshold >= 0:
        raise ValueError(f"pair_threshold must be a non-negative distance, got {pair_threshold}")
    # cells of the pair search are this wide in the unit box; keep their count sane
    radius = max(float(pair_threshold) / scale, 1e-6) if pair_threshold > 0 else 0.0
    world = positions.copy()
    limit = n if max_collapses is None else int(max_collapses)
    state = np.zeros(2, dtype=np.int64)
    result = {}

    def run():
        result["log"] = _decimate_kernel(unit, world, scale, lo, faces, quadrics, kind,
                                         int(min_vertices), limit, float(flip_cos), radius, state,
                                         corner_wedge, wq, wval, *columns, bool(preserve_volume))

    if progress is None and cancel is None:
        run()
    else:
        # The kernel releases the GIL (nogil=True); this thread polls its counter.
        worker = threading.Thread(target=run, daemon=True)
        worker.start()
        while worker.is_alive():
            worker.join(0.1)
            if cancel is not None and cancel.is_set():
                state[1] = 1
            if progress is not None:
                progress(int(state[0]), n)
        if progress is not None:
            progress(int(state[0]), n)
    if "log" not in result:
        raise RuntimeError("the decimation kernel failed")
    (s, r, p, cost, area, killed_off, killed, moved_off, moved, rejected, passes,
     merge_off, merge_s, merge_r, merge_v) = result["log"]

    error = np.sqrt(cost / np.maximum(area, np.finfo(float).tiny)) * scale
    merges = {}
    if attributes is not None:
        # back from sqrt(weight)-scaled to input units
        merges = dict(merge_offsets=merge_off.copy(), merge_survivor=merge_s.copy(),
                      merge_removed=merge_r.copy(), merge_value=merge_v / scales)
    return CollapseLog(
        survivor=s.copy(), removed=r.copy(), position=p.copy(), error=error,
        killed_offsets=killed_off.copy(), killed_faces=killed.copy(),
        moved_offsets=moved_off.copy(), moved_corners=moved.copy(),
        rejected=dict(zip(REJECT_REASONS, (int(x) for x in rejected))), passes=int(passes),
        **merges)


def _texture_seams(mesh: Mesh):
    """``seam_edges`` over the wedges as UVs and colours alone see them.

    Seams where only the normal changes are creases: the geometric quadrics
    already keep a real crease, and pinning the many shallow ones that
    exporters leave (Duck.glb's median 13 degrees) with planes costs far more
    geometric error than it saves.
    """
    attributes = mesh.attributes
    keep = np.ones(attributes.width, dtype=bool)
    normal = attributes.columns("NORMAL")
    if normal is not None:
        keep[normal] = False
    if not keep.any():
        return None
    rows = np.concatenate([mesh.wedge_vertices()[:, None].astype(np.float64),
                           attributes.values[:, keep]], axis=1)
    _, texture_wedge = np.unique(rows, axis=0, return_inverse=True)
    return seam_edges(mesh.faces, texture_wedge.ravel()[attributes.corners])


def attribute_scales(layout, weights: dict | None) -> np.ndarray:
    """(d,) float64: sqrt(weight) for every attribute column of ``layout``."""
    weights = {**DEFAULT_ATTRIBUTE_WEIGHTS, **(weights or {})}
    unknown = set(weights) - {name for name, _ in layout} - set(DEFAULT_ATTRIBUTE_WEIGHTS)
    if unknown:
        raise ValueError(f"no attribute named {', '.join(sorted(unknown))}; "
                         f"known are {', '.join(DEFAULT_ATTRIBUTE_WEIGHTS)}")
    scales = []
    for name, width in layout:
        weight = float(weights[name])
        if not 0 < weight < float("inf"):
            raise ValueError(f"the weight of {name} must be a positive number, got {weight}")
        scales += [np.sqrt(weight)] * width
    return np.array(scales, dtype=np.float64)


def _wedge_inputs(attributes, unit, faces, weights):
    """The kernel's wedge arguments: corner_wedge (3m,), wq (w, 11 + 4d), wval
    (w, d) scaled by sqrt(weight), those scales (d,), then normal_col,
    normal_len, color_col, color_max. Empty arrays for a geometry-only mesh."""
    if attributes is None:
        return (np.zeros(0, dtype=np.int64), np.zeros((0, 11)), np.zeros((0, 0)), np.ones(0),
                -1, 1.0, -1, 1.0)
    scales = attribute_scales(attributes.layout, weights)
    wval = attributes.values * scales
    wq = wedge_quadrics(unit, faces, attributes.corners, wval)
    normal = attributes.columns("NORMAL")
    color = attributes.columns("COLOR_0")
    return (attributes.corners.ravel(), wq, wval, scales,
            -1 if normal is None else normal.start,
            1.0 if normal is None else float(scales[normal.start]),
            -1 if color is None else color.start,
            1.0 if color is None else float(scales[color.start]))
