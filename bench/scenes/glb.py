"""A small GLB reader and writer for the scene benchmark (bench/scenes/).

Works on the two halves of a GLB as they are: the JSON document (a dict) and
the BIN chunk (bytes). :func:`read_glb` splits a file, :func:`accessor` reads
one accessor as a numpy array (strides, normalised integers, sparse values),
:func:`repack` rebuilds the binary buffer keeping only the buffer views that
accessors and images still use (so a replaced primitive leaves no dead bytes
behind), and :func:`triangle_count` counts the triangles of every mesh of a
document, once per mesh (not per instancing node).

This is benchmark tooling, not lodserver's reader: it trusts its inputs (the
shared sample scenes and the files lodserver and gltfpack write).
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

COMPONENT = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16,
             5125: np.uint32, 5126: np.float32}
WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963


def read_glb(path: Path) -> tuple[dict, bytes]:
    """(JSON document, BIN chunk bytes; b"" if none) of a .glb file."""
    data = Path(path).read_bytes()
    if data[:4] != b"glTF":
        raise ValueError(f"{path} is not a GLB")
    chunks, at = {}, 12
    while at + 8 <= len(data):
        length, kind = struct.unpack_from("<I4s", data, at)
        chunks.setdefault(kind, data[at + 8 : at + 8 + length])
        at += 8 + length
    return json.loads(chunks[b"JSON"]), chunks.get(b"BIN\x00", b"")


def write_glb(path: Path, document: dict, binary: bytes) -> None:
    """Write a GLB: the JSON chunk padded with spaces, the BIN chunk with zeros."""
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    binary = binary + b"\0" * (-len(binary) % 4)
    chunks = struct.pack("<I4s", len(text), b"JSON") + text
    if binary:
        chunks += struct.pack("<I4s", len(binary), b"BIN\x00") + binary
    Path(path).write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks)


def _view_array(document, binary, view_index, offset, dtype, count, width):
    view = document["bufferViews"][view_index]
    start = view.get("byteOffset", 0) + offset
    item = np.dtype(dtype).itemsize * width
    stride = view.get("byteStride") or item
    raw = np.frombuffer(binary, np.uint8, count=(count - 1) * stride + item if count else 0,
                        offset=start)
    if count == 0:
        return np.zeros((0, width), dtype)
    # rows of `stride` bytes, of which the first `item` hold the element
    rows = np.lib.stride_tricks.as_strided(raw, (count, item), (stride, 1))
    return np.ascontiguousarray(rows).view(dtype).reshape(count, width)


def accessor(document: dict, binary: bytes, index: int) -> np.ndarray:
    """Accessor ``index`` as an (count, width) array: float64 for floats and
    normalised integers (mapped to [0, 1] or [-1, 1]), the integer type otherwise."""
    acc = document["accessors"][index]
    dtype, width, count = COMPONENT[acc["componentType"]], WIDTH[acc["type"]], acc["count"]
    if "bufferView" in acc:
        values = _view_array(document, binary, acc["bufferView"], acc.get("byteOffset", 0),
                             dtype, count, width).copy()
    else:
        values = np.zeros((count, width), dtype)
    sparse = acc.get("sparse")
    if sparse:
        idx = sparse["indices"]
        where = _view_array(document, binary, idx["bufferView"], idx.get("byteOffset", 0),
                            COMPONENT[idx["componentType"]], sparse["count"], 1)[:, 0]
        val = sparse["values"]
        values[where] = _view_array(document, binary, val["bufferView"],
                                    val.get("byteOffset", 0), dtype, sparse["count"], width)
    if acc.get("normalized"):
        scale = float(np.iinfo(dtype).max)
        return np.maximum(values.astype(np.float64) / scale, -1.0)
    return values.astype(np.float64) if dtype == np.float32 else values


def triangle_count(document: dict) -> int:
    """Triangles of every triangle primitive of every mesh, each mesh counted once."""
    total = 0
    for mesh in document.get("meshes", []):
        for primitive in mesh["primitives"]:
            mode = primitive.get("mode", 4)
            if "indices" in primitive:
                n = document["accessors"][primitive["indices"]]["count"]
            else:
                n = document["accessors"][primitive["attributes"]["POSITION"]]["count"]
            total += n // 3 if mode == 4 else max(n - 2, 0) if mode in (5, 6) else 0
    return total


def repack(document: dict, binary: bytes, new_arrays: dict[int, tuple[np.ndarray, int]]
           ) -> tuple[dict, bytes]:
    """A copy of the document with one compact buffer.

    ``new_arrays`` maps accessor index -> (array, target): those accessors get
    fresh bytes (the array as the accessor's componentType, C order) in a view
    of their own with ``target`` (ARRAY_BUFFER or ELEMENT_ARRAY_BUFFER); every
    other accessor and image keeps its old bytes. Accessors no primitive,
    skin or animation uses are dropped and every reference renumbered; views
    nothing uses are dropped. Returns (document, BIN bytes).
    """
    doc = json.loads(json.dumps(document))
    used = set()
    for mesh in doc.get("meshes", []):
        for p in mesh["primitives"]:
            used.update(p["attributes"].values())
            used.update(i for t in p.get("targets", []) for i in t.values())
            if "indices" in p:
                used.add(p["indices"])
    for skin in doc.get("skins", []):
        if "inverseBindMatrices" in skin:
            used.add(skin["inverseBindMatrices"])
    for anim in doc.get("animations", []):
        for s in anim["samplers"]:
            used.update((s["input"], s["output"]))
    order = sorted(used)
    renumber = {old: new for new, old in enumerate(order)}

    out, views, view_map = bytearray(), [], {}

    def add(data: bytes, extra: dict) -> int:
        out.extend(b"\0" * (-len(out) % 4))  # every view 4-byte aligned
        views.append({"buffer": 0, "byteOffset": len(out), "byteLength": len(data), **extra})
        out.extend(data)
        return len(views) - 1

    def old_view(index: int) -> int:
        if index not in view_map:
            v = doc["bufferViews"][index]
            start = v.get("byteOffset", 0)
            extra = {k: v[k] for k in ("byteStride", "target") if k in v}
            view_map[index] = add(binary[start : start + v["byteLength"]], extra)
        return view_map[index]

    accessors = []
    for old in order:
        acc = doc["accessors"][old]
        if old in new_arrays:
            array, target = new_arrays[old]
            data = np.ascontiguousarray(array, COMPONENT[acc["componentType"]])
            acc = {k: v for k, v in acc.items() if k not in ("byteOffset", "sparse")}
            acc["count"] = len(data)
            acc["bufferView"] = add(data.tobytes(), {"target": target})
        else:
            if "bufferView" in acc:
                acc["bufferView"] = old_view(acc["bufferView"])
            for part in ("indices", "values"):
                if part in acc.get("sparse", {}):
                    acc["sparse"][part]["bufferView"] = old_view(acc["sparse"][part]["bufferView"])
        accessors.append(acc)
    for image in doc.get("images", []):
        if "bufferView" in image:
            image["bufferView"] = old_view(image["bufferView"])
    for mesh in doc.get("meshes", []):
        for p in mesh["primitives"]:
            p["attributes"] = {k: renumber[v] for k, v in p["attributes"].items()}
            if "targets" in p:
                p["targets"] = [{k: renumber[v] for k, v in t.items()} for t in p["targets"]]
            if "indices" in p:
                p["indices"] = renumber[p["indices"]]
    for skin in doc.get("skins", []):
        if "inverseBindMatrices" in skin:
            skin["inverseBindMatrices"] = renumber[skin["inverseBindMatrices"]]
    for anim in doc.get("animations", []):
        for s in anim["samplers"]:
            s["input"], s["output"] = renumber[s["input"]], renumber[s["output"]]
    doc["accessors"], doc["bufferViews"] = accessors, views
    doc["buffers"] = [{"byteLength": len(out) + (-len(out) % 4)}]
    return doc, bytes(out)
