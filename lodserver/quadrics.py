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
"""

from __future__ import annotations

import numpy as np
from numba import njit

QUADRIC_SIZE = 11

# A 3x3 system is solved directly only when |det(A)| > DET_RELATIVE_EPS * trace(A)^3.
# det/trace^3 is scale-free and at most 1/27 (isotropic A); below this the
# optimum slides along a flat region or a crease and the direct solve amplifies noise.
DET_RELATIVE_EPS = 1e-7
# Eigenvalues below this fraction of the largest are treated as zero in the
# pseudo-inverse fallback (Lindstrom 2000's truncated-SVD placement).
EIGEN_RELATIVE_EPS = 1e-6


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


def face_quadrics(positions, faces):
    """Area-weighted plane quadric of every face.

    Parameters
    ----------
    positions : (n, 3) float
    faces : (m, 3) int

    Returns
    -------
    quadrics : (m, 11) float64
        Degenerate faces (zero area) give all-zero rows.
    normals : (m, 3) float64
        Unit face normals (zero for degenerate faces).
    """
    tri = positions[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    double_area = np.linalg.norm(cross, axis=1)
    normals = np.zeros_like(cross)
    ok = double_area > 0
    normals[ok] = cross[ok] / double_area[ok, None]
    area = 0.5 * double_area
    offsets = -np.einsum("ij,ij->i", normals, tri[:, 0])
    return plane_quadrics(normals, offsets, area, area), normals


def boundary_edges(faces):
    """Directed edges ``(a, b)`` used by exactly one face, and that face.

    Returns
    -------
    edges : (k, 2) int64
        Boundary edges in their face's winding.
    edge_faces : (k,) int64
    """
    faces = np.asarray(faces, dtype=np.int64)
    directed = np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2)
    _, inverse, counts = np.unique(edge_keys(directed), return_inverse=True, return_counts=True)
    once = counts[inverse] == 1
    return directed[once], np.nonzero(once)[0] // 3


def edge_keys(edges):
    """One int64 per undirected edge, ``min * 2^32 + max``: sorting and
    ``np.unique`` on 1-D keys is several times faster than on rows.

    edges : (k, 2) int, vertex ids below 2^31.
    """
    edges = np.asarray(edges, dtype=np.int64)
    lo = np.minimum(edges[:, 0], edges[:, 1])
    hi = np.maximum(edges[:, 0], edges[:, 1])
    return (lo << 32) | hi


def vertex_quadrics(positions, faces, *, boundary_weight=1.0):
    """Sum of face and boundary-constraint quadrics at every vertex.

    Parameters
    ----------
    positions : (n, 3) float
    faces : (m, 3) int
    boundary_weight : float
        Weight of the plane perpendicular to each boundary edge, relative to a
        face of area ``|edge|^2``. 0 leaves borders free to shrink.

    Returns
    -------
    (n, 11) float64
    """
    positions = np.asarray(positions, dtype=np.float64)
    n = len(positions)
    fq, normals = face_quadrics(positions, faces)
    # Each face's quadric goes to its three corners (G&H sum over incident planes).
    q = np.zeros((n, QUADRIC_SIZE), dtype=np.float64)
    _scatter_add(q, faces[:, 0], fq)
    _scatter_add(q, faces[:, 1], fq)
    _scatter_add(q, faces[:, 2], fq)
    if boundary_weight > 0:
        edges, edge_faces = boundary_edges(faces)
        if len(edges):
            a, b = positions[edges[:, 0]], positions[edges[:, 1]]
            along = b - a
            # The constraint plane contains the edge and the face normal, so it
            # penalises motion across the border but not along it or off the surface.
            perp = np.cross(along, normals[edge_faces])
            length = np.linalg.norm(perp, axis=1)
            ok = length > 0
            perp = perp[ok] / length[ok, None]
            weight = boundary_weight * np.einsum("ij,ij->i", along[ok], along[ok])
            bq = plane_quadrics(perp, -np.einsum("ij,ij->i", perp, a[ok]), weight,
                                np.zeros(len(perp)))
            _scatter_add(q, edges[ok, 0], bq)
            _scatter_add(q, edges[ok, 1], bq)
    return q


@njit(cache=True, nogil=True)
def _scatter_add(out, rows, values):
    """``out[rows[i]] += values[i]`` with repeated rows summed (np.add.at, 20x faster)."""
    for i in range(rows.shape[0]):
        r = rows[i]
        for j in range(values.shape[1]):
            out[r, j] += values[i, j]


@njit(cache=True, nogil=True)
def quadric_error(q, x, y, z):
    """Q(p) for the quadric row ``q`` at ``p = (x, y, z)``; squared length x area."""
    return (q[0] * x * x + 2.0 * q[1] * x * y + 2.0 * q[2] * x * z
            + q[3] * y * y + 2.0 * q[4] * y * z + q[5] * z * z
            + 2.0 * (q[6] * x + q[7] * y + q[8] * z) + q[9])


@njit(cache=True, nogil=True)
def _pseudo_inverse_position(q, mx, my, mz, out):
    """Minimise Q nearest to ``m`` when A is (nearly) singular.

    Truncated eigen-decomposition: along directions where A has no curvature
    (a flat patch, a crease line) the point stays at ``m`` instead of running
    off to where rounding noise puts it.
    """
    a = np.empty((3, 3))
    a[0, 0] = q[0]; a[0, 1] = q[1]; a[0, 2] = q[2]
    a[1, 0] = q[1]; a[1, 1] = q[3]; a[1, 2] = q[4]
    a[2, 0] = q[2]; a[2, 1] = q[4]; a[2, 2] = q[5]
    # Residual gradient at m: -(A m + b)
    r0 = -(a[0, 0] * mx + a[0, 1] * my + a[0, 2] * mz + q[6])
    r1 = -(a[1, 0] * mx + a[1, 1] * my + a[1, 2] * mz + q[7])
    r2 = -(a[2, 0] * mx + a[2, 1] * my + a[2, 2] * mz + q[8])
    w, v = np.linalg.eigh(a)
    top = max(abs(w[0]), abs(w[1]), abs(w[2]))
    out[0] = mx
    out[1] = my
    out[2] = mz
    if top <= 0.0:
        return
    for i in range(3):
        if w[i] > EIGEN_RELATIVE_EPS * top:
            s = (v[0, i] * r0 + v[1, i] * r1 + v[2, i] * r2) / w[i]
            out[0] += s * v[0, i]
            out[1] += s * v[1, i]
            out[2] += s * v[2, i]


@njit(cache=True, nogil=True)
def optimal_position(q, pa, pb, out):
    """Write into ``out`` the point minimising ``q`` for collapsing edge (pa, pb).

    Solves A p = -b directly when A is well conditioned. Otherwise takes the
    best of the pseudo-inverse point nearest the midpoint, the two endpoints
    and the midpoint (G&H's fallback, made stronger by the first candidate).

    Returns the quadric error at ``out``.
    """
    a00 = q[0]; a01 = q[1]; a02 = q[2]; a11 = q[3]; a12 = q[4]; a22 = q[5]
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    det = a00 * c00 + a01 * c01 + a02 * c02
    trace = a00 + a11 + a22
    if trace > 0.0 and abs(det) > DET_RELATIVE_EPS * trace * trace * trace:
        c11 = a00 * a22 - a02 * a02
        c12 = a01 * a02 - a00 * a12
        c22 = a00 * a11 - a01 * a01
        inv = -1.0 / det
        out[0] = (c00 * q[6] + c01 * q[7] + c02 * q[8]) * inv
        out[1] = (c01 * q[6] + c11 * q[7] + c12 * q[8]) * inv
        out[2] = (c02 * q[6] + c12 * q[7] + c22 * q[8]) * inv
        return quadric_error(q, out[0], out[1], out[2])

    mx = 0.5 * (pa[0] + pb[0])
    my = 0.5 * (pa[1] + pb[1])
    mz = 0.5 * (pa[2] + pb[2])
    _pseudo_inverse_position(q, mx, my, mz, out)
    best = quadric_error(q, out[0], out[1], out[2])
    e = quadric_error(q, mx, my, mz)
    if e < best:
        best = e
        out[0] = mx; out[1] = my; out[2] = mz
    e = quadric_error(q, pa[0], pa[1], pa[2])
    if e < best:
        best = e
        out[0] = pa[0]; out[1] = pa[1]; out[2] = pa[2]
    e = quadric_error(q, pb[0], pb[1], pb[2])
    if e < best:
        best = e
        out[0] = pb[0]; out[1] = pb[1]; out[2] = pb[2]
    return best
