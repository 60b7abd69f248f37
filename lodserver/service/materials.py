"""A mesh's materials and images as a client fetches them beside its levels.

The progressive mesh keeps the glTF material, texture, sampler and image
records of its source (``mesh.Materials``) with the image bytes apart. A
client gets the records once (:func:`materials_document`), each image record
carrying a ``uri`` relative to the document (``images/{i}``, glTF's rule for
relative URIs), and fetches the images it needs (:func:`image_of`).
"""

from __future__ import annotations

from ..io.gltf import extension_names
from ..io.images import image_type
from ..progressive.mesh import ProgressiveMesh
from ..scene.asset import SceneAsset


class AbsentError(LookupError):
    """The mesh has no materials, or no image with that index."""


def materials_document(pm: ProgressiveMesh | SceneAsset, *,
                       image_uri=lambda i: f"images/{i}") -> dict:
    """The glTF ``materials``, ``textures``, ``samplers`` and ``images`` records of
    ``pm``, every image with its ``uri`` and ``mimeType``; ``extensionsUsed``
    naming the extensions these records use (``KHR_texture_transform``,
    ``KHR_materials_emissive_strength``, ...), and ``extensionsRequired`` when
    the source required some of them. Every channel the records hold is kept
    as the source wrote it (base colour, metallic-roughness, normal,
    occlusion, emissive, alpha mode and cutoff, double-sided, extensions).

    Raises
    ------
    AbsentError
        When the mesh has no materials.
    """
    if pm.materials is None:
        raise AbsentError("this mesh has no materials (its source had none, or it was built "
                          "without attributes)")
    gltf = pm.materials.gltf
    document = {key: list(gltf.get(key, ())) for key in ("materials", "textures", "samplers")}
    # the type the bytes are (image_of sends no other), whatever the record says
    document["images"] = [
        {**record, "uri": image_uri(i),
         "mimeType": image_type(data) or "application/octet-stream"}
        for i, (record, data) in enumerate(zip(gltf.get("images", ()), pm.materials.images))]
    used = sorted(extension_names([document[key] for key in ("materials", "textures", "images")]))
    if used:
        document["extensionsUsed"] = used
    if gltf.get("extensionsRequired"):
        document["extensionsRequired"] = list(gltf["extensionsRequired"])
    return document


def image_of(pm: ProgressiveMesh | SceneAsset, index: int) -> tuple[bytes, str]:
    """The bytes of image ``index`` and its media type, sniffed from the bytes.

    Only image types are ever returned (PNG, JPEG, WebP, KTX2): the loaders
    refuse anything else, and bytes stored before they did (an artefact whose
    "image" is HTML, say) are refused here rather than served as what their
    record claims.

    Raises
    ------
    AbsentError
        When the mesh has no such image, or its bytes are no image type.
    """
    images = pm.materials.images if pm.materials is not None else ()
    if not 0 <= index < len(images):
        raise AbsentError(f"this mesh has {len(images)} images; there is no image {index}")
    data = images[index]
    media = image_type(data)
    if media is None:
        raise AbsentError(f"image {index} of this mesh is not a PNG, JPEG, WebP or KTX2 image")
    return data, media
