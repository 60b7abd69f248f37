"""The progressive file: one GLB that any static host serves and a client streams
from with HTTP range requests (docs/packets.md, "The progressive file").

The file is an ordinary GLB of the asset at its base level (a single mesh with
its materials and images, or the whole scene with its node tree, skins,
animations and cameras), which any glTF viewer draws, and the root extension
:data:`EXTENSION` holding an index of what its BIN chunk holds besides: per
part, the base level's json form (the state packets start from, byte for byte
``GET /meshes/{id}/lod?format=json`` at the default grid but for its
``materials`` link) and the split and collapse records in chunks of
``chunkSplits`` records between fixed levels, each chunk an independently
decodable version 4 packet (``packets.records_v4.packet_between_v4``). A client
reads the header and JSON with one range request and any level with one more.
"""

from __future__ import annotations

import json
import struct

from ..io.gltf_document import parse_container
from ..io.glb import pack_glb
from ..io.limits import LoadLimits
from ..packets.grids import default_bits
from ..packets.records_v4 import packet_between_v4
from ..scene.asset import SceneAsset
from ..scene.write import scene_glb
from .levels import checked_bits, encode_level

EXTENSION = "LODSERVER_progressive"
# The packet version the chunks are written in (docs/packets.md, "Version 4").
CHUNK_PACKET_VERSION = 4
# What a base level's json form says of its materials: they are the file's own
# (the GLB's materials, textures, samplers and images).
MATERIALS_HERE = "#materials"
# Records per chunk: a power of two, about 1/32 of a part's splits, so that a
# client stops within a few percent of the level it asks for, within these bounds:
# below MIN_CHUNK a chunk's adaptive models hardly learn before they restart;
# MAX_CHUNK is a version 4 segment (encode_v4.SEGMENT_RECORDS), coded once per mesh.
MIN_CHUNK, MAX_CHUNK, CHUNKS_PER_PART = 512, 8192, 32


def chunk_splits(splits: int) -> int:
    """The records per chunk of a part of ``splits`` splits (see MIN_CHUNK)."""
    size = MIN_CHUNK
    while size < MAX_CHUNK and size * CHUNKS_PER_PART < splits:
        size *= 2
    return size


def chunk_levels(base: int, full: int, size: int) -> list[int]:
    """The levels chunks start and end at: ``base``, every ``size`` splits, ``full``."""
    return list(range(base, full, size)) + [full]


def progressive_glb(asset: SceneAsset, *, name: str = "", bits: int | None = None) -> bytes:
    """The progressive file of ``asset`` (a single mesh or a scene), as bytes.

    Parameters
    ----------
    asset : SceneAsset
        A built asset, as the store keeps it.
    name : str
        The mesh's name, kept in the summary (``GET /meshes/{id}``'s ``name``).
    bits : int, optional
        The grid of every part's base level and records, bits per axis (as
        ``/lod?format=json&bits=``); by default each part's own
        (``packets.grids.default_bits``). Another grid is encoded afresh, chunk
        by chunk, rather than cut from the mesh's cached records. LevelError
        outside the grids a packet can hold.

    Returns
    -------
    bytes
        A GLB: the base level drawn by any glTF viewer, and :data:`EXTENSION` in
        the root ``extensions`` (listed in ``extensionsUsed``, not required).
    """
    bits = checked_bits(bits)
    bases = {part.index: part.pm.base_vertices for part in asset.parts}
    if asset.single is not None:
        glb = encode_level(asset.single, bases[0], file_type="glb")
    else:
        glb = scene_glb(asset, bases)
    document, binary = parse_container(bytes(glb), LoadLimits.unbounded())
    binary = bytes(binary or b"")
    blobs = [binary, b"\0" * (-len(binary) % 4)]
    at = len(binary) + len(blobs[1])

    def place(data: bytes) -> list[int]:
        nonlocal at
        blobs.append(data)
        at += len(data)
        return [at - len(data), len(data)]

    parts = []
    for part in asset.parts:
        pm = part.pm
        base, full = pm.base_vertices, pm.vertex_count
        size = chunk_splits(full - base)
        levels = chunk_levels(base, full, size)
        record = {"part": part.index, "mesh": part.mesh if asset.single is None else 0,
                  "chunkSplits": size, "bits": bits or default_bits(pm),
                  "base": [base, *place(bytes(encode_level(
                      pm, base, file_type="json", bits=bits, materials_href=MATERIALS_HERE)))]}
        # splits ascending, collapses descending: the chunks on the way to any
        # level, either way, are one range of bytes
        record["splits"] = [[a, b, *place(packet_between_v4(pm, a, b, bits=bits))]
                            for a, b in zip(levels, levels[1:])]
        record["collapses"] = [[b, a, *place(packet_between_v4(pm, b, a, bits=bits))]
                               for a, b in reversed(list(zip(levels, levels[1:])))]
        parts.append(record)
    summary = {key: value for key, value in asset.summary().items() if key != "metadata"}
    summary["name"] = name
    document["extensions"] = {**document.get("extensions", {}), EXTENSION: {
        "packetVersion": CHUNK_PACKET_VERSION,
        "glbBytes": len(binary),
        "summary": summary,
        "parts": parts}}
    document["extensionsUsed"] = sorted({*document.get("extensionsUsed", ()), EXTENSION})
    document["buffers"] = [{"byteLength": at}]
    return pack_glb(document, *blobs)


def read_index(data: bytes) -> tuple[dict, int]:
    """``(the extension's record, the BIN chunk's data offset in the file)`` of a
    progressive file's bytes (at least its header and JSON chunk); ValueError
    when they are not one."""
    if len(data) < 20 or data[:4] != b"glTF":
        raise ValueError("not a GLB file")
    length, kind = struct.unpack_from("<I4s", data, 12)
    if kind != b"JSON" or len(data) < 20 + length:
        raise ValueError("the GLB's JSON chunk is missing or cut short")
    document = json.loads(data[20:20 + length])
    record = document.get("extensions", {}).get(EXTENSION)
    if not isinstance(record, dict):
        raise ValueError(f"the GLB has no {EXTENSION} extension")
    return record, 20 + length + 8
