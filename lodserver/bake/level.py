"""A far level made by merging: the whole surface clustered to a face budget,
its look baked into one atlas.

``merged_level(full, budget)`` is what ``--reach merge`` draws where edge
collapse stops above the budget: vertex clustering of the full-detail mesh
(which joins parts and closes gaps smaller than a cell) on the continuous
cell size that lands within :data:`REACH_WINDOW` of the budget
(``simplify.cluster.cluster_within``). When the full mesh has any look to
keep (materials, UVs, colours or normals), :func:`bake_level` then gives the
level new UVs (``atlas.make_atlas``) and one material whose textures hold, at
each texel, the full-detail surface's nearest point's channels
(``surface.NearestSurface``, ``textures.SurfaceLook``): base colour with alpha,
a tangent-space normal map (``normalmap``), occlusion-roughness-metallic where
the source has those textures or they vary, emissive where it has any.
"""

from __future__ import annotations

import io

import numpy as np

from ..mesh import Attributes, Materials, Mesh
from ..simplify.cluster import cluster_within
from .atlas import conservative, dilate, make_atlas, rasterize
from .normalmap import encode_normals, vertex_normals_of, wedge_tangents
from .surface import NearestSurface
from .textures import SurfaceLook, linear_to_srgb

# How far a merged level may land from its face budget (a fraction of it).
REACH_WINDOW = 0.1
# Atlas sizes: a power of two between these; by default twice the pixels the
# level spans at the largest screen coverage it is drawn at (a texel per pixel
# of its front and its back), on a 1080-pixel screen.
MIN_ATLAS, MAX_ATLAS, DEFAULT_ATLAS = 64, 2048, 512
SCREEN_PIXELS = 1080
# glTF sampler: linear, trilinear mips, clamped (charts never wrap)
_SAMPLER = {"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}


def atlas_size(coverage: float | None) -> int:
    """The atlas side for a level drawn up to ``coverage`` of the screen's height
    (None: :data:`DEFAULT_ATLAS`)."""
    if coverage is None or not coverage > 0:
        return DEFAULT_ATLAS
    wanted = 2.0 * coverage * SCREEN_PIXELS
    return int(np.clip(2 ** np.ceil(np.log2(max(wanted, 1.0))), MIN_ATLAS, MAX_ATLAS))


def merged_level(full: Mesh, budget: int, *, atlas: int | None = None,
                 coverage: float | None = None) -> Mesh:
    """``full`` remeshed by vertex clustering to ``budget`` faces (within
    :data:`REACH_WINDOW` where the grid allows it), its look baked
    (:func:`bake_level`, an ``atlas`` texels a side, else sized from
    ``coverage``) when it has any: positions (k, 3), faces (f, 3), and then
    ``NORMAL``, ``TANGENT``, ``TEXCOORD_0`` and one material."""
    joined = cluster_within(Mesh(full.positions, full.faces), budget, REACH_WINDOW)
    if full.attributes is None and full.materials is None:
        return joined
    return bake_level(full, joined, atlas or atlas_size(coverage))


def bake_level(full: Mesh, level: Mesh, size: int) -> Mesh:
    """``level`` (positions and faces, in ``full``'s space) with an atlas of
    ``size`` x ``size`` texels sampled from ``full``: one primitive, one material.

    The level's faces are turned to face as the full surface nearest their
    centres does (clustering does not keep orientation); its normals are the
    area-weighted normals of those faces. Deterministic: the same meshes and
    size give the same bytes (fixed xatlas options, fixed sample seed, no threads).
    """
    surface = NearestSurface(full.positions, full.faces)
    look = SurfaceLook(full)
    positions = np.asarray(level.positions, dtype=np.float64)
    faces = _oriented(positions, np.asarray(level.faces), surface, look)
    vertex_normals = vertex_normals_of(positions, faces)
    # many small charts may need a larger side, never past the largest atlas
    vertex, uv, corners, size = make_atlas(positions, faces, size, max(size, MAX_ATLAS))
    faces = vertex[corners]              # xatlas may turn a face to fix its chart's winding
    normal = vertex_normals[vertex]
    tangent = wedge_tangents(positions, faces, corners, uv, normal)
    face_of, bary = conservative(*rasterize(uv, corners, size), uv, corners)
    filled = face_of >= 0
    f, b = face_of[filled], bary[filled]
    point = np.einsum("pk,pkc->pc", b, positions[faces[f]])
    n = np.einsum("pk,pkc->pc", b, normal[corners[f]])
    t = np.einsum("pk,pkc->pc", b, tangent[corners[f], :3])
    bitangent = np.cross(normal, tangent[:, :3]) * tangent[:, 3:]
    bt = np.einsum("pk,pkc->pc", b, bitangent[corners[f]])
    unit = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    source_face, source_bary = surface.nearest(point, unit)
    channels = look.channels(source_face, source_bary, surface.normals)
    shading = _towards(channels["normal"], _face_normals(positions, faces)[f])
    maps = _maps(look, channels, encode_normals(shading, n, t, bt))
    images, textures, material = [], [], _material(look)
    for key, (values, slot) in maps.items():
        canvas = np.zeros((size, size, values.shape[1]))
        canvas[filled] = values
        images.append(_png(dilate(canvas, filled)))
        textures.append({"sampler": 0, "source": len(images) - 1})
        slot(material, len(textures) - 1)
    layout = (("NORMAL", 3), ("TANGENT", 4), ("TEXCOORD_0", 2))
    attributes = Attributes(layout, np.concatenate([normal, tangent, uv], axis=1), corners)
    gltf = {"materials": [material], "textures": textures, "samplers": [dict(_SAMPLER)],
            "images": [{"mimeType": "image/png", "name": f"baked_{key}"} for key in maps]}
    return Mesh(positions, faces, attributes, np.zeros(len(faces), np.int32),
                Materials(gltf, tuple(images)))


def with_skin(full: Mesh, level: Mesh) -> Mesh:
    """``level`` (a merged level of the skinned ``full``, in its bind space) with
    ``full``'s skin: every ``JOINTS_n``/``WEIGHTS_n`` set of each level vertex
    copied from the full-detail wedge nearest it (the corner of the nearest
    point's face with the largest barycentric), so every wedge of a vertex has
    the same influences and the level moves with the same skeleton."""
    names = [(name, width) for name, width in full.attributes.layout
             if name.startswith(("JOINTS_", "WEIGHTS_"))]
    surface = NearestSurface(full.positions, full.faces)
    face, bary = surface.nearest(level.positions)
    wedge = full.attributes.corners[face, np.argmax(bary, axis=1)]
    skin = np.concatenate([full.attributes.values[wedge, full.attributes.columns(name)]
                           for name, _ in names], axis=1)
    own = level.attributes
    values = np.concatenate([own.values, skin[level.wedge_vertices()]], axis=1)
    return Mesh(level.positions, level.faces,
                Attributes(own.layout + tuple(names), values, own.corners),
                level.face_material, level.materials)


# The most a baked normal may lean from its far-level face: a coarse face across a
# thin part sees the part's sides edge-on, and drawing those would darken it.
MAX_LEAN = np.radians(70.0)


def _face_normals(positions, faces) -> np.ndarray:
    corner = positions[faces]
    own = np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0])
    return own / np.maximum(np.linalg.norm(own, axis=1, keepdims=True), 1e-300)


def _towards(shading: np.ndarray, face: np.ndarray) -> np.ndarray:
    """Unit normals ``shading`` (p, 3) on the side of their far-level faces' unit
    normals ``face`` (p, 3) (the full surface seen from the level's side: a thin
    part's back), leaning at most :data:`MAX_LEAN` from them. The renderer turns
    both for a face seen from behind (double-sided), so the front is what counts."""
    shading = shading * np.where(np.sum(shading * face, axis=1, keepdims=True) < 0, -1.0, 1.0)
    cos = np.sum(shading * face, axis=1, keepdims=True)
    across = shading - face * cos
    across /= np.maximum(np.linalg.norm(across, axis=1, keepdims=True), 1e-300)
    leaned = face * np.cos(MAX_LEAN) + across * np.sin(MAX_LEAN)
    return np.where(cos < np.cos(MAX_LEAN), leaned, shading)


def _oriented(positions, faces, surface, look) -> np.ndarray:
    """``faces`` with each one's winding turned to agree with the full surface's
    shading normal nearest its centre."""
    face, bary = surface.nearest(positions[faces].mean(axis=1))
    source = look.attribute("NORMAL", face, bary)
    source = surface.normals[face] if source is None else source
    flip = np.sum(_face_normals(positions, faces) * source, axis=1) < 0
    faces = faces.copy()
    faces[flip] = faces[flip][:, ::-1]
    return faces


def _material(look: SurfaceLook) -> dict:
    """The baked material's record before its textures: alpha as the source's
    (blend over mask over opaque), drawn from both sides (clustering joins the
    two sides of thin parts into one sheet)."""
    modes = [record.get("alphaMode", "OPAQUE") for record in look.records]
    material = {"name": "baked", "pbrMetallicRoughness": {}, "doubleSided": True}
    if "BLEND" in modes:
        material["alphaMode"] = "BLEND"
    elif "MASK" in modes:
        material["alphaMode"] = "MASK"
        material["alphaCutoff"] = min(record.get("alphaCutoff", 0.5) for record in look.records
                                      if record.get("alphaMode") == "MASK")
    return material


def _maps(look: SurfaceLook, channels: dict, normal_texels) -> dict:
    """name -> (texel values (p, c) in [0, 1], how the material names the texture)."""
    blended = any(record.get("alphaMode", "OPAQUE") != "OPAQUE" for record in look.records)
    color = linear_to_srgb(channels["color"])
    if blended:
        color = np.concatenate([color, np.clip(channels["alpha"], 0, 1)], axis=1)

    def pbr(key):
        return lambda material, index: material["pbrMetallicRoughness"].update(
            {key: {"index": index}})

    def top(key, **extra):
        return lambda material, index: material.update({key: {"index": index}, **extra})

    maps = {"color": (color, pbr("baseColorTexture")),
            "normal": (normal_texels, top("normalTexture"))}
    metallic, roughness = channels["metallic"], channels["roughness"]
    occluded = look.has("occlusionTexture")
    if (occluded or look.has("metallicRoughnessTexture") or np.ptp(metallic) > 0
            or np.ptp(roughness) > 0):
        orm = np.concatenate([channels["occlusion"], roughness, metallic], axis=1)

        def slot(material, index):
            pbr("metallicRoughnessTexture")(material, index)
            if occluded:
                material["occlusionTexture"] = {"index": index}
        maps["orm"] = (np.clip(orm, 0, 1), slot)
    else:
        # one value everywhere: factors instead of a texture
        constant = {"metallicFactor": float(metallic[0, 0]) if len(metallic) else 1.0,
                    "roughnessFactor": float(roughness[0, 0]) if len(roughness) else 1.0}
        maps["color"] = (color, lambda material, index: material["pbrMetallicRoughness"].update(
            {"baseColorTexture": {"index": index}, **constant}))
    if look.has("emissive"):
        maps["emissive"] = (linear_to_srgb(channels["emissive"]),
                            top("emissiveTexture", emissiveFactor=[1.0, 1.0, 1.0]))
    return maps


def _png(values: np.ndarray) -> bytes:
    """(h, w, c) values in [0, 1] as PNG bytes (8 bits, fixed compression: the same
    pixels give the same bytes)."""
    from PIL import Image

    pixels = np.clip(np.rint(values * 255.0), 0, 255).astype(np.uint8)
    mode = {1: "L", 3: "RGB", 4: "RGBA"}[pixels.shape[2]]
    buffer = io.BytesIO()
    Image.fromarray(pixels[..., 0] if mode == "L" else pixels, mode).save(
        buffer, format="PNG", compress_level=9, optimize=False)
    return buffer.getvalue()
