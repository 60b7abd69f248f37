"""A mesh's materials and images as a client fetches them beside its levels.

The progressive mesh keeps the glTF material, texture, sampler and image
records of its source (``mesh.Materials``) with the image bytes apart. A
client gets the records once (:func:`materials_document`), each image record
carrying a ``uri`` relative to the document (``images/{i}``, glTF's rule for
relative URIs), and fetches the images it needs (:func:`image_of`).
"""

from __future__ import annotations

from .progressive import ProgressiveMesh

# Image kinds recognized by their first bytes when a record has no mimeType.
_SIGNATURES = ((b"\x89PNG\r\n\x1a\n", "image/png"), (b"\xff\xd8\xff", "image/jpeg"),
               (b"RIFF", "image/webp"), (b"\xabKTX 20\xbb", "image/ktx2"))


class AbsentError(LookupError):
    """The mesh has no materials, or no image with that index."""


def materials_document(pm: ProgressiveMesh, *, image_uri=lambda i: f"images/{i}") -> dict:
    """The glTF ``materials``, ``textures``, ``samplers`` and ``images`` records of
    ``pm`` (and ``extensionsRequired`` when the source had it), every image with
    its ``uri`` and ``mimeType``.

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
    document["images"] = [
        {**record, "uri": image_uri(i), "mimeType": image_of(pm, i)[1]}
        for i, record in enumerate(gltf.get("images", ()))]
    if gltf.get("extensionsRequired"):
        document["extensionsRequired"] = list(gltf["extensionsRequired"])
    return document


def image_of(pm: ProgressiveMesh, index: int) -> tuple[bytes, str]:
    """The bytes of image ``index`` and its media type.

    Raises
    ------
    AbsentError
        When the mesh has no such image.
    """
    images = pm.materials.images if pm.materials is not None else ()
    if not 0 <= index < len(images):
        raise AbsentError(f"this mesh has {len(images)} images; there is no image {index}")
    data = images[index]
    records = pm.materials.gltf.get("images", ())
    media = records[index].get("mimeType") if index < len(records) else None
    if not media:
        media = next((kind for magic, kind in _SIGNATURES if data.startswith(magic)),
                     "application/octet-stream")
    return data, media
