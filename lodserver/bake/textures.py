"""The full-detail surface's look at given points: its materials evaluated.

``SurfaceLook(mesh)`` reads the mesh's materials (glTF records,
``mesh.Materials``), decodes the images they use once (Pillow), and
:meth:`SurfaceLook.channels` gives, at points (face, barycentrics) of the mesh,
every channel a glTF metal-roughness material has: base colour (linear RGB
and alpha: factor x texture x ``COLOR_0``), the shading normal (interpolated
``NORMAL`` perturbed by the normal map in the mesh's tangent frame), metallic,
roughness, occlusion and emissive. Textures are sampled bilinearly with their
sampler's wrap modes and ``KHR_texture_transform``, as glTF says.
"""

from __future__ import annotations

import io

import numpy as np

from ..mesh import Mesh

# glTF sampler wrap modes
REPEAT, CLAMP, MIRROR = 10497, 33071, 33648


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)


def _wrap(t: np.ndarray, size: int, mode: int) -> np.ndarray:
    """Integer texel indices ``t`` wrapped into [0, size) by glTF wrap ``mode``."""
    if mode == CLAMP:
        return np.clip(t, 0, size - 1)
    if mode == MIRROR:
        period = np.mod(t, 2 * size)
        return np.where(period < size, period, 2 * size - 1 - period)
    return np.mod(t, size)


def sample_image(image: np.ndarray, uv: np.ndarray, wrap_s: int = REPEAT,
                 wrap_t: int = REPEAT) -> np.ndarray:
    """Bilinear samples (p, c) of ``image`` (h, w, c) float at glTF UVs ``uv`` (p, 2)."""
    h, w = image.shape[:2]
    x = uv[:, 0] * w - 0.5
    y = uv[:, 1] * h - 0.5
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    xa, xb = _wrap(x0, w, wrap_s), _wrap(x0 + 1, w, wrap_s)
    ya, yb = _wrap(y0, h, wrap_t), _wrap(y0 + 1, h, wrap_t)
    top = image[ya, xa] * (1 - fx) + image[ya, xb] * fx
    bottom = image[yb, xa] * (1 - fx) + image[yb, xb] * fx
    return top * (1 - fy) + bottom * fy


def transformed(uv: np.ndarray, info: dict) -> np.ndarray:
    """``uv`` (p, 2) through a texture info's ``KHR_texture_transform``, if any."""
    transform = (info.get("extensions") or {}).get("KHR_texture_transform")
    if not transform:
        return uv
    ox, oy = transform.get("offset", (0.0, 0.0))
    sx, sy = transform.get("scale", (1.0, 1.0))
    r = float(transform.get("rotation", 0.0))
    cos, sin = np.cos(r), np.sin(r)
    u, v = uv[:, 0] * sx, uv[:, 1] * sy
    return np.stack([cos * u + sin * v + ox, -sin * u + cos * v + oy], axis=1)


def decode(data: bytes) -> np.ndarray | None:
    """An image file as (h, w, 4) float RGBA in [0, 1] (values as stored, no
    colour-space change), or None for what Pillow cannot read (KTX2)."""
    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as image:
            return np.asarray(image.convert("RGBA"), dtype=np.float64) / 255.0
    except Exception:       # Pillow raises many kinds for formats it lacks
        return None


class SurfaceLook:
    """The materials of ``mesh`` (full detail), evaluated at points of its faces."""

    def __init__(self, mesh: Mesh):
        self.mesh = mesh
        gltf = mesh.materials.gltf if mesh.materials is not None else {}
        self.records = gltf.get("materials") or []
        self.textures = gltf.get("textures") or []
        self.samplers = gltf.get("samplers") or []
        self.images = mesh.materials.images if mesh.materials is not None else ()
        self._decoded = {}
        self.unread = set()     # images that could not be decoded (sampled as white)

    def record(self, material: int) -> dict:
        """The glTF record of ``material`` (-1: glTF's default material)."""
        return self.records[material] if 0 <= material < len(self.records) else {}

    def has(self, key: str) -> bool:
        """Whether any material uses ``key`` (a texture, or emissive light)."""
        for record in self.records:
            if key == "emissive" and any(record.get("emissiveFactor", (0, 0, 0))):
                return True
            if key == "metallicRoughnessTexture" and (record.get("pbrMetallicRoughness") or {}
                                                      ).get(key):
                return True
            if key in record and key != "emissive":
                return True
        return False

    def _image(self, texture: int) -> tuple:
        record = self.textures[texture] if 0 <= texture < len(self.textures) else {}
        source = record.get("source")
        sampler = self.samplers[record["sampler"]] if 0 <= record.get(
            "sampler", -1) < len(self.samplers) else {}
        if source is None or not 0 <= source < len(self.images):
            return None, sampler
        if source not in self._decoded:
            self._decoded[source] = decode(self.images[source])
            if self._decoded[source] is None:
                self.unread.add(source)
        return self._decoded[source], sampler

    def attribute(self, name: str, face: np.ndarray, bary: np.ndarray) -> np.ndarray | None:
        """Attribute ``name`` interpolated at (face, bary), (p, width), or None."""
        attributes = self.mesh.attributes
        columns = attributes.columns(name) if attributes is not None else None
        if columns is None:
            return None
        wedges = attributes.corners[face]
        values = attributes.values[:, columns]
        return np.einsum("pk,pkc->pc", bary, values[wedges])

    def texture(self, info: dict | None, face, bary) -> np.ndarray | None:
        """The texture of texture info ``info`` at (face, bary), (p, 4) as stored."""
        if not info or "index" not in info:
            return None
        image, sampler = self._image(info["index"])
        uv = self.attribute(f"TEXCOORD_{info.get('texCoord', 0)}", face, bary)
        if image is None or uv is None:
            return None
        return sample_image(image, transformed(uv, info), sampler.get("wrapS", REPEAT),
                            sampler.get("wrapT", REPEAT))

    def channels(self, face: np.ndarray, bary: np.ndarray, geometric: np.ndarray) -> dict:
        """Every channel at the points (face (p,), bary (p, 3)); ``geometric`` (m, 3)
        the mesh's unit face normals, for faces without ``NORMAL``.

        Returns a dict of (p, c) float arrays: ``color`` linear RGB, ``alpha``,
        ``normal`` unit world-space (mesh space), ``metallic``, ``roughness``,
        ``occlusion``, ``emissive`` linear RGB."""
        p = len(face)
        out = {"color": np.ones((p, 3)), "alpha": np.ones((p, 1)), "metallic": np.ones((p, 1)),
               "roughness": np.ones((p, 1)), "occlusion": np.ones((p, 1)),
               "emissive": np.zeros((p, 3))}
        normal = self.attribute("NORMAL", face, bary)
        normal = geometric[face].copy() if normal is None else normal
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
        color = self.attribute("COLOR_0", face, bary)
        if color is not None:
            out["color"] *= color[:, :3]
            if color.shape[1] == 4:
                out["alpha"] *= color[:, 3:4]
        material = (self.mesh.face_material[face] if self.mesh.face_material is not None
                    else np.full(p, -1))
        for m in np.unique(material):
            rows = np.flatnonzero(material == m)
            self._material(self.record(int(m)), face[rows], bary[rows], rows, out, normal)
        out["normal"] = normal
        return out

    def _material(self, record, face, bary, rows, out, normal):
        pbr = record.get("pbrMetallicRoughness") or {}
        factor = np.asarray(pbr.get("baseColorFactor", (1, 1, 1, 1)), dtype=np.float64)
        out["color"][rows] *= factor[:3]
        out["alpha"][rows] *= factor[3]
        base = self.texture(pbr.get("baseColorTexture"), face, bary)
        if base is not None:
            out["color"][rows] *= srgb_to_linear(base[:, :3])
            out["alpha"][rows] *= base[:, 3:4]
        out["metallic"][rows] *= pbr.get("metallicFactor", 1.0)
        out["roughness"][rows] *= pbr.get("roughnessFactor", 1.0)
        mr = self.texture(pbr.get("metallicRoughnessTexture"), face, bary)
        if mr is not None:
            out["roughness"][rows] *= mr[:, 1:2]
            out["metallic"][rows] *= mr[:, 2:3]
        occlusion = self.texture(record.get("occlusionTexture"), face, bary)
        if occlusion is not None:
            strength = record["occlusionTexture"].get("strength", 1.0)
            out["occlusion"][rows] = 1.0 + strength * (occlusion[:, 0:1] - 1.0)
        out["emissive"][rows] = record.get("emissiveFactor", (0.0, 0.0, 0.0))
        emissive = self.texture(record.get("emissiveTexture"), face, bary)
        if emissive is not None:
            out["emissive"][rows] *= srgb_to_linear(emissive[:, :3])
        info = record.get("normalTexture")
        tangent_map = self.texture(info, face, bary)
        if tangent_map is not None:
            normal[rows] = self._perturbed(info, tangent_map, face, bary, normal[rows])

    def _perturbed(self, info, tangent_map, face, bary, normal):
        """``normal`` (p, 3) bent by a normal map's texels in the mesh's tangent
        frame: ``TANGENT`` where the mesh has it, else each face's UV gradient."""
        scale = info.get("scale", 1.0)
        local = tangent_map[:, :3] * 2.0 - 1.0
        local[:, :2] *= scale
        tangent = self.attribute("TANGENT", face, bary)
        if tangent is not None:
            t, sign = tangent[:, :3], np.where(tangent[:, 3] < 0, -1.0, 1.0)
        else:
            t, sign = self._face_tangents(info.get("texCoord", 0), face)
        t = t - normal * np.sum(t * normal, axis=1, keepdims=True)
        t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
        b = np.cross(normal, t) * sign[:, None]
        bent = t * local[:, 0:1] + b * local[:, 1:2] + normal * local[:, 2:3]
        return bent / np.maximum(np.linalg.norm(bent, axis=1, keepdims=True), 1e-12)

    def _face_tangents(self, texcoord: int, face):
        """Per face: the direction of growing u on it (p, 3), and the handedness
        (p,) of (u, v) against the face's winding."""
        from .normalmap import face_tangents

        attributes = self.mesh.attributes
        columns = attributes.columns(f"TEXCOORD_{texcoord}")
        uv = attributes.values[:, columns][attributes.corners[face]]
        return face_tangents(self.mesh.positions[self.mesh.faces[face]], uv)
