"""A mesh's parts: each glTF mesh of a scene with its own levels and packets.

A single mesh is a scene of one part: ``/meshes/{id}/parts/0/...`` answers
byte for byte (and ETag for ETag) as ``/meshes/{id}/lod`` and ``/splits``.
The parameters, formats and caching by version are those routes' (``lods.py``).
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, HTTPException, Path, Query, Request, Response

from ...io import SERVED_FORMATS
from ...scene.asset import PartError, part_of
from ..bodies import BodiesDep
from ..caching import VersionQuery, load_versioned
from ..deps import MeshId, StoreDep
from ..models import Message
from ...packets.served import DEFAULT_VERSION
from ...chains import DEFAULT_REACH
from .lods import Bits, LevelFormat, PacketVersion, Reach, level_response, splits_response

router = APIRouter(prefix="/meshes", tags=["parts"])

_ERRORS = {code: {"model": Message} for code in (404, 409, 422, 503)}
_COUNT = Query(ge=1, le=2**31 - 1)
_LEVEL = {"ge": 0, "le": 2**31 - 1,
          "description": "A level: a vertex count between the part's base_vertices and vertices."}
PartIndex = Annotated[int, Path(ge=0, le=2**31 - 1, description="The part's index, as "
                                "GET /meshes/{id} lists it in parts.")]


def _part(store, mesh_id: str, index: int, v: str | None):
    """(the part's progressive mesh, digest, Cache-Control, part tag for ETags: None
    for a single mesh, whose part 0 shares the mesh's own ETags)."""
    asset, digest, policy = load_versioned(store, mesh_id, v)
    try:
        pm = part_of(asset, index)
    except PartError as exc:
        raise HTTPException(404, f"mesh {mesh_id}: {exc}") from None
    return pm, digest, policy, None if asset.single is not None else index


@router.get("/{mesh_id}/parts/{index}/lod", responses={**_ERRORS, 200: {"content": {
    media: {} for media in SERVED_FORMATS.values()}, "description": "The part's level."}})
def get_part_lod(mesh_id: MeshId, index: PartIndex, store: StoreDep, bodies: BodiesDep,
                 request: Request, vertices: Annotated[int | None, _COUNT] = None,
                 faces: Annotated[int | None, _COUNT] = None,
                 ratio: Annotated[float | None, Query(gt=0, le=1)] = None,
                 error: Annotated[float | None, Query(ge=0)] = None,
                 format: LevelFormat = "json",
                 bits: Bits = None, reach: Reach = DEFAULT_REACH,
                 v: VersionQuery = None) -> Response:
    """One level of part ``index``, as ``GET /meshes/{id}/lod`` gives a mesh's (the
    part's glTF mesh in its own local space), ``reach`` included."""
    pm, digest, policy, part = _part(store, mesh_id, index, v)
    return level_response(pm, digest, policy, request, bodies, mesh_id=mesh_id,
                          criterion={"vertices": vertices, "faces": faces, "ratio": ratio,
                                     "error": error}, format=format, bits=bits, v=v, part=part,
                          reach=reach)


@router.get("/{mesh_id}/parts/{index}/splits", responses={**_ERRORS, 200: {"content": {
    "application/octet-stream": {}}, "description": "The vsplit packet (docs/packets.md)."}})
def get_part_splits(mesh_id: MeshId, index: PartIndex, store: StoreDep, bodies: BodiesDep,
                    request: Request, start: Annotated[int, Query(alias="from", **_LEVEL)],
                    to: Annotated[int, Query(**_LEVEL)], bits: Bits = None,
                    version: PacketVersion = DEFAULT_VERSION,
                    v: VersionQuery = None) -> Response:
    """The packet taking part ``index`` from level ``from`` to ``to``, as
    ``GET /meshes/{id}/splits`` does a mesh."""
    pm, digest, policy, part = _part(store, mesh_id, index, v)
    return splits_response(pm, digest, policy, request, bodies, start=start, to=to, bits=bits,
                           part=part, version=version)
