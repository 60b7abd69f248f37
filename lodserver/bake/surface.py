"""The nearest point of the full-detail surface, for every texel of a far level.

A scipy ``cKDTree`` over a dense, area-proportional sample of the full mesh's
faces (each sample knows its face) gives candidate faces near a query point;
the exact closest point on each candidate triangle (Ericson 2005, 5.1.5)
decides. A k-d tree of points is used rather than a BVH of triangles because
scipy has it built, deterministic and fast, and with samples denser than the
far level's texels the true nearest face is among the candidates of its
nearest samples. Ties between the two sides of a thin part are broken by the
far level's normal: a face facing away is charged a fraction of the spacing.
"""

from __future__ import annotations

import numpy as np
from numba import njit

# Samples per face at least, and in all at most: dense enough that a texel's
# nearest samples hold its nearest face, bounded in memory.
_SAMPLES_PER_FACE = 4
_MAX_SAMPLES = 2_000_000
_CANDIDATES = 12
# The charge for a face whose normal opposes the query's, as a fraction of the
# sample spacing: small enough that a truly nearer face still wins.
_FACING_CHARGE = 0.5
_SEED = 2028


class NearestSurface:
    """Nearest points on the triangles ``faces`` (m, 3) of ``positions`` (n, 3)."""

    def __init__(self, positions: np.ndarray, faces: np.ndarray):
        from scipy.spatial import cKDTree

        self.positions = np.ascontiguousarray(positions, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        a, b, c = (self.positions[self.faces[:, k]] for k in range(3))
        cross = np.cross(b - a, c - a)
        area = 0.5 * np.linalg.norm(cross, axis=1)
        self.normals = cross / np.maximum(2 * area, 1e-300)[:, None]
        total = max(float(area.sum()), 1e-300)
        wanted = min(_MAX_SAMPLES, _SAMPLES_PER_FACE * len(self.faces))
        count = 1 + np.floor(area / total * wanted).astype(np.int64)
        owner = np.repeat(np.arange(len(self.faces)), count)
        # the first sample of each face its centroid, the rest uniform in it
        # (a fixed seed: the same surface gives the same samples everywhere)
        rng = np.random.default_rng(_SEED)
        u, v = rng.random(len(owner)), rng.random(len(owner))
        flip = u + v > 1
        u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
        first = np.concatenate([[0], np.cumsum(count)[:-1]])
        u[first], v[first] = 1 / 3, 1 / 3
        points = (a[owner] + u[:, None] * (b - a)[owner] + v[:, None] * (c - a)[owner])
        self.owner = owner
        self.spacing = float(np.sqrt(total / len(owner)))
        self.tree = cKDTree(points)

    def nearest(self, points: np.ndarray, normals: np.ndarray | None = None):
        """For points (p, 3) (and the far level's unit normals (p, 3) there):
        ``(face, bary)``, the nearest face (p,) int64 and the barycentrics (p, 3)
        of the nearest point on it."""
        points = np.ascontiguousarray(points, dtype=np.float64)
        if normals is None:
            normals = np.zeros_like(points)
        k = min(_CANDIDATES, len(self.owner))
        _, sample = self.tree.query(points, k=k, workers=1)
        candidates = self.owner[np.asarray(sample).reshape(len(points), k)]
        face = np.empty(len(points), dtype=np.int64)
        bary = np.empty((len(points), 3))
        _closest(points, np.ascontiguousarray(normals, dtype=np.float64), candidates,
                 self.positions, self.faces, self.normals, _FACING_CHARGE * self.spacing,
                 face, bary)
        return face, bary


@njit(cache=True, nogil=True)
def _triangle_closest(p, a, b, c):
    """Barycentrics (u, v, w) of the point of triangle abc nearest p (Ericson 5.1.5)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = ab @ ap
    d2 = ac @ ap
    if d1 <= 0.0 and d2 <= 0.0:
        return 1.0, 0.0, 0.0
    bp = p - b
    d3 = ab @ bp
    d4 = ac @ bp
    if d3 >= 0.0 and d4 <= d3:
        return 0.0, 1.0, 0.0
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        t = d1 / (d1 - d3)
        return 1.0 - t, t, 0.0
    cp = p - c
    d5 = ab @ cp
    d6 = ac @ cp
    if d6 >= 0.0 and d5 <= d6:
        return 0.0, 0.0, 1.0
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        t = d2 / (d2 - d6)
        return 1.0 - t, 0.0, t
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return 0.0, 1.0 - t, t
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return 1.0 - v - w, v, w


@njit(cache=True, nogil=True)
def _closest(points, normals, candidates, positions, faces, face_normals, charge,
             face_out, bary_out):
    for i in range(points.shape[0]):
        p = points[i]
        best = np.inf
        for j in range(candidates.shape[1]):
            f = candidates[i, j]
            a = positions[faces[f, 0]]
            b = positions[faces[f, 1]]
            c = positions[faces[f, 2]]
            u, v, w = _triangle_closest(p, a, b, c)
            q = u * a + v * b + w * c
            d = np.sqrt(((p - q) ** 2).sum())
            facing = normals[i] @ face_normals[f]
            if facing < 0.0:
                d += charge * (-facing)
            if d < best:
                best = d
                face_out[i] = f
                bary_out[i, 0] = u
                bary_out[i, 1] = v
                bary_out[i, 2] = w
