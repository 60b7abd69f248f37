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


def accessor_identity(accessor) -> tuple | None:
    """What makes two accessors read the same values: bufferView, byteOffset,
    componentType, type, count and normalized, for one without sparse values (None
    for any other, whose values are its own). Accessors of one identity alias one
    byte range: read, stored and written once."""
    if not isinstance(accessor, dict) or "bufferView" not in accessor or accessor.get("sparse"):
        return None
    key = (accessor["bufferView"], accessor.get("byteOffset", 0), accessor.get("componentType"),
           accessor.get("type"), accessor.get("count"), bool(accessor.get("normalized", False)))
    if not all(isinstance(value, (int, str)) for value in key):
        return None         # malformed: the reader says why
    return key


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
    limits.check("max_triangles_total", sum(per_mesh[m][0] * k for m, k in instances),
                 "triangles after placing every mesh instance")
    limits.check("max_vertices", sum(per_mesh[m][1] * k for m, k in instances),
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
    extensions = primitive.get("extensions")
    if isinstance(extensions, dict) and "KHR_draco_mesh_compression" in extensions:
        return      # its values are in the Draco bitstream, whose header io.draco checks
    for what, index in named:
        if index is None:
            continue
        accessor = record(document, "accessors", index, f"{label} {what}")
        count = accessor.get("count") or 0
        sparse = accessor.get("sparse") if isinstance(accessor.get("sparse"), dict) else {}
        if "bufferView" not in accessor and count and sparse.get("count") != count:
            raise MeshError(f"its {label} has {what} (accessor {index}) without a bufferView, "
                            f"so most of its {count} values would be zeros")


def gpu_instances(document: dict, node: dict, label: str) -> int | None:
    """The instances ``node``'s ``EXT_mesh_gpu_instancing`` declares (the largest
    count of its attribute accessors), None without the extension: read from the
    accessor records, before any of their values."""
    extensions = node.get("extensions")
    instancing = extensions.get("EXT_mesh_gpu_instancing") if isinstance(extensions, dict) \
        else None
    if not isinstance(instancing, dict):
        return None
    attributes = instancing.get("attributes")
    if not isinstance(attributes, dict):
        raise MeshError(f"its {label} has EXT_mesh_gpu_instancing without attributes")
    return max((natural(record(document, "accessors", index, f"{label} instancing").get("count"),
                        f"{label} instancing {str(name):.40} count")
                for name, index in attributes.items()), default=0)


def scene_meshes(document: dict, limits: LoadLimits) -> list[tuple[int, int]]:
    """(mesh index, copies) of every node placing a mesh (no transforms yet): those of
    the default scene, once each or once per ``EXT_mesh_gpu_instancing`` instance, and
    the instanced nodes of no default scene (their instances are placed and written
    all the same). Nodes and GPU instances count against ``max_instances``."""
    nodes = document.get("nodes") or []
    if not isinstance(nodes, list):
        raise MeshError("its nodes are not a list")
    # every node's GPU instances, in any scene or none: each is a transform to derive
    copies = {}
    for index, node in enumerate(nodes):
        if isinstance(node, dict) and "mesh" in node:
            count = gpu_instances(document, node, f"node {index}")
            if count is not None:
                copies[index] = count
    extra = sum(max(count - 1, 0) for count in copies.values())
    limits.check("max_instances", extra, "GPU instances (EXT_mesh_gpu_instancing)")
    if not document.get("scenes"):
        roots = []
    else:
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
        limits.check("max_instances", len(seen) + extra,
                     "nodes in its default scene and GPU instances")
        if "mesh" in node:
            record(document, "meshes", node["mesh"], f"node {index}")
            meshes.append((node["mesh"], copies.get(index, 1)))
        children = node.get("children", [])
        if not isinstance(children, list):
            raise MeshError(f"its node {index} has children that are not a list")
        stack.extend(children)
    for index, count in copies.items():
        if index not in seen:
            record(document, "meshes", nodes[index]["mesh"], f"node {index}")
            meshes.append((nodes[index]["mesh"], count))
    return meshes


# bytes of one component, and components of one element, by glTF accessor type
_COMPONENT_BYTES = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
_TYPE_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
# vertex attributes every mesh has (solved by the simplifier, not carried through it)
_SOLVED = ("POSITION", "NORMAL", "TEXCOORD_", "COLOR_")
# bytes of one (4, 4) float64 transform: an instance's or a skinned node's joint's
TRANSFORM_BYTES = 128
_TARGET_KINDS = ("POSITION", "NORMAL", "TANGENT")


def _accessor_bytes(document: dict, index, label: str) -> int:
    """Bytes of an accessor's values in its own type, from its record: at most its
    bufferView's length (one that declares more runs past it, which the reader
    refuses when it comes to it)."""
    accessor = record(document, "accessors", index, label)
    count = natural(accessor.get("count"), f"{label} count")
    size = (count * _TYPE_WIDTHS.get(accessor.get("type"), 16)
            * _COMPONENT_BYTES.get(accessor.get("componentType"), 4))
    if "bufferView" in accessor:
        view = record(document, "bufferViews", accessor["bufferView"], label)
        length = view.get("byteLength")
        if isinstance(length, int) and not isinstance(length, bool):
            size = min(size, max(length, 0))
    return size


def _carried_width(document: dict, primitives: list, label: str) -> tuple[int, int]:
    """(skin and custom attribute columns, morph target columns) a mesh's triangle
    primitives give every vertex: the union over them, as the reader's layout has it
    (a primitive lacking a column gets a neutral value, held all the same)."""
    columns, targets = {}, 0
    for primitive in primitives:
        attributes = primitive.get("attributes")
        for name, index in (attributes.items() if isinstance(attributes, dict) else ()):
            if not isinstance(name, str) or name.startswith(_SOLVED):
                continue
            accessor = record(document, "accessors", index, f"{label} {name:.40}")
            columns[name] = _TYPE_WIDTHS.get(accessor.get("type"), 0)
        found = primitive.get("targets")
        targets = max(targets, len(found) if isinstance(found, list) else 0)
    # each target holds its POSITION, NORMAL and TANGENT deltas at most, 3 wide each
    kinds = {kind for p in primitives for t in (p.get("targets") or ()) if isinstance(t, dict)
             for kind in t if kind in _TARGET_KINDS}
    return sum(columns.values()), targets * 3 * max(len(kinds), 1)


def carried_bytes(document: dict, carried) -> dict:
    """What a scene's carried data holds once read, in bytes, by what holds it, from
    the declarations alone (no value read).

    Parameters
    ----------
    document : dict
        The glTF JSON, its declared sizes checked (:func:`check_declared`).
    carried : iterable of int
        The accessors written as they are (``io.scene.carried_accessors``):
        animation samplers, inverse bind matrices, instancing, meshes kept as they are.

    Returns
    -------
    dict of str to int
        ``"animations, skins and instancing accessors"``: those accessors in their own
        type, each byte range once however many accessors alias it
        (:func:`accessor_identity`); ``"tangents, skin and custom attributes of mesh m"`` and
        ``"morph targets of mesh m"``: per vertex of its triangle primitives, float64
        (what the reader holds them as); ``"joint transforms of skinned nodes"``:
        128 bytes for every joint of a skinned node's skin, times its GPU instances.
    """
    found = {}
    seen, total = set(), 0
    for index in carried:
        key = accessor_identity(record(document, "accessors", index, "carried data"))
        if key is None or key not in seen:
            total += _accessor_bytes(document, index, f"accessor {index}")
            seen.add(key)
    found["animations, skins and instancing accessors"] = total
    nodes = [n for n in document.get("nodes") or () if isinstance(n, dict)]
    used = sorted({n["mesh"] for n in nodes if "mesh" in n}, key=str)
    for m in used:
        mesh = record(document, "meshes", m, "a node")
        primitives = [p for p in mesh.get("primitives") or ()
                      if isinstance(p, dict) and p.get("mode", TRIANGLES) in
                      (TRIANGLES, TRIANGLE_STRIP, TRIANGLE_FAN)]
        label = f"mesh {m}"
        columns, targets = _carried_width(document, primitives, label)
        vertices = sum(natural(record(document, "accessors", p["attributes"]["POSITION"],
                                      f"{label} POSITION").get("count"), f"{label} vertex count")
                       for p in primitives)
        found[f"tangents, skin and custom attributes of {label}"] = 8 * vertices * columns
        found[f"morph targets of {label}"] = 8 * vertices * targets
    transforms = 0
    for number, node in enumerate(nodes):
        if "mesh" in node and "skin" in node:
            # one transform per joint per instance (instances alone are bounded by
            # max_instances; their product with a skin's joints is not)
            copies = gpu_instances(document, node, f"node {number}")
            skin = record(document, "skins", node["skin"], f"node {number}")
            transforms += (1 if copies is None else copies) * len(skin.get("joints") or ())
    found["joint transforms of skinned nodes"] = TRANSFORM_BYTES * transforms
    return found


def check_carried(document: dict, carried, upload_bytes: int, limits: LoadLimits) -> None:
    """LimitError when a scene's carried data (:func:`carried_bytes`) would take more
    bytes than ``limits.carried_bytes(upload_bytes)`` allows: before any is read."""
    bound = limits.carried_bytes(upload_bytes)
    if bound is None:
        return
    found = carried_bytes(document, carried)
    total = sum(found.values())
    if total > bound:
        largest = max(found, key=found.get)
        raise LimitError(f"its animation, skin, instancing, morph target and custom attribute "
                         f"data would take {total} bytes once read ({found[largest]} for the "
                         f"{largest}), more than the {bound} this server allows a file of "
                         f"{upload_bytes} bytes")
