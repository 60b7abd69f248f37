"""Levels of detail and the vsplit packets between them (cacheable, by version).

Bodies come from ``Bodies`` (``api/bodies.py``): from memory or a body file when
encoded before, else encoded under the heavy-request limit, weighed by its
estimated bytes (503 when its slots are taken), large ones written to a body
file and streamed from it.

Every route takes ``v``, the artefact's version as ``GET /meshes/{id}`` hands
it out in its URLs: with it a response is cacheable for a year by any cache (a
CDN), without it for a minute then revalidated by ETag (``api/caching.py``).
"""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response

from ...io import SERVED_FORMATS, encode_mesh
from ...mesh import MeshError
from ...io.glb import COMPRESSIONS, coverage_from_ratios, encode_lod_chain
from ...packets import MAX_BITS, MIN_BITS, prepare_records, records_ready
from ...packets.served import DEFAULT_VERSION, PACKET_WRITERS, SERVED_VERSIONS
from ...chains import (DEFAULT_LODS, DEFAULT_REACH, REACH_METHODS, lod_chain, out_of_reach,
                       parse_lods, reached_level, shared_materials)
from ...service.levels import (
    LevelError,
    chain_bytes,
    check_level,
    checked_bits,
    encode_level,
    level_bytes,
    packet_bytes,
    resolve_level,
    scene_bytes,
)
from ...scene.asset import SceneAsset, scene_levels_for
from ...scene.textures import chain_with_texture_levels, texture_levels_bytes
from ...scene.write import far_scene_glb, scene_budget_beyond_reach, scene_chain_glb, scene_glb
from ..bodies import BodiesDep
from ..caching import VersionQuery, etag_for, load_versioned, version_of
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
# (a range: the versions written are consecutive, and a query's string is not a Literal's int)
PacketVersion = Annotated[int, Query(
    ge=min(SERVED_VERSIONS), le=max(SERVED_VERSIONS), description=(
    "The packet format version (docs/packets.md): 3 (the default, for clients written "
    "before version 4) or 4 (entropy-coded, smaller); GET /meshes/{id} lists them as "
    "packet_versions."))]
# The formats a level is served in: those of the output-format registry (io/save.py).
LevelFormat = Literal[tuple(SERVED_FORMATS)]
Compress = Annotated[Literal[tuple(COMPRESSIONS)], Query(description=(
    "How a GLB stores the level: none (float32), quantize (KHR_mesh_quantization) or meshopt "
    "(also EXT_meshopt_compression); quantize and meshopt in vertex cache order."))]
_GLB = SERVED_FORMATS["glb"]
Reach = Annotated[Literal[tuple(REACH_METHODS)], Query(description=(
    "Levels whose face budget edge collapse cannot reach (separate parts, soups): merge "
    "(the default, as lodserver export --lods) remeshes the full mesh by clustering and "
    "bakes its look into one atlas and one material; cluster remeshes positions only; "
    "none keeps the coarsest level edge collapse reaches."))]


@router.get("/{mesh_id}/lod", responses={**_ERRORS, 200: {"content": {
    media: {} for media in SERVED_FORMATS.values()},
    "description": "The level in the asked format."}})
def get_lod(mesh_id: MeshId, store: StoreDep, bodies: BodiesDep, request: Request,
            vertices: Annotated[int | None, _COUNT] = None,
            faces: Annotated[int | None, _COUNT] = None,
            ratio: Annotated[float | None, Query(gt=0, le=1)] = None,
            error: Annotated[float | None, Query(ge=0)] = None,
            format: LevelFormat = "json",
            bits: Bits = None, compress: Compress = "none", reach: Reach = DEFAULT_REACH,
            v: VersionQuery = None) -> Response:
    """One level, chosen by exactly one of vertices, faces, ratio or error.

    ``format=json`` is the quantized form packets start from and end in
    (docs/packets.md); glb, obj and ply carry exact positions. A json level
    names its materials document, at version ``v`` when it is given.

    A glb, obj or ply level asked for by ``faces`` or ``ratio`` that edge
    collapse cannot bring within ``chains.REACH_SLACK`` of its budget is made
    as ``reach`` says (``chains.reached_level``; a merged level in GLB has one
    material, its baked atlas). Such a level is made from the full mesh, so it
    takes every heavy slot while it is made (``api/bodies.py``), and is cached
    like any level. A json level is always edge collapse's: packets apply to it.

    A scene's level is the whole scene as GLB (``format=glb``), chosen by ratio
    (of the scene's triangles, one budget over its parts) or error (a fraction
    of its bounding-box diagonal); each part's glTF mesh says its part in
    ``extras.lodserver_part``. Its parts' levels: ``/meshes/{id}/parts/{p}/lod``.
    A scene's level by ratio that edge collapse leaves over its budget is, with
    ``reach=merge``, merged as ``export --separate`` merges it
    (``scene.write.far_scene_glb``): a static scene as one mesh, remeshed and
    baked; a moving one by groups of the meshes that move together.
    """
    asset, digest, policy = load_versioned(store, mesh_id, v)
    if asset.single is None:
        return _scene_lod(asset, digest, policy, request, bodies, mesh_id=mesh_id,
                          vertices=vertices, faces=faces, ratio=ratio, error=error,
                          format=format, compress=compress, reach=reach)
    return level_response(asset.single, digest, policy, request, bodies, mesh_id=mesh_id,
                          criterion={"vertices": vertices, "faces": faces, "ratio": ratio,
                                     "error": error}, format=format, bits=bits, v=v,
                          compress=compress, reach=reach)


def level_response(pm, digest: str, policy: str, request: Request, bodies, *, mesh_id: str,
                   criterion: dict, format: str, bits: int | None, v: str | None,
                   part: int | None = None, compress: str = "none",
                   reach: str = "none") -> Response:
    """The response of one level of ``pm`` (a mesh, or part ``part`` of a scene:
    None for a single mesh, whose part 0 is then the mesh's own level, ETag too);
    beyond edge collapse's reach made as ``reach`` says (:func:`get_lod`)."""
    level = resolve_level(pm, **criterion)
    budget = _budget(pm, criterion)
    if reach != "none" and format != "json" and budget is not None and out_of_reach(pm, budget):
        return _reached_response(pm, digest, policy, request, bodies, mesh_id=mesh_id,
                                 budget=budget, reach=reach, format=format, part=part,
                                 compress=compress, fallback=level)
    bits = checked_bits(bits) if format == "json" else None
    if format == "json":
        prepare_records(pm)     # the json form is where packet clients start
    # a json level links its materials the way it was asked for: at its version
    # when it was, else by id; so its ETag tells the two bodies apart
    linked = format == "json" and v is not None
    scope = () if part is None else ("part", part)
    if compress != "none" and format != "glb":
        raise LevelError(f"compress={compress} applies to format=glb only")
    etag = etag_for(digest, *scope, "lod", level, format, bits, *(["v"] if linked else []),
                    *([compress] if compress != "none" else []))
    href = f"/meshes/{mesh_id}/materials" + (f"?v={version_of(digest)}" if linked else "")
    return bodies.cached(
        request, etag, policy, lambda: encode_level(pm, level, file_type=format, bits=bits,
                                                    materials_href=href, copy=False,
                                                    compress=compress),
        media_type=SERVED_FORMATS[format],
        filename=None if format == "json" else
        f"{mesh_id}-{'' if part is None else f'part{part}-'}{level}.{format}",
        estimate=lambda: level_bytes(pm, level, format, bits))


@router.get("/{mesh_id}/splits", responses={**_ERRORS, 200: {"content": {
    "application/octet-stream": {}}, "description": "The vsplit packet (docs/packets.md)."}})
def get_splits(mesh_id: MeshId, store: StoreDep, bodies: BodiesDep, request: Request,
               start: Annotated[int, Query(alias="from", **_LEVEL)],
               to: Annotated[int, Query(**_LEVEL)], bits: Bits = None,
               version: PacketVersion = DEFAULT_VERSION, v: VersionQuery = None) -> Response:
    """The packet taking a client at level ``from`` to level ``to``: vertex splits
    forward, edge collapses backward.

    At the default ``bits`` a packet is cut from the mesh's records, encoded once
    per direction; other ``bits`` are encoded for the packet (under the heavy
    limit), and each such packet once: its body is cached like a level's.
    A scene's packets are its parts': ``/meshes/{id}/parts/{p}/splits``."""
    asset, digest, policy = load_versioned(store, mesh_id, v)
    if asset.single is None:
        raise LevelError(f"mesh {mesh_id} is a scene of {len(asset.parts)} parts; its "
                         f"packets are its parts': /meshes/{mesh_id}/parts/{{p}}/splits")
    return splits_response(asset.single, digest, policy, request, bodies, start=start, to=to,
                           bits=bits, version=version)


def _budget(pm, criterion: dict) -> int | None:
    """The face budget a level criterion names (``faces`` or ``ratio``), else None."""
    if criterion.get("faces") is not None:
        return int(criterion["faces"])
    if criterion.get("ratio") is not None:
        return max(1, round(criterion["ratio"] * pm.face_count))
    return None


def _reached_response(pm, digest: str, policy: str, request: Request, bodies, *, mesh_id: str,
                      budget: int, reach: str, format: str, part: int | None, compress: str,
                      fallback: int) -> Response:
    """The level of ``budget`` faces that ``reach`` makes of ``pm``'s full mesh
    (edge collapse's level ``fallback`` where clustering keeps no face), named by
    the budget and method. Its atlas is sized for the coverage a chain from full
    detail to this budget would draw it up to."""
    if compress != "none" and format != "glb":
        raise LevelError(f"compress={compress} applies to format=glb only")
    scope = () if part is None else ("part", part)
    etag = etag_for(digest, *scope, "lod-reach", reach, budget, format,
                    *([compress] if compress != "none" else []))
    # out of reach, so the budget is below the mesh's faces
    coverage = coverage_from_ratios([1.0, budget / pm.face_count])[0]

    def make():
        mesh = reached_level(pm, budget, reach, coverage=coverage)
        return encode_mesh(pm.at(fallback) if mesh is None else mesh, format, compress=compress)
    return bodies.cached(
        request, etag, policy, make, media_type=SERVED_FORMATS[format],
        filename=f"{mesh_id}-{'' if part is None else f'part{part}-'}{budget}f.{format}",
        # made from the full mesh: every slot while it is made
        estimate=lambda: bodies.heavy.budget)


def splits_response(pm, digest: str, policy: str, request: Request, bodies, *, start: int,
                    to: int, bits: int | None, part: int | None = None,
                    version: int = DEFAULT_VERSION) -> Response:
    """The response of the packet from ``start`` to ``to`` of ``pm`` in packet format
    ``version`` (``part`` as for :func:`level_response`)."""
    start = check_level(pm, start, name="from")
    to = check_level(pm, to, name="to")
    bits = checked_bits(bits)
    # the default version's ETags stay what they were, so caches keep their entries
    etag = etag_for(digest, *(() if part is None else ("part", part)), "splits", start, to, bits,
                    *([f"version{version}"] if version != DEFAULT_VERSION else []))
    write = PACKET_WRITERS[version]
    forward = to > start
    # a packet at the default grid is a slice once its direction's records are
    # encoded (by the build, the background preparation or an earlier packet)
    light = start == to or (bits is None and records_ready(pm, forward))
    return bodies.cached(request, etag, policy, lambda: write(pm, start, to, bits=bits),
                         media_type="application/octet-stream",
                         estimate=lambda: 0 if light else packet_bytes(pm, start, to, bits))


MAX_CHAIN_LEVELS = 16
# A chain's levels hold at most this many times the mesh's faces. The encoder
# holds the whole chain in memory: 16 levels near full detail of a mesh at the
# 10M-triangle limit would be ~12 GB, while the default chain is 1.75 times.
MAX_CHAIN_FACES = 4


@router.get("/{mesh_id}/chain", responses={**_ERRORS, 200: {"content": {
    _GLB: {}}, "description": "One GLB: the levels as nodes linked by MSFT_lod."}})
def get_chain(mesh_id: MeshId, store: StoreDep, bodies: BodiesDep, request: Request,
              lods: Annotated[str, Query(max_length=200, description=(
                  "Face ratios of the levels, finest first, comma-separated, each in (0, 1] "
                  "and decreasing."))] = ",".join(map(str, DEFAULT_LODS)),
              reach: Reach = DEFAULT_REACH,
              compress: Compress = "none",
              texture_scale: Annotated[Literal["none", "auto"], Query(description=(
                  "auto: each level's images scaled to its screen size, as lodserver "
                  "export --texture-scale auto (KTX2 kept as it is)."))] = "none",
              v: VersionQuery = None) -> Response:
    """A chain of levels of detail in one GLB, as ``lodserver export`` writes it:
    node 0 the finest level, ``MSFT_lod`` naming the others, with
    ``MSFT_screencoverage`` hints.

    Levels edge collapse cannot bring within ``chains.REACH_SLACK`` of their
    budget are made as ``reach`` says (``chains.lod_chain``: merged, by default,
    into one baked material that the chain's materials list gains).

    The encoder holds the whole chain in memory while it builds it, so an
    uncached chain weighs the bytes of all its levels (``api/bodies.py``), and
    one with a level made by ``reach`` (which works on the full mesh) every heavy
    slot; a large one is then written to a body file and streamed from it. A
    chain whose levels edge collapse all reaches is the same whatever ``reach``
    says, and so is its ETag.

    A scene's chain is the scene with ``MSFT_lod`` on every node placing a part,
    level k of every part at scene ratio k (one budget over the parts), all made
    by edge collapse (``reach`` applies to a scene's single levels)."""
    asset, digest, policy = load_versioned(store, mesh_id, v)
    ratios = parse_lods(lods)
    if len(ratios) > MAX_CHAIN_LEVELS:
        raise LevelError(f"a chain holds at most {MAX_CHAIN_LEVELS} levels, got {len(ratios)}")
    pm = asset.single
    if pm is None:
        return _scene_chain(asset, digest, policy, request, bodies, mesh_id=mesh_id,
                            ratios=ratios, reach=reach, compress=compress,
                            texture_scale=texture_scale)
    levels = [pm.level_for(ratio=ratio) for ratio in ratios]
    faces = sum(pm.faces_at_level(level) for level in levels)
    full = pm.faces_at_level(pm.vertex_count)
    if faces > MAX_CHAIN_FACES * full:
        raise LevelError(f"a chain's levels hold at most {MAX_CHAIN_FACES} times the mesh's "
                         f"faces; these ratios add up to {faces / full:.2f} times")
    scaled = texture_scale if texture_scale != "none" else None
    if not any(out_of_reach(pm, max(1, round(ratio * full))) for ratio in ratios):
        reach = "none"
    etag = etag_for(digest, "chain", ",".join(map(repr, ratios)), reach,
                    *([compress] if compress != "none" else []),
                    *(["textures", scaled] if scaled else []))
    # a level made by reach works on the full mesh: it takes every slot
    return bodies.cached(
        request, etag, policy,
        lambda: encode_lod_chain(*_with_textures(*lod_chain(pm, ratios, reach=reach)[:2],
                                                 scaled), compress),
        media_type=_GLB, filename=f"{mesh_id}-lods.glb",
        estimate=lambda: bodies.heavy.budget if reach != "none" else (
            chain_bytes(pm, levels) + (texture_levels_bytes(pm.materials) if scaled else 0)))


def _with_textures(meshes: list, coverage: list, texture_scale) -> tuple[list, list]:
    """A mesh's chain (its levels and coverage hints) with its texture levels, a
    baked level's material joined to the rest (``chains.shared_materials``)."""
    meshes = chain_with_texture_levels(meshes, texture_scale, separate=False)[0]
    return shared_materials(meshes), coverage


def _scene_levels(asset: SceneAsset, **criterion) -> dict:
    try:
        return scene_levels_for(asset, **criterion)
    except (ValueError, TypeError) as exc:
        raise LevelError(str(exc)) from exc


def _scene_lod(asset: SceneAsset, digest: str, policy: str, request: Request, bodies, *,
               mesh_id: str, vertices, faces, ratio, error, format: str,
               compress: str = "none", reach: str = "none") -> Response:
    """The whole scene at one level (``get_lod``), as GLB stored as ``compress`` says."""
    if format != "glb":
        raise LevelError(f"mesh {mesh_id} is a scene of {len(asset.parts)} parts: its levels "
                         "are GLB files of the whole scene (format=glb); a part's level in any "
                         f"format is /meshes/{mesh_id}/parts/{{p}}/lod")
    if vertices is not None or faces is not None or (ratio is None) == (error is None):
        raise LevelError("a scene's level is chosen by exactly one of ratio (of the scene's "
                         "triangles) and error (a fraction of its bounding-box diagonal)")
    levels = _scene_levels(asset, ratio=ratio, error=error)
    budget = scene_budget_beyond_reach(asset, ratio, levels) if ratio is not None \
        and reach == "merge" else None
    if budget is not None:
        def make():
            try:
                return far_scene_glb(asset, ratio, levels, compress)
            except MeshError:       # a scene of a few faces asked for fewer
                return scene_glb(asset, levels, compress)
        etag = etag_for(digest, "scene-lod-reach", reach, budget,
                        *([compress] if compress != "none" else []))
        # made from every part's full detail: every slot while it is made
        return bodies.cached(request, etag, policy, make, media_type=_GLB,
                             filename=f"{mesh_id}-scene.glb",
                             estimate=lambda: bodies.heavy.budget)
    # named by the levels it holds: two criteria giving the same levels share a body
    etag = etag_for(digest, "scene-lod", *(levels[p] for p in sorted(levels)),
                    *([compress] if compress != "none" else []))
    return bodies.cached(request, etag, policy, lambda: scene_glb(asset, levels, compress),
                         media_type=_GLB,
                         filename=f"{mesh_id}-scene.glb",
                         estimate=lambda: scene_bytes(asset, [levels]))


def _scene_chain(asset: SceneAsset, digest: str, policy: str, request: Request, bodies, *,
                 mesh_id: str, ratios, reach: str, compress: str = "none",
                 texture_scale: str = "none") -> Response:
    """The ``MSFT_lod`` scene (``get_chain``). Its levels are edge collapse's whatever
    ``reach`` says: ``MSFT_lod`` links levels per node, each part's own, so a
    scene merged into one mesh has no node to be a level of; a static scene's
    merged far level is ``get_lod``'s (``reach=merge``)."""
    pms = asset.pms
    chain = [_scene_levels(asset, ratio=ratio) for ratio in ratios]
    faces = sum(pms[p].faces_at_level(level) for levels in chain for p, level in levels.items())
    full = sum(pm.face_count for pm in pms.values()) or 1
    if faces > MAX_CHAIN_FACES * full:
        raise LevelError(f"a chain's levels hold at most {MAX_CHAIN_FACES} times the mesh's "
                         f"faces; these ratios add up to {faces / full:.2f} times")
    scaled = texture_scale if texture_scale != "none" else None
    etag = etag_for(digest, "scene-chain", ",".join(map(repr, ratios)),
                    *([compress] if compress != "none" else []),
                    *(["textures", scaled] if scaled else []))
    return bodies.cached(
        request, etag, policy,
        lambda: scene_chain_glb(asset, ratios, coverage_from_ratios(ratios),
                                compress=compress, texture_scale=scaled),
        media_type=_GLB, filename=f"{mesh_id}-lods.glb",
        estimate=lambda: scene_bytes(asset, chain)
        + (texture_levels_bytes(asset.materials) if scaled else 0))
