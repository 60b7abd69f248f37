"""One level of a progressive mesh as the bytes of a response.

``glb``, ``obj`` and ``ply`` carry the level's exact positions (as precise as
the format allows, see ``io``); ``glb`` also its wedge attributes, materials and
images, ``obj`` its UVs and normals (one ``vt``/``vn`` per wedge), ``ply``
positions only. ``json`` carries its *quantized form*, the
state a packet client starts from and ends in (``packets/grids.py``)::

    {"level": v, "vertex_count": v, "face_count": f, "error": e,
     "grid": {"origin": [x, y, z], "step": s, "bits": b},
     "positions": [[qx, qy, qz], ...],   # grid coordinates, position = origin + q * step
     "faces": [[a, b, c], ...]}          # in prefix-layout slots

and, for a mesh with attributes and materials (docs/packets.md)::

     "layout": [["NORMAL", 3], ["TEXCOORD_0", 2]],
     "attribute_grid": {"NORMAL": {"encoding": "octahedral", ...}, "TEXCOORD_0": {...}},
     "wedge_capacity": w,                # wedges at full detail (the most of any level)
     "wedges": [[...], ...],             # grid coordinates per wedge, attribute after attribute
     "corners": [[a, b, c], ...],        # the wedge of every face corner
     "face_material": [m, ...],          # per face, -1 for none
     "material_faces": [n0, ..., n_none],  # faces per material at full detail, last: none
     "materials": "/meshes/{id}/materials"
"""

from __future__ import annotations

import numpy as np
import orjson

from ..io.glb import level_glb
from ..io import OUTPUT_FORMATS, SERVED_FORMATS, encode_mesh
from ..mesh import MeshError
from ..packets import MAX_BITS, check_bits, default_bits, grid_of, quantized_level
from ..progressive.mesh import ProgressiveMesh

class LevelError(MeshError):
    """A level request is malformed or outside the mesh's levels."""


def resolve_level(pm: ProgressiveMesh, *, vertices=None, faces=None, ratio=None,
                  error=None) -> int:
    """The level (vertex count) asked for by exactly one criterion (``level_for``)."""
    try:
        return pm.level_for(vertices=vertices, faces=faces, ratio=ratio, error=error)
    except (ValueError, TypeError) as exc:
        raise LevelError(str(exc)) from exc


def check_level(pm: ProgressiveMesh, level: int, *, name: str = "level") -> int:
    """``level`` if it is one of ``pm``'s levels, else :class:`LevelError`."""
    if not pm.base_vertices <= level <= pm.vertex_count:
        raise LevelError(f"{name} must be a level in [{pm.base_vertices}, {pm.vertex_count}] "
                         f"(a vertex count), got {level}")
    return int(level)


def checked_bits(bits: int | None) -> int | None:
    """``bits`` unchanged if None or in range, else :class:`LevelError`."""
    if bits is None:
        return None
    try:
        return check_bits(bits)
    except ValueError as exc:
        raise LevelError(str(exc)) from exc


def encode_level(pm: ProgressiveMesh, level: int, *, file_type: str,
                 bits: int | None = None, materials_href: str | None = None,
                 copy: bool = True, compress: str = "none") -> bytes | memoryview:
    """The bytes of ``level`` in ``file_type`` (one of :data:`lodserver.io.SERVED_FORMATS`).

    ``copy=False`` allows a read-only memoryview in place of bytes where that
    saves a copy (the GLB of a geometry-only level, written in place).

    ``bits`` sets the grid of the ``json`` form (default ``packets.default_bits``)
    and must match the packets the client applies to it. ``materials_href`` is
    where the ``json`` form says the mesh's materials are (when it has some).
    ``compress`` is one of the format's ``compressions`` (``io.OUTPUT_FORMATS``):
    a quantized or meshopt GLB, in vertex cache order (the json form and the
    packets keep the progressive mesh's order).
    """
    level = check_level(pm, level)
    if file_type not in SERVED_FORMATS:
        raise LevelError(f"format must be one of {', '.join(SERVED_FORMATS)}, "
                         f"got {file_type!r}")
    if file_type == "json":
        grid = grid_of(pm, bits=checked_bits(bits))
        state = quantized_level(pm, level, grid)
        document = {"level": level, "vertex_count": level, "face_count": len(state.faces),
                    "error": pm.error_at_level(level), "grid": grid.as_dict(),
                    "positions": np.ascontiguousarray(state.positions),
                    "faces": np.ascontiguousarray(state.faces)}
        if state.attribute_grids:
            document.update(layout=[list(x) for x in pm.attribute_layout],
                            attribute_grid={g.name: g.as_dict() for g in state.attribute_grids},
                            wedge_capacity=int(pm.wedge_counts[-1]),
                            wedges=np.ascontiguousarray(state.wedges),
                            corners=np.ascontiguousarray(state.corners))
        if state.face_material is not None:
            count = pm.materials.count if pm.materials is not None else 0
            document.update(face_material=np.ascontiguousarray(state.face_material),
                            material_faces=material_face_counts(pm.face_material, count))
        if pm.materials is not None and materials_href:
            document["materials"] = materials_href
        # orjson writes numpy arrays directly: the same bytes as json.dumps of
        # their lists, without a Python object per number.
        return json_in_slices(document, copy=copy)
    if compress not in OUTPUT_FORMATS[file_type].compressions:
        raise LevelError(f"compress={str(compress)[:40]} applies to format=glb only "
                         f"({', '.join(OUTPUT_FORMATS['glb'].compressions)})")
    if compress != "none":
        return encode_mesh(pm.at(level), file_type, compress=compress)
    if file_type == "glb" and not pm.has_attributes and pm.face_material is None \
            and pm.materials is None:
        # the server's hot path: the level is written straight into the file
        return level_glb(level, pm.faces_at_level(level),
                         lambda positions, faces: pm.write_level(level, positions, faces),
                         copy=copy)
    return encode_mesh(pm.at(level), file_type)


def material_face_counts(face_material: np.ndarray, count: int) -> list[int]:
    """Faces per material (``count`` of them), then faces without one (-1): the sizes
    of a viewer's per-material index ranges at full detail."""
    counts = np.bincount(np.asarray(face_material) + 1, minlength=count + 1)
    return [int(x) for x in counts[1:]] + [int(counts[0])]


# Rows of an array serialized at a time. orjson holds the GIL while it writes,
# and no other request (nor /healthz) is served meanwhile: the json form of a
# million-face level in one call would be a long pause, a slice of 16k rows
# is a short one.
JSON_SLICE_ROWS = 16_384


def json_in_slices(document: dict, *, copy: bool = True) -> bytes | memoryview:
    """``orjson.dumps(document, option=OPT_SERIALIZE_NUMPY)``, byte for byte, with the
    arrays of more than JSON_SLICE_ROWS rows written a slice at a time (other
    threads run between slices) into one growing buffer (so the body is held
    once, not as pieces and their join). ``copy=False``: a read-only memoryview
    of that buffer instead of a copy of it as bytes."""
    big = [key for key, value in document.items()
           if isinstance(value, np.ndarray) and len(value) > JSON_SLICE_ROWS]
    if not big:
        return orjson.dumps(document, option=orjson.OPT_SERIALIZE_NUMPY)
    marks = {key: f"lodserver-slices:{key}" for key in big}
    rest = orjson.dumps({**document, **marks}, option=orjson.OPT_SERIALIZE_NUMPY)
    out = bytearray()
    for key in big:
        before, rest = rest.split(orjson.dumps(marks[key]), 1)
        out += before
        array = document[key]
        for start in range(0, len(array), JSON_SLICE_ROWS):
            out += b"," if start else b"["
            out += orjson.dumps(array[start:start + JSON_SLICE_ROWS],
                                option=orjson.OPT_SERIALIZE_NUMPY)[1:-1]
        out += b"]"
    out += rest
    return bytes(out) if copy else memoryview(out).toreadonly()


# ---- what a body weighs --------------------------------------------------------------
# Estimates of a body's bytes, from counts and widths only (no encoding), for the
# heavy-request limit (api/bodies.py): an encoder's peak memory is a small multiple
# of the body it makes. They err on the large side: every number is given its
# widest text, every wedge its own vertex row.

# Bytes a document's fixed part may take: keys, grid, layout, materials link.
_HEAD_BYTES = 4096
# OBJ writes each coordinate with %.17g: at most 24 characters and a separator.
_OBJ_FLOAT = 25
# PLY (binary, as trimesh writes it): float64 x, y, z; a count byte and 3 int32.
_PLY_VERTEX, _PLY_FACE = 24, 13


def _text_int(largest: int) -> int:
    """Bytes of a non-negative integer up to ``largest`` in JSON or OBJ text, with
    its separator (and room for a sign)."""
    return len(str(max(int(largest), 1))) + 2


def level_bytes(pm: ProgressiveMesh, level: int, file_type: str,
                bits: int | None = None) -> int:
    """The estimated size of :func:`encode_level` ``(pm, level, file_type=...)``, in
    bytes: close to it for large levels, above it for most (a GLB of many
    materials repeats the vertices its materials share, a little more).

    Parameters
    ----------
    pm : ProgressiveMesh
    level : int
        A level of ``pm`` (a vertex count).
    file_type : str
        One of :data:`lodserver.io.SERVED_FORMATS`.
    bits : int, optional
        The json form's position grid bits (default: the mesh's).

    Returns
    -------
    int
        Bytes: counts (vertices ``v``, faces ``f``, wedges ``w`` of ``d``
        attribute columns) times what a format writes for each, plus the images.
    """
    v, f = int(level), int(pm.faces_at_level(level))
    width = sum(int(x) for _, x in pm.attribute_layout)
    w = int(pm.wedge_counts[level - pm.base_vertices]) if pm.has_attributes else 0
    if file_type == "json":
        cell = _text_int(2 ** (bits or default_bits(pm)))
        size = v * (3 * cell + 2) + f * (3 * _text_int(v) + 2)
        if pm.has_attributes:
            size += w * (width * _text_int(2 ** MAX_BITS) + 2) + f * (3 * _text_int(w) + 2)
        if pm.face_material is not None:
            size += f * (_text_int(pm.materials.count if pm.materials else 0) + 1)
        return _HEAD_BYTES + size
    if file_type == "obj":
        size = v * (3 * _OBJ_FLOAT + 3) + f * (3 * 3 * _text_int(max(v, w)) + 3)
        return _HEAD_BYTES + size + w * ((3 + 2) * _OBJ_FLOAT + 6)      # vt and vn lines
    if file_type == "ply":
        return _HEAD_BYTES + v * _PLY_VERTEX + f * _PLY_FACE
    return _HEAD_BYTES + _glb_geometry(pm, level) + _images(pm.materials)


def _glb_geometry(pm: ProgressiveMesh, level: int) -> int:
    """Bytes of a level's geometry in a GLB: a float32 row per vertex or wedge
    (position and attribute columns), uint32 indices."""
    width = sum(int(x) for _, x in pm.attribute_layout)
    w = int(pm.wedge_counts[level - pm.base_vertices]) if pm.has_attributes else 0
    return max(int(level), w) * 4 * (3 + width) + int(pm.faces_at_level(level)) * 12


def _images(materials) -> int:
    return sum(len(x) for x in materials.images) if materials is not None else 0


def packet_bytes(pm: ProgressiveMesh, start: int, to: int, bits: int | None = None) -> int:
    """The estimated working size of encoding the packet ``start -> to`` afresh, in
    bytes: its encoder holds the quantized state of its finer end, as the json form
    of that level does, so it weighs that json form."""
    return level_bytes(pm, max(start, to), "json", bits)


def chain_bytes(pm: ProgressiveMesh, levels) -> int:
    """The estimated size of the GLB chain of ``levels`` of ``pm``, in bytes: each
    level's geometry, the images once."""
    return (_HEAD_BYTES + sum(_glb_geometry(pm, level) for level in levels)
            + _images(pm.materials))


def scene_bytes(asset, chain: list) -> int:
    """The estimated size of a scene's GLB holding, for every level set in ``chain``
    (part index -> level; one for a scene level, several for its chain), each part
    at its level, in bytes: the parts' geometry, plus what the scene carries as it
    is (animations, skins, instancing, meshes kept without levels: its accessors'
    bytes), the images and the document.

    ``asset`` is a ``scene.asset.SceneAsset``.
    """
    pms = asset.pms
    geometry = sum(_glb_geometry(pms[p], level) for levels in chain
                   for p, level in levels.items())
    document = len(orjson.dumps(asset.scene.document))
    return (_HEAD_BYTES + document + geometry + _images(asset.materials)
            + carried_bytes(asset.scene.carried))


def carried_bytes(carried: dict) -> int:
    """Bytes of a scene's carried accessors (``Scene.carried``: index -> (values,
    record, role)) as a GLB writes them: each accessor's values."""
    return sum(int(np.asarray(values).nbytes) for values, _, _ in carried.values())
