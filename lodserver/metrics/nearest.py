"""The exact nearest point on a triangle mesh, for many query points at once.

Triangles go into a bounding-volume hierarchy (median splits, built in
parallel); queries are ordered along a Z-curve and walk it in parallel chunks,
each testing exact point-to-triangle distance (a flat triangle counts as its
three edges). Plain arrays in, no validation: :mod:`.surface` checks inputs.
"""

from __future__ import annotations

import numba
import numpy as np

from ..mesh import Mesh, unit_box

# Triangles per BVH leaf: small leaves prune well; fewer than 4 only deepens the tree.
_LEAF_SIZE = 4
# A triangle whose largest angle has sin below this is treated as its three edges:
# its height is then < 1e-8 of its edges, which is also about the error the
# plane-based face test would make on such a flat cap (eps / sin).
FLAT_SIN2 = 1e-16
# Query points per parallel work item; each item owns its traversal stack.
_CHUNK = 256
# Stack depth: a median-split tree over 2**62 triangles is still only ~62 levels.
_STACK = 128


# ---------------------------------------------------------------------------
# Kernels (plain arrays in, no validation)
# ---------------------------------------------------------------------------


@numba.njit(cache=True, inline="always")
def closest_on_segment(px, py, pz, ux, uy, uz, vx, vy, vz):
    dx, dy, dz = vx - ux, vy - uy, vz - uz
    den = dx * dx + dy * dy + dz * dz
    t = 0.0
    if den > 0.0:  # a zero-length segment is its start point
        t = ((px - ux) * dx + (py - uy) * dy + (pz - uz) * dz) / den
        t = min(max(t, 0.0), 1.0)
    qx, qy, qz = ux + t * dx, uy + t * dy, uz + t * dz
    ex, ey, ez = px - qx, py - qy, pz - qz
    return ex * ex + ey * ey + ez * ez, qx, qy, qz


@numba.njit(cache=True, inline="always")
def cross(ux, uy, uz, vx, vy, vz):
    """``u x v`` as three floats."""
    return uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx


@numba.njit(cache=True, inline="always")
def edge_side(nx, ny, nz, ex, ey, ez, qx, qy, qz):
    """``n . (e x q)``: which side of an edge ``e`` a point ``q`` (relative to the
    edge's start) lies on, seen along the face normal ``n``."""
    return (
        nx * (ey * qz - ez * qy)
        + ny * (ez * qx - ex * qz)
        + nz * (ex * qy - ey * qx)
    )


@numba.njit(cache=True)
def _closest_on_triangle(px, py, pz, tri, j):
    """Squared distance and closest point from p to triangle row ``tri[j]``.

    Rows are stored with vertex a opposite the longest edge (largest angle),
    which makes the normal ``ab x ac`` as accurate as the triangle allows.
    Face region: p projects inside all three edges (signs of n . (edge x (p - v)),
    first-order in the rounding unlike the Lagrange-identity barycentrics of
    Ericson's version, which square the conditioning). Otherwise the nearest
    point lies on an edge that p's projection is outside of, so only those are
    measured. Flat or collapsed triangles are measured as their three edges.
    """
    ax, ay, az = tri[j, 0], tri[j, 1], tri[j, 2]
    bx, by, bz = tri[j, 3], tri[j, 4], tri[j, 5]
    cx, cy, cz = tri[j, 6], tri[j, 7], tri[j, 8]
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    nx, ny, nz = cross(abx, aby, abz, acx, acy, acz)
    nn = nx * nx + ny * ny + nz * nz
    abab = abx * abx + aby * aby + abz * abz
    acac = acx * acx + acy * acy + acz * acz
    out_ab = True
    out_bc = True
    out_ca = True
    if nn > FLAT_SIN2 * abab * acac:
        apx, apy, apz = px - ax, py - ay, pz - az
        # side of each edge: n . (edge x (p - its start)); edge ca is -ac
        s_ab = edge_side(nx, ny, nz, abx, aby, abz, apx, apy, apz)
        s_bc = edge_side(nx, ny, nz, cx - bx, cy - by, cz - bz, px - bx, py - by, pz - bz)
        s_ca = -edge_side(nx, ny, nz, acx, acy, acz, px - cx, py - cy, pz - cz)
        out_ab = s_ab < 0.0
        out_bc = s_bc < 0.0
        out_ca = s_ca < 0.0
        if not (out_ab or out_bc or out_ca):
            h = apx * nx + apy * ny + apz * nz
            t = h / nn
            return h * t, px - t * nx, py - t * ny, pz - t * nz
    best = np.inf
    qx = qy = qz = 0.0
    if out_ab:
        d2, sx, sy, sz = closest_on_segment(px, py, pz, ax, ay, az, bx, by, bz)
        if d2 < best:
            best, qx, qy, qz = d2, sx, sy, sz
    if out_bc:
        d2, sx, sy, sz = closest_on_segment(px, py, pz, bx, by, bz, cx, cy, cz)
        if d2 < best:
            best, qx, qy, qz = d2, sx, sy, sz
    if out_ca:
        d2, sx, sy, sz = closest_on_segment(px, py, pz, cx, cy, cz, ax, ay, az)
        if d2 < best:
            best, qx, qy, qz = d2, sx, sy, sz
    return best, qx, qy, qz


@numba.njit(cache=True, parallel=True)
def _triangle_table(positions, faces):
    """(m, 9) corner coordinates, rotated so corner 0 is opposite the longest edge,
    and (m, 3) centroids."""
    m = faces.shape[0]
    tri = np.empty((m, 9))
    cent = np.empty((m, 3))
    for j in numba.prange(m):
        i0, i1, i2 = faces[j, 0], faces[j, 1], faces[j, 2]
        l0 = 0.0  # |v1 - v2|^2, opposite corner 0
        l1 = 0.0
        l2 = 0.0
        for k in range(3):
            l0 += (positions[i1, k] - positions[i2, k]) ** 2
            l1 += (positions[i2, k] - positions[i0, k]) ** 2
            l2 += (positions[i0, k] - positions[i1, k]) ** 2
        # cyclic rotation keeps the winding
        if l1 > l0 and l1 >= l2:
            i0, i1, i2 = i1, i2, i0
        elif l2 > l0 and l2 > l1:
            i0, i1, i2 = i2, i0, i1
        for k in range(3):
            tri[j, k] = positions[i0, k]
            tri[j, 3 + k] = positions[i1, k]
            tri[j, 6 + k] = positions[i2, k]
            cent[j, k] = (positions[i0, k] + positions[i1, k] + positions[i2, k]) / 3.0
    return tri, cent


@numba.njit(cache=True, parallel=True)
def face_areas(positions, faces):
    m = faces.shape[0]
    area = np.empty(m)
    for j in numba.prange(m):
        a, b, c = positions[faces[j, 0]], positions[faces[j, 1]], positions[faces[j, 2]]
        ux, uy, uz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
        vx, vy, vz = c[0] - a[0], c[1] - a[1], c[2] - a[2]
        nx, ny, nz = cross(ux, uy, uz, vx, vy, vz)
        area[j] = 0.5 * np.sqrt(nx * nx + ny * ny + nz * nz)
    return area


@numba.njit(cache=True)
def _select(cent, perm, lo, hi, kth, axis):
    """Partial sort of rows lo..hi-1 of cent (and perm alongside) on one axis so
    row kth holds its sorted value (Hoare quickselect; copes with equal keys)."""
    hi -= 1
    while hi > lo:
        pivot = cent[(lo + hi) // 2, axis]
        i, j = lo, hi
        while i <= j:
            while cent[i, axis] < pivot:
                i += 1
            while cent[j, axis] > pivot:
                j -= 1
            if i <= j:
                for k in range(3):
                    cent[i, k], cent[j, k] = cent[j, k], cent[i, k]
                perm[i], perm[j] = perm[j], perm[i]
                i += 1
                j -= 1
        if kth <= j:
            hi = j
        elif kth >= i:
            lo = i
        else:
            break


@numba.njit(cache=True, parallel=True)
def _build_bvh(tri, cent, leaf_size):
    """Median-split BVH in breadth-first layout; siblings are adjacent (right =
    left + 1) so one visit reads both child boxes from the same cache lines.

    Returns (box (N, 6) lo/hi, child (N,) left index or -1 for a leaf,
    start (N,), count (N,) into the reordered triangle table, tri reordered,
    perm mapping reordered rows to original face indices).
    """
    m = tri.shape[0]
    cent = cent.copy()
    perm = np.arange(m)
    # each leaf keeps at least ceil(leaf_size / 2) triangles when m > leaf_size
    cap = 2 * (m // max(1, (leaf_size + 1) // 2)) + 3
    start = np.empty(cap, np.int64)
    count = np.empty(cap, np.int64)
    child = np.full(cap, -1, np.int64)
    start[0] = 0
    count[0] = m
    level_begin, level_end = 0, 1
    while level_begin < level_end:
        width = level_end - level_begin
        split = np.zeros(width, np.bool_)
        # nodes of one level own disjoint row ranges, so they partition in parallel
        for w in numba.prange(width):
            i = level_begin + w
            s, n = start[i], count[i]
            if n > leaf_size:
                lo0, lo1, lo2 = np.inf, np.inf, np.inf
                hi0, hi1, hi2 = -np.inf, -np.inf, -np.inf
                for r in range(s, s + n):
                    lo0 = min(lo0, cent[r, 0])
                    hi0 = max(hi0, cent[r, 0])
                    lo1 = min(lo1, cent[r, 1])
                    hi1 = max(hi1, cent[r, 1])
                    lo2 = min(lo2, cent[r, 2])
                    hi2 = max(hi2, cent[r, 2])
                e0, e1, e2 = hi0 - lo0, hi1 - lo1, hi2 - lo2
                axis = 0
                if e1 > e0 and e1 >= e2:
                    axis = 1
                elif e2 > e0 and e2 > e1:
                    axis = 2
                _select(cent, perm, s, s + n, s + n // 2, axis)
                split[w] = True
        nxt = level_end
        for w in range(width):
            if split[w]:
                i = level_begin + w
                s, n = start[i], count[i]
                child[i] = nxt
                start[nxt] = s
                count[nxt] = n // 2
                start[nxt + 1] = s + n // 2
                count[nxt + 1] = n - n // 2
                nxt += 2
        level_begin, level_end = level_end, nxt
    total = level_end
    start = start[:total]
    count = count[:total]
    child = child[:total]

    sorted_tri = np.empty_like(tri)
    for r in numba.prange(m):
        sorted_tri[r] = tri[perm[r]]

    box = np.empty((total, 6))
    for i in numba.prange(total):
        if child[i] < 0:
            for k in range(3):
                lo = np.inf
                hi = -np.inf
                for r in range(start[i], start[i] + count[i]):
                    for c in range(3):
                        v = sorted_tri[r, 3 * c + k]
                        lo = min(lo, v)
                        hi = max(hi, v)
                box[i, k] = lo
                box[i, 3 + k] = hi
    # children come after their parent in breadth-first order
    for i in range(total - 1, -1, -1):
        c = child[i]
        if c >= 0:
            for k in range(3):
                box[i, k] = min(box[c, k], box[c + 1, k])
                box[i, 3 + k] = max(box[c, 3 + k], box[c + 1, 3 + k])
    return box, child, start, count, sorted_tri, perm


@numba.njit(cache=True, inline="always")
def _box_distance2(box, i, px, py, pz):
    # per axis: how far p lies outside [lo, hi] (0 inside)
    dx = max(box[i, 0] - px, 0.0, px - box[i, 3])
    dy = max(box[i, 1] - py, 0.0, py - box[i, 4])
    dz = max(box[i, 2] - pz, 0.0, pz - box[i, 5])
    return dx * dx + dy * dy + dz * dz


@numba.njit(cache=True, parallel=True)
def _nearest(points, box, child, start, count, tri, perm, chunk):
    """Nearest triangle per point: depth-first branch and bound, nearer child
    first, pruning any box no closer than the best triangle found so far.

    Returns squared distances (k,), original face indices (k,) and the closest
    points (k, 3).
    """
    k = points.shape[0]
    dist2 = np.empty(k)
    face = np.empty(k, np.int64)
    closest = np.empty((k, 3))
    chunks = (k + chunk - 1) // chunk
    for c in numba.prange(chunks):
        stack_node = np.empty(_STACK, np.int64)
        stack_d2 = np.empty(_STACK)
        for q in range(c * chunk, min(k, (c + 1) * chunk)):
            px, py, pz = points[q, 0], points[q, 1], points[q, 2]
            best = np.inf
            best_j = -1
            bx = by = bz = 0.0
            stack_node[0] = 0
            stack_d2[0] = _box_distance2(box, 0, px, py, pz)
            sp = 1
            while sp > 0:
                sp -= 1
                if stack_d2[sp] >= best:
                    continue
                node = stack_node[sp]
                left = child[node]
                if left < 0:
                    for j in range(start[node], start[node] + count[node]):
                        d2, qx, qy, qz = _closest_on_triangle(px, py, pz, tri, j)
                        if d2 < best:
                            best, best_j, bx, by, bz = d2, j, qx, qy, qz
                else:
                    dl = _box_distance2(box, left, px, py, pz)
                    dr = _box_distance2(box, left + 1, px, py, pz)
                    # push the farther child first so the nearer one is popped next
                    if dl <= dr:
                        near, far, dn, df = left, left + 1, dl, dr
                    else:
                        near, far, dn, df = left + 1, left, dr, dl
                    if df < best:
                        stack_node[sp] = far
                        stack_d2[sp] = df
                        sp += 1
                    if dn < best:
                        stack_node[sp] = near
                        stack_d2[sp] = dn
                        sp += 1
            dist2[q] = best
            face[q] = perm[best_j]
            closest[q, 0] = bx
            closest[q, 1] = by
            closest[q, 2] = bz
    return dist2, face, closest


# ---------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------


def as_mesh(mesh) -> Mesh:
    if isinstance(mesh, Mesh):
        return mesh
    if isinstance(mesh, tuple) and len(mesh) == 2:
        return Mesh(*mesh)  # validates shapes, finiteness and index range
    raise TypeError(
        f"expected a Mesh or a (positions, faces) tuple, got {type(mesh).__name__}"
    )


def used_diagonal(mesh: Mesh) -> float:
    used = np.zeros(len(mesh.positions), dtype=bool)
    used[mesh.faces.ravel()] = True  # cheaper than np.unique on millions of indices
    p = mesh.positions[used]
    return float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))


def _morton_order(points: np.ndarray) -> np.ndarray:
    """Order along a Z-curve, so consecutive queries walk the same BVH branches."""
    lo, span = unit_box(points)
    cells = ((points - lo) * ((2**21 - 1) / span)).astype(np.uint64)
    code = np.zeros(len(points), dtype=np.uint64)
    for axis in range(3):
        x = cells[:, axis]
        # spread 21 bits so two zero bits follow each one
        x = (x | (x << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
        x = (x | (x << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
        x = (x | (x << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
        x = (x | (x << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
        x = (x | (x << np.uint64(2))) & np.uint64(0x1249249249249249)
        code |= x << np.uint64(axis)
    return np.argsort(code, kind="stable")


def nearest_on_mesh(points, mesh: Mesh):
    """(squared distance, face index, closest point) for each point: the public
    wrappers' shared core, kept for judges that need the point itself."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (k, 3), got {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("points must be finite")
    if len(points) == 0:
        return np.empty(0), np.empty(0, np.int64), np.empty((0, 3))
    tri, cent = _triangle_table(mesh.positions, mesh.faces)
    box, child, start, count, tri, perm = _build_bvh(tri, cent, _LEAF_SIZE)
    order = _morton_order(points)
    d2, face, closest = _nearest(
        points[order], box, child, start, count, tri, perm, _CHUNK
    )
    inverse = np.empty_like(order)
    inverse[order] = np.arange(len(order))
    return d2[inverse], face[inverse], closest[inverse]
