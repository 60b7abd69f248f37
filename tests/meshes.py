"""Meshes for the tests: generated ones (always there) and the shared real ones."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import trimesh

from lodserver.io import load_mesh
from lodserver.mesh import Mesh

DATA = Path(__file__).resolve().parent / "data"
SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "meshes"


def _grid(nx=24, ny=18):
    """An open, gently curved height field: a border all round."""
    x, y = np.meshgrid(np.linspace(0, 1, nx), np.linspace(0, 1, ny))
    z = 0.1 * np.sin(3 * x) * np.cos(2 * y)
    positions = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return positions, faces


GENERATED = {
    "icosphere": lambda: (lambda s: (s.vertices, s.faces))(trimesh.creation.icosphere(3)),
    "torus": lambda: (lambda s: (s.vertices, s.faces))(
        trimesh.creation.torus(major_radius=1.0, minor_radius=0.3, major_sections=40,
                               minor_sections=16)),
    "grid": _grid,
    # two spheres sharing nothing: several components
    "two_boxes": lambda: (lambda s: (s.vertices, s.faces))(
        trimesh.util.concatenate([trimesh.creation.box(), trimesh.creation.box().apply_translation([3, 0, 0])])),
}


@lru_cache(maxsize=None)
def mesh(name: str) -> Mesh:
    """A test mesh by name: a generator key, ``spot`` (shipped), or a path under shared/meshes."""
    if name in GENERATED:
        positions, faces = GENERATED[name]()
        from lodserver.io import clean_mesh
        return clean_mesh(np.asarray(positions, float), np.asarray(faces, np.int64))[0]
    if name == "spot":
        return load_mesh(DATA / "spot.obj")[0]
    return load_mesh(SHARED / name)[0]


@lru_cache(maxsize=None)
def progressive(name: str):
    from lodserver import build
    return build(mesh(name))


def canonical_faces(positions, faces):
    """Faces as sorted rows of corner positions, each rotated to start at its
    smallest corner (winding kept): equal for equal meshes whatever the numbering."""
    positions, faces = np.asarray(positions), np.asarray(faces)
    # rank vertices by position (x, then y, then z): independent of numbering
    rank = np.empty(len(positions), dtype=np.int64)
    rank[np.lexsort(positions.T[::-1])] = np.arange(len(positions))
    first = np.argmin(rank[faces], axis=1)
    roll = (first[:, None] + np.arange(3)) % 3
    rotated = positions[np.take_along_axis(faces, roll, axis=1)].reshape(len(faces), 9)
    return rotated[np.lexsort(rotated.T[::-1])]
