"""A mesh's materials and their images (cacheable by version, as levels: ``api/caching.py``)."""

from __future__ import annotations

from typing import Annotated

import orjson
from fastapi import APIRouter, Path, Request, Response

from ...service.materials import AbsentError, image_of, materials_document
from ..caching import VersionQuery, etag_for, immutable, load_versioned, respond_cached
from ..deps import MeshId, StoreDep
from ..models import Message

router = APIRouter(prefix="/meshes", tags=["materials"])

_ERRORS = {code: {"model": Message} for code in (404, 409)}
# The only media types an image is served with. The loaders already refuse other
# images; this keeps a stored record saying text/html (an artefact written before
# that check, say) from ever reaching a browser as that type.
IMAGE_TYPES = ("image/png", "image/jpeg", "image/webp", "image/ktx2")


@router.get("/{mesh_id}/materials", responses={**_ERRORS, 200: {"content": {
    "application/json": {}}, "description": "glTF materials, textures, samplers and images."}})
def get_materials(mesh_id: MeshId, store: StoreDep, request: Request,
                  v: VersionQuery = None) -> Response:
    """The mesh's glTF material, texture, sampler and image records; each image's
    ``uri`` (``images/{i}``, relative to this document) is ``GET .../images/{i}``,
    at version ``v`` when it is given (``images/{i}?v=...``).
    404 when the mesh has no materials."""
    asset, digest, policy = load_versioned(store, mesh_id, v)
    etag = etag_for(digest, "materials", *(["v"] if v else []))
    uri = (lambda i: f"images/{i}?v={v}") if v else (lambda i: f"images/{i}")
    return respond_cached(request, etag, policy, lambda: immutable(
        orjson.dumps(materials_document(asset, image_uri=uri)), media_type="application/json",
        etag=etag))


@router.get("/{mesh_id}/images/{index}", responses={**_ERRORS, 200: {"content": {
    media: {} for media in IMAGE_TYPES}, "description": "The image's bytes, as uploaded."}})
def get_image(mesh_id: MeshId, store: StoreDep, request: Request,
              index: Annotated[int, Path(ge=0, le=2**31 - 1)],
              v: VersionQuery = None) -> Response:
    """Image ``index`` of the mesh's materials, byte for byte, with its media type
    (PNG, JPEG, WebP or KTX2; 404 for any other)."""
    asset, digest, policy = load_versioned(store, mesh_id, v)
    data, media = image_of(asset, index)
    if media not in IMAGE_TYPES:
        raise AbsentError(f"image {index} of this mesh is not a PNG, JPEG, WebP or KTX2 "
                          "image, so it is not served")
    etag = etag_for(digest, "image", index)
    return respond_cached(request, etag, policy,
                          lambda: immutable(data, media_type=media, etag=etag))
