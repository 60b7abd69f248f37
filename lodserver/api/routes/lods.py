"""Levels of detail and the vsplit packets between them (cacheable, by version).

Bodies come from ``Bodies`` (``api/bodies.py``): from memory or a body file when
encoded before, else encoded under the heavy-request limit (503 when it is
taken), large ones written to a body file and streamed from it.

Every route takes ``v``, the artefact's version as ``GET /meshes/{id}`` hands
it out in its URLs: with it a response is cacheable for a year by any cache (a
CDN), without it for a minute then revalidated by ETag (``api/caching.py``).
"""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response

from ...io.glb import encode_lod_chain
from ...packets import MAX_BITS, MIN_BITS, packet_between, prepare_records, records_ready
from ...pipeline import DEFAULT_LODS, lod_chain, parse_lods
from ...service.levels import (
    FORMATS,
    LevelError,
    check_level,
    checked_bits,
    encode_level,
    resolve_level,
)
from ..bodies import LIGHT_FACES, BodiesDep
from ..caching import (
    VersionQuery,
    etag_for,
    immutable,
    is_fresh,
    load_versioned,
    version_of,
    with_cache_control,
)
from ..deps import MeshId, StoreDep
from ..models import Message

router = APIRouter(prefix="/meshes", tags=["lods"])

_ERRORS = {code: {"model": Message} for code in (404, 409, 422, 503)}
_COUNT = Query(ge=1, le=2**31 - 1)
_LEVEL = {"ge": 0, "le": 2**31 - 1,
          "description": "A level: a vertex count between the mesh's base_vertices and vertices."}
Bits = Annotated[int | None, Query(ge=MIN_BITS, le=MAX_BITS, description="Quantization grid "
                                   "bits of the json form and of packets (default: by mesh size). "
                                   "A client must use the same value for both.")]


@router.get("/{mesh_id}/lod", responses={**_ERRORS, 200: {"content": {
    media: {} for media in FORMATS.values()}, "description": "The level in the asked format."}})
def get_lod(mesh_id: MeshId, store: StoreDep, bodies: BodiesDep, request: Request,
            vertices: Annotated[int | None, _COUNT] = None,
            faces: Annotated[int | None, _COUNT] = None,
            ratio: Annotated[float | None, Query(gt=0, le=1)] = None,
            error: Annotated[float | None, Query(ge=0)] = None,
            format: Literal["glb", "obj", "ply", "json"] = "json",
            bits: Bits = None, v: VersionQuery = None) -> Response:
    """One level, chosen by exactly one of vertices, faces, ratio or error.

    ``format=json`` is the quantized form packets start from and end in
    (docs/packets.md); glb, obj and ply carry exact positions. A json level
    names its materials document, at version ``v`` when it is given.
    """
    pm, digest, policy = load_versioned(store, mesh_id, v)
    level = resolve_level(pm, vertices=vertices, faces=faces, ratio=ratio, error=error)
    bits = checked_bits(bits) if format == "json" else None
    if format == "json":
        prepare_records(pm)     # the json form is where packet clients start
    # a json level links its materials the way it was asked for: at its version
    # when it was, else by id; so its ETag tells the two bodies apart
    linked = format == "json" and v is not None
    etag = etag_for(digest, "lod", level, format, bits, *(["v"] if linked else []))
    if is_fresh(request, etag):
        return with_cache_control(immutable(None, media_type=FORMATS[format], etag=etag), policy)
    href = f"/meshes/{mesh_id}/materials" + (f"?v={version_of(digest)}" if linked else "")
    return with_cache_control(bodies.respond(
        etag, lambda: encode_level(pm, level, file_type=format, bits=bits,
                                   materials_href=href, copy=False),
        media_type=FORMATS[format],
        filename=None if format == "json" else f"{mesh_id}-{level}.{format}",
        weight=int(pm.faces_at_level(level) > LIGHT_FACES)), policy)


@router.get("/{mesh_id}/splits", responses={**_ERRORS, 200: {"content": {
    "application/octet-stream": {}}, "description": "The vsplit packet (docs/packets.md)."}})
def get_splits(mesh_id: MeshId, store: StoreDep, bodies: BodiesDep, request: Request,
               start: Annotated[int, Query(alias="from", **_LEVEL)],
               to: Annotated[int, Query(**_LEVEL)], bits: Bits = None,
               v: VersionQuery = None) -> Response:
    """The packet taking a client at level ``from`` to level ``to``: vertex splits
    forward, edge collapses backward.

    At the default ``bits`` a packet is cut from the mesh's records, encoded once
    per direction; other ``bits`` are encoded for the packet (under the heavy
    limit), and each such packet once: its body is cached like a level's."""
    pm, digest, policy = load_versioned(store, mesh_id, v)
    start = check_level(pm, start, name="from")
    to = check_level(pm, to, name="to")
    bits = checked_bits(bits)
    etag = etag_for(digest, "splits", start, to, bits)
    if is_fresh(request, etag):
        return with_cache_control(immutable(None, media_type="application/octet-stream",
                                            etag=etag), policy)
    forward = to > start
    # a packet at the default grid is a slice once its direction's records are
    # encoded (by the build, the background preparation or an earlier packet)
    light = start == to or (bits is None and records_ready(pm, forward))
    return with_cache_control(bodies.respond(
        etag, lambda: packet_between(pm, start, to, bits=bits),
        media_type="application/octet-stream", weight=0 if light else 1), policy)


MAX_CHAIN_LEVELS = 16
# A chain's levels hold at most this many times the mesh's faces. The encoder
# holds the whole chain in memory: 16 levels near full detail of a mesh at the
# 10M-triangle limit would be ~12 GB, while the default chain is 1.75 times.
MAX_CHAIN_FACES = 4


@router.get("/{mesh_id}/chain", responses={**_ERRORS, 200: {"content": {
    FORMATS["glb"]: {}}, "description": "One GLB: the levels as nodes linked by MSFT_lod."}})
def get_chain(mesh_id: MeshId, store: StoreDep, bodies: BodiesDep, request: Request,
              lods: Annotated[str, Query(max_length=200, description=(
                  "Face ratios of the levels, finest first, comma-separated, each in (0, 1] "
                  "and decreasing."))] = ",".join(map(str, DEFAULT_LODS)),
              reach: Annotated[Literal["none", "cluster"], Query(description=(
                  "cluster: levels edge collapse cannot bring down to their budget are made "
                  "by vertex clustering (positions only)."))] = "none",
              v: VersionQuery = None) -> Response:
    """A chain of levels of detail in one GLB, as ``lodserver export`` writes it:
    node 0 the finest level, ``MSFT_lod`` naming the others, with
    ``MSFT_screencoverage`` hints.

    The encoder holds the whole chain in memory while it builds it (about 700 MB
    at peak for 16 levels of a 1.1M-face mesh), so an uncached chain of more than
    ``LIGHT_FACES`` faces takes every heavy slot; it is then written to a body
    file and streamed from it."""
    pm, digest, policy = load_versioned(store, mesh_id, v)
    ratios = parse_lods(lods)
    if len(ratios) > MAX_CHAIN_LEVELS:
        raise LevelError(f"a chain holds at most {MAX_CHAIN_LEVELS} levels, got {len(ratios)}")
    faces = sum(pm.faces_at_level(pm.level_for(ratio=ratio)) for ratio in ratios)
    full = pm.faces_at_level(pm.vertex_count)
    if faces > MAX_CHAIN_FACES * full:
        raise LevelError(f"a chain's levels hold at most {MAX_CHAIN_FACES} times the mesh's "
                         f"faces; these ratios add up to {faces / full:.2f} times")
    etag = etag_for(digest, "chain", ",".join(map(repr, ratios)), reach)
    if is_fresh(request, etag):
        return with_cache_control(immutable(None, media_type=FORMATS["glb"], etag=etag), policy)
    # clustering (reach) works on the full mesh: never light
    return with_cache_control(bodies.respond(
        etag, lambda: encode_lod_chain(*lod_chain(pm, ratios, reach=reach)[:2]),
        media_type=FORMATS["glb"], filename=f"{mesh_id}-lods.glb",
        weight=0 if reach == "none" and faces <= LIGHT_FACES else bodies.heavy.slots), policy)
