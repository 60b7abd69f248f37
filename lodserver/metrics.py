"""Geometric error between two triangle meshes: the judge for simplifiers.

The benchmark compares our output with meshoptimizer, pymeshlab and
fast-simplification through :func:`surface_distance` alone, so every number it
reports comes from the same samples and the same exact distance code.

- :func:`sample_surface` draws area-weighted uniform points on a surface.
- :func:`point_to_mesh_distance` gives the exact Euclidean distance from points
  to the nearest point on any triangle (not the nearest vertex), through a
  bounding-volume hierarchy queried in parallel.
- :func:`surface_distance` combines them into the two-sided metric.

Degenerate (zero-area) triangles get no samples but still count as surface
(a segment or a point) when distances are measured to them. Unreferenced
vertices are ignored everywhere, including in the bounding-box diagonal.
"""

from __future__ import annotations

import numba
import numpy as np

from .mesh import Mesh

__all__ = [
    "sample_surface",
    "point_to_mesh_distance",
    "surface_distance",
    "attribute_deviation",
]

# Triangles per BVH leaf: small leaves prune well; fewer than 4 only deepens the tree.
_LEAF_SIZE = 4
# A triangle whose largest angle has sin below this is treated as its three edges:
# its height is then < 1e-8 of its edges, which is also about the error the
# plane-based face test would make on such a flat cap (eps / sin).
_FLAT_SIN2 = 1e-16
# Query points per parallel work item; each item owns its traversal stack.
_CHUNK = 256
# Stack depth: a median-split tree over 2**62 triangles is still only ~62 levels.
_STACK = 128


# ---------------------------------------------------------------------------
# Kernels (plain arrays in, no validation)
# ---------------------------------------------------------------------------


@numba.njit(cache=True, inline="always")
def _closest_on_segment(px, py, pz, ux, uy, uz, vx, vy, vz):
    dx, dy, dz = vx - ux, vy - uy, vz - uz
    den = dx * dx + dy * dy + dz * dz
    t = 0.0
    if den > 0.0:  # a zero-length segment is its start point
        t = ((px - ux) * dx + (py - uy) * dy + (pz - uz) * dz) / den
        t = min(max(t, 0.0), 1.0)
    qx, qy, qz = ux + t * dx, uy + t * dy, uz + t * dz
    ex, ey, ez = px - qx, py - qy, pz - qz
    return ex * ex + ey * ey + ez * ez, qx, qy, qz


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
    nx = aby * acz - abz * acy
    ny = abz * acx - abx * acz
    nz = abx * acy - aby * acx
    nn = nx * nx + ny * ny + nz * nz
    abab = abx * abx + aby * aby + abz * abz
    acac = acx * acx + acy * acy + acz * acz
    out_ab = True
    out_bc = True
    out_ca = True
    if nn > _FLAT_SIN2 * abab * acac:
        apx, apy, apz = px - ax, py - ay, pz - az
        # side of edge ab: n . (ab x ap)
        s_ab = (
            nx * (aby * apz - abz * apy)
            + ny * (abz * apx - abx * apz)
            + nz * (abx * apy - aby * apx)
        )
        bcx, bcy, bcz = cx - bx, cy - by, cz - bz
        bpx, bpy, bpz = px - bx, py - by, pz - bz
        s_bc = (
            nx * (bcy * bpz - bcz * bpy)
            + ny * (bcz * bpx - bcx * bpz)
            + nz * (bcx * bpy - bcy * bpx)
        )
        # edge ca = -ac, cp = ap - ac
        cpx, cpy, cpz = px - cx, py - cy, pz - cz
        s_ca = -(
            nx * (acy * cpz - acz * cpy)
            + ny * (acz * cpx - acx * cpz)
            + nz * (acx * cpy - acy * cpx)
        )
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
        d2, sx, sy, sz = _closest_on_segment(px, py, pz, ax, ay, az, bx, by, bz)
        if d2 < best:
            best, qx, qy, qz = d2, sx, sy, sz
    if out_bc:
        d2, sx, sy, sz = _closest_on_segment(px, py, pz, bx, by, bz, cx, cy, cz)
        if d2 < best:
            best, qx, qy, qz = d2, sx, sy, sz
    if out_ca:
        d2, sx, sy, sz = _closest_on_segment(px, py, pz, cx, cy, cz, ax, ay, az)
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
def _face_areas(positions, faces):
    m = faces.shape[0]
    area = np.empty(m)
    for j in numba.prange(m):
        a, b, c = positions[faces[j, 0]], positions[faces[j, 1]], positions[faces[j, 2]]
        ux, uy, uz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
        vx, vy, vz = c[0] - a[0], c[1] - a[1], c[2] - a[2]
        nx = uy * vz - uz * vy
        ny = uz * vx - ux * vz
        nz = ux * vy - uy * vx
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


def _as_mesh(mesh) -> Mesh:
    if isinstance(mesh, Mesh):
        return mesh
    if isinstance(mesh, tuple) and len(mesh) == 2:
        return Mesh(*mesh)  # validates shapes, finiteness and index range
    raise TypeError(
        f"expected a Mesh or a (positions, faces) tuple, got {type(mesh).__name__}"
    )


def _used_diagonal(mesh: Mesh) -> float:
    used = np.zeros(len(mesh.positions), dtype=bool)
    used[mesh.faces.ravel()] = True  # cheaper than np.unique on millions of indices
    p = mesh.positions[used]
    return float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))


def _morton_order(points: np.ndarray) -> np.ndarray:
    """Order along a Z-curve, so consecutive queries walk the same BVH branches."""
    lo = points.min(axis=0)
    span = float((points.max(axis=0) - lo).max()) or 1.0
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


def _nearest_on_mesh(points, mesh: Mesh):
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


def sample_surface(positions, faces, count, *, seed=0) -> np.ndarray:
    """``count`` points drawn uniformly over the surface area, shape (count, 3).

    Each point picks a face with probability proportional to its area, then a
    uniform point on it: with r1, r2 ~ U[0, 1) and s = sqrt(r1), the point is
    (1 - s) a + s (1 - r2) b + s r2 c. Zero-area faces are never picked.
    ``seed`` is anything :func:`numpy.random.default_rng` accepts; the same seed
    gives the same points. Raises ValueError if the surface has zero area.
    """
    return _sample(_as_mesh((positions, faces)), count, seed)


def _sample(mesh: Mesh, count, seed) -> np.ndarray:
    face, s, r2 = _sample_parameters(mesh, count, seed)
    corners = mesh.faces[face]
    a, b, c = (mesh.positions[corners[:, k]] for k in range(3))
    return (1.0 - s) * a + s * (1.0 - r2) * b + s * r2 * c


def _sample_barycentric(mesh: Mesh, count, seed):
    """:func:`sample_surface`'s points (k, 3), the same for the same seed, with
    the face each lies on (k,) and its barycentric weights (k, 3) on that
    face's corners."""
    face, s, r2 = _sample_parameters(mesh, count, seed)
    corners = mesh.faces[face]
    a, b, c = (mesh.positions[corners[:, k]] for k in range(3))
    points = (1.0 - s) * a + s * (1.0 - r2) * b + s * r2 * c
    bary = np.concatenate([1.0 - s, s * (1.0 - r2), s * r2], axis=1)
    return points, face, bary


def _sample_parameters(mesh: Mesh, count, seed):
    """The face (k,) and the (k, 1) columns s, r2 of each sample (see
    :func:`sample_surface`)."""
    count = int(count)
    if count < 0:
        raise ValueError(f"count must be >= 0, got {count}")
    rng = np.random.default_rng(seed)
    area = _face_areas(mesh.positions, mesh.faces)
    cdf = np.cumsum(area)
    total = cdf[-1]
    if not total > 0.0:
        raise ValueError("the surface has zero area: nothing to sample")
    # side="right" skips zero-area faces (their cdf step is empty); the clip
    # catches u * total rounding up to total, landing on the last positive face
    last = int(np.flatnonzero(area > 0.0)[-1])
    pick = np.searchsorted(cdf, rng.random(count) * total, side="right")
    face = np.minimum(pick, last)
    r1, r2 = rng.random(count), rng.random(count)
    return face, np.sqrt(r1)[:, None], r2[:, None]


def point_to_mesh_distance(points, positions, faces) -> np.ndarray:
    """Exact Euclidean distance, shape (k,), from each point to the nearest point
    on any triangle of (positions, faces): interiors, edges and corners alike,
    not merely the nearest vertex. Degenerate triangles count as the segment or
    point they collapse to.
    """
    mesh = _as_mesh((positions, faces))
    d2, _, _ = _nearest_on_mesh(points, mesh)
    return np.sqrt(d2)


def _judged(reference, candidate, samples):
    """The two meshes as ``Mesh``, the sample count checked, and the reference's
    used bounding-box diagonal (errors are reported relative to it)."""
    reference = _as_mesh(reference)
    candidate = _as_mesh(candidate)
    samples = int(samples)
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    diagonal = _used_diagonal(reference)
    if not diagonal > 0.0:
        raise ValueError("the reference mesh has a zero bounding-box diagonal")
    return reference, candidate, samples, diagonal


def surface_distance(reference, candidate, *, samples=200_000, seed=0) -> dict:
    """Two-sided surface distance between a reference mesh and a candidate.

    Both arguments are :class:`~lodserver.mesh.Mesh` objects or
    ``(positions, faces)`` tuples. What is computed:

    1. ``samples`` area-weighted uniform points on the reference surface
       (:func:`sample_surface`), and ``samples`` on the candidate surface, from
       two independent streams spawned from ``seed`` (the reference's points
       depend only on the reference and the seed, so candidates compared with
       one reference are all measured from the same points).
    2. For each reference point the exact Euclidean distance to the nearest
       point on any candidate triangle (:func:`point_to_mesh_distance`), giving
       d_ab; for each candidate point the distance to the reference, d_ba.
    3. Everything is divided by ``diagonal``, the length of the axis-aligned
       bounding-box diagonal of the reference vertices used by its faces.

    Returns a dict of floats:

    - ``rms_ab`` = sqrt(mean(d_ab**2)) / diagonal  (reference -> candidate)
    - ``rms_ba`` = sqrt(mean(d_ba**2)) / diagonal  (candidate -> reference)
    - ``rms`` = sqrt(mean of d**2 over both sets pooled) / diagonal, i.e.
      sqrt((rms_ab**2 + rms_ba**2) / 2) since both sets have ``samples`` points
    - ``hausdorff_ab`` = max(d_ab) / diagonal, ``hausdorff_ba`` = max(d_ba) / diagonal
    - ``hausdorff`` = max(hausdorff_ab, hausdorff_ba)
    - ``diagonal`` = the reference diagonal, in mesh units

    The Hausdorff values are the maximum over the samples, so they estimate
    (from below) the true Hausdorff distance. Degenerate faces of either mesh
    get no samples but are still surface that distances are measured to;
    unreferenced vertices play no part. Raises ValueError if either surface has
    zero area or the reference diagonal is zero.
    """
    reference, candidate, samples, diagonal = _judged(reference, candidate, samples)
    seed_ref, seed_cand = np.random.SeedSequence(seed).spawn(2)
    on_ref = _sample(reference, samples, seed_ref)
    on_cand = _sample(candidate, samples, seed_cand)
    d2_ab, _, _ = _nearest_on_mesh(on_ref, candidate)
    d2_ba, _, _ = _nearest_on_mesh(on_cand, reference)
    ms_ab, ms_ba = float(d2_ab.mean()), float(d2_ba.mean())
    h_ab, h_ba = float(np.sqrt(d2_ab.max())), float(np.sqrt(d2_ba.max()))
    return {
        "rms": float(np.sqrt(0.5 * (ms_ab + ms_ba))) / diagonal,
        "hausdorff": max(h_ab, h_ba) / diagonal,
        "rms_ab": float(np.sqrt(ms_ab)) / diagonal,
        "rms_ba": float(np.sqrt(ms_ba)) / diagonal,
        "hausdorff_ab": h_ab / diagonal,
        "hausdorff_ba": h_ba / diagonal,
        "diagonal": diagonal,
    }


# ---------------------------------------------------------------------------
# Appearance: attributes compared at corresponding surface points
# ---------------------------------------------------------------------------

# Attributes attribute_deviation always reports (None where it cannot compare).
_COMPARED = ("NORMAL", "TEXCOORD_0", "TEXCOORD_1", "COLOR_0")


@numba.njit(cache=True, parallel=True)
def _closest_barycentrics(positions, faces, face, closest):
    """(k, 3) barycentric weights, on the corners of ``faces[face[q]]`` in their
    stored order, of the point ``closest[q]``, which lies on that triangle.

    Weights come from cross products against the face normal (first-order
    accurate, unlike the Gram-matrix form); rounding just outside the triangle
    is clamped and the weights renormalised. A flat triangle (the distance
    kernel's test) has the point on one of its edges: the nearest edge gives
    the weights.
    """
    k = face.shape[0]
    out = np.empty((k, 3))
    for q in numba.prange(k):
        f = face[q]
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        ax, ay, az = positions[i0, 0], positions[i0, 1], positions[i0, 2]
        e0x, e0y, e0z = positions[i1, 0] - ax, positions[i1, 1] - ay, positions[i1, 2] - az
        e1x, e1y, e1z = positions[i2, 0] - ax, positions[i2, 1] - ay, positions[i2, 2] - az
        px, py, pz = closest[q, 0] - ax, closest[q, 1] - ay, closest[q, 2] - az
        nx = e0y * e1z - e0z * e1y
        ny = e0z * e1x - e0x * e1z
        nz = e0x * e1y - e0y * e1x
        nn = nx * nx + ny * ny + nz * nz
        l0 = e0x * e0x + e0y * e0y + e0z * e0z
        l1 = e1x * e1x + e1y * e1y + e1z * e1z
        w0 = w1 = w2 = 0.0
        if nn > _FLAT_SIN2 * l0 * l1 and nn > 0.0:
            # p = w1 e0 + w2 e1: n . (p x e1) = w1 nn, n . (e0 x p) = w2 nn
            w1 = (nx * (py * e1z - pz * e1y) + ny * (pz * e1x - px * e1z)
                  + nz * (px * e1y - py * e1x)) / nn
            w2 = (nx * (e0y * pz - e0z * py) + ny * (e0z * px - e0x * pz)
                  + nz * (e0x * py - e0y * px)) / nn
            w1 = min(max(w1, 0.0), 1.0)
            w2 = min(max(w2, 0.0), 1.0)
            w0 = max(1.0 - w1 - w2, 0.0)
            total = w0 + w1 + w2
            w0, w1, w2 = w0 / total, w1 / total, w2 / total
        else:
            best = np.inf
            for edge in range(3):
                # edge from corner u to corner v, as offsets from corner 0
                if edge == 0:
                    ux, uy, uz, vx, vy, vz = 0.0, 0.0, 0.0, e0x, e0y, e0z
                elif edge == 1:
                    ux, uy, uz, vx, vy, vz = e0x, e0y, e0z, e1x, e1y, e1z
                else:
                    ux, uy, uz, vx, vy, vz = e1x, e1y, e1z, 0.0, 0.0, 0.0
                d2, sx, sy, sz = _closest_on_segment(px, py, pz, ux, uy, uz, vx, vy, vz)
                if d2 < best:
                    best = d2
                    dx, dy, dz = vx - ux, vy - uy, vz - uz
                    den = dx * dx + dy * dy + dz * dz
                    t = 0.0
                    if den > 0.0:
                        t = ((sx - ux) * dx + (sy - uy) * dy + (sz - uz) * dz) / den
                        t = min(max(t, 0.0), 1.0)
                    if edge == 0:
                        w0, w1, w2 = 1.0 - t, t, 0.0
                    elif edge == 1:
                        w0, w1, w2 = 0.0, 1.0 - t, t
                    else:
                        w0, w1, w2 = t, 0.0, 1.0 - t
        out[q, 0] = w0
        out[q, 1] = w1
        out[q, 2] = w2
    return out


@numba.njit(cache=True, parallel=True)
def _interpolate(values, corners, face, bary, lo, hi):
    """(k, hi - lo): columns lo..hi-1 of the wedge values, blended over each
    point's face corners with its barycentric weights."""
    k = face.shape[0]
    out = np.zeros((k, hi - lo))
    for q in numba.prange(k):
        f = face[q]
        for c in range(3):
            w = bary[q, c]
            row = corners[f, c]
            for j in range(lo, hi):
                out[q, j - lo] += w * values[row, j]
    return out


@numba.njit(cache=True, parallel=True)
def _sample_texture(image, uv):
    """(k, c) bilinear texture lookups at glTF UVs (u right, v down from the
    top-left corner), texel centres at half-integers, REPEAT wrapping."""
    h, w, channels = image.shape
    k = uv.shape[0]
    out = np.empty((k, channels))
    for q in numba.prange(k):
        x = uv[q, 0] * w - 0.5
        y = uv[q, 1] * h - 0.5
        fx, fy = np.floor(x), np.floor(y)
        tx, ty = x - fx, y - fy
        x0 = int(fx) % w
        y0 = int(fy) % h
        x1 = (x0 + 1) % w
        y1 = (y0 + 1) % h
        for c in range(channels):
            top = (1.0 - tx) * image[y0, x0, c] + tx * image[y0, x1, c]
            bottom = (1.0 - tx) * image[y1, x0, c] + tx * image[y1, x1, c]
            out[q, c] = (1.0 - ty) * top + ty * bottom
    return out


def _error_stats(errors_ab: np.ndarray, errors_ba: np.ndarray) -> dict:
    """RMS, median, 99th percentile and maximum of per-sample errors, pooled
    over both directions, plus each direction's RMS."""
    pooled = np.concatenate([errors_ab, errors_ba])
    if len(pooled) == 0:
        return None

    def rms(e):
        return float(np.sqrt(np.mean(e * e))) if len(e) else None

    return {
        "rms": rms(pooled),
        "p50": float(np.percentile(pooled, 50)),
        "p99": float(np.percentile(pooled, 99)),
        "max": float(pooled.max()),
        "rms_ab": rms(errors_ab),
        "rms_ba": rms(errors_ba),
    }


def _angle_degrees(n1: np.ndarray, n2: np.ndarray):
    """Angles between the renormalised rows, and the mask of rows where both
    are long enough to have a direction."""
    l1 = np.linalg.norm(n1, axis=1)
    l2 = np.linalg.norm(n2, axis=1)
    ok = (l1 > 1e-12) & (l2 > 1e-12)
    a = n1[ok] / l1[ok, None]
    b = n2[ok] / l2[ok, None]
    # atan2(|a x b|, a . b) keeps small angles accurate, unlike acos
    angle = np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), (a * b).sum(axis=1)))
    return angle, ok


def _texture_array(texture) -> np.ndarray:
    image = np.asarray(texture)
    if image.ndim == 2:
        image = image[:, :, None]
    if image.ndim != 3 or image.shape[0] < 1 or image.shape[1] < 1 or image.shape[2] < 1:
        raise ValueError(f"texture must have shape (h, w) or (h, w, c), got {np.shape(texture)}")
    # RGB(A): compare the colour channels only; alpha is coverage, not colour
    return np.ascontiguousarray(image[:, :, : min(3, image.shape[2])], dtype=np.float64)


def attribute_deviation(reference, candidate, *, samples=100_000, seed=0, texture=None) -> dict:
    """How far a candidate mesh's surface and appearance attributes are from a
    reference's, at corresponding surface points.

    Both arguments are :class:`~lodserver.mesh.Mesh` objects (or ``(positions,
    faces)`` tuples, which have no attributes). What is computed, in each
    direction (reference -> candidate, then candidate -> reference):

    1. ``samples`` area-weighted uniform points on the source surface, from the
       same two seed streams as :func:`surface_distance` (so the geometric
       figures equal ``surface_distance(reference, candidate, samples=samples,
       seed=seed)`` exactly), each with the source's attributes interpolated
       barycentrically over its face's corners (``values[corners]``).
    2. The closest point on the other surface (the same exact BVH search), its
       barycentric weights on the triangle it lies on, and the other mesh's
       attributes interpolated there.
    3. Per sample, the difference, pooled over both directions.

    Returns a dict:

    - ``samples`` (per direction), ``diagonal`` (the reference's, as in
      :func:`surface_distance`).
    - ``geometry``: ``rms``, ``hausdorff`` and the one-sided ``rms_ab``,
      ``rms_ba``, ``hausdorff_ab``, ``hausdorff_ba``, as fractions of the
      diagonal: :func:`surface_distance`'s figures.
    - ``NORMAL``, ``TEXCOORD_0``, ``TEXCOORD_1``, ``COLOR_0``: None unless both
      meshes carry that attribute; otherwise ``rms``, ``p50``, ``p99``,
      ``max`` of the per-sample error pooled over both directions, and the
      one-sided ``rms_ab``, ``rms_ba``. The error is the UV distance (UV
      units) for texture coordinates; the angle in degrees between the
      renormalised normals for ``NORMAL`` (samples where either normal has
      zero length are left out and counted in ``excluded``); the RMS over the
      four channels of the RGBA difference for ``COLOR_0``.
    - ``texture``: None unless ``texture`` is given and both meshes have
      ``TEXCOORD_0``; otherwise the same statistics of the colour difference
      (RMS over its first three channels, in the image's units: 8-bit levels
      for a uint8 image) between ``texture`` looked up bilinearly at the two
      points' UVs (glTF convention: origin top-left, v down; REPEAT wrap). This
      is what a viewer sees of a base-colour texture, and it forgives UV
      differences that land on the same texels.

    Near a UV seam the closest point may legitimately lie in the other chart,
    where the UVs differ a lot and the texture colour not at all, and near a
    hard edge on the other side of the crease: ``max`` reports those, ``p99``
    is the figure robust to them. Raises ValueError like
    :func:`surface_distance`.
    """
    reference, candidate, samples, diagonal = _judged(reference, candidate, samples)
    image = None if texture is None else _texture_array(texture)
    seed_ref, seed_cand = np.random.SeedSequence(seed).spawn(2)

    ra, ca = reference.attributes, candidate.attributes
    shared = []
    if ra is not None and ca is not None:
        shared = [name for name in _COMPARED
                  if ra.columns(name) is not None and ca.columns(name) is not None]

    def one_way(source, source_seed, target):
        """Squared distances and, per shared attribute, (source, target) values."""
        points, face, bary = _sample_barycentric(source, samples, source_seed)
        d2, target_face, closest = _nearest_on_mesh(points, target)
        values = {}
        if shared:
            target_bary = _closest_barycentrics(target.positions, target.faces,
                                                target_face, closest)
            for name in shared:
                pair = []
                for mesh, f, b in ((source, face, bary), (target, target_face, target_bary)):
                    cols = mesh.attributes.columns(name)
                    pair.append(_interpolate(mesh.attributes.values, mesh.attributes.corners,
                                             f, b, cols.start, cols.stop))
                values[name] = pair
        return d2, values

    d2_ab, values_ab = one_way(reference, seed_ref, candidate)
    d2_ba, values_ba = one_way(candidate, seed_cand, reference)
    ms_ab, ms_ba = float(d2_ab.mean()), float(d2_ba.mean())
    h_ab, h_ba = float(np.sqrt(d2_ab.max())), float(np.sqrt(d2_ba.max()))
    report = {
        "samples": samples,
        "diagonal": diagonal,
        "geometry": {
            "rms": float(np.sqrt(0.5 * (ms_ab + ms_ba))) / diagonal,
            "hausdorff": max(h_ab, h_ba) / diagonal,
            "rms_ab": float(np.sqrt(ms_ab)) / diagonal,
            "rms_ba": float(np.sqrt(ms_ba)) / diagonal,
            "hausdorff_ab": h_ab / diagonal,
            "hausdorff_ba": h_ba / diagonal,
        },
    }
    for name in _COMPARED:
        report[name] = None
    report["texture"] = None
    for name in shared:
        (a_src, a_dst), (b_src, b_dst) = values_ab[name], values_ba[name]
        if name == "NORMAL":
            e_ab, ok_ab = _angle_degrees(a_src, a_dst)
            e_ba, ok_ba = _angle_degrees(b_src, b_dst)
            stats = _error_stats(e_ab, e_ba)
            if stats is not None:
                stats["excluded"] = int((~ok_ab).sum() + (~ok_ba).sum())
        elif name.startswith("TEXCOORD"):
            stats = _error_stats(np.linalg.norm(a_src - a_dst, axis=1),
                                 np.linalg.norm(b_src - b_dst, axis=1))
        else:
            stats = _error_stats(np.sqrt(((a_src - a_dst) ** 2).mean(axis=1)),
                                 np.sqrt(((b_src - b_dst) ** 2).mean(axis=1)))
        report[name] = stats
    if image is not None and "TEXCOORD_0" in shared:
        errors = []
        for src, dst in (values_ab["TEXCOORD_0"], values_ba["TEXCOORD_0"]):
            diff = _sample_texture(image, src) - _sample_texture(image, dst)
            errors.append(np.sqrt((diff * diff).mean(axis=1)))
        report["texture"] = _error_stats(*errors)
    return report
