"""Garland–Heckbert error quadrics as plain arrays.

A quadric measures the sum of weighted squared distances from a point ``p`` to
a set of planes ``n . p + d = 0``::

    Q(p) = p^T A p + 2 b . p + c        A = sum w n n^T,  b = sum w d n,  c = sum w d^2

It is stored as one row of 11 float64 (``QUADRIC_SIZE``)::

    [a00, a01, a02, a11, a12, a22, b0, b1, b2, c, area]

``area`` is the total face area folded into the quadric (boundary planes add
none); ``Q(p) / area`` is then a mean squared distance, whose square root is the
error lodserver reports in mesh units.

Face quadrics are weighted by triangle area (units: length^4 for ``Q``) so the
metric does not depend on how finely a region happens to be tessellated.
Boundary edges add a plane through the edge, perpendicular to its face, weighted
by ``boundary_weight * |edge|^2`` so it has the same units as the face terms.

Reference: M. Garland and P. Heckbert, "Surface Simplification Using Quadric
Error Metrics", SIGGRAPH 1997, sections 4 and 5.

Appearance attributes (Hoppe, "New quadric metric for simplifying meshes with
appearance attributes", IEEE Visualization 1999): on each face every attribute
scalar ``s_j`` is fitted by a linear field ``g_j . p + d_j`` (``g_j`` in the
face plane), and a wedge sums ``area * (g_j . p + d_j - s_j)^2`` over its
faces. Expanded, that is the geometric quadric's form plus, per scalar, one
gradient and one offset, so a wedge quadric row has ``11 + 4 d`` entries
instead of the ``(4 + d)(5 + d) / 2`` of a dense quadric over ``(p, s)``::

    [a00, a01, a02, a11, a12, a22, b0, b1, b2, c, area, (G_j (3), D_j) for j < d]

with ``A = sum area g g^T``, ``b = sum area d g``, ``c = sum area d^2`` (summed
over faces and scalars), ``G_j = sum area g_j`` and ``D_j = sum area d_j``:

    E(p, s) = p^T A p + 2 b . p + c - 2 sum_j s_j (G_j . p + D_j) + area |s|^2

For a given ``p`` the best ``s_j`` is ``(G_j . p + D_j) / area``; putting it
back gives a plain 3D quadric (``add_reduced``), so position and attributes are
solved together with the same 3x3 solve as geometry alone.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ..mesh import read_only
from .state import NO_REFCOUNT

QUADRIC_SIZE = 11


def wedge_quadric_size(width: int) -> int:
    """Entries in a wedge quadric row for ``width`` attribute scalars."""
    return QUADRIC_SIZE + 4 * width

# Placement solves (A + eps I) p = eps m - b with eps = REGULARIZATION * trace(A):
# a Tikhonov pull towards the edge midpoint m. Where A has curvature (eigenvalue
# >> eps) the optimum is unchanged to ~1e-6 relative; along directions where it
# has none (a flat patch, a crease line) p stays at m instead of running off to
# where rounding noise puts it. Same effect as Lindstrom's truncated-SVD
# placement, at the cost of one 3x3 Cramer solve and no eigen-decomposition.
REGULARIZATION = 1e-6
# Below this det(A) / trace(A)^3 (scale-free, at most 1/27) the system counts as
# singular and G&H's candidates (endpoints, midpoint) are compared as well.
DET_RELATIVE_EPS = 1e-7


def plane_quadrics(normals, offsets, weights, areas):
    """Quadrics of weighted planes ``n . p + d = 0``.

    Parameters
    ----------
    normals : (k, 3) float
        Unit plane normals.
    offsets : (k,) float
        Plane offsets ``d``.
    weights : (k,) float
        Weight of each plane (area for face planes).
    areas : (k,) float
        Area to record in the ``area`` column.

    Returns
    -------
    (k, 11) float64
    """
    n = np.asarray(normals, dtype=np.float64)
    d = np.asarray(offsets, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    q = np.empty((len(n), QUADRIC_SIZE), dtype=np.float64)
    q[:, 0] = w * n[:, 0] * n[:, 0]
    q[:, 1] = w * n[:, 0] * n[:, 1]
    q[:, 2] = w * n[:, 0] * n[:, 2]
    q[:, 3] = w * n[:, 1] * n[:, 1]
    q[:, 4] = w * n[:, 1] * n[:, 2]
    q[:, 5] = w * n[:, 2] * n[:, 2]
    q[:, 6:9] = (w * d)[:, None] * n
    q[:, 9] = w * d * d
    q[:, 10] = areas
    return q


def vertex_quadrics(positions, faces, *, boundary_weight=1.0, boundary=None, seams=None,
                    seam_weight=1.0):
    """Sum of face and boundary-constraint quadrics at every vertex.

    Parameters
    ----------
    positions : (n, 3) float
    faces : (m, 3) int
    boundary_weight : float
        Weight of the plane perpendicular to each boundary edge, relative to a
        face of area ``|edge|^2``. 0 leaves borders free to shrink.
    boundary : (edges (k, 2), faces (k,)), optional
        Boundary edges in face winding and their faces, if already known
        (``topology.census``); found here otherwise.
    seams : (edges (k, 2), faces (k,)), optional
        Attribute seams (``seam_edges``), one row per side: each gets the same
        perpendicular plane as a border, weighted by ``seam_weight``, so a
        seam keeps its place on the surface as it is simplified.

    Returns
    -------
    (n, 11) float64
    """
    positions = read_only(positions, np.float64)
    faces = read_only(faces, np.int64)
    q = np.zeros((len(positions), QUADRIC_SIZE), dtype=np.float64)
    # Each face's quadric goes to its three corners (G&H sum over incident planes).
    _accumulate_face_quadrics(positions, faces, q)
    if boundary_weight > 0:
        if boundary is None:
            from .topology import census
            found = census(faces, len(positions))
            boundary = (found.boundary_edges, found.boundary_faces)
        add_edge_planes(q, positions, faces, *boundary, boundary_weight)
    if seams is not None and seam_weight > 0:
        add_edge_planes(q, positions, faces, *seams, seam_weight)
    return q


def add_edge_planes(q, positions, faces, edges, edge_faces, weight):
    """Add to both ends of every edge the plane through it perpendicular to its face."""
    if not len(edges):
        return
    a, b = positions[edges[:, 0]], positions[edges[:, 1]]
    along = b - a
    tri = positions[faces[edge_faces]]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    # The constraint plane contains the edge and the face normal, so it
    # penalises motion across the edge but not along it or off the surface.
    perp = np.cross(along, normals)
    length = np.linalg.norm(perp, axis=1)
    ok = length > 0
    perp = perp[ok] / length[ok, None]
    w = weight * np.einsum("ij,ij->i", along[ok], along[ok])
    bq = plane_quadrics(perp, -np.einsum("ij,ij->i", perp, a[ok]), w, np.zeros(len(perp)))
    _scatter_add(q, edges[ok, 0], bq)
    _scatter_add(q, edges[ok, 1], bq)


def seam_edges(faces, corners):
    """Edges where the wedges on the two sides differ: UV seams, hard edges,
    material borders.

    Parameters
    ----------
    faces : (m, 3) int
    corners : (m, 3) int
        The wedge of every face corner.

    Returns
    -------
    edges : (k, 2) int64
        One row per side of a seam, in that side's face winding.
    edge_faces : (k,) int64
        The face on that side.

    Only edges with exactly two faces, wound oppositely, are considered:
    borders and non-manifold edges have constraints of their own.
    """
    faces = np.asarray(faces, dtype=np.int64)
    corners = np.asarray(corners, dtype=np.int64)
    m = len(faces)
    u = faces.ravel()
    v = faces[:, [1, 2, 0]].ravel()
    wu = corners.ravel()
    wv = corners[:, [1, 2, 0]].ravel()
    lo, hi = np.minimum(u, v), np.maximum(u, v)
    order = np.lexsort((hi, lo))
    key_lo, key_hi = lo[order], hi[order]
    same = (key_lo[1:] == key_lo[:-1]) & (key_hi[1:] == key_hi[:-1])
    # runs of exactly two half-edges: the pair (i, i+1) with no third on either side
    pair = same.copy()
    pair[1:] &= ~same[:-1]
    pair[:-1] &= ~same[1:]
    first, second = order[:-1][pair], order[1:][pair]
    opposite = u[first] == v[second]
    first, second = first[opposite], second[opposite]
    # the twin runs v -> u, so its wedges line up crosswise
    seam = (wu[first] != wv[second]) | (wv[first] != wu[second])
    sides = np.concatenate([first[seam], second[seam]])
    edges = np.stack([u[sides], v[sides]], axis=1)
    return edges, sides // 3 if m else sides


def wedge_quadrics(positions, faces, corners, values):
    """Hoppe's attribute quadric of every wedge (see the module docstring).

    Parameters
    ----------
    positions : (n, 3) float
    faces : (m, 3) int
    corners : (m, 3) int
        The wedge of every face corner.
    values : (w, d) float
        Attribute vector of every wedge, already scaled by sqrt(weight).

    Returns
    -------
    (w, 11 + 4 d) float64
        Attribute terms only: the geometric plane quadric stays on the vertex.
    """
    values = read_only(values, np.float64)
    out = np.zeros((len(values), wedge_quadric_size(values.shape[1])), dtype=np.float64)
    _accumulate_wedge_quadrics(read_only(positions, np.float64), read_only(faces, np.int64),
                               read_only(corners, np.int64), values, out)
    return out


@njit(cache=True, nogil=True, inline="always")
def edge_vectors(positions, i, j, k):
    """The edges ``p_j - p_i`` and ``p_k - p_i`` of triangle (i, j, k) of
    ``positions`` (n, 3), as six floats (x, y, z of each)."""
    return (positions[j, 0] - positions[i, 0], positions[j, 1] - positions[i, 1],
            positions[j, 2] - positions[i, 2], positions[k, 0] - positions[i, 0],
            positions[k, 1] - positions[i, 1], positions[k, 2] - positions[i, 2])


@njit(cache=True, nogil=True, inline="always")
def cross(ux, uy, uz, vx, vy, vz):
    """``u x v`` as three floats; of a triangle's two edges from one corner, its
    normal with twice its area as length."""
    return uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx


@njit(cache=True, nogil=True)
def _accumulate_wedge_quadrics(positions, faces, corners, values, out):
    d = values.shape[1]
    g = np.empty((d, 4))
    for f in range(faces.shape[0]):
        i, j, k = faces[f, 0], faces[f, 1], faces[f, 2]
        e1x, e1y, e1z, e2x, e2y, e2z = edge_vectors(positions, i, j, k)
        g11 = e1x * e1x + e1y * e1y + e1z * e1z
        g12 = e1x * e2x + e1y * e2y + e1z * e2z
        g22 = e2x * e2x + e2y * e2y + e2z * e2z
        det = g11 * g22 - g12 * g12      # = (2 area)^2
        if det <= 1e-30 * (g11 + g22) * (g11 + g22):
            continue                     # no plane to fit a field on
        area = 0.5 * np.sqrt(det)
        wi, wj, wk = corners[f, 0], corners[f, 1], corners[f, 2]
        # the field g . p + d through the three corner values, g in the face plane:
        # g = alpha e1 + beta e2 with g . e1 = s_j - s_i and g . e2 = s_k - s_i
        for c in range(d):
            d1 = values[wj, c] - values[wi, c]
            d2 = values[wk, c] - values[wi, c]
            alpha = (g22 * d1 - g12 * d2) / det
            beta = (g11 * d2 - g12 * d1) / det
            gx = alpha * e1x + beta * e2x
            gy = alpha * e1y + beta * e2y
            gz = alpha * e1z + beta * e2z
            g[c, 0] = gx
            g[c, 1] = gy
            g[c, 2] = gz
            g[c, 3] = values[wi, c] - (gx * positions[i, 0] + gy * positions[i, 1]
                                       + gz * positions[i, 2])
        for w in (wi, wj, wk):
            for c in range(d):
                gx, gy, gz, dd = g[c, 0], g[c, 1], g[c, 2], g[c, 3]
                out[w, 0] += area * gx * gx
                out[w, 1] += area * gx * gy
                out[w, 2] += area * gx * gz
                out[w, 3] += area * gy * gy
                out[w, 4] += area * gy * gz
                out[w, 5] += area * gz * gz
                out[w, 6] += area * dd * gx
                out[w, 7] += area * dd * gy
                out[w, 8] += area * dd * gz
                out[w, 9] += area * dd * dd
                o = QUADRIC_SIZE + 4 * c
                out[w, o] += area * gx
                out[w, o + 1] += area * gy
                out[w, o + 2] += area * gz
                out[w, o + 3] += area * dd
            out[w, 10] += area


@njit(cache=True, nogil=True, inline="always")
def add_fixed(q, wq, w, value, sign):
    """``q += sign * E_w(p, value)`` as a quadric in ``p``: wedge ``w`` keeping
    the attribute vector ``value`` (d,) wherever its vertex goes."""
    for j in range(10):
        q[j] += sign * wq[w, j]
    area = wq[w, 10]
    for c in range(value.shape[0]):
        s = value[c]
        o = QUADRIC_SIZE + 4 * c
        q[6] -= sign * s * wq[w, o]
        q[7] -= sign * s * wq[w, o + 1]
        q[8] -= sign * s * wq[w, o + 2]
        q[9] += sign * s * (area * s - 2.0 * wq[w, o + 3])


@njit(cache=True, nogil=True, inline="always")
def add_reduced(q, wq, wa, wb, d):
    """``q += min_s (E_wa + E_wb)(p, s)``: the wedges ``wa`` and ``wb`` merged,
    their attributes at the best value for each ``p`` (Hoppe's sparse form)."""
    for j in range(10):
        q[j] += wq[wa, j] + wq[wb, j]
    area = wq[wa, 10] + wq[wb, 10]
    if area <= 0.0:
        return
    inv = 1.0 / area
    for c in range(d):
        o = QUADRIC_SIZE + 4 * c
        gx = wq[wa, o] + wq[wb, o]
        gy = wq[wa, o + 1] + wq[wb, o + 1]
        gz = wq[wa, o + 2] + wq[wb, o + 2]
        dd = wq[wa, o + 3] + wq[wb, o + 3]
        q[0] -= gx * gx * inv
        q[1] -= gx * gy * inv
        q[2] -= gx * gz * inv
        q[3] -= gy * gy * inv
        q[4] -= gy * gz * inv
        q[5] -= gz * gz * inv
        q[6] -= gx * dd * inv
        q[7] -= gy * dd * inv
        q[8] -= gz * dd * inv
        q[9] -= dd * dd * inv


@njit(cache=True, nogil=True, inline="always")
def best_attributes(wq, w, x, y, z, out):
    """The attribute vector minimising wedge quadric ``w`` at ``p``: (G_j . p + D_j) / area."""
    area = wq[w, 10]
    for c in range(out.shape[0]):
        o = QUADRIC_SIZE + 4 * c
        out[c] = (wq[w, o] * x + wq[w, o + 1] * y + wq[w, o + 2] * z + wq[w, o + 3]) / area


@njit(cache=True, nogil=True, inline="always")
def face_plane(positions, i, j, k):
    """The plane of triangle (i, j, k): unit normal (nx, ny, nz), offset d with
    n . p + d = 0, and area; area 0 (and a zero normal) for a degenerate face."""
    ux, uy, uz, vx, vy, vz = edge_vectors(positions, i, j, k)
    nx, ny, nz = cross(ux, uy, uz, vx, vy, vz)
    double_area = np.sqrt(nx * nx + ny * ny + nz * nz)
    if double_area == 0.0:
        return 0.0, 0.0, 0.0, 0.0, 0.0
    nx /= double_area
    ny /= double_area
    nz /= double_area
    d = -(nx * positions[i, 0] + ny * positions[i, 1] + nz * positions[i, 2])
    return nx, ny, nz, d, 0.5 * double_area


@njit(cache=True, nogil=True, inline="always")
def add_plane(out, v, area, nx, ny, nz, d):
    """``out[v] +=`` the quadric of plane (n, d) weighted by ``area`` (a row of 11)."""
    out[v, 0] += area * nx * nx
    out[v, 1] += area * nx * ny
    out[v, 2] += area * nx * nz
    out[v, 3] += area * ny * ny
    out[v, 4] += area * ny * nz
    out[v, 5] += area * nz * nz
    out[v, 6] += area * d * nx
    out[v, 7] += area * d * ny
    out[v, 8] += area * d * nz
    out[v, 9] += area * d * d
    out[v, 10] += area


@njit(cache=True, nogil=True)
def _accumulate_face_quadrics(positions, faces, out):
    """Add every face's area-weighted plane quadric to its three vertices' rows
    of ``out`` (n, 11); one pass, no (m, 11) temporary. Zero-area faces add nothing."""
    for f in range(faces.shape[0]):
        i, j, k = faces[f, 0], faces[f, 1], faces[f, 2]
        nx, ny, nz, d, area = face_plane(positions, i, j, k)
        if area == 0.0:
            continue
        for v in (i, j, k):
            add_plane(out, v, area, nx, ny, nz, d)


@njit(cache=True, nogil=True)
def _scatter_add(out, rows, values):
    """``out[rows[i]] += values[i]`` with repeated rows summed: what np.add.at does,
    as one compiled loop instead of numpy's slow unbuffered path."""
    for i in range(rows.shape[0]):
        r = rows[i]
        for j in range(values.shape[1]):
            out[r, j] += values[i, j]


# The solves and evaluations below run millions of times a build and
# allocate nothing: compiled without reference counting (``state.NO_REFCOUNT``),
# as every array argument otherwise costs a count taken and dropped per call.
@njit(**NO_REFCOUNT)
def quadric_error(q, x, y, z):
    """Q(p) for the quadric row ``q`` at ``p = (x, y, z)``; squared length x area."""
    return (q[0] * x * x + 2.0 * q[1] * x * y + 2.0 * q[2] * x * z
            + q[3] * y * y + 2.0 * q[4] * y * z + q[5] * z * z
            + 2.0 * (q[6] * x + q[7] * y + q[8] * z) + q[9])


@njit(**NO_REFCOUNT)
def optimal_position(q, pa, pb, out):
    """Write into ``out`` the point minimising ``q`` for collapsing edge (pa, pb).

    Solves the regularised system (see REGULARIZATION). When A itself is
    singular or ill-conditioned, the endpoints and the midpoint are tried too
    and the best of the four is kept (G&H's fallback).

    Returns the quadric error at ``out``.
    """
    return optimal_position_xyz(q, pa[0], pa[1], pa[2], pb[0], pb[1], pb[2], out)


@njit(cache=True, nogil=True, inline="always")
def symmetric_cofactors(a00, a01, a02, a11, a12, a22):
    """Cofactors (c00, c01, c02, c11, c12, c22) and determinant of the symmetric
    3x3 matrix with upper triangle ``a``: ``A^-1 = C / det``. The packet format
    spells out these operations in this order (docs/packets.md), so every
    language gets the same bits: keep them as they are."""
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    return c00, c01, c02, c11, c12, c22, det


@njit(cache=True, nogil=True, inline="always")
def _regularized_cofactors(q):
    """The regularised ``A = Q[:3, :3] + eps I`` (see REGULARIZATION) of quadric
    row ``q``: (trace of Q's A, eps, cofactors c00 c01 c02 c11 c12 c22, det),
    so that ``A^-1 = C / det`` with C symmetric."""
    trace = q[0] + q[3] + q[5]
    eps = REGULARIZATION * trace
    return (trace, eps, *symmetric_cofactors(q[0] + eps, q[1], q[2], q[3] + eps, q[4],
                                             q[5] + eps))


@njit(**NO_REFCOUNT)
def solve_regularized(q, mx, my, mz, out):
    """The one 3x3 solve: write into ``out`` the minimiser of quadric row
    ``q`` regularised towards ``m = (mx, my, mz)``, i.e. the solution of
    ``(A + eps I) p = eps m - b`` (see REGULARIZATION), by cofactors.

    Returns False, leaving ``out`` alone, when ``q`` has no planes or the
    system is not positive definite (a non-PSD sum from rounding)."""
    trace, eps, c00, c01, c02, c11, c12, c22, det = _regularized_cofactors(q)
    r0 = eps * mx - q[6]
    r1 = eps * my - q[7]
    r2 = eps * mz - q[8]
    if trace <= 0.0 or det <= 0.0:
        return False
    inv = 1.0 / det
    out[0] = (c00 * r0 + c01 * r1 + c02 * r2) * inv
    out[1] = (c01 * r0 + c11 * r1 + c12 * r2) * inv
    out[2] = (c02 * r0 + c12 * r1 + c22 * r2) * inv
    return True


@njit(**NO_REFCOUNT)
def optimal_position_xyz(q, ax, ay, az, bx, by, bz, out):
    """``optimal_position`` with the endpoints as scalars: the kernel calls it
    millions of times, and slicing rows into array views costs more than the solve."""
    mx = 0.5 * (ax + bx)
    my = 0.5 * (ay + by)
    mz = 0.5 * (az + bz)
    if not solve_regularized(q, mx, my, mz, out):
        # no planes at all (or a non-PSD sum from rounding): stay at the midpoint
        out[0] = mx; out[1] = my; out[2] = mz
        best = quadric_error(q, mx, my, mz)
    else:
        best = quadric_error(q, out[0], out[1], out[2])
        # conditioning of A itself, not of the regularised system
        trace = q[0] + q[3] + q[5]
        raw_det = symmetric_cofactors(q[0], q[1], q[2], q[3], q[4], q[5])[6]
        if raw_det > DET_RELATIVE_EPS * trace * trace * trace:
            return best
    e = quadric_error(q, mx, my, mz)
    if e < best:
        best = e
        out[0] = mx; out[1] = my; out[2] = mz
    e = quadric_error(q, ax, ay, az)
    if e < best:
        best = e
        out[0] = ax; out[1] = ay; out[2] = az
    e = quadric_error(q, bx, by, bz)
    if e < best:
        best = e
        out[0] = bx; out[1] = by; out[2] = bz
    return best


@njit(cache=True, nogil=True)
def cell_representatives(q, mean, out):
    """``solve_regularized`` of every row of ``q`` (k, 11) towards the row of
    ``mean`` (k, 3), into ``out`` (k, 3); a row without planes (or singular)
    stays at its mean. Vertex clustering's representatives (Lindstrom 2000)."""
    for c in range(q.shape[0]):
        if not solve_regularized(q[c], mean[c, 0], mean[c, 1], mean[c, 2], out[c]):
            out[c, 0] = mean[c, 0]; out[c, 1] = mean[c, 1]; out[c, 2] = mean[c, 2]


@njit(**NO_REFCOUNT)
def constrain_to_plane(q, nx, ny, nz, h, out):
    """Move the minimiser ``out`` of ``q`` onto the plane ``N . p = h`` along
    the quadric's own metric (Lagrange: ``p += A^-1 N (h - N . p) / (N . A^-1 N)``).

    Used for volume preservation (Lindstrom & Turk 1998; Hoppe 1999, section 4):
    the collapse then neither adds nor removes volume. Returns False, leaving
    ``out`` alone, when the plane is undefined or ``A`` is singular.
    """
    nn = nx * nx + ny * ny + nz * nz
    trace, _eps, c00, c01, c02, c11, c12, c22, det = _regularized_cofactors(q)
    if trace <= 0.0 or nn <= 0.0:
        return False
    if det <= DET_RELATIVE_EPS * trace * trace * trace:
        return False
    ux = (c00 * nx + c01 * ny + c02 * nz) / det
    uy = (c01 * nx + c11 * ny + c12 * nz) / det
    uz = (c02 * nx + c12 * ny + c22 * nz) / det
    nu = nx * ux + ny * uy + nz * uz
    if nu <= 0.0:
        return False
    step = (h - (nx * out[0] + ny * out[1] + nz * out[2])) / nu
    out[0] += step * ux
    out[1] += step * uy
    out[2] += step * uz
    return True
