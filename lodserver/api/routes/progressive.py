"""The progressive file of a mesh or scene: the bytes ``lodserver export MESH
--progressive`` writes (``service/progressive_file.py``), immutable at the mesh's
version, read by clients with ``Range`` requests as from any static host."""

from __future__ import annotations

import re

from fastapi import APIRouter, HTTPException, Request, Response

from ...service.levels import level_bytes, packet_bytes
from ...service.progressive_file import progressive_glb
from ..bodies import BodiesDep
from ..caching import BufferResponse, VersionQuery, etag_for, load_versioned
from ..deps import MeshId, StoreDep
from ..models import Message
from .lods import Bits

router = APIRouter(prefix="/meshes", tags=["progressive"])

_GLB = "model/gltf-binary"
_ERRORS = {code: {"model": Message} for code in (404, 409, 416, 503)}
# One range of bytes: first-last, first- (to the end) or -suffix (the last bytes).
_RANGE = re.compile(r"bytes=(\d*)-(\d*)")


@router.get("/{mesh_id}/progressive", responses={**_ERRORS, 200: {"content": {_GLB: {}},
            "description": "The progressive file (docs/packets.md, \"The progressive file\")."},
            206: {"description": "The bytes a Range asked for."}})
def get_progressive(mesh_id: MeshId, store: StoreDep, bodies: BodiesDep, request: Request,
                    v: VersionQuery = None, bits: Bits = None) -> Response:
    """One GLB holding the base level (drawn by any glTF viewer), the base's json
    form and every split and collapse record in chunks, indexed in the root
    extension ``LODSERVER_progressive``: a client reads its header and JSON with
    one ``Range`` request and any level with one more. A scene's file holds every
    part and the whole document (skins, animations). ``bits`` sets the grid of
    the base and the records, as ``/lod?format=json&bits=`` (``lodserver export
    --progressive --bits``)."""
    asset, digest, policy = load_versioned(store, mesh_id, v)
    # the file's summary names the mesh: its name is part of the bytes' identity
    name = store.get(mesh_id=mesh_id).name
    etag = etag_for(digest, "progressive", name, *(() if bits is None else ("bits", bits)))
    pms = asset.pms.values()
    response = bodies.cached(
        request, etag, policy, lambda: progressive_glb(asset, name=name, bits=bits),
        media_type=_GLB, filename=f"{mesh_id}.glb",
        estimate=lambda: sum(level_bytes(pm, pm.base_vertices, "glb")
                             + 2 * packet_bytes(pm, pm.base_vertices, pm.vertex_count, bits)
                             for pm in pms))
    return ranged(request, response)


def ranged(request: Request, response: Response) -> Response:
    """``response`` cut to the request's one byte range (206 with Content-Range), or
    a 416 when the range starts past the end. A body file's response (a
    FileResponse) cuts its own ranges; a Range of several ranges, or one that is not
    of bytes, is answered whole, as HTTP allows."""
    response.headers["Accept-Ranges"] = "bytes"
    asked = request.headers.get("range")
    match = _RANGE.fullmatch(asked.strip()) if asked else None
    if (match is None or not isinstance(response, BufferResponse) or response.status_code != 200
            or match.groups() == ("", "")):
        return response
    body = memoryview(response.body).cast("B")
    size = len(body)
    first, last = match.groups()
    if first == "":
        start, stop = max(0, size - int(last)), size
    else:
        start, stop = int(first), size if last == "" else min(size, int(last) + 1)
    if start >= size or stop <= start:
        raise HTTPException(416, f"the range {asked[:60]} lies outside the file's {size} bytes",
                            headers={"Content-Range": f"bytes */{size}"})
    headers = {key: value for key, value in response.headers.items()
               if key.lower() not in ("content-length", "content-type")}
    headers["Content-Range"] = f"bytes {start}-{stop - 1}/{size}"
    return BufferResponse(body[start:stop], status_code=206, media_type=_GLB, headers=headers)
