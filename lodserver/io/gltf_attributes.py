"""Vertex attributes of glTF primitives: which are kept, and their values per face corner.

:func:`attribute_layout` picks, from the primitives placed, the columns of the
:class:`~lodserver.mesh.Attributes` layout (glTF names, :data:`~lodserver.mesh.ATTRIBUTE_RULES`)
and the names not kept; :func:`primitive_corners` gives one primitive's (t, 3, d) corner
values in that layout. Two modes:

- a scene part (``every=True``, :func:`lodserver.io.gltf.read_gltf_meshes`): every
  attribute: NORMAL, TEXCOORD_n, COLOR_n, TANGENT, JOINTS_n, WEIGHTS_n, morph targets
  (``primitive.targets[t]``'s POSITION/NORMAL/TANGENT as ``TARGET{t}_POSITION`` ...) and
  custom ``_NAME`` attributes (SCALAR to VEC4), in the mesh's local space.
- a flattened scene (``every=False``, :func:`lodserver.io.gltf.read_gltf`): the same but
  JOINTS_n, WEIGHTS_n and morph targets, which mean nothing once every node is baked into
  world space; NORMAL and TANGENT follow each node's transform.

Dropped (named in ``dropped_attributes``): matrix-typed custom attributes, morph target
attributes other than POSITION/NORMAL/TANGENT (a target left with none keeps zero
POSITION deltas, so the morph weights still match the targets), names no rule knows,
and in the flattened mode the skin and the targets.

A primitive without an attribute another primitive of the same mesh has gets a
neutral value (spec §3.7.2.1 where it says one):

=============  ===================================================================
NORMAL         the face's normal (flat shading, as the spec prescribes)
TEXCOORD_n     (0, 0)
COLOR_n        white, opaque (COLOR_0 multiplies the base colour: no change)
TANGENT        a unit vector perpendicular to the corner's normal, handedness +1
JOINTS_n       joint 0
WEIGHTS_n      weight 1 on the first influence (JOINTS_0.x) when the primitive has no
               weights at all, else 0
TARGET{t}_*    zero delta (the target does not move that primitive)
_NAME          zeros
=============  ===================================================================

Values are float64: normalized integers mapped as the spec says (§3.11), joint indices
as exact integers, a VEC3 colour given alpha 1.
"""

from __future__ import annotations

import re

import numpy as np

from ..mesh import MAX_ATTRIBUTES, MeshError, attribute_rule
from .gltf_document import record
from .limits import LimitError

_TYPE_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}

# Normalized integers map to [0, 1] (unsigned) or [-1, 1] (signed, -128 clamped): spec §3.11.
_NORMALIZED_SCALE = {5120: 127.0, 5121: 255.0, 5122: 32767.0, 5123: 65535.0}

_INTEGER_COMPONENTS = (5120, 5121, 5122, 5123, 5125)

# layout order: NORMAL, TEXCOORD_n, COLOR_n, TANGENT first, then the carried ones: carried
# columns only ever come after, so the first four keep their places in every layout
_ORDER = (r"NORMAL", r"TEXCOORD_(\d+)", r"COLOR_(\d+)", r"TANGENT", r"JOINTS_(\d+)",
          r"WEIGHTS_(\d+)", r"TARGET(\d+)_(POSITION|NORMAL|TANGENT)", r"(_[A-Za-z0-9_]+)")
_TARGET_KINDS = ("POSITION", "NORMAL", "TANGENT")

# the glTF type each fixed-width semantic must have (COLOR_n may be VEC3 too)
_TYPES = {"NORMAL": ("VEC3",), "TEXCOORD": ("VEC2",), "COLOR": ("VEC3", "VEC4"),
          "TANGENT": ("VEC4",), "JOINTS": ("VEC4",), "WEIGHTS": ("VEC4",)}

# At most this many attribute floats per corner on average at the triangle limit: a
# document declaring 500 morph targets on a large mesh would otherwise need tens of GB.
FLOATS_PER_LIMIT_CORNER = 16

# The longest attribute name kept (what a packet record can name, packets.format.MAX_NAME);
# a custom _NAME is held to 63 characters by its rule, but TEXCOORD_000...1 is not.
MAX_NAME = 64


def _order_key(name: str):
    for group, pattern in enumerate(_ORDER):
        match = re.fullmatch(pattern, name)
        if match:
            parts = match.groups()
            number = int(parts[0]) if parts and parts[0].isdigit() else 0
            kind = _TARGET_KINDS.index(parts[1]) if len(parts) > 1 else 0
            return group, number, kind, name
    return len(_ORDER), 0, 0, name


def as_float(values: np.ndarray, accessor: dict) -> np.ndarray:
    """float64 values of an attribute accessor, normalized integers mapped as the spec says."""
    if accessor.get("normalized"):
        scale = _NORMALIZED_SCALE[accessor["componentType"]]
        return np.maximum(values / scale, -1.0)
    return values.astype(np.float64)


def _sources(primitive: dict, every: bool):
    """(layout name, accessor index) of every vertex attribute of ``primitive``, and the
    names it has that are not kept (in the flattened mode: skin and targets)."""
    found, dropped = [], []
    for name, index in primitive["attributes"].items():
        if name == "POSITION":
            continue
        if not every and name.startswith(("JOINTS_", "WEIGHTS_")):
            dropped.append(name)
            continue
        found.append((name, index))
    for t, target in enumerate(primitive.get("targets") or ()):
        for name, index in target.items():
            if every and name in _TARGET_KINDS:
                found.append((f"TARGET{t}_{name}", index))
            else:
                dropped.append(f"TARGET{t}_{name}")
    return found, dropped


def attribute_layout(document: dict, primitives: list, every: bool) -> tuple[tuple, list]:
    """``(layout, dropped)`` for the triangle primitives placed: the columns every
    primitive's corners get ((name, width), ... in a fixed order: NORMAL, TEXCOORD_n,
    COLOR_n, TANGENT, JOINTS_n, WEIGHTS_n, TARGET{t}_*, custom by name) and the sorted
    names not kept. A known semantic of the wrong glTF type is a MeshError."""
    widths, dropped = {}, set()
    for primitive in primitives:
        found, lost = _sources(primitive, every)
        dropped.update(lost)
        for name, index in found:
            if len(name) > MAX_NAME:
                dropped.add(name)       # a packet names an attribute in at most 64 bytes
                continue
            accessor = record(document, "accessors", index, f"primitive {_shown(name)}")
            kind = accessor.get("type")
            if kind not in _TYPE_WIDTHS:
                raise MeshError(f"its {_label(name)} accessor has type {kind!r}")
            semantic = name.split("_")[0] if not name.startswith("TARGET") else None
            try:
                width = attribute_rule(name, _TYPE_WIDTHS[kind])[0] if name.startswith("_") \
                    else attribute_rule(name)[0]
            except MeshError:
                dropped.add(name)       # a matrix-typed custom attribute, or no rule's name
                continue
            allowed = _TYPES.get(semantic, ("VEC3",) if name.startswith("TARGET") else None)
            if allowed is not None and kind not in allowed:
                raise MeshError(f"its {_label(name)} accessor is {kind}, not "
                                f"{' or '.join(allowed)}")
            if name.startswith("_") and widths.get(name, width) != width:
                raise MeshError(f"its custom attribute {name} has {widths[name]} components "
                                f"in one primitive and {width} in another")
            if semantic == "JOINTS" and accessor.get("componentType") not in _INTEGER_COMPONENTS:
                raise MeshError(f"its {name} accessor holds floats, not joint indices")
            widths[name] = width
    if every:
        # a target whose attributes were all dropped still counts (the mesh's and nodes'
        # morph weights name it): it moves nothing, zero POSITION deltas
        count = max((len(p.get("targets") or ()) for p in primitives), default=0)
        for t in range(count):
            if not any(name.startswith(f"TARGET{t}_") for name in widths):
                widths[f"TARGET{t}_POSITION"] = 3
    if len(widths) > MAX_ATTRIBUTES:
        # refused from the declarations, before (faces, 3, width) corners are allocated
        raise MeshError(f"it has {len(widths)} vertex attributes; at most {MAX_ATTRIBUTES} "
                        "are supported")
    layout = tuple((name, widths[name]) for name in sorted(widths, key=_order_key))
    return layout, sorted({_shown(name) for name in dropped - set(widths)})


def _shown(name: str) -> str:
    """``name`` cut to 64 characters: a dropped attribute's name is echoed in notes and
    reports, and a document may name one by ten kilobytes."""
    return name if len(name) <= 64 else f"{name[:48]}... ({len(name)} characters)"


def check_attribute_size(limits, corners: int, layout: tuple) -> None:
    """LimitError when ``corners`` face corners of ``layout`` would hold more floats
    than :data:`FLOATS_PER_LIMIT_CORNER` per corner of the triangle limit."""
    if limits is None or limits.max_triangles is None:
        return
    width = sum(w for _, w in layout)
    bound = FLOATS_PER_LIMIT_CORNER * 3 * limits.max_triangles
    if corners * width > bound:
        raise LimitError(f"its {len(layout)} vertex attributes hold {corners * width} values "
                         f"over {corners} face corners, more than the {bound} allowed")


def primitive_corners(document, primitive, linear, triangles, world, layout, accessor,
                      every: bool):
    """(t, 3, d) float64 corner attribute vectors of one placed primitive in ``layout``.

    ``linear`` (3, 3) is the node's world linear map (identity for a scene part),
    ``triangles`` (t, 3) its triangles (already reversed under a mirror), ``world``
    (n, 3) its placed positions, ``accessor(index)`` the reader of accessors.
    Attributes it lacks get the defaults of the module docstring.
    """
    sources = dict(_sources(primitive, every)[0])
    count = len(world)
    mirrored = np.linalg.det(linear) < 0
    identity = np.allclose(linear, np.eye(3), rtol=0, atol=1e-15)
    has_weights = any(name.startswith("WEIGHTS_") for name in sources)
    columns, normals = [], None
    for name, width in layout:
        if name in sources:
            stored = record(document, "accessors", sources[name], f"primitive {name}")
            if stored.get("count") != count:  # checked before reading: it could be huge
                raise MeshError(f"a primitive's {_label(name)} has {stored.get('count')!r} "
                                f"values for {count} vertices")
            values = as_float(accessor(sources[name]), stored)
            if len(values) != count:
                raise MeshError(f"a primitive's {_label(name)} has {len(values)} values "
                                f"for {count} vertices")
            if name == "NORMAL":
                values = transform_normals(values, linear)
            elif name == "TANGENT" and not identity:
                values = transform_tangents(values, linear, mirrored)
            elif name.startswith("COLOR_") and values.shape[1] == 3:
                values = np.column_stack([values, np.ones(count)])  # RGB means opaque
            corner = values[triangles]
        elif name == "NORMAL":
            corner = np.repeat(face_normals(world, triangles)[:, None], 3, axis=1)
        elif name == "TANGENT":
            around = normals if normals is not None else np.repeat(
                face_normals(world, triangles)[:, None], 3, axis=1)
            corner = np.concatenate([perpendicular(around.reshape(-1, 3)).reshape(-1, 3, 3),
                                     np.ones((len(triangles), 3, 1))], axis=2)
        else:
            fill = np.zeros(width)
            if name.startswith("COLOR_"):
                fill[:] = 1.0
            elif name == "WEIGHTS_0" and not has_weights:
                fill[0] = 1.0
            corner = np.broadcast_to(fill, (len(triangles), 3, width))
        if name == "NORMAL":
            normals = corner
        columns.append(corner)
    return np.concatenate(columns, axis=2)


def _label(name: str) -> str:
    """``name`` as glTF spells it: ``TARGET1_NORMAL`` is morph target 1's NORMAL."""
    morph = re.fullmatch(r"TARGET(\d+)_(\w+)", name)
    return f"morph target {morph[1]}'s {morph[2]}" if morph else _shown(name)


def check_joints(document: dict, mesh_index: int, layout: tuple, corner_values) -> None:
    """MeshError unless every joint index of ``corner_values`` (m, 3, d) exists in the
    skin of every node that uses mesh ``mesh_index`` with a skin, and no skin weight
    is negative."""
    start, largest = 0, -1
    for name, width in layout:
        if name.startswith("JOINTS_") and len(corner_values):
            largest = max(largest, int(corner_values[:, :, start:start + width].max()))
        if name.startswith("WEIGHTS_") and len(corner_values) \
                and (corner_values[:, :, start:start + width] < 0).any():
            # the spec: joint weights MUST be non-negative (a negative one turns a
            # blend of rigid joints into an extrapolation that tears the mesh)
            raise MeshError(f"mesh {mesh_index} has negative skin weights ({name})")
        start += width
    if largest < 0:
        return
    for number, node in enumerate(document.get("nodes", ())):
        if not isinstance(node, dict) or node.get("mesh") != mesh_index or "skin" not in node:
            continue
        skin = record(document, "skins", node["skin"], f"node {number}")
        joints = len(skin.get("joints") or ())
        if largest >= joints:
            raise MeshError(f"mesh {mesh_index} uses joint {largest}, but skin {node['skin']} "
                            f"of node {number} has {joints} joints")


def transform_normals(normals: np.ndarray, linear: np.ndarray) -> np.ndarray:
    """Normals (n, 3) under the linear map (3, 3): inverse transpose, renormalised.

    Normals must stay perpendicular to the surface, which a non-uniform scale
    would break if they were transformed like positions. Zero normals stay zero.
    """
    if np.allclose(linear, np.eye(3), rtol=0, atol=1e-15):
        return normals
    moved = normals @ np.linalg.pinv(linear)  # row form of inv(L).T @ n; pinv survives scale 0
    return _unit_or_zero(moved)


def transform_tangents(tangents: np.ndarray, linear: np.ndarray, mirrored: bool) -> np.ndarray:
    """Tangents (n, 4) under the linear map (3, 3): xyz like a direction in the surface
    (``linear @ t``), renormalised (zero stays zero); w negated under a mirroring map,
    since the bitangent ``w * cross(n, t)`` would otherwise flip with the winding."""
    xyz = _unit_or_zero(tangents[:, :3] @ np.asarray(linear).T)
    w = -tangents[:, 3:] if mirrored else tangents[:, 3:]
    return np.column_stack([xyz, w])


def perpendicular(normals: np.ndarray) -> np.ndarray:
    """(n, 3) unit vectors perpendicular to ``normals`` (n, 3) (+X for a zero normal):
    the cross product with the axis least aligned with each normal."""
    normals = np.asarray(normals, dtype=np.float64)
    axis = np.zeros_like(normals)
    axis[np.arange(len(normals)), np.argmin(np.abs(normals), axis=1)] = 1.0
    out = _unit_or_zero(np.cross(normals, axis))
    out[np.linalg.norm(out, axis=1) == 0] = (1.0, 0.0, 0.0)
    return out


def _unit_or_zero(vectors: np.ndarray) -> np.ndarray:
    length = np.linalg.norm(vectors, axis=1, keepdims=True)
    return np.divide(vectors, length, out=np.zeros_like(vectors), where=length > 0)


def face_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit normals (m, 3) of triangles (m, 3) by their winding; zero for zero-area faces."""
    corners = positions[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return _unit_or_zero(cross)
