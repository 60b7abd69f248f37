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


def vertex_quadrics(positions, faces, *, boundary_weight=1.0, boundary=None):
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

    Returns
    -------
    (n, 11) float64
    """
    positions = np.ascontiguousarray(positions, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    q = np.zeros((len(positions), QUADRIC_SIZE), dtype=np.float64)
    # Each face's quadric goes to its three corners (G&H sum over incident planes).
    _accumulate_face_quadrics(positions, faces, q)
    if boundary_weight > 0:
        if boundary is None:
            from .topology import census
            found = census(faces, len(positions))
            boundary = (found.boundary_edges, found.boundary_faces)
        edges, edge_faces = boundary
        if len(edges):
            a, b = positions[edges[:, 0]], positions[edges[:, 1]]
            along = b - a
            tri = positions[faces[edge_faces]]
            normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            # The constraint plane contains the edge and the face normal, so it
            # penalises motion across the border but not along it or off the surface.
            perp = np.cross(along, normals)
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
def _accumulate_face_quadrics(positions, faces, out):
    """Add every face's area-weighted plane quadric to its three vertices' rows
    of ``out`` (n, 11); one pass, no (m, 11) temporary. Zero-area faces add nothing."""
    for f in range(faces.shape[0]):
        i, j, k = faces[f, 0], faces[f, 1], faces[f, 2]
        ux = positions[j, 0] - positions[i, 0]
        uy = positions[j, 1] - positions[i, 1]
        uz = positions[j, 2] - positions[i, 2]
        vx = positions[k, 0] - positions[i, 0]
        vy = positions[k, 1] - positions[i, 1]
        vz = positions[k, 2] - positions[i, 2]
        nx = uy * vz - uz * vy
        ny = uz * vx - ux * vz
        nz = ux * vy - uy * vx
        double_area = np.sqrt(nx * nx + ny * ny + nz * nz)
        if double_area == 0.0:
            continue
        nx /= double_area
        ny /= double_area
        nz /= double_area
        area = 0.5 * double_area
        d = -(nx * positions[i, 0] + ny * positions[i, 1] + nz * positions[i, 2])
        for v in (i, j, k):
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
def optimal_position(q, pa, pb, out):
    """Write into ``out`` the point minimising ``q`` for collapsing edge (pa, pb).

    Solves the regularised system (see REGULARIZATION). When A itself is
    singular or ill-conditioned, the endpoints and the midpoint are tried too
    and the best of the four is kept (G&H's fallback).

    Returns the quadric error at ``out``.
    """
    return optimal_position_xyz(q, pa[0], pa[1], pa[2], pb[0], pb[1], pb[2], out)


@njit(cache=True, nogil=True)
def optimal_position_xyz(q, ax, ay, az, bx, by, bz, out):
    """``optimal_position`` with the endpoints as scalars: the kernel calls it
    millions of times, and slicing rows into array views costs more than the solve."""
    mx = 0.5 * (ax + bx)
    my = 0.5 * (ay + by)
    mz = 0.5 * (az + bz)
    trace = q[0] + q[3] + q[5]
    eps = REGULARIZATION * trace
    a00 = q[0] + eps; a01 = q[1]; a02 = q[2]
    a11 = q[3] + eps; a12 = q[4]; a22 = q[5] + eps
    r0 = eps * mx - q[6]
    r1 = eps * my - q[7]
    r2 = eps * mz - q[8]
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    det = a00 * c00 + a01 * c01 + a02 * c02
    if trace <= 0.0 or det <= 0.0:
        # no planes at all (or a non-PSD sum from rounding): stay at the midpoint
        out[0] = mx; out[1] = my; out[2] = mz
        best = quadric_error(q, mx, my, mz)
    else:
        c11 = a00 * a22 - a02 * a02
        c12 = a01 * a02 - a00 * a12
        c22 = a00 * a11 - a01 * a01
        inv = 1.0 / det
        out[0] = (c00 * r0 + c01 * r1 + c02 * r2) * inv
        out[1] = (c01 * r0 + c11 * r1 + c12 * r2) * inv
        out[2] = (c02 * r0 + c12 * r1 + c22 * r2) * inv
        best = quadric_error(q, out[0], out[1], out[2])
        # conditioning of A itself, not of the regularised system
        raw_det = (q[0] * (q[3] * q[5] - q[4] * q[4]) + q[1] * (q[2] * q[4] - q[1] * q[5])
                   + q[2] * (q[1] * q[4] - q[2] * q[3]))
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
