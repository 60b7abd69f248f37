"""The indexed triangle mesh every stage of lodserver passes along.

A :class:`Mesh` is a thin, validated container of two arrays:

- ``positions`` : (n, 3) float64, vertex positions in the file's units.
- ``faces``     : (m, 3) int64, counter-clockwise vertex indices into ``positions``.

Validation happens once, on construction, so the kernels downstream can trust
their input (finite coordinates, indices in range) without re-checking.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class MeshError(ValueError):
    """A mesh (or a file that should hold one) cannot be used; the message says why."""


@dataclass(frozen=True, eq=False)
class Mesh:
    """Positions (n, 3) float64 and triangle faces (m, 3) int64, both read-only."""

    positions: np.ndarray
    faces: np.ndarray

    def __post_init__(self):
        positions = np.ascontiguousarray(self.positions, dtype=np.float64)
        faces = np.asarray(self.faces)
        if positions.ndim != 2 or positions.shape[1] != 3:
            raise MeshError(f"positions must have shape (n, 3), got {positions.shape}")
        if faces.size == 0:
            faces = faces.reshape(0, 3)
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise MeshError(f"faces must have shape (m, 3), got {faces.shape}")
        if faces.size and not np.issubdtype(faces.dtype, np.integer):
            raise MeshError(f"faces must hold integer indices, got dtype {faces.dtype}")
        faces = np.ascontiguousarray(faces, dtype=np.int64)
        if len(faces) == 0:
            raise MeshError("the mesh has no faces")
        if not np.isfinite(positions).all():
            bad = int((~np.isfinite(positions).all(axis=1)).sum())
            raise MeshError(f"{bad} vertex positions are NaN or infinite")
        lo, hi = int(faces.min()), int(faces.max())
        if lo < 0 or hi >= len(positions):
            raise MeshError(
                f"face indices must lie in [0, {len(positions) - 1}], found {lo}..{hi}"
            )
        positions.setflags(write=False)
        faces.setflags(write=False)
        object.__setattr__(self, "positions", positions)
        object.__setattr__(self, "faces", faces)

    @property
    def vertex_count(self) -> int:
        return len(self.positions)

    @property
    def face_count(self) -> int:
        return len(self.faces)

    @property
    def bounding_box_diagonal(self) -> float:
        """Length of the axis-aligned bounding box diagonal, in mesh units."""
        used = self.positions[np.unique(self.faces)]
        return float(np.linalg.norm(used.max(axis=0) - used.min(axis=0)))

    def __repr__(self) -> str:
        return f"Mesh(vertices={self.vertex_count}, faces={self.face_count})"
