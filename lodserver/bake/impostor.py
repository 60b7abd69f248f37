"""Octahedral impostors: an asset's farthest level as views baked to one atlas.

:func:`bake_impostor` renders the full-detail mesh (``raster.rasterize_view``,
orthographic, framed by its bounding sphere) from ``grid`` x ``grid``
directions laid on an octahedron (:func:`decode`; ``"full"`` for objects seen
from everywhere, ``"hemi"`` for objects seen from above only) and shades each
pixel from the mesh's materials (``textures.SurfaceLook``): one colour+alpha
atlas (sRGB base colour, alpha = coverage x the material's alpha) and one
normal+depth atlas (object-space unit normal in RGB, depth along the view in
A). :func:`impostor_glb` writes them as a glTF quad whose material shows the
colour atlas and whose ``extras.impostor`` names the layout
(docs/pipeline.md); ``static/impostor.js`` draws it, picking and blending the
three views nearest the camera's direction.

The octahedral square ``p`` in [-1, 1]^2 maps to directions ``d`` (unit, from
the sphere's centre towards the viewer; y up, glTF's): full,
``p = (x, z) / (|x| + |y| + |z|)``, folded over the square's corners for
``y < 0``; hemi, the upper half on the whole square (``y`` clamped to 0).
View (i, j) of the grid sits at ``p = (2 i / (grid - 1) - 1, 2 j / (grid - 1) - 1)``
and fills atlas cell column i, row j (row 0 at the top); its image's x runs
along ``right = normalize(cross(up_ref, d))``, its rows down ``up = cross(d, right)``,
``up_ref`` y, or -z / +z at the poles (:func:`view_basis`).
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np

from ..mesh import Mesh, MeshError
from .atlas import dilate
from .raster import rasterize_view
from .textures import SurfaceLook, linear_to_srgb

KINDS = ("full", "hemi")
# Views a side, pixels a view side, and pixels rendered per output pixel a side
# (the edge's coverage antialiased into alpha)
DEFAULT_GRID, DEFAULT_FRAME, SUPERSAMPLE = 12, 64, 2
MIN_GRID, MAX_GRID, MIN_FRAME, MAX_FRAME = 2, 32, 8, 512
# The colour atlas's side at most: the bake holds a few float arrays of it
# (a few hundred megabytes at this side)
MAX_SIDE = 2048
# Near a pole the view's "up" leans on the z axis: y is too close to the direction.
_POLE = 0.999
# glTF sampler: linear, trilinear mips, clamped
_SAMPLER = {"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}


@dataclass(frozen=True)
class Impostor:
    """A baked impostor: ``color`` (h, w, 4) and ``normal`` (h / 2, w / 2, 4) uint8
    atlases of ``grid`` x ``grid`` views of ``frame`` (``frame / 2``) pixels each,
    framed by the sphere (``center`` (3,), ``radius``, mesh units)."""

    color: np.ndarray
    normal: np.ndarray
    grid: int
    frame: int
    kind: str
    center: np.ndarray
    radius: float


def encode(directions: np.ndarray, kind: str = "full") -> np.ndarray:
    """Unit directions (p, 3) -> points (p, 2) of the octahedral square [-1, 1]^2."""
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    if kind == "hemi":
        y = np.maximum(y, 0.0)
        total = np.maximum(np.abs(x) + y + np.abs(z), 1e-300)
        a, b = x / total, z / total
        return np.stack([a + b, a - b], axis=1)
    total = np.maximum(np.abs(x) + np.abs(y) + np.abs(z), 1e-300)
    a, b = x / total, z / total
    below = y < 0
    fa = (1.0 - np.abs(b)) * np.where(a >= 0, 1.0, -1.0)
    fb = (1.0 - np.abs(a)) * np.where(b >= 0, 1.0, -1.0)
    return np.stack([np.where(below, fa, a), np.where(below, fb, b)], axis=1)


def decode(points: np.ndarray, kind: str = "full") -> np.ndarray:
    """Points (p, 2) of the octahedral square -> unit directions (p, 3)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if kind == "hemi":
        a, b = (p[:, 0] + p[:, 1]) * 0.5, (p[:, 0] - p[:, 1]) * 0.5
        y = 1.0 - np.abs(a) - np.abs(b)
    else:
        a, b = p[:, 0], p[:, 1]
        y = 1.0 - np.abs(a) - np.abs(b)
        below = y < 0
        fa = (1.0 - np.abs(b)) * np.where(a >= 0, 1.0, -1.0)
        fb = (1.0 - np.abs(a)) * np.where(b >= 0, 1.0, -1.0)
        a, b = np.where(below, fa, a), np.where(below, fb, b)
    d = np.stack([a, y, b], axis=1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def view_points(grid: int) -> np.ndarray:
    """The octahedral points (grid * grid, 2) of the views, row j then column i."""
    axis = np.linspace(-1.0, 1.0, grid)
    j, i = np.meshgrid(np.arange(grid), np.arange(grid), indexing="ij")
    return np.stack([axis[i.ravel()], axis[j.ravel()]], axis=1)


def nearest_view(directions: np.ndarray, grid: int, kind: str = "full") -> np.ndarray:
    """(column, row) (p, 2) int64 of the grid view nearest each direction's point."""
    g = (encode(directions, kind) + 1.0) * 0.5 * (grid - 1)
    return np.clip(np.rint(g), 0, grid - 1).astype(np.int64)


def view_basis(direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(right, up) unit vectors (3,) of the view looking from ``direction`` (unit,
    centre towards the viewer) back at the centre."""
    d = np.asarray(direction, dtype=np.float64)
    if abs(d[1]) > _POLE:
        reference = np.array([0.0, 0.0, -1.0 if d[1] > 0 else 1.0])
    else:
        reference = np.array([0.0, 1.0, 0.0])
    right = np.cross(reference, d)
    right /= np.linalg.norm(right)
    return right, np.cross(d, right)


def check_layout(grid: int, frame: int, kind: str) -> None:
    """``MeshError`` (one sentence) for a grid, view size or kind out of range."""
    if kind not in KINDS:
        raise MeshError(f"an impostor's octahedron is one of {', '.join(KINDS)}, got "
                        f"{str(kind)[:20]!r}")
    if not (isinstance(grid, int) and MIN_GRID <= grid <= MAX_GRID):
        raise MeshError(f"an impostor has {MIN_GRID} to {MAX_GRID} views a side, got {grid}")
    if not (isinstance(frame, int) and MIN_FRAME <= frame <= MAX_FRAME and frame % 2 == 0):
        raise MeshError(f"an impostor's views are an even {MIN_FRAME} to {MAX_FRAME} pixels "
                        f"a side, got {frame}")
    if grid * frame > MAX_SIDE:
        raise MeshError(f"an impostor's atlas is at most {MAX_SIDE} pixels a side, and "
                        f"{grid} views of {frame} pixels make {grid * frame}")


def bake_impostor(mesh: Mesh, grid: int = DEFAULT_GRID, frame: int = DEFAULT_FRAME,
                  kind: str = "full") -> Impostor:
    """``mesh`` (full detail, with its materials) seen from ``grid`` x ``grid``
    directions, each view ``frame`` pixels a side (see the module docstring).

    Deterministic: one thread, faces in order, fixed supersampling; the same
    mesh and options give the same atlases."""
    check_layout(grid, frame, kind)
    if mesh.face_count == 0:
        raise MeshError("an impostor needs faces to draw, and the mesh has none")
    positions = np.asarray(mesh.positions, dtype=np.float64)
    center = (positions.min(axis=0) + positions.max(axis=0)) * 0.5
    radius = float(np.sqrt(((positions - center) ** 2).sum(axis=1).max()))
    if not radius > 0:
        raise MeshError("an impostor needs a mesh of some size, and this one is a point")
    look = SurfaceLook(mesh)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    corner = positions[faces]
    geometric = np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0])
    geometric /= np.maximum(np.linalg.norm(geometric, axis=1, keepdims=True), 1e-300)
    alpha_rule = _alpha_rule(look, mesh)
    side = grid * frame
    color = np.zeros((side, side, 4))
    normal = np.zeros((side, side, 4))
    for view, direction in enumerate(decode(view_points(grid), kind)):
        row, column = divmod(view, grid)
        cell = np.s_[row * frame:(row + 1) * frame, column * frame:(column + 1) * frame]
        color[cell], normal[cell] = _view(positions - center, faces, geometric, look,
                                          alpha_rule, direction, radius, frame)
    filled = color[..., 3] > 0
    # the background takes its neighbours' colour, so that filtering and mips
    # blend an edge with itself rather than with black
    color[..., :3] = dilate(color[..., :3], filled)
    normal = _halved(dilate(normal, filled))
    return Impostor(_bytes(color), _bytes(normal), grid, frame, kind, center, radius)


def _halved(normal: np.ndarray) -> np.ndarray:
    """The normal+depth atlas (h, w, 4) at half its side (h / 2, w / 2, 4): each
    pixel the mean of 2 x 2, its normal made unit again. Shading varies slowly
    across a view and the drawing blends three views anyway; the colour atlas
    keeps the detail, and the file is a quarter of the normals' bytes."""
    h, w, _ = normal.shape
    block = normal.reshape(h // 2, 2, w // 2, 2, 4).mean(axis=(1, 3))
    unit = block[..., :3] * 2.0 - 1.0
    unit /= np.maximum(np.linalg.norm(unit, axis=2, keepdims=True), 1e-12)
    block[..., :3] = unit * 0.5 + 0.5
    return block


def _alpha_rule(look: SurfaceLook, mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Per face: its material's alpha mode (0 opaque, 1 mask, 2 blend) and cutoff."""
    records = [look.record(m) for m in range(len(look.records))] + [{}]
    modes = np.array([{"MASK": 1, "BLEND": 2}.get(r.get("alphaMode"), 0) for r in records])
    cutoffs = np.array([float(r.get("alphaCutoff", 0.5)) for r in records])
    material = (np.asarray(mesh.face_material, dtype=np.int64) if mesh.face_material is not None
                else np.full(mesh.face_count, -1))
    return modes[material], cutoffs[material]       # -1: the default material, last


def _view(positions, faces, geometric, look, alpha_rule, direction, radius, frame):
    """One view's colour and normal+depth pixels, (frame, frame, 4) floats each."""
    right, up = view_basis(direction)
    size = frame * SUPERSAMPLE
    scale = 0.5 * size / radius
    pixels = np.stack([positions @ right * scale + 0.5 * size,
                       0.5 * size - positions @ up * scale], axis=1)
    depth = positions @ direction
    face, bary = rasterize_view(pixels, depth, faces, size)
    covered = face >= 0
    f, b = face[covered], bary[covered]
    channels = look.channels(f, b, geometric)
    mode, cutoff = alpha_rule[0][f], alpha_rule[1][f]
    alpha = np.clip(channels["alpha"][:, 0], 0.0, 1.0)
    alpha = np.where(mode == 0, 1.0, np.where(mode == 1, (alpha >= cutoff) * 1.0, alpha))
    n = channels["normal"]
    n = n * np.where(n @ direction < 0, -1.0, 1.0)[:, None]     # seen from behind: turned
    point_depth = np.einsum("pk,pk->p", b, depth[faces[f]])
    fine = np.zeros((size, size, 8))
    fine[covered, 0:3] = channels["color"] * alpha[:, None]
    fine[covered, 3] = alpha
    fine[covered, 4:7] = n * alpha[:, None]
    fine[covered, 7] = point_depth / radius * alpha
    # each output pixel the mean of its supersamples; colour, normal and depth
    # weighted by alpha (premultiplied), so the background adds nothing to them
    block = fine.reshape(frame, SUPERSAMPLE, frame, SUPERSAMPLE, 8).mean(axis=(1, 3))
    weight = np.maximum(block[..., 3:4], 1e-12)
    color = np.zeros((frame, frame, 4))
    color[..., :3] = linear_to_srgb(block[..., 0:3] / weight)
    color[..., 3] = block[..., 3]
    unit = block[..., 4:7]
    unit = unit / np.maximum(np.linalg.norm(unit, axis=2, keepdims=True), 1e-12)
    normal = np.zeros((frame, frame, 4))
    normal[..., :3] = unit * 0.5 + 0.5
    normal[..., 3] = np.clip(block[..., 7:8] / weight, -1.0, 1.0)[..., 0] * 0.5 + 0.5
    empty = block[..., 3] <= 0
    color[empty] = 0.0
    normal[empty] = 0.0
    return color, normal


def _bytes(values: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(values * 255.0), 0, 255).astype(np.uint8)


def _png(pixels: np.ndarray) -> bytes:
    """RGBA uint8 pixels as PNG bytes (fixed compression: the same pixels, the same bytes)."""
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(pixels, "RGBA").save(buffer, format="PNG", compress_level=9, optimize=False)
    return buffer.getvalue()


def layout(impostor: Impostor) -> dict:
    """The ``extras.impostor`` record naming the atlases' layout (docs/pipeline.md)."""
    return {"kind": impostor.kind, "grid": impostor.grid, "frame": impostor.frame,
            "center": [float(c) for c in impostor.center], "radius": impostor.radius,
            "normalFrame": impostor.frame // 2,
            "colorTexture": 0, "normalTexture": 1, "normalImage": 1,
            "normalSpace": "object", "depth": "normal alpha: 0.5 + 0.5 * depth / radius"}


def impostor_glb(impostor: Impostor, *, name: str = "impostor") -> bytes:
    """The impostor as a GLB: one quad (one primitive, two triangles) of the
    sphere's size, facing +z, whose material shows the colour atlas's view
    nearest +z (any glTF viewer draws that); ``extras.impostor`` on the mesh
    and the material names the layout (:func:`layout`). The normal atlas is
    texture 1, which the material does not use."""
    from ..io.glb import pack_glb

    c, r = impostor.center, impostor.radius
    positions = np.array([[-r, -r, 0], [r, -r, 0], [r, r, 0], [-r, r, 0]]) + [c[0], c[1], c[2]]
    column, row = nearest_view(np.array([[0.0, 0.0, 1.0]]), impostor.grid, impostor.kind)[0]
    g = impostor.grid
    uv = (np.array([[0, 1], [1, 1], [1, 0], [0, 0]], dtype=np.float64) + [column, row]) / g
    normals = np.tile([0.0, 0.0, 1.0], (4, 1))
    indices = np.array([0, 1, 2, 0, 2, 3], dtype=np.uint16)
    chunks = [positions.astype(np.float32).tobytes(), normals.astype(np.float32).tobytes(),
              uv.astype(np.float32).tobytes(), indices.tobytes()]
    images = [_png(impostor.color), _png(impostor.normal)]
    for image in images:
        chunks.append(image + b"\0" * (-len(image) % 4))
    offsets = np.concatenate([[0], np.cumsum([len(chunk) for chunk in chunks])]).tolist()
    lengths = [48, 48, 32, 12, len(images[0]), len(images[1])]
    views = [{"buffer": 0, "byteOffset": offsets[k], "byteLength": lengths[k]}
             for k in range(6)]
    for k, target in ((0, 34962), (1, 34962), (2, 34962), (3, 34963)):
        views[k]["target"] = target
    lo, hi = positions.min(axis=0).astype(np.float32), positions.max(axis=0).astype(np.float32)
    extras = {"impostor": layout(impostor)}
    document = {
        "asset": {"version": "2.0", "generator": "lodserver impostor"},
        "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": name}],
        "meshes": [{"name": name, "extras": extras, "primitives": [{
            "attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2},
            "indices": 3, "material": 0}]}],
        "materials": [{"name": "impostor", "extras": extras, "doubleSided": True,
                       "alphaMode": "MASK", "alphaCutoff": 0.5,
                       "pbrMetallicRoughness": {"baseColorTexture": {"index": 0},
                                                "metallicFactor": 0.0, "roughnessFactor": 1.0}}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
             "min": [float(v) for v in lo], "max": [float(v) for v in hi]},
            {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC3"},
            {"bufferView": 2, "componentType": 5126, "count": 4, "type": "VEC2"},
            {"bufferView": 3, "componentType": 5123, "count": 6, "type": "SCALAR"}],
        "bufferViews": views,
        "buffers": [{"byteLength": offsets[-1]}],
        "images": [{"bufferView": 4, "mimeType": "image/png", "name": "impostor colour"},
                   {"bufferView": 5, "mimeType": "image/png", "name": "impostor normal+depth"}],
        "samplers": [_SAMPLER],
        "textures": [{"sampler": 0, "source": 0}, {"sampler": 0, "source": 1}],
    }
    return pack_glb(document, *chunks)
