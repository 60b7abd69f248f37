"""What each level of detail in a GLB file draws, and the bytes it takes: the report's reader.

:func:`glb_levels` reads a GLB's document (not its data) and tells its levels
apart the way engines do: a node with ``MSFT_lod`` draws level 0 and names the
nodes of levels 1, 2, ...; else nodes named ``..._LOD<k>`` draw level k
(``glb.lod_name``). A mesh no such node draws (a file of one level, or a
scene's mesh kept without levels) is drawn at every level. The levels are
those the file holds, in order: one for a file of ``--separate``.

Per level it counts what the file holds for it: triangles (each glTF mesh once,
however many nodes place it) and vertices (its primitives' ``POSITION``
counts), and bytes by kind: ``geometry`` (the bufferViews of its accessors, the
compressed bytes of an ``EXT_meshopt_compression`` view) and ``images`` (the
bufferViews of the images its materials name); a bufferView two levels share is
counted in each.
"""

from __future__ import annotations

import json
import re
import struct

from ..mesh import MeshError

_LOD_SUFFIX = re.compile(r"_LOD(\d+)$")
_MODE_TRIANGLES = 4


def glb_document(data) -> dict:
    """The JSON document of GLB bytes (MeshError, one sentence, if it is not one)."""
    data = memoryview(data)
    if len(data) < 20 or bytes(data[:4]) != b"glTF":
        raise MeshError("not a GLB file")
    length, kind = struct.unpack_from("<I4s", data, 12)
    if kind != b"JSON" or 20 + length > len(data):
        raise MeshError("a GLB file whose first chunk is not its JSON")
    try:
        return json.loads(bytes(data[20:20 + length]))
    except ValueError:
        raise MeshError("a GLB file whose JSON cannot be read") from None


def glb_levels(data) -> list[dict]:
    """Each level of a GLB, finest first: ``{"triangles", "vertices", "geometry",
    "images"}`` (counts; bytes), as the module docstring says."""
    document = glb_document(data)
    nodes = document.get("nodes", [])
    meshes = document.get("meshes", [])
    by_level, placed = {}, set()

    def draw(level: int, node: int):
        if 0 <= node < len(nodes) and isinstance(nodes[node].get("mesh"), int):
            by_level.setdefault(level, set()).add(nodes[node]["mesh"])
            placed.add(nodes[node]["mesh"])

    for number, node in enumerate(nodes):
        ids = (node.get("extensions") or {}).get("MSFT_lod", {}).get("ids")
        if isinstance(ids, list):
            draw(0, number)
            for level, other in enumerate(ids, start=1):
                draw(level, other)
    if not by_level:
        for number, node in enumerate(nodes):
            found = _LOD_SUFFIX.search(str(node.get("name", "")))
            if found:
                draw(int(found[1]), number)
    everywhere = set(range(len(meshes))) - placed
    # the levels a file holds, in order (a --separate file's one node is LOD<k> alone)
    return [_level(document, by_level[level] | everywhere) for level in sorted(by_level)] \
        or [_level(document, everywhere)]


def _level(document: dict, drawn: set) -> dict:
    """The counts and bytes of the glTF meshes ``drawn`` (indices)."""
    meshes, accessors = document.get("meshes", []), document.get("accessors", [])
    triangles = vertices = 0
    used, materials = set(), set()
    for index in drawn:
        for primitive in meshes[index].get("primitives", []):
            attributes = primitive.get("attributes", {})
            count = accessors[attributes["POSITION"]]["count"] if "POSITION" in attributes \
                else 0
            vertices += count
            if primitive.get("mode", _MODE_TRIANGLES) == _MODE_TRIANGLES:
                corners = accessors[primitive["indices"]]["count"] if "indices" in primitive \
                    else count
                triangles += corners // 3
            named = [*attributes.values(), primitive.get("indices")]
            for target in primitive.get("targets", []):
                named += list(target.values())
            used.update(accessors[a].get("bufferView") for a in named
                        if isinstance(a, int) and a < len(accessors))
            if isinstance(primitive.get("material"), int):
                materials.add(primitive["material"])
    return {"triangles": triangles, "vertices": vertices,
            "geometry": _view_bytes(document, used - {None}),
            "images": _view_bytes(document, _image_views(document, materials))}


def _image_views(document: dict, materials: set) -> set:
    """The bufferViews of the images the materials (indices) name through their textures."""
    records = document.get("materials", [])
    textures, images = document.get("textures", []), document.get("images", [])
    named = set()

    def visit(value):
        if isinstance(value, dict):
            for key, item in value.items():
                if key.endswith("Texture") and isinstance(item, dict) and \
                        isinstance(item.get("index"), int) and item["index"] < len(textures):
                    texture = textures[item["index"]]
                    sources = [texture.get("source"), *(
                        extension.get("source") for extension in
                        (texture.get("extensions") or {}).values() if isinstance(extension, dict))]
                    named.update(s for s in sources if isinstance(s, int) and s < len(images))
                visit(item)
        elif isinstance(value, list):
            for item in value:
                visit(item)

    visit([records[m] for m in materials if m < len(records)])
    return {images[i].get("bufferView") for i in named} - {None}


def _view_bytes(document: dict, views: set) -> int:
    """Bytes the bufferViews take in the file: a meshopt-compressed view's
    compressed length, else its own."""
    records = document.get("bufferViews", [])
    total = 0
    for view in views:
        record = records[view]
        compressed = (record.get("extensions") or {}).get("EXT_meshopt_compression")
        total += (compressed or record)["byteLength"]
    return total
