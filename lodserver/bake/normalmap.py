"""Tangent frames from UVs, and normals written as a tangent-space normal map.

Tangents follow MikkTSpace's definition without its exact welding rules: per
face, the tangent is the surface direction of growing u and the bitangent the
direction of shrinking glTF v (glTF's v runs down the image, MikkTSpace's up);
per wedge, the area-weighted sum over its faces, made orthogonal to the wedge's
normal, with handedness ``w`` = the sign of ``cross(N, T) . B``. The far level
is written with these tangents (``TANGENT``), and the map is baked in the very
frame a renderer rebuilds from them (``B = cross(N, T) * w``, each interpolated
across the face), so that frame's agreement with MikkTSpace does not matter.
"""

from __future__ import annotations

import numpy as np


def vertex_normals_of(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(n, 3) unit area-weighted normals of the faces (f, 3) around each vertex of
    ``positions`` (n, 3); +z for a vertex no face (or only degenerate ones) uses."""
    corner = positions[faces]
    own = np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0])
    total = np.zeros_like(positions, dtype=np.float64)
    for k in range(3):
        np.add.at(total, faces[:, k], own)
    length = np.linalg.norm(total, axis=1, keepdims=True)
    return np.where(length > 0, total / np.maximum(length, 1e-300), [[0.0, 0.0, 1.0]])


def face_tangents(corners: np.ndarray, uv: np.ndarray):
    """``corners`` (p, 3, 3) positions of each face, ``uv`` (p, 3, 2) their glTF
    UVs: (tangent (p, 3) unit, sign (p,) +-1 so that ``cross(n, t) * sign`` runs
    towards shrinking v, ``n`` the face's winding normal)."""
    tangent, bitangent = _gradients(corners, uv)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    sign = np.where(np.sum(np.cross(normal, tangent) * bitangent, axis=1) < 0, -1.0, 1.0)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-300)
    return tangent, sign


def _gradients(corners, uv):
    """Per face (dP/du, -dP/dv), each (p, 3), scaled by the face's UV area sign."""
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    d1, d2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    inverse = np.where(np.abs(det) > 1e-20, 1.0 / np.where(det == 0, 1.0, det), 0.0)[:, None]
    tangent = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) * inverse
    bitangent = -(e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) * inverse
    return tangent, bitangent


def wedge_tangents(positions: np.ndarray, faces: np.ndarray, corners: np.ndarray,
                   uv: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(w, 4) glTF ``TANGENT`` of each wedge: xyz unit and orthogonal to the
    wedge's ``normal`` (w, 3), w = +-1.

    ``positions`` (n, 3) and ``faces`` (f, 3) the mesh, ``corners`` (f, 3) the
    wedge of each face corner, ``uv`` (w, 2) the wedges' UVs."""
    corner_positions = positions[faces]
    tangent, bitangent = _gradients(corner_positions, uv[corners])
    area = 0.5 * np.linalg.norm(np.cross(corner_positions[:, 1] - corner_positions[:, 0],
                                         corner_positions[:, 2] - corner_positions[:, 0]),
                                axis=1)[:, None]
    # each face's gradients carry 1 / (uv area): weight by area over its length
    # so large and small faces count by their surface
    weight = area / np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-300)
    t_sum = np.zeros((len(uv), 3))
    b_sum = np.zeros((len(uv), 3))
    for k in range(3):
        np.add.at(t_sum, corners[:, k], tangent * weight)
        np.add.at(b_sum, corners[:, k], bitangent * weight)
    t = t_sum - normal * np.sum(t_sum * normal, axis=1, keepdims=True)
    length = np.linalg.norm(t, axis=1, keepdims=True)
    # a wedge without a UV gradient takes any direction across its normal
    fallback = np.cross(normal, np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0, 0]],
                                         [[0, 1.0, 0]]))
    t = np.where(length > 1e-12, t / np.maximum(length, 1e-300), fallback)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-300)
    w = np.where(np.sum(np.cross(normal, t) * b_sum, axis=1) < 0, -1.0, 1.0)
    return np.concatenate([t, w[:, None]], axis=1)


def encode_normals(target: np.ndarray, normal: np.ndarray, tangent: np.ndarray,
                   bitangent: np.ndarray) -> np.ndarray:
    """(p, 3) texel values in [0, 1] of unit normals ``target`` (p, 3) in the
    frame a renderer builds from interpolated ``tangent``, ``bitangent`` and
    ``normal`` (each (p, 3), normalised here as a shader does): the unit
    (x, y, z) with ``normalize(T x + B y + N z) = target``."""
    unit = [v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)
            for v in (tangent, bitangent, normal)]
    frame = np.stack(unit, axis=2)              # (p, 3, 3), columns T, B, N
    bad = np.abs(np.linalg.det(frame)) < 1e-6
    frame[bad] = np.eye(3)
    local = np.linalg.solve(frame, target[:, :, None])[:, :, 0]
    local[bad] = [0.0, 0.0, 1.0]
    # z may be negative: where the interpolated normal runs against the face
    # (vertices shared by the two sides of a thin part), the map turns it back
    local /= np.maximum(np.linalg.norm(local, axis=1, keepdims=True), 1e-300)
    return local * 0.5 + 0.5
