"""Levels of detail and the vsplit packets between them (immutable, cacheable)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response

from ...export import FORMATS, LevelError, check_level, checked_bits, encode_level, resolve_level
from ...gltf import encode_lod_chain
from ...packets import MAX_BITS, MIN_BITS, packet_between, prepare_records
from ...pipeline import DEFAULT_LODS, lod_chain, parse_lods
from ..caching import etag_for, immutable, is_fresh
from ..deps import CacheDep, MeshId, StoreDep
from ..models import Message

router = APIRouter(prefix="/meshes", tags=["lods"])

_ERRORS = {code: {"model": Message} for code in (404, 409, 422)}
_COUNT = Query(ge=1, le=2**31 - 1)
_LEVEL = {"ge": 0, "le": 2**31 - 1,
          "description": "A level: a vertex count between the mesh's base_vertices and vertices."}
Bits = Annotated[int | None, Query(ge=MIN_BITS, le=MAX_BITS, description="Quantization grid "
                                   "bits of the json form and of packets (default: by mesh size). "
                                   "A client must use the same value for both.")]


@router.get("/{mesh_id}/lod", responses={**_ERRORS, 200: {"content": {
    media: {} for media in FORMATS.values()}, "description": "The level in the asked format."}})
def get_lod(mesh_id: MeshId, store: StoreDep, cache: CacheDep, request: Request,
            vertices: Annotated[int | None, _COUNT] = None,
            faces: Annotated[int | None, _COUNT] = None,
            ratio: Annotated[float | None, Query(gt=0, le=1)] = None,
            error: Annotated[float | None, Query(ge=0)] = None,
            format: Literal["glb", "obj", "ply", "json"] = "json",
            bits: Bits = None) -> Response:
    """One level, chosen by exactly one of vertices, faces, ratio or error.

    ``format=json`` is the quantized form packets start from and end in
    (docs/packets.md); glb, obj and ply carry exact positions.
    """
    pm = store.load(mesh_id=mesh_id)
    level = resolve_level(pm, vertices=vertices, faces=faces, ratio=ratio, error=error)
    bits = checked_bits(bits) if format == "json" else None
    if format == "json":
        prepare_records(pm)     # the json form is where packet clients start
    etag = etag_for(store.get(mesh_id=mesh_id).digest, "lod", level, format, bits)
    if is_fresh(request, etag):
        return immutable(None, media_type=FORMATS[format], etag=etag)
    href = f"/meshes/{mesh_id}/materials"
    body = cache.get_or_make(etag, lambda: encode_level(pm, level, file_type=format, bits=bits,
                                                        materials_href=href, copy=False))
    return immutable(body, media_type=FORMATS[format], etag=etag,
                     filename=None if format == "json" else f"{mesh_id}-{level}.{format}")


@router.get("/{mesh_id}/splits", responses={**_ERRORS, 200: {"content": {
    "application/octet-stream": {}}, "description": "The vsplit packet (docs/packets.md)."}})
def get_splits(mesh_id: MeshId, store: StoreDep, cache: CacheDep, request: Request,
               start: Annotated[int, Query(alias="from", **_LEVEL)],
               to: Annotated[int, Query(**_LEVEL)], bits: Bits = None) -> Response:
    """The packet taking a client at level ``from`` to level ``to``: vertex splits
    forward, edge collapses backward."""
    pm = store.load(mesh_id=mesh_id)
    start = check_level(pm, start, name="from")
    to = check_level(pm, to, name="to")
    bits = checked_bits(bits)
    etag = etag_for(store.get(mesh_id=mesh_id).digest, "splits", start, to, bits)
    if is_fresh(request, etag):
        return immutable(None, media_type="application/octet-stream", etag=etag)
    body = cache.get_or_make(etag, lambda: packet_between(pm, start, to, bits=bits))
    return immutable(body, media_type="application/octet-stream", etag=etag)


MAX_CHAIN_LEVELS = 16


@router.get("/{mesh_id}/chain", responses={**_ERRORS, 200: {"content": {
    FORMATS["glb"]: {}}, "description": "One GLB: the levels as nodes linked by MSFT_lod."}})
def get_chain(mesh_id: MeshId, store: StoreDep, cache: CacheDep, request: Request,
              lods: Annotated[str, Query(max_length=200, description=(
                  "Face ratios of the levels, finest first, comma-separated, each in (0, 1] "
                  "and decreasing."))] = ",".join(map(str, DEFAULT_LODS)),
              reach: Annotated[Literal["none", "cluster"], Query(description=(
                  "cluster: levels edge collapse cannot bring down to their budget are made "
                  "by vertex clustering (positions only)."))] = "none") -> Response:
    """A chain of levels of detail in one GLB, as ``lodserver export`` writes it:
    node 0 the finest level, ``MSFT_lod`` naming the others, with
    ``MSFT_screencoverage`` hints."""
    pm = store.load(mesh_id=mesh_id)
    ratios = parse_lods(lods)
    if len(ratios) > MAX_CHAIN_LEVELS:
        raise LevelError(f"a chain holds at most {MAX_CHAIN_LEVELS} levels, got {len(ratios)}")
    etag = etag_for(store.get(mesh_id=mesh_id).digest, "chain", ",".join(map(repr, ratios)), reach)
    if is_fresh(request, etag):
        return immutable(None, media_type=FORMATS["glb"], etag=etag)
    body = cache.get_or_make(etag, lambda: encode_lod_chain(*lod_chain(pm, ratios,
                                                                       reach=reach)[:2]))
    return immutable(body, media_type=FORMATS["glb"], etag=etag,
                     filename=f"{mesh_id}-lods.glb")
