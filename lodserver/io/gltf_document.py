"""The glTF document before its data: the container parsed, declared sizes checked.

Everything here runs before any buffer is read or array allocated, on the JSON
alone: :func:`parse_container` splits a GLB (or takes .gltf text) under the
JSON size and depth limits; :func:`check_declared` refuses a document whose
declared primitives, triangles, vertices or instances exceed
:class:`~lodserver.io.limits.LoadLimits`, or whose geometry no bytes give
values to. :func:`record` and :func:`natural` are the checked look-ups every
glTF reader of lodserver uses, so a bad index or count is one sentence.
"""

from __future__ import annotations

import json
import struct

from ..mesh import MeshError
from .limits import LimitError, LoadLimits

# Primitive modes with triangles (spec 3.7.2.1).
TRIANGLES, TRIANGLE_STRIP, TRIANGLE_FAN = 4, 5, 6


def parse_container(data: bytes, limits: LoadLimits) -> tuple[dict, bytes | None]:
    """The JSON document and the BIN chunk (None if absent) of GLB or .gltf bytes."""
    if data[:4] != b"glTF":
        return parse_json(data, limits), None
    version, total = struct.unpack_from("<II", data, 4)
    if version != 2:
        raise ValueError(f"GLB container version {version}, expected 2")
    chunks, at = {}, 12
    while at + 8 <= min(total, len(data)):
        length, kind = struct.unpack_from("<I4s", data, at)
        chunks.setdefault(kind, data[at + 8 : at + 8 + length])
        at += 8 + length
    if b"JSON" not in chunks:
        raise ValueError("the GLB has no JSON chunk")
    return parse_json(chunks[b"JSON"], limits), chunks.get(b"BIN\x00")


def parse_json(data: bytes, limits: LoadLimits) -> dict:
    """The glTF JSON document, within the size and depth limits."""
    limits.check("max_json_bytes", len(data), "bytes of glTF JSON")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise MeshError("its glTF JSON is not UTF-8 text") from None
    try:
        document = json.loads(text)
    except RecursionError:
        raise MeshError("its glTF JSON is nested too deeply to read") from None
    except ValueError as exc:
        raise MeshError(f"its glTF JSON is malformed ({exc})") from None
    if not isinstance(document, dict):
        raise MeshError("its glTF JSON is not an object")
    if limits.max_json_depth is not None:
        # iteratively, so that the check itself cannot overflow the stack
        stack = [(document, 1)]
        while stack:
            value, depth = stack.pop()
            if depth > limits.max_json_depth:
                raise LimitError(f"its glTF JSON is nested more than {limits.max_json_depth} "
                                 "levels deep")
            children = value.values() if isinstance(value, dict) else value
            stack.extend((child, depth + 1) for child in children
                         if isinstance(child, (dict, list)))
    return document


def natural(value, what: str) -> int:
    """``value`` as a non-negative int (JSON gives floats and strings too), or a MeshError."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise MeshError(f"its {what} is {value!r}, not a non-negative integer")
    return value


def record(document: dict, key: str, index, what: str) -> dict:
    """``document[key][index]`` for a valid int index, else a MeshError naming ``what``."""
    records = document.get(key)
    if (isinstance(index, bool) or not isinstance(index, int) or not isinstance(records, list)
            or not 0 <= index < len(records) or not isinstance(records[index], dict)):
        raise MeshError(f"its {what} refers to {key} {index!r}, which does not exist")
    return records[index]


def declared_triangles(document: dict, primitive: dict, label: str) -> tuple[int, int]:
    """(triangles, vertices) a primitive declares by its accessor counts, 0 for points/lines."""
    mode = primitive.get("mode", TRIANGLES)
    if mode not in (TRIANGLES, TRIANGLE_STRIP, TRIANGLE_FAN):
        return 0, 0
    attributes = primitive.get("attributes")
    if not isinstance(attributes, dict) or "POSITION" not in attributes:
        raise MeshError(f"its {label} has no POSITION attribute")
    position = record(document, "accessors", attributes["POSITION"], f"{label} POSITION")
    vertices = natural(position.get("count"), f"{label} POSITION count")
    corners = vertices
    if "indices" in primitive:
        indices = record(document, "accessors", primitive["indices"], f"{label} indices")
        corners = natural(indices.get("count"), f"{label} index count")
    triangles = corners // 3 if mode == TRIANGLES else max(corners - 2, 0)
    return triangles, vertices


def check_declared(document: dict, limits: LoadLimits) -> None:
    """Refuse a document whose declared primitives, instances, triangles or vertices
    exceed ``limits``, from the accessor counts alone: before any data is read."""
    meshes = document.get("meshes") or []
    if not isinstance(meshes, list):
        raise MeshError("its meshes are not a list")
    primitives = [mesh.get("primitives") if isinstance(mesh, dict) else None for mesh in meshes]
    if any(not isinstance(p, list) for p in primitives):
        raise MeshError("a mesh of it has no list of primitives")
    limits.check("max_primitives", sum(len(p) for p in primitives), "glTF primitives")
    per_mesh = []
    for m, records in enumerate(primitives):
        counts = [declared_triangles(document, p, f"primitive {n} of mesh {m}")
                  if isinstance(p, dict) else (0, 0) for n, p in enumerate(records)]
        triangles = sum(t for t, _ in counts)
        limits.check("max_triangles", triangles, f"triangles in mesh {m}")
        per_mesh.append((triangles, sum(v for _, v in counts)))
    instances = scene_meshes(document, limits)
    limits.check("max_triangles_total", sum(per_mesh[m][0] for m in instances),
                 "triangles after placing every mesh instance")
    limits.check("max_vertices", sum(per_mesh[m][1] for m in instances),
                 "vertices after placing every mesh instance")
    for m, records in enumerate(primitives):
        for n, primitive in enumerate(records):
            if isinstance(primitive, dict):
                check_geometry_has_data(document, primitive, f"primitive {n} of mesh {m}")


def check_geometry_has_data(document: dict, primitive: dict, label: str) -> None:
    """Refuse positions or indices that no bytes of the file give values to.

    An accessor without a bufferView reads as zeros (bar its sparse values), so
    a few hundred bytes of JSON could declare millions of vertices all at the
    origin: within the limits, yet minutes of parsing and welding for a mesh of
    nothing but degenerate faces. Geometry must come from the file's bytes.
    """
    attributes = primitive.get("attributes") or {}
    named = [("POSITION", attributes.get("POSITION")), ("indices", primitive.get("indices"))]
    for what, index in named:
        if index is None:
            continue
        accessor = record(document, "accessors", index, f"{label} {what}")
        count = accessor.get("count") or 0
        sparse = accessor.get("sparse") if isinstance(accessor.get("sparse"), dict) else {}
        if "bufferView" not in accessor and count and sparse.get("count") != count:
            raise MeshError(f"its {label} has {what} (accessor {index}) without a bufferView, "
                            f"so most of its {count} values would be zeros")


def scene_meshes(document: dict, limits: LoadLimits) -> list[int]:
    """Mesh index of every node placing one in the default scene (no transforms yet)."""
    if not document.get("scenes"):
        return []
    scene = record(document, "scenes", document.get("scene", 0), "default scene")
    roots = scene.get("nodes", [])
    if not isinstance(roots, list):
        raise MeshError("its default scene has nodes that are not a list")
    stack, seen, meshes = list(roots), set(), []
    while stack:
        index = stack.pop()
        node = record(document, "nodes", index, "scene graph")
        if index in seen:
            continue
        seen.add(index)
        # nodes without a mesh cost a transform each, so they count too
        limits.check("max_instances", len(seen), "nodes in its default scene")
        if "mesh" in node:
            record(document, "meshes", node["mesh"], f"node {index}")
            meshes.append(node["mesh"])
        children = node.get("children", [])
        if not isinstance(children, list):
            raise MeshError(f"its node {index} has children that are not a list")
        stack.extend(children)
    return meshes
