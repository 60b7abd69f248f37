"""Texture levels: each level of a chain drawn with images scaled to its screen size.

A level seen from afar covers few pixels, so full-size images are wasted on it.
:func:`texture_scales` gives each level a scale of its images' sides, and
:func:`texture_levels` makes the materials each level is written with: its
images resampled (``io.image_scale``: Lanczos, base colour in linear light,
normals renormalized, each in its own format), each (image, size) made and
written once however many levels use it.

**The rule of ``auto``.** A chain's coverage hints hand a level with ``f`` of the
finest level's ``f0`` faces the screen sizes up to ``sqrt(f / f0)`` of the
finest level's (``glb.coverage_from_ratios``: constant triangle density on
screen); texels are needed per screen pixel, so the images' sides follow the
same ``sqrt(f / f0)``, of the faces the level really has (a level that stops
above its budget keeps the texels its triangles need). The scale is rounded to
a power of two (1, 1/2, 1/4, ...), so neighbouring levels share images and a
power-of-two image stays one, and no side goes below :data:`MIN_SIDE` pixels
(nor above the original).

KTX2 images (``KHR_texture_basisu``) are kept as they are at every level: a
supercompressed texture cannot be resampled without transcoding it; a note
says so.
"""

from __future__ import annotations

import copy
import math

import numpy as np

from ..io.image_scale import image_size, scaled_images
from ..io.images import image_type
from ..mesh import Materials, Mesh, MeshError

__all__ = ["MIN_SIDE", "TextureLevels", "chain_with_texture_levels", "check_texture_scale",
           "level_meshes", "parse_texture_scale", "texture_levels", "texture_levels_bytes",
           "texture_scales"]

# No image side of a scaled level goes below this (or below the original's own).
MIN_SIDE = 64

# How a texture's texels are filtered (io.image_scale.ROLES), by the material slot
# naming it: sRGB colour slots in linear light, normal maps as vectors, the rest as data.
_ROLES = {"baseColorTexture": "colour", "emissiveTexture": "colour",
          "diffuseTexture": "colour", "specularGlossinessTexture": "colour",
          "specularColorTexture": "colour", "sheenColorTexture": "colour",
          "normalTexture": "normal", "clearcoatNormalTexture": "normal"}


def parse_texture_scale(text: str):
    """``"auto"`` or the per-level scales of ``"1,0.5,0.25"`` (MeshError otherwise)."""
    if text == "auto":
        return "auto"
    try:
        return check_texture_scale(tuple(float(part) for part in text.split(",")))
    except ValueError:
        raise MeshError(f"texture scale must be auto or comma-separated numbers like "
                        f"1,0.5,0.25, got {text[:40]!r}") from None


def check_texture_scale(scale, levels: int | None = None):
    """``scale`` checked: None, ``"auto"`` or one number in (0, 1] per level
    (``levels`` of them when given)."""
    if scale is None or scale == "auto":
        return scale
    if isinstance(scale, str):
        raise MeshError(f"texture scale must be auto or numbers, got {scale[:40]!r}")
    values = tuple(float(value) for value in scale)
    if not values or not all(0 < value <= 1 for value in values):
        raise MeshError(f"every texture scale must be in (0, 1], got {list(values)}")
    if levels is not None and len(values) != levels:
        raise MeshError(f"{levels} levels need {levels} texture scales, got {len(values)}")
    return values


def texture_scales(scale, faces) -> list[float]:
    """The scale of each level's image sides: ``scale`` as given, or for ``"auto"``
    ``sqrt(faces[k] / faces[0])`` rounded to a power of two (the module's rule).

    ``faces`` : the triangles of each level, finest first (a scene's: drawn)."""
    if scale != "auto":
        return [float(value) for value in check_texture_scale(scale, len(faces))]
    full = max(int(faces[0]), 1)
    return [min(1.0, 2.0 ** round(math.log2(math.sqrt(max(int(f), 1) / full))))
            for f in faces]


def scaled_size(size: tuple[int, int], scale: float) -> tuple[int, int]:
    """An image's (width, height) at ``scale``: each side the power of two nearest
    ``side * scale``, at least ``MIN_SIDE`` (or the side, if smaller) and at most
    the side; the size itself when ``scale`` is 1."""
    if scale >= 1.0:
        return tuple(size)
    out = []
    for side in size:
        nearest = 2 ** round(math.log2(max(side * scale, 1.0)))
        out.append(int(min(side, max(nearest, MIN_SIDE))))
    return tuple(out)


class TextureLevels:
    """The materials of each level of one chain, with scaled images.

    Attributes
    ----------
    separate : list of Materials
        Level k's materials written on their own (``--separate``): the same records,
        each image at level k's size.
    chain : Materials
        Every level's materials in one list (one GLB holding the chain): a copy of
        the materials and textures for each set of sizes some level uses, naming
        its images; each (image, size) once.
    offsets : list of int
        Level k's material m is ``chain``'s material ``offsets[k] + m``.
    notes : list of str
        What was kept at full size, and why.
    """

    def __init__(self, materials: Materials, scales):
        gltf = materials.gltf
        roles = _image_roles(gltf)
        sizes = [image_size(data) for data in materials.images]
        self.notes = []
        kept = [index for index, data in enumerate(materials.images)
                if image_type(data) == "image/ktx2"]
        if kept:
            self.notes.append(f"{len(kept)} KTX2 image(s) kept at full size at every level "
                              f"(a supercompressed texture is not resampled)")
        unreadable = [index for index, size in enumerate(sizes)
                      if size is None and index not in kept]
        if unreadable:
            self.notes.append(f"{len(unreadable)} image(s) Pillow cannot read kept at full size")
        targets = [[size if size is None else scaled_size(size, scale) for size in sizes]
                   for scale in scales]
        wanted = {}         # image -> the sizes some level needs, each made once
        for level in targets:
            for index, target in enumerate(level):
                if target is not None and target != sizes[index]:
                    wanted.setdefault(index, []).append(target)
        made, images, records = {}, list(materials.images), list(gltf.get("images", ()))
        for index, needed in wanted.items():
            needed = list(dict.fromkeys(needed))
            try:
                encoded = scaled_images(materials.images[index], needed,
                                        roles.get(index, "data"))
            except MeshError as exc:
                self.notes.append(f"image {index} kept at full size: {exc}")
                continue
            for target, data in zip(needed, encoded):
                record = dict(records[index]) if index < len(records) else {}
                if record.get("name"):
                    record["name"] = _sized_name(record["name"], target)
                made[(index, target)] = len(images)
                images.append(data)
                records.append(record)
        maps = [tuple(made.get((index, target), index) for index, target in enumerate(level))
                for level in targets]
        self.separate = [_with_images(gltf, images, records, mapping) for mapping in maps]
        self.chain, self.offsets = _chained(gltf, images, records, maps)


def _sized_name(name: str, size: tuple[int, int]) -> str:
    """An image's name with its size: ``wood.png`` -> ``wood_512x512.png``."""
    stem, dot, suffix = str(name).rpartition(".")
    if not dot or suffix.lower() not in ("png", "jpg", "jpeg", "webp"):
        stem, suffix = str(name), ""
    return f"{stem}_{size[0]}x{size[1]}" + (f".{suffix}" if suffix else "")


def _with_images(gltf: dict, images: list, records: list, mapping) -> Materials:
    """The materials of ``gltf`` whose texture sources go through ``mapping``
    (old image -> new), holding only the images they name."""
    used = list(dict.fromkeys(mapping))     # each image where the original was
    where = {old: new for new, old in enumerate(used)}
    out = copy.deepcopy(gltf)
    out["images"] = [records[index] for index in used]
    for texture in out.get("textures", ()):
        _remap_sources(texture, lambda source: where[mapping[source]])
    return Materials(out, tuple(images[index] for index in used))


def _chained(gltf: dict, images: list, records: list, maps) -> tuple[Materials, list[int]]:
    """One Materials for every level (:class:`TextureLevels`'s ``chain``) and each
    level's offset into its materials: a copy of the materials and textures per
    distinct ``maps`` entry, in order of first use (the first at the original
    indices, so that records naming a material directly still find one), holding
    only the images some level uses."""
    count = len(gltf.get("materials", ()))
    texture_count = len(gltf.get("textures", ()))
    groups = list(dict.fromkeys(maps))
    used = sorted({index for mapping in groups for index in mapping})
    where = {old: new for new, old in enumerate(used)}
    materials, textures = [], []
    for number, mapping in enumerate(groups):
        for texture in gltf.get("textures", ()):
            texture = copy.deepcopy(texture)
            _remap_sources(texture, lambda source, mapping=mapping: where[mapping[source]])
            textures.append(texture)
        for material in gltf.get("materials", ()):
            material = copy.deepcopy(material)
            _shift_textures(material, number * texture_count)
            materials.append(material)
    out = dict(gltf, images=[records[index] for index in used], textures=textures,
               materials=materials)
    offsets = [groups.index(mapping) * count for mapping in maps]
    return Materials(out, tuple(images[index] for index in used)), offsets


def _remap_sources(texture: dict, remap) -> None:
    """Every image ``source`` of a texture record (its own and its extensions':
    EXT_texture_webp, KHR_texture_basisu, ...) through ``remap``, in place."""
    if isinstance(texture.get("source"), int):
        texture["source"] = remap(texture["source"])
    for extension in (texture.get("extensions") or {}).values():
        if isinstance(extension, dict) and isinstance(extension.get("source"), int):
            extension["source"] = remap(extension["source"])


def _shift_textures(record, shift: int) -> None:
    """Every texture reference (``{"index": i}`` under a key ending in ``Texture``)
    in a material record, nested in extensions too, moved by ``shift``, in place."""
    if isinstance(record, dict):
        for key, value in record.items():
            if key.endswith("Texture") and isinstance(value, dict) and \
                    isinstance(value.get("index"), int):
                value["index"] += shift
            _shift_textures(value, shift)
    elif isinstance(record, list):
        for value in record:
            _shift_textures(value, shift)


def _image_roles(gltf: dict) -> dict:
    """Image index -> how it is filtered (``_ROLES``): ``"colour"`` only when every
    slot naming it is a colour slot, ``"normal"`` when one is a normal map."""
    textures = gltf.get("textures", ())
    found = {}

    def visit(record):
        if isinstance(record, dict):
            for key, value in record.items():
                if key.endswith("Texture") and isinstance(value, dict) and \
                        isinstance(value.get("index"), int) and value["index"] < len(textures):
                    sources = []
                    _remap_sources(copy.deepcopy(textures[value["index"]]),
                                   lambda source: sources.append(source) or source)
                    for source in sources:
                        found.setdefault(source, set()).add(_ROLES.get(key, "data"))
                visit(value)
        elif isinstance(record, list):
            for value in record:
                visit(value)

    visit(gltf.get("materials", ()))
    return {index: "normal" if "normal" in roles else "colour" if roles == {"colour"}
            else "data" for index, roles in found.items()}


def texture_levels(materials: Materials | None, scale, faces) -> TextureLevels | None:
    """The :class:`TextureLevels` of a chain whose levels have ``faces`` triangles
    (finest first) under ``scale`` (``"auto"`` or one per level); None when there is
    nothing to scale (no scale, no images, or every level at full size)."""
    if scale is None or materials is None or not materials.images:
        return None
    scales = texture_scales(scale, faces)
    if all(value >= 1.0 for value in scales):
        return None
    return TextureLevels(materials, scales)


def texture_levels_bytes(materials: Materials | None) -> int:
    """What making the texture levels of ``materials`` holds in memory at most, in
    bytes (a server's estimate): the largest image decoded as four float32 bands
    twice over (source and filtered), and the scaled images, at most a third of
    the originals (each size a quarter of the one before)."""
    if materials is None:
        return 0
    pixels = [width * height for width, height in
              filter(None, (image_size(data) for data in materials.images))]
    return 32 * max(pixels, default=0) + sum(map(len, materials.images)) // 3


def level_meshes(meshes: list[Mesh], levels: TextureLevels, *, separate: bool) -> list[Mesh]:
    """``meshes`` (a chain's levels, finest first) drawn with their texture levels:
    each with its own materials (``separate``), or all with the chain's materials,
    level k's faces naming its copies (``offsets[k]``). A level without materials
    (a clustered one) stays without them, and one with materials of its own (a
    merged level's baked atlas, already sized for its coverage) keeps those."""
    out = []
    for k, mesh in enumerate(meshes):
        if mesh.materials is None or mesh.materials is not meshes[0].materials:
            out.append(mesh)
            continue
        if separate:
            out.append(Mesh(mesh.positions, mesh.faces, mesh.attributes, mesh.face_material,
                            levels.separate[k]))
            continue
        used = mesh.face_material
        if used is not None and levels.offsets[k]:
            used = np.where(used >= 0, used + levels.offsets[k], used).astype(np.int32)
        out.append(Mesh(mesh.positions, mesh.faces, mesh.attributes, used, levels.chain))
    return out


def chain_with_texture_levels(meshes: list[Mesh], scale, *,
                              separate: bool) -> tuple[list[Mesh], list[str]]:
    """A single mesh's chain (levels finest first) with its texture levels under
    ``scale`` (None, ``"auto"`` or one per level): the levels with their materials
    (:func:`level_meshes`), and notes on the images kept at full size."""
    found = texture_levels(meshes[0].materials, scale, [mesh.face_count for mesh in meshes])
    if found is None:
        return meshes, []
    return level_meshes(meshes, found, separate=separate), found.notes
