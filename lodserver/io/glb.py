"""Writing GLB: one mesh, or levels of detail linked by MSFT_lod.

:func:`encode_glb` and :func:`encode_lod_chain` make one primitive per
material, one render vertex per wedge that primitive uses (glTF has a single
index per corner, so a seam vertex is written once per wedge), float32
attributes, uint32 indices, the images embedded as bufferViews, and every
bufferView 4-byte aligned. A mesh without attributes and materials takes a
separate, faster path that writes its positions and indices alone.

Every layout column is written (:func:`render_attributes`): NORMAL, TEXCOORD_n,
COLOR_n, TANGENT and custom ``_NAME`` as FLOAT, JOINTS_n as UNSIGNED_BYTE (or
UNSIGNED_SHORT) and WEIGHTS_n as FLOAT summing to 1 per vertex, and the
``TARGET{t}_*`` columns as the primitive's morph ``targets`` (POSITION with min
and max, NORMAL and TANGENT deltas). The mesh's ``weights`` and
``extras.targetNames`` are the scene writer's (:mod:`.scene_glb`).

The ``Materials.gltf`` dict holds ``materials``, ``textures``, ``samplers`` and
``images`` lists as in a glTF document (images as ``{"mimeType", "name"}``,
bytes in ``Materials.images``) and, when the source required extensions used by
those records, ``extensionsRequired``.
"""

from __future__ import annotations

import itertools
import json
import re
import struct

import numpy as np

from ..mesh import Materials, Mesh, MeshError
from .gltf import (ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER, FLOAT, TRIANGLES, UINT,
                   extension_names)
from .meshopt import EXTENSION as MESHOPT, encode_view
from .quantize import (EXTENSION as QUANTIZATION, attribute_stream, grid_transform,
                       merge_vertices, plain_stream, position_grid, position_stream)
from .vertex_order import optimize_order
# re-exported: the scene writer and tests import them from this module
from .render_vertices import (render_attributes, render_primitives,  # noqa: F401
                              skin_influences, unit_tangents)

# How a GLB's meshes may be stored (GlbWriter): the CLI's --compress and the server's
# compress= take these. "none": float32 in the progressive mesh's order, what every
# glTF reader opens; "quantize": KHR_mesh_quantization, which the mainstream engines
# read (three.js, Babylon.js, Unity's glTFast, Godot 4, Blender); "meshopt": also
# EXT_meshopt_compression, which needs a decoder in the viewer (three.js's
# MeshoptDecoder, glTFast, Babylon.js): gltfpack -cc's form.
COMPRESSIONS = ("none", "quantize", "meshopt")
# What `lodserver export` writes unless told: quantized, as gltfpack writes by default
# (its compression is opt-in, -c/-cc, and so is ours): smaller than floats, and every
# mainstream engine reads it without a decoder.
DEFAULT_COMPRESS = "quantize"

# How a chain's levels are told apart (encode_lod_chain): the MSFT_lod extension
# (Babylon.js reads it; three.js, Godot and glTFast do not), the _LODn name suffix
# engines import LOD groups by (Unity, Unreal), or both.
LOD_NAMINGS = ("msft", "suffix", "both")


# numpy dtype -> glTF componentType of the accessors written, and back
_COMPONENTS = {"<f4": FLOAT, "<u4": UINT, "|u1": 5121, "<u2": 5123}
_DTYPES = {FLOAT: "<f4", UINT: "<u4", 5121: "<u1", 5123: "<u2", 5120: "<i1", 5122: "<i2"}

_TARGET = re.compile(r"TARGET(\d+)_(POSITION|NORMAL|TANGENT)")


def encode_glb(mesh: Mesh, compress: str = "none", *, name: str | None = None) -> bytes:
    """A binary glTF 2.0 file of one mesh, with its attributes and materials.

    One node, one mesh, one primitive per material used (faces without a
    material in a primitive of their own); every image, texture and material of
    ``mesh.materials`` is written, used or not. A mesh with neither attributes
    nor materials is written by the positions-only fast path, uncompressed.
    ``compress`` is one of :data:`COMPRESSIONS` (see :class:`GlbWriter`); ``name``
    names the node (``chair_LOD1``: one level of a chain written file by file).
    """
    check_compress(compress)
    if compress == "none" and mesh.attributes is None and mesh.face_material is None \
            and mesh.materials is None and name is None:
        return geometry_glb(mesh.positions, mesh.faces)
    writer = GlbWriter(mesh.materials, compress, boxes=[_box(mesh)])
    writer.add_mesh(mesh)
    node = {"mesh": 0} if name is None else {"name": name, "mesh": 0}
    return writer.finish([writer.placed(node)], scene_nodes=[0])


def check_compress(compress: str) -> None:
    """MeshError unless ``compress`` is one of :data:`COMPRESSIONS`."""
    if compress not in COMPRESSIONS:
        raise MeshError(f"compress must be one of {', '.join(COMPRESSIONS)}, "
                        f"got {str(compress)[:40]!r}")


def _box(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """(lo (3,), hi (3,)) of a mesh's positions (zeros for a mesh without any)."""
    if not len(mesh.positions):
        return np.zeros(3), np.zeros(3)
    return mesh.positions.min(axis=0), mesh.positions.max(axis=0)


def lod_name(name: str, level: int) -> str:
    """The node name of level ``level`` of asset ``name`` by the suffix convention
    engines import LOD groups by (Unity's and Unreal's ``_LOD0``, ``_LOD1``, ...)."""
    return f"{name}_LOD{level}"


def encode_lod_chain(meshes: list[Mesh], screen_coverage: list[float],
                     compress: str = "none", *, naming: str = "msft",
                     name: str = "lods") -> bytes:
    """One GLB holding levels of detail, finest first, linked by the ``MSFT_lod`` extension
    or named by the ``_LODn`` suffix convention (``naming``, :data:`LOD_NAMINGS`).

    Parameters
    ----------
    meshes : list of Mesh
        The levels, finest first. All share ``meshes[0].materials`` (written
        once); each level's ``face_material`` indexes into it.
    screen_coverage : list of float
        One value per level in [0, 1], non-increasing: level i is meant to be
        drawn while the object covers at least ``screen_coverage[i]`` of the
        screen (and less than ``screen_coverage[i - 1]``); see
        :func:`coverage_from_ratios`.
    compress : str
        One of :data:`COMPRESSIONS`: how the levels are stored (:class:`GlbWriter`).
    naming : str
        ``"msft"``: node i (named ``LOD{i}``) draws mesh i; node 0, the only one in
        the scene (so a viewer without the extension shows the finest level),
        carries ``extensions.MSFT_lod.ids = [1, ..., n - 1]`` and
        ``extras.MSFT_screencoverage``. ``"suffix"``: a root node ``name`` (with the
        coverage in its extras) whose children ``name_LOD0`` ... ``name_LODn``
        draw the levels, all in the scene, no extension (engines that import LOD
        groups by name pick them; a plain viewer draws them all, on top of each
        other). ``"both"``: MSFT_lod as ``"msft"``, the nodes named ``name_LODi``.
    name : str
        The asset's name for the suffix convention (the output file's stem).

    Returns
    -------
    bytes
        The GLB file.
    """
    if not meshes:
        raise MeshError("a LOD chain needs at least one mesh")
    coverage = [float(value) for value in screen_coverage]
    if len(coverage) != len(meshes):
        raise MeshError(f"{len(meshes)} levels need {len(meshes)} screen coverage values, "
                        f"got {len(coverage)}")
    if not all(0.0 <= value <= 1.0 for value in coverage) or any(
            later > earlier for earlier, later in itertools.pairwise(coverage)):
        raise MeshError(f"screen coverage values must lie in [0, 1] and not increase, "
                        f"got {coverage}")
    check_compress(compress)
    if naming not in LOD_NAMINGS:
        raise MeshError(f"LOD naming must be one of {', '.join(LOD_NAMINGS)}, "
                        f"got {str(naming)[:40]!r}")
    materials = meshes[0].materials
    count = materials.count if materials is not None else 0
    # one position grid for every level, so that every LOD node has the same transform
    writer = GlbWriter(materials, compress, boxes=[_box(mesh) for mesh in meshes])
    nodes = []
    for level, mesh in enumerate(meshes):
        used = mesh.face_material
        if used is not None and used.size and used.max() >= count:
            raise MeshError(f"level {level} uses material {int(used.max())}, "
                            f"but the first level has {count} materials")
        writer.add_mesh(mesh)
        label = f"LOD{level}" if naming == "msft" else lod_name(name, level)
        nodes.append(writer.placed({"name": label, "mesh": level}))
    if naming == "suffix":
        root = {"name": name, "children": list(range(len(meshes))),
                "extras": {"MSFT_screencoverage": coverage}}
        return writer.finish([*nodes, root], scene_nodes=[len(meshes)])
    extensions = []
    if len(meshes) > 1:
        nodes[0]["extensions"] = {"MSFT_lod": {"ids": list(range(1, len(meshes)))}}
        nodes[0]["extras"] = {"MSFT_screencoverage": coverage}
        extensions = ["MSFT_lod"]
    return writer.finish(nodes, scene_nodes=[0], extensions=extensions)


def coverage_from_ratios(ratios) -> list[float]:
    """Screen coverage hints for levels with these face ratios (finest first, decreasing).

    Screen coverage is the fraction of the viewport height the object spans, so
    its projected area grows with the square of it. Keeping the triangle density
    on screen constant, a level with ratio ``r`` of the finest level's faces
    serves down to coverage ``0.5 * sqrt(r / ratios[0])``, taking the finest
    level as made for an object half the screen high. Level i therefore hands
    over to level i + 1 at that coverage of level i + 1:
    ``coverage[i] = 0.5 * sqrt(ratios[i + 1] / ratios[0])``; the coarsest level
    gets 0, drawn however small (culling is the application's choice).

    >>> [round(c, 3) for c in coverage_from_ratios([1, 0.5, 0.2, 0.05])]
    [0.354, 0.224, 0.112, 0.0]
    """
    ratios = np.asarray(ratios, dtype=np.float64)
    if ratios.ndim != 1 or len(ratios) == 0 or not (ratios > 0).all() or (np.diff(ratios) >= 0).any():
        raise MeshError(f"LOD ratios must be positive and strictly decreasing, "
                        f"got {ratios.tolist()}")
    return [*(0.5 * np.sqrt(ratios[1:] / ratios[0])).tolist(), 0.0]


class GlbWriter:
    """Accumulates the binary chunk, bufferViews, accessors and meshes of one GLB.

    ``compress`` (one of :data:`COMPRESSIONS`) chooses how meshes are stored:
    ``"none"`` float32 attributes and uint32 indices in the mesh's face order;
    ``"quantize"`` KHR_mesh_quantization (:mod:`.quantize`: int8 normals and
    tangents, uint16 UVs and colours, and, when ``boxes`` is given, 14-bit positions
    on one grid whose transform :meth:`placed` puts on every node drawing a mesh)
    with each primitive in vertex cache and fetch order (:mod:`.vertex_order`);
    ``"meshopt"`` the same (triangles in the strip-like cache order, which the codec
    compresses best), every vertex and index bufferView compressed by
    EXT_meshopt_compression (normals and tangents by its octahedral filter), the
    compressed bytes in the GLB's buffer and the decoded layout in a uri-less
    fallback buffer (so the extension is required).
    """

    def __init__(self, materials: Materials | None, compress: str = "none", *, boxes=None):
        check_compress(compress)
        self.blobs, self.size = [], 0
        self.views, self.accessors, self.meshes = [], [], []
        self.materials = materials
        self.compress = compress
        self.grid = position_grid(boxes) if boxes and compress != "none" else None
        self.fallback = 0       # bytes of the decoded views in the fallback buffer
        self.same = _same_materials(materials)

    def placed(self, node: dict) -> dict:
        """``node`` (one drawing a mesh of this writer) with the transform that undoes
        the position grid, when positions are quantized on one."""
        return {**node, **grid_transform(self.grid)} if self.grid is not None else node

    def add_streams(self, streams: list, kind: str, *, bounds: bool = False) -> list[int]:
        """One accessor over each of ``streams`` (:class:`.quantize.Stream` of one
        type and stride), their rows back to back in one bufferView (meshopt
        compressed when the writer compresses): one view for a mesh's primitives,
        as the codec's fixed cost and the JSON are per view. Their indices."""
        rows = np.concatenate([stream.rows for stream in streams])
        stride = rows.shape[1]
        if self.compress == "meshopt" and len(rows):
            view = self.add_compressed_view(rows, "ATTRIBUTES", streams[0].filter, ARRAY_BUFFER)
        else:
            view = self.add_view(rows.tobytes(), ARRAY_BUFFER)
        if stride != _element_bytes(streams[0]):
            self.views[view]["byteStride"] = stride     # rows padded to 4 bytes
        found, start = [], 0
        for stream in streams:
            accessor = {"bufferView": view, "componentType": stream.component,
                        "count": len(stream.rows), "type": kind}
            if start:
                accessor["byteOffset"] = start * stride
            if stream.normalized:
                accessor["normalized"] = True
            if bounds:
                accessor["min"], accessor["max"] = _bounds(stream.values)
            self.accessors.append(accessor)
            found.append(len(self.accessors) - 1)
            start += len(stream.rows)
        return found

    def add_compressed_view(self, elements: np.ndarray, mode: str, kind: str = "NONE",
                            target: int | None = None) -> int:
        """A bufferView of ``elements`` (:func:`.meshopt.encode_view`'s input) stored
        by EXT_meshopt_compression; its index."""
        data, extension = encode_view(elements, mode, kind)
        padding = -self.size % 4
        if padding:
            self.blobs.append(b"\0" * padding)
            self.size += padding
        extension.update(buffer=0, byteOffset=self.size)
        self.blobs.append(data)
        self.size += len(data)
        length = extension["count"] * extension["byteStride"]
        view = {"buffer": 1, "byteOffset": self.fallback, "byteLength": length,
                "extensions": {MESHOPT: extension}}
        if target is not None:
            view["target"] = target
        self.fallback += length + (-length % 4)
        self.views.append(view)
        return len(self.views) - 1

    def add_view(self, data: bytes, target: int | None = None) -> int:
        padding = -self.size % 4  # every bufferView starts 4-byte aligned
        if padding:
            self.blobs.append(b"\0" * padding)
            self.size += padding
        view = {"buffer": 0, "byteOffset": self.size, "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        self.views.append(view)
        self.blobs.append(data)
        self.size += len(data)
        return len(self.views) - 1

    def add_accessor(self, values: np.ndarray, kind: str, *, bounds: bool = False,
                     target: int = ARRAY_BUFFER) -> int:
        """An accessor over ``values`` (float32, uint32, or uint8/uint16 joint indices),
        min/max when ``bounds``."""
        component = _COMPONENTS.get(values.dtype.newbyteorder("<").str, UINT)
        values = np.ascontiguousarray(values, dtype=_DTYPES[component])
        accessor = {"bufferView": self.add_view(values.tobytes(), target),
                    "componentType": component, "count": len(values), "type": kind}
        if bounds:
            accessor["min"], accessor["max"] = _bounds(values)
        self.accessors.append(accessor)
        return len(self.accessors) - 1

    def add_mesh(self, mesh: Mesh) -> int:
        """A glTF mesh of ``mesh``'s primitives; its index."""
        if self.compress != "none":
            return self._add_compressed_mesh(mesh)
        primitives = []
        for material, vertices, attributes, indices in render_primitives(mesh):
            # glTF requires POSITION bounds, taken from the float32 values written
            record = {"attributes": {"POSITION": self.add_accessor(vertices.astype(np.float32),
                                                                   "VEC3", bounds=True)}}
            targets = {}
            for name, values in attributes.items():
                kind = "SCALAR" if values.shape[1] == 1 else f"VEC{values.shape[1]}"
                morph = _TARGET.fullmatch(name)
                if morph:
                    # a morph target's POSITION needs min and max, like any POSITION
                    index = self.add_accessor(values, kind, bounds=morph[2] == "POSITION")
                    targets.setdefault(int(morph[1]), {})[morph[2]] = index
                else:
                    record["attributes"][name] = self.add_accessor(values, kind)
            if targets:
                record["targets"] = [targets.get(t) or {"POSITION": self.add_accessor(
                    np.zeros((len(vertices), 3), np.float32), "VEC3", bounds=True)}
                    for t in range(max(targets) + 1)]
            record["indices"] = self.add_accessor(indices.ravel(), "SCALAR",
                                                  target=ELEMENT_ARRAY_BUFFER)
            if material >= 0:
                record["material"] = material
            record["mode"] = TRIANGLES
            primitives.append(record)
        self.meshes.append({"primitives": primitives})
        return len(self.meshes) - 1

    def _add_compressed_mesh(self, mesh: Mesh) -> int:
        """:meth:`add_mesh` when quantizing or compressing: one primitive per distinct
        material record, its attributes as :mod:`.quantize` stores them, vertices
        equal once stored merged, then in vertex cache and fetch order; the
        primitives' streams of one kind share a bufferView, their indices another."""
        octahedral = self.compress == "meshopt"
        records, shared, triangles = [], {}, []
        if mesh.face_material is not None and self.same is not None:
            # faces of equal materials drawn by one primitive (the duplicates stay
            # in the materials list, unused)
            mesh = Mesh(mesh.positions, mesh.faces, mesh.attributes,
                        np.where(mesh.face_material >= 0,
                                 self.same[np.maximum(mesh.face_material, 0)], -1)
                        .astype(np.int32), mesh.materials)
        for material, vertices, attributes, indices in render_primitives(mesh):
            streams = {"POSITION": position_stream(vertices, self.grid) if self.grid is not None
                       else plain_stream(vertices.astype(np.float32))}
            for name, values in attributes.items():
                streams[name] = plain_stream(values) if _TARGET.fullmatch(name) else \
                    attribute_stream(name, values, octahedral=octahedral)
            merged, kept = merge_vertices(streams, indices)
            if len(kept):   # (a primitive smaller than the grid's step is kept as it is)
                streams, indices = merged, kept
            indices, order = optimize_order(indices, len(streams["POSITION"].rows),
                                            strip=octahedral)
            record = {"attributes": {}, "mode": TRIANGLES}
            if material >= 0:
                record["material"] = material
            for name, stream in streams.items():
                stream = stream.take(order)
                key = (name, stream.component, stream.width, stream.rows.shape[1],
                       stream.normalized, stream.filter)
                shared.setdefault(key, []).append((len(records), stream))
            records.append(record)
            triangles.append(indices)
        targets = [{} for _ in records]
        for (name, _, width, *_), members in shared.items():
            kind = "SCALAR" if width == 1 else f"VEC{width}"
            morph = _TARGET.fullmatch(name)
            # POSITION and a morph target's POSITION need min and max
            found = self.add_streams([stream for _, stream in members], kind,
                                     bounds=name == "POSITION" or bool(morph)
                                     and morph[2] == "POSITION")
            for (number, _), index in zip(members, found):
                if morph:
                    targets[number].setdefault(int(morph[1]), {})[morph[2]] = index
                else:
                    records[number]["attributes"][name] = index
        for record, found, indices in zip(records, targets, triangles):
            if found:
                count = self.accessors[record["attributes"]["POSITION"]]["count"]
                record["targets"] = [found.get(t) or {"POSITION": self.add_streams(
                    [plain_stream(np.zeros((count, 3), np.float32))], "VEC3", bounds=True)[0]}
                    for t in range(max(found) + 1)]
        for record, index in zip(records, self._add_indices(triangles)):
            record["indices"] = index
        self.meshes.append({"primitives": records})
        return len(self.meshes) - 1

    def _add_indices(self, triangles: list) -> list[int]:
        """The index accessors of a mesh's primitives ((f, 3) triangles each), back to
        back in one bufferView: uint16 when every primitive's vertices allow."""
        wide = any(len(t) and int(t.max()) > 0xFFFF for t in triangles)
        dtype = "<u4" if wide else "<u2"
        flat = np.concatenate([np.ravel(t) for t in triangles]).astype(dtype)
        if self.compress == "meshopt" and flat.size:
            view = self.add_compressed_view(flat, "TRIANGLES", target=ELEMENT_ARRAY_BUFFER)
        else:
            view = self.add_view(flat.tobytes(), ELEMENT_ARRAY_BUFFER)
        found, start = [], 0
        for t in triangles:
            accessor = {"bufferView": view, "componentType": UINT if wide else 5123,
                        "count": int(t.size), "type": "SCALAR"}
            if start:
                accessor["byteOffset"] = start * np.dtype(dtype).itemsize
            self.accessors.append(accessor)
            found.append(len(self.accessors) - 1)
            start += t.size
        return found

    def finish(self, nodes: list, *, scene_nodes: list, extensions=()) -> bytes:
        document = {"asset": {"version": "2.0", "generator": "lodserver"}, "scene": 0,
                    "scenes": [{"nodes": scene_nodes}], "nodes": nodes, "meshes": self.meshes}
        return self.finish_document(document, extensions=extensions)

    def finish_document(self, document: dict, *, extensions=(), required=None) -> bytes:
        """The GLB of ``document`` (everything but materials, textures, samplers,
        images, accessors, bufferViews and buffers, which this adds): the
        materials' extensions join ``extensions`` in ``extensionsUsed``;
        ``required``, when given, is the ``extensionsRequired`` list."""
        used = list(extensions)
        if self.materials is not None:
            gltf = self.materials.gltf
            # images go after the geometry: their bufferViews have no target
            images = [{**record, "bufferView": self.add_view(data)}
                      for record, data in zip(gltf.get("images", ()), self.materials.images)]
            # glTF forbids empty top-level arrays, so absent kinds are left out
            for key, records in (("materials", gltf.get("materials")),
                                 ("textures", gltf.get("textures")),
                                 ("samplers", gltf.get("samplers")), ("images", images)):
                if records:
                    document[key] = records
            records = [gltf.get(key) for key in ("materials", "textures", "images")]
            used += sorted(extension_names(records) - set(used))
            if gltf.get("extensionsRequired"):
                document["extensionsRequired"] = list(gltf["extensionsRequired"])
        if required is not None:
            document.pop("extensionsRequired", None)
            if required:
                document["extensionsRequired"] = list(required)
        buffers = [{"byteLength": self.size + (-self.size % 4)}]
        if self.compress != "none":
            # what this writer's own meshes need to be read at all
            needed = [QUANTIZATION] + ([MESHOPT] if self.fallback else [])
            used += [name for name in needed if name not in used]
            document["extensionsRequired"] = [*document.get("extensionsRequired", ()),
                                              *(name for name in needed if name not in
                                                document.get("extensionsRequired", ()))]
        if self.fallback:
            buffers.append({"byteLength": self.fallback,
                            "extensions": {MESHOPT: {"fallback": True}}})
        document.update(accessors=self.accessors, bufferViews=self.views, buffers=buffers)
        if used:
            document["extensionsUsed"] = used
        self.blobs.append(b"\0" * (-self.size % 4))
        return pack_glb(document, *self.blobs)


def geometry_glb(positions, faces) -> bytes:
    """A binary glTF 2.0 file with one triangle mesh (positions float32, indices uint32).

    The fast path for meshes without attributes or materials: packed straight
    from the arrays, and byte for byte what lodserver has always written.
    """
    vertices = np.ascontiguousarray(positions, dtype="<f4")
    indices = np.ascontiguousarray(faces, dtype="<u4").ravel()
    # glTF requires POSITION bounds, taken from the float32 values written
    document = _geometry_document(len(vertices), len(indices) // 3, *_bounds(vertices))
    # both sizes are multiples of 4, so the chunk needs no padding
    return pack_glb(document, memoryview(vertices).cast("B"), memoryview(indices).cast("B"))


def _geometry_document(vertex_count: int, face_count: int, lo: list, hi: list) -> dict:
    """The glTF document of one triangle mesh: POSITION (float32, bounds ``lo``,
    ``hi``) then uint32 indices, back to back in buffer 0."""
    vertex_bytes, index_bytes = 12 * vertex_count, 12 * face_count
    return {
        "asset": {"version": "2.0", "generator": "lodserver"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1,
                                     "mode": TRIANGLES}]}],
        "accessors": [
            {"bufferView": 0, "componentType": FLOAT, "count": vertex_count, "type": "VEC3",
             "min": lo, "max": hi},
            {"bufferView": 1, "componentType": UINT, "count": 3 * face_count, "type": "SCALAR"},
        ],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": vertex_bytes,
             "target": ARRAY_BUFFER},
            {"buffer": 0, "byteOffset": vertex_bytes, "byteLength": index_bytes,
             "target": ELEMENT_ARRAY_BUFFER},
        ],
        "buffers": [{"byteLength": vertex_bytes + index_bytes}],
    }


def level_glb(vertex_count: int, face_count: int, fill, *, copy: bool = True) -> bytes:
    """:func:`geometry_glb` of a mesh whose arrays ``fill(vertices, indices)``
    writes straight into the file's buffer: ``vertices`` (vertex_count, 3) float32,
    ``indices`` (face_count, 3) uint32.

    For the server's levels of a million faces: no float64 or int64 copies of the
    level, no conversions, one copy into the returned bytes. The JSON chunk is
    written after the arrays (it holds their bounds) into room reserved for the
    longest bounds, and padded with spaces like any JSON chunk. ``copy=False``
    returns a read-only memoryview of that buffer instead of bytes: a server
    sends it as it is, saving a copy of every byte (and the page faults of a
    fresh buffer the size of the file).
    """
    vertex_bytes, index_bytes = 12 * vertex_count, 12 * face_count
    # six floats of at most 24 characters (repr of a float32's double) and their commas
    empty = _geometry_document(vertex_count, face_count, [], [])
    room = len(json.dumps(empty, separators=(",", ":"))) + 6 * 25
    room += -room % 4
    at = 12 + 8 + room + 8                  # where the BIN chunk's data starts
    out = np.empty(at + vertex_bytes + index_bytes, dtype=np.uint8)
    vertices = out[at:at + vertex_bytes].view("<f4").reshape(vertex_count, 3)
    indices = out[at + vertex_bytes:].view("<u4").reshape(face_count, 3)
    fill(vertices, indices)
    document = _geometry_document(vertex_count, face_count, *_bounds(vertices))
    header = json.dumps(document, separators=(",", ":")).encode()
    header += b" " * (room - len(header))
    out[:20] = np.frombuffer(struct.pack("<4sIII4s", b"glTF", 2, len(out), room, b"JSON"),
                             dtype=np.uint8)
    out[20:20 + room] = np.frombuffer(header, dtype=np.uint8)
    out[20 + room:at] = np.frombuffer(struct.pack("<I4s", vertex_bytes + index_bytes, b"BIN\x00"),
                                      dtype=np.uint8)
    if not copy:
        out.flags.writeable = False
        return memoryview(out)
    return out.tobytes()


def _same_materials(materials: Materials | None) -> np.ndarray | None:
    """(k,) int32: for each material, the first one whose record is equal to it
    (textures are named by index, so equal records draw alike); None when all differ."""
    records = (materials.gltf.get("materials") or []) if materials is not None else []
    first, same = {}, []
    for index, record in enumerate(records):
        same.append(first.setdefault(json.dumps(record, sort_keys=True), index))
    if same == list(range(len(records))):
        return None
    return np.asarray(same, dtype=np.int32)


def _element_bytes(stream) -> int:
    """Bytes of one element of a :class:`.quantize.Stream`'s accessor, unpadded."""
    return np.dtype(_DTYPES[stream.component]).itemsize * stream.width


def _bounds(values: np.ndarray) -> tuple[list, list]:
    """Per-column min and max of (n, k) ``values``, as lists.

    Column by column: numpy's ``min(axis=0)`` on a narrow (n, 3) array is a
    slow strided reduction, which matters on the million-face levels the
    server writes.
    """
    columns = values.reshape(len(values), -1).T
    return [c.min().item() for c in columns], [c.max().item() for c in columns]


def pack_glb(document: dict, *binary) -> bytes:
    """The GLB container: 12-byte header, JSON chunk (space padded), BIN chunk
    (the concatenation of ``binary``, byte buffers; copied once; zero padded)."""
    header = json.dumps(document, separators=(",", ":")).encode()
    header += b" " * (-len(header) % 4)  # chunks are 4-byte aligned
    size = sum(len(b) for b in binary)
    # the BIN chunk too: its length may exceed the buffer's byteLength by up to 3
    binary = (*binary, b"\0" * (-size % 4))
    size += -size % 4
    total = 12 + 8 + len(header) + 8 + size
    return b"".join([struct.pack("<4sII", b"glTF", 2, total),
                     struct.pack("<I4s", len(header), b"JSON"), header,
                     struct.pack("<I4s", size, b"BIN\x00"), *binary])
