"""KHR_draco_mesh_compression: the accessors of Draco-compressed primitives, decoded.

A primitive with the extension (KhronosGroup/glTF, extensions/2.0/Khronos/
KHR_draco_mesh_compression) keeps its ``attributes`` and ``indices`` accessors
for their counts and types, without data; the extension names a bufferView
holding one Draco bitstream and, for each attribute, the Draco attribute's
unique id. :class:`DracoAccessors` gives those accessors their values, decoding
a primitive (Google's Draco through PyPI ``DracoPy``) the first time one of its
accessors is read.

Before the decoder runs, the bitstream's header (:func:`draco_header`) must
declare the triangles and vertices the accessors declare, which
:func:`~.gltf_document.check_declared` has held to the limits: a few bytes of
Draco declaring a billion faces are refused, not decoded. Versions 2.2 (every
glTF encoder since Draco 1.3) of the mesh bitstream are read, sequential and
edgebreaker; the decoded counts must match the accessors' exactly, and a
decoder's failure is one sentence.
"""

from __future__ import annotations

import numpy as np

from ..mesh import MeshError
from .gltf_document import natural, record

EXTENSION = "KHR_draco_mesh_compression"

# glTF componentType -> numpy dtype of the accessor values handed to the reader
_DTYPES = {5120: "<i1", 5121: "<u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}

SEQUENTIAL, EDGEBREAKER = 0, 1
_METADATA_FLAG = 0x8000


def _varint(data: bytes, at: int) -> tuple[int, int]:
    """An unsigned LEB128 value (at most 5 bytes: Draco's uint32) at ``at``; (value, next)."""
    value = 0
    for shift in range(0, 35, 7):
        if at >= len(data):
            raise MeshError("its Draco bitstream ends inside its header")
        byte = data[at]
        at += 1
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return value, at
    raise MeshError("its Draco bitstream has a malformed number in its header")


def _skip_metadata(data: bytes, at: int) -> int:
    """Past the metadata block (attribute metadata, then the geometry's), iteratively:
    entries and sub-metadata nest, and a crafted stream must not recurse deep."""
    count, at = _varint(data, at)
    pending = 1                             # the geometry metadata after the attributes'
    for _ in range(count):
        _, at = _varint(data, at)           # the attribute's unique id
        pending += 1
    while pending:
        pending -= 1
        entries, at = _varint(data, at)
        for _ in range(entries):
            for _ in range(2):              # key and value: a size byte, then the bytes
                if at >= len(data):
                    raise MeshError("its Draco bitstream ends inside its metadata")
                at += 1 + data[at]
        subs, at = _varint(data, at)
        for _ in range(subs):
            if at >= len(data):
                raise MeshError("its Draco bitstream ends inside its metadata")
            at += 1 + data[at]              # the sub-metadata's name
            pending += 1
        if at > len(data):
            raise MeshError("its Draco bitstream ends inside its metadata")
    return at


def draco_header(data: bytes) -> tuple[int, int, int]:
    """(method, faces, vertices) a Draco mesh bitstream declares, read without decoding.

    ``method`` is :data:`SEQUENTIAL` (``vertices`` is the decoded point count) or
    :data:`EDGEBREAKER` (``vertices`` is the count of encoded positions, at most the
    decoded points: seams split them). MeshError for anything but a version 2.2
    triangle mesh.
    """
    data = bytes(data[:4096])       # the header and metadata sit at the front
    if data[:5] != b"DRACO" or len(data) < 11:
        raise MeshError("its KHR_draco_mesh_compression data is not a Draco bitstream")
    major, minor, kind, method = data[5:9]
    flags = int.from_bytes(data[9:11], "little")
    if (major, minor) != (2, 2):
        raise MeshError(f"its Draco bitstream is version {major}.{minor}; lodserver reads 2.2")
    if kind != 1:
        raise MeshError("its Draco bitstream holds a point cloud, not a triangle mesh")
    at = 11
    if flags & _METADATA_FLAG:
        at = _skip_metadata(data, at)
    if method == SEQUENTIAL:
        faces, at = _varint(data, at)
        vertices, at = _varint(data, at)
    elif method == EDGEBREAKER:
        at += 1                             # the traversal decoder's type
        vertices, at = _varint(data, at)
        faces, at = _varint(data, at)
    else:
        raise MeshError(f"its Draco bitstream uses encoding method {method}, neither "
                        "sequential nor edgebreaker")
    return method, faces, vertices


def _decoder():
    try:
        import DracoPy
    except ImportError:
        raise MeshError(f"it is compressed with {EXTENSION} and the DracoPy package is not "
                        "installed (pip install DracoPy)") from None
    return DracoPy


class DracoAccessors:
    """The accessors of a document's Draco primitives, decoded when first read.

    ``index in accessors`` says whether a Draco primitive gives accessor ``index``
    its values; ``accessors.get(index)`` is those values, (count, width) in the
    accessor's own dtype, as ``io.gltf`` reads any accessor.
    """

    def __init__(self, document: dict, views: list):
        self.document, self.views = document, views
        self.owner = {}             # accessor index -> (mesh, primitive number)
        self.values = {}            # accessor index -> its decoded values
        for m, mesh in enumerate(document.get("meshes") or ()):
            for n, primitive in enumerate((mesh or {}).get("primitives") or ()):
                extension = draco_extension(primitive)
                if extension is None:
                    continue
                for index in draco_accessors(primitive, extension):
                    self.owner.setdefault(index, (m, n))

    def __contains__(self, index) -> bool:
        return index in self.owner

    def get(self, index) -> np.ndarray:
        if index not in self.values:
            m, n = self.owner[index]
            primitive = self.document["meshes"][m]["primitives"][n]
            self.values.update(self._decode(primitive, f"primitive {n} of mesh {m}"))
        return self.values[index]

    def _decode(self, primitive: dict, label: str) -> dict:
        """{accessor index: values} of one Draco primitive, its header checked first."""
        extension = draco_extension(primitive)
        record(self.document, "bufferViews", extension.get("bufferView"), f"{label} {EXTENSION}")
        data = self.views[extension["bufferView"]]
        attributes = primitive.get("attributes") or {}
        points = natural(record(self.document, "accessors", attributes.get("POSITION"),
                                f"{label} POSITION").get("count"), f"{label} POSITION count")
        if "indices" not in primitive:
            raise MeshError(f"its {label} is Draco-compressed without an indices accessor")
        corners = natural(record(self.document, "accessors", primitive["indices"],
                                 f"{label} indices").get("count"), f"{label} index count")
        method, faces, vertices = draco_header(data)
        # the decoder allocates what the header says: it must be what the accessors say,
        # which the limits have bounded
        if 3 * faces != corners or vertices > points or (method == SEQUENTIAL
                                                         and vertices != points):
            raise MeshError(f"its {label} declares {corners // 3} triangles and {points} "
                            f"vertices, but its Draco bitstream {faces} triangles and "
                            f"{vertices} vertices")
        try:
            mesh = _decoder().decode(bytes(data))
        except MeshError:
            raise
        except Exception as exc:        # DracoPy raises its own types and ValueError
            raise MeshError(f"its {label} could not be decoded from {EXTENSION} "
                            f"({type(exc).__name__})") from None
        found_faces = np.asarray(mesh.faces).reshape(-1, 3)
        found_points = len(np.asarray(mesh.points).reshape(-1, 3))
        if len(found_faces) != faces or found_points != points:
            raise MeshError(f"its {label} decodes to {len(found_faces)} triangles and "
                            f"{found_points} vertices from Draco, not the {corners // 3} and "
                            f"{points} its accessors declare")
        out = {primitive["indices"]: self._typed(found_faces.reshape(-1, 1), primitive["indices"],
                                                 label)}
        for name, unique_id in extension["attributes"].items():
            attribute = mesh.get_attribute_by_unique_id(unique_id)
            if attribute is None or name not in attributes:
                raise MeshError(f"its {label} names Draco attribute {unique_id!r} for "
                                f"{str(name)[:40]}, which it does not hold")
            values = np.asarray(attribute["data"])
            out[attributes[name]] = self._typed(values.reshape(points, -1), attributes[name],
                                                label)
        return out

    def _typed(self, values: np.ndarray, index: int, label: str) -> np.ndarray:
        """Decoded ``values`` (count, k) as accessor ``index``'s dtype, its width checked."""
        accessor = record(self.document, "accessors", index, label)
        width = _WIDTHS.get(accessor.get("type"))
        dtype = _DTYPES.get(accessor.get("componentType"))
        if width != values.shape[1] or dtype is None:
            raise MeshError(f"its {label} has accessor {index} of type {accessor.get('type')!r}, "
                            f"but Draco decodes {values.shape[1]} components for it")
        return np.ascontiguousarray(values).astype(dtype)


def draco_extension(primitive) -> dict | None:
    """A primitive's ``KHR_draco_mesh_compression`` object, None without one; a
    MeshError for one without a bufferView or attributes."""
    extensions = primitive.get("extensions") if isinstance(primitive, dict) else None
    extension = extensions.get(EXTENSION) if isinstance(extensions, dict) else None
    if extension is None:
        return None
    if not isinstance(extension, dict) or "bufferView" not in extension \
            or not isinstance(extension.get("attributes"), dict):
        raise MeshError(f"a primitive has a {EXTENSION} without bufferView and attributes")
    return extension


def draco_accessors(primitive: dict, extension: dict) -> list:
    """The accessor indices a Draco primitive gives values to: its indices and the
    attributes the extension names."""
    attributes = primitive.get("attributes") or {}
    found = [attributes[name] for name in extension["attributes"] if name in attributes]
    if "indices" in primitive:
        found.append(primitive["indices"])
    return found
