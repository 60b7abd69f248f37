"""Meshes for the tests: generated ones (always there) and the shared real ones."""

from __future__ import annotations

import json
import struct
from functools import lru_cache
from pathlib import Path

import numpy as np
import trimesh

from lodserver.io import load_mesh
from lodserver.mesh import Attributes, Materials, Mesh

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


def textured_sphere(nu=32, nv=16, hard_equator=False) -> Mesh:
    """A UV sphere with normals and UVs: a UV seam from pole to pole (u = 0 | 1),
    one wedge per face corner at the poles, and, with ``hard_equator``, a hard
    normal edge round the equator (flat normals per hemisphere side)."""
    u, v = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="ij")
    theta, phi = 2 * np.pi * u.ravel(), np.pi * v.ravel()
    grid = np.stack([np.sin(phi) * np.cos(theta), np.sin(phi) * np.sin(theta), np.cos(phi)], 1)
    idx = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
    a, b = idx[:-1, :-1], idx[1:, :-1]
    c, d = idx[1:, 1:], idx[:-1, 1:]
    # outward winding; the triangles touching the poles would be degenerate
    upper = np.stack([a, d, b], -1)[:, 1:].reshape(-1, 3)
    lower = np.stack([b, d, c], -1)[:, :-1].reshape(-1, 3)
    render_faces = np.concatenate([upper, lower])
    normals = grid.copy()
    if hard_equator:
        normals[:, 2] = np.where(v.ravel() < 0.5, 1.0, -1.0) * 0.5 + normals[:, 2] * 0.5
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    values = np.concatenate([normals, np.stack([u.ravel(), v.ravel()], 1)], 1)
    if hard_equator:
        # the equator row gets the upper side's normals on upper faces only
        row = (v.ravel() == 0.5)
        extra = values[row].copy()
        extra[:, 2] = -extra[:, 2]
    # weld positions; wedges = distinct (vertex, attribute vector)
    _, first, vertex_of = np.unique(np.round(grid, 12), axis=0, return_index=True,
                                    return_inverse=True)
    vertex_of = vertex_of.ravel()
    faces = vertex_of[render_faces]
    corner_values = values[render_faces]
    if hard_equator:
        # corners on the equator take the normal of their face's hemisphere
        centre_z = grid[render_faces][:, :, 2].mean(axis=1)
        on_row = row[render_faces]
        lower_face = (centre_z < 0)[:, None] & on_row
        corner_values[lower_face, 2] = -corner_values[lower_face, 2]
    keys = np.concatenate([faces.reshape(-1, 1), corner_values.reshape(-1, 5)], 1)
    wedge_rows, corners = np.unique(keys, axis=0, return_inverse=True)
    attributes = Attributes((("NORMAL", 3), ("TEXCOORD_0", 2)), wedge_rows[:, 1:],
                            corners.reshape(-1, 3))
    return Mesh(grid[first], faces, attributes)


def textured_spot() -> Mesh:
    """spot with its UVs and its texture (``data/spot_texture.png``, public domain,
    Keenan Crane) as the base colour of one material on every face."""
    m = mesh("spot")
    materials = Materials(
        {"materials": [{"name": "spot", "pbrMetallicRoughness": {
            "baseColorTexture": {"index": 0}, "metallicFactor": 0.0, "roughnessFactor": 0.8}}],
         "textures": [{"source": 0, "sampler": 0}],
         "samplers": [{"magFilter": 9729, "minFilter": 9987}],
         "images": [{"mimeType": "image/png", "name": "spot_texture"}]},
        ((DATA / "spot_texture.png").read_bytes(),))
    return Mesh(m.positions, m.faces, m.attributes, np.zeros(m.face_count, np.int32), materials)


def textured_spot_glb() -> bytes:
    """:func:`textured_spot` as a GLB file, to upload."""
    from lodserver.io import encode_mesh
    return encode_mesh(textured_spot(), "glb")


@lru_cache(maxsize=None)
def mesh(name: str) -> Mesh:
    """A test mesh by name: a generator key, ``spot`` (shipped), or a path under shared/meshes."""
    if name == "textured_sphere":
        return textured_sphere()
    if name == "hard_sphere":
        return textured_sphere(hard_equator=True)
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


def skinned_sphere(nu=32, nv=16) -> Mesh:
    """:func:`textured_sphere` with every kind of carried attribute on its wedges:
    TANGENT (along u, handedness -1 on the lower half), JOINTS_0/WEIGHTS_0 (three
    joints blended smoothly along z), two morph targets (inflate; lift the top) and a
    custom ``_BAND`` (the quarter of u a wedge lies in)."""
    base = textured_sphere(nu, nv)
    a = base.attributes
    wedge_vertex = base.wedge_vertices()
    p = base.positions[wedge_vertex]
    normal, u = a.values[:, 0:3], a.values[:, 3]
    theta = 2 * np.pi * u
    tangent = np.stack([-np.sin(theta), np.cos(theta), np.zeros_like(theta)], 1)
    tangent -= normal * (tangent * normal).sum(1, keepdims=True)
    length = np.linalg.norm(tangent, axis=1, keepdims=True)
    tangent = np.where(length > 1e-9, tangent / np.maximum(length, 1e-12), [1.0, 0.0, 0.0])
    handed = np.where(p[:, 2] < 0, -1.0, 1.0)[:, None]
    z = p[:, 2]
    raw = np.stack([np.clip(-z, 0, 1), 1 - np.abs(z), np.clip(z, 0, 1), np.zeros_like(z)], 1)
    weights = raw / raw.sum(1, keepdims=True)
    joints = np.tile([0.0, 1.0, 2.0, 0.0], (len(z), 1))
    inflate = 0.1 * p / np.linalg.norm(p, axis=1, keepdims=True)      # per vertex, not corner
    lift = np.stack([np.zeros_like(z), np.zeros_like(z), 0.3 * np.clip(z, 0, 1)], 1)
    band = np.floor(np.clip(u, 0, 0.999) * 4)[:, None]
    layout = a.layout + (("TANGENT", 4), ("JOINTS_0", 4), ("WEIGHTS_0", 4),
                         ("TARGET0_POSITION", 3), ("TARGET1_POSITION", 3), ("_BAND", 1))
    values = np.concatenate([a.values, tangent, handed, joints, weights, inflate, lift, band], 1)
    return Mesh(base.positions, base.faces, Attributes(layout, values, a.corners))


class GlbBuilder:
    """A GLB assembled by hand: :meth:`add` appends an array to the binary chunk as an
    accessor (returning its index); :meth:`glb` packs a document around them."""

    def __init__(self):
        self.binary, self.views, self.accessors = bytearray(), [], []

    def add(self, values, kind, component, target=None, bounds=False) -> int:
        data = np.ascontiguousarray(values).tobytes()
        self.binary.extend(b"\0" * (-len(self.binary) % 4))
        view = {"buffer": 0, "byteOffset": len(self.binary), "byteLength": len(data)}
        if target:
            view["target"] = target
        self.views.append(view)
        self.binary.extend(data)
        accessor = {"bufferView": len(self.views) - 1, "componentType": component,
                    "count": len(values), "type": kind}
        if bounds:
            accessor["min"] = np.min(values, axis=0).tolist()
            accessor["max"] = np.max(values, axis=0).tolist()
        self.accessors.append(accessor)
        return len(self.accessors) - 1

    def glb(self, document: dict) -> bytes:
        """``document`` with the accessors, views and buffer added, as GLB bytes."""
        binary = self.binary + b"\0" * (-len(self.binary) % 4)
        document = {**document, "accessors": self.accessors, "bufferViews": self.views,
                    "buffers": [{"byteLength": len(binary)}]}
        text = json.dumps(document).encode()
        text += b" " * (-len(text) % 4)
        total = 12 + 8 + len(text) + 8 + len(binary)
        return (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<I4s", len(text), b"JSON")
                + text + struct.pack("<I4s", len(binary), b"BIN\0") + bytes(binary))
