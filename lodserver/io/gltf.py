"""Reading glTF 2.0 (.gltf and .glb): the default scene flattened into arrays.

:func:`read_gltf` walks the default scene and places every triangle
primitive by its node's world transform, giving the arrays
:func:`lodserver.io.clean_mesh` takes:

- ``positions``     : (n, 3) float64, world-space vertex positions.
- ``faces``         : (m, 3) int64, triangles (strips and fans unrolled).
- ``corner_values`` : (m, 3, d) float64 or None, each face corner's attribute
  vector in ``layout`` order: NORMAL (world space, unit or zero), TEXCOORD_0,
  TEXCOORD_1 (as stored: glTF's v-down convention) and COLOR_0 (linear RGBA).
- ``face_material`` : (m,) int32 or None, the primitive's material, -1 for none.
- ``materials``     : :class:`~lodserver.mesh.Materials` or None, every material,
  texture, sampler and image of the document, the image bytes as stored.

The traversal is the one trimesh's loader uses (depth first, last child
first, one instance per node and primitive, winding reversed under a mirroring
transform), so vertices and faces come in the order lodserver read them
through trimesh before it parsed glTF itself. Transforms are used as stored,
whereas trimesh snaps nearly rigid ones to exact rotations: positions can differ
from trimesh's by the float32 rounding of the stored matrices (4e-8 relative on
2CylinderEngine.glb), with the same weld and face counts. Attributes lodserver
does not carry (TANGENT, JOINTS_n, WEIGHTS_n, more UV or colour sets) are
listed in ``dropped_attributes``: renderers regenerate tangents from normals
and UVs. Points and lines are skipped; mesh compression is refused.

Everything the file declares is checked before it is read: accessor counts
and byte ranges against their bufferViews and buffers, primitive, instance,
triangle and vertex totals against :class:`~lodserver.io.limits.LoadLimits`,
the JSON's size and depth; buffer and image files are read by the rule of
:mod:`lodserver.io.references`; an image whose bytes are not PNG, JPEG, WebP or
KTX2 is refused and the sniffed mimeType replaces the declared one.

The ``Materials.gltf`` dict holds ``materials``, ``textures``, ``samplers`` and
``images`` lists as in a glTF document (images as ``{"mimeType", "name"}``,
bytes in ``Materials.images``) and, when the source required extensions used by
those records, ``extensionsRequired``.
"""

from __future__ import annotations

import base64
import binascii
import json
import struct
from pathlib import Path, PurePosixPath
from urllib.parse import unquote

import numpy as np

from ..mesh import ATTRIBUTE_WIDTHS, Materials, MeshError
from .images import image_type
from .limits import LimitError, LoadLimits
from .references import read_reference, resolve_reference

# glTF 2.0 accessor component types and element widths.
_COMPONENT_DTYPES = {5120: "<i1", 5121: "<u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}


_TYPE_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


# Normalized integers map to [0, 1] (unsigned) or [-1, 1] (signed, -128 clamped): spec §3.11.
_NORMALIZED_SCALE = {5120: 127.0, 5121: 255.0, 5122: 32767.0, 5123: 65535.0}


FLOAT, UINT = 5126, 5125


ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963


TRIANGLES, _TRIANGLE_STRIP, _TRIANGLE_FAN = 4, 5, 6


# Geometry compressed by these has no plain accessor data to fall back on.
_UNDECODABLE = ("KHR_draco_mesh_compression", "EXT_meshopt_compression")


# What a primitive without the attribute looks like (spec §3.7.2.1: flat normals,
# and COLOR_0 multiplies the base colour, so white changes nothing).
_DEFAULT_COLOR = (1.0, 1.0, 1.0, 1.0)


def read_gltf(path: Path, kind: str, *, root: Path | None = None,
              limits: LoadLimits | None = None) -> dict:
    """The triangles of a .gltf or .glb file's default scene, flattened.

    Parameters
    ----------
    path : Path
        The file; a ``.gltf`` finds its buffers and images relative to it.
    kind : str
        ``"gltf"`` or ``"glb"``, for messages (the container is sniffed).
    root : Path, optional
        Confine every buffer and image file to this folder
        (:func:`lodserver.references.resolve_reference`).
    limits : LoadLimits, optional
        Bounds checked on the declared sizes before any accessor is read;
        default :meth:`LoadLimits.unbounded`.

    Returns
    -------
    dict
        ``positions``, ``faces``, ``corner_values``, ``layout``,
        ``face_material``, ``materials`` (see the module docstring; the last
        five are keyword arguments of ``io.clean_mesh``) and
        ``dropped_attributes``, a sorted list of attribute names not kept.

    Raises
    ------
    MeshError
        If the file is not glTF, a buffer or image it names is missing or not
        allowed, an accessor runs past its data, an image is not PNG, JPEG,
        WebP or KTX2, it needs a compression extension, or it places no
        triangles.
    LimitError
        If what it declares exceeds ``limits``.
    """
    limits = limits or LoadLimits.unbounded()
    data = read_reference(path, path.name, "file", limit=limits.max_file_bytes)
    try:
        document, binary = _parse_container(data, limits)
        required = [name for name in document.get("extensionsRequired", ()) if name in _UNDECODABLE]
        if required:
            raise MeshError(f"it requires the glTF extension {required[0]}, which lodserver "
                            "cannot decode (export it without mesh compression)")
        _check_declared(document, limits)
        files = _ReferencedFiles(path.parent, root, limits)
        buffers = _load_buffers(document, binary, files)
        views = [_view_bytes(buffers, view, i)
                 for i, view in enumerate(document.get("bufferViews", ()))]
        return _flatten_scene(document, views, files)
    except MeshError:
        raise
    except (KeyError, IndexError, TypeError, ValueError, OverflowError, struct.error) as exc:
        # a malformed document shows up as a missing key or a bad index somewhere
        raise MeshError(
            f"it could not be parsed as {kind.upper()} ({type(exc).__name__}: {exc})"
        ) from exc


def _parse_container(data: bytes, limits: LoadLimits) -> tuple[dict, bytes | None]:
    """The JSON document and the BIN chunk (None if absent) of GLB or .gltf bytes."""
    if data[:4] != b"glTF":
        return _parse_json(data, limits), None
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
    return _parse_json(chunks[b"JSON"], limits), chunks.get(b"BIN\x00")


def _parse_json(data: bytes, limits: LoadLimits) -> dict:
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


def _natural(value, what: str) -> int:
    """``value`` as a non-negative int (JSON gives floats and strings too), or a MeshError."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise MeshError(f"its {what} is {value!r}, not a non-negative integer")
    return value


def _record(document: dict, key: str, index, what: str) -> dict:
    """``document[key][index]`` for a valid int index, else a MeshError naming ``what``."""
    records = document.get(key)
    if (isinstance(index, bool) or not isinstance(index, int) or not isinstance(records, list)
            or not 0 <= index < len(records) or not isinstance(records[index], dict)):
        raise MeshError(f"its {what} refers to {key} {index!r}, which does not exist")
    return records[index]


def _declared_triangles(document: dict, primitive: dict, label: str) -> tuple[int, int]:
    """(triangles, vertices) a primitive declares by its accessor counts, 0 for points/lines."""
    mode = primitive.get("mode", TRIANGLES)
    if mode not in (TRIANGLES, _TRIANGLE_STRIP, _TRIANGLE_FAN):
        return 0, 0
    attributes = primitive.get("attributes")
    if not isinstance(attributes, dict) or "POSITION" not in attributes:
        raise MeshError(f"its {label} has no POSITION attribute")
    position = _record(document, "accessors", attributes["POSITION"], f"{label} POSITION")
    vertices = _natural(position.get("count"), f"{label} POSITION count")
    corners = vertices
    if "indices" in primitive:
        indices = _record(document, "accessors", primitive["indices"], f"{label} indices")
        corners = _natural(indices.get("count"), f"{label} index count")
    triangles = corners // 3 if mode == TRIANGLES else max(corners - 2, 0)
    return triangles, vertices


def _check_declared(document: dict, limits: LoadLimits) -> None:
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
        counts = [_declared_triangles(document, p, f"primitive {n} of mesh {m}")
                  if isinstance(p, dict) else (0, 0) for n, p in enumerate(records)]
        triangles = sum(t for t, _ in counts)
        limits.check("max_triangles", triangles, f"triangles in mesh {m}")
        per_mesh.append((triangles, sum(v for _, v in counts)))
    instances = _scene_meshes(document, limits)
    limits.check("max_triangles_total", sum(per_mesh[m][0] for m in instances),
                 "triangles after placing every mesh instance")
    limits.check("max_vertices", sum(per_mesh[m][1] for m in instances),
                 "vertices after placing every mesh instance")
    for m, records in enumerate(primitives):
        for n, primitive in enumerate(records):
            if isinstance(primitive, dict):
                _check_geometry_has_data(document, primitive, f"primitive {n} of mesh {m}")


def _check_geometry_has_data(document: dict, primitive: dict, label: str) -> None:
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
        accessor = _record(document, "accessors", index, f"{label} {what}")
        count = accessor.get("count") or 0
        sparse = accessor.get("sparse") if isinstance(accessor.get("sparse"), dict) else {}
        if "bufferView" not in accessor and count and sparse.get("count") != count:
            raise MeshError(f"its {label} has {what} (accessor {index}) without a bufferView, "
                            f"so most of its {count} values would be zeros")


def _scene_meshes(document: dict, limits: LoadLimits) -> list[int]:
    """Mesh index of every node placing one in the default scene (no transforms yet)."""
    if not document.get("scenes"):
        return []
    scene = _record(document, "scenes", document.get("scene", 0), "default scene")
    roots = scene.get("nodes", [])
    if not isinstance(roots, list):
        raise MeshError("its default scene has nodes that are not a list")
    stack, seen, meshes = list(roots), set(), []
    while stack:
        index = stack.pop()
        node = _record(document, "nodes", index, "scene graph")
        if index in seen:
            continue
        seen.add(index)
        # nodes without a mesh cost a transform each, so they count too
        limits.check("max_instances", len(seen), "nodes in its default scene")
        if "mesh" in node:
            _record(document, "meshes", node["mesh"], f"node {index}")
            meshes.append(node["mesh"])
        children = node.get("children", [])
        if not isinstance(children, list):
            raise MeshError(f"its node {index} has children that are not a list")
        stack.extend(children)
    return meshes


class _ReferencedFiles:
    """The files a document names, each resolved by the reference rule and read once.

    Several buffers or images may name one file; it is read (and counted) once.
    """

    def __init__(self, folder: Path, root: Path | None, limits: LoadLimits):
        self.folder, self.root, self.limits = folder, root, limits
        self.cache: dict[Path, bytes] = {}
        self.whole: set[Path] = set()  # files read to their end

    def read(self, uri: str, what: str, length: int | None = None) -> bytes:
        """The bytes behind a data: URI or a file reference (the first ``length`` of them)."""
        if not isinstance(uri, str):
            raise MeshError(f"its {what} uri is not a string")
        if uri[:5].lower() == "data:":
            return _data_uri_bytes(uri, what)
        file = resolve_reference(uri, self.folder, self.root, what)
        data = self.cache.get(file)
        if data is None or (length is None or length > len(data)) and file not in self.whole:
            # the first read of a buffer takes only its byteLength (a longer file is not
            # read to the end); a second that needs more reads it all, so each file is
            # read at most twice however many references name it
            wanted = length if data is None else None
            data = read_reference(file, uri, what, limit=self.limits.max_file_bytes,
                                  length=wanted, follow=self.root is None)
            self.cache[file] = data
            if wanted is None:
                self.whole.add(file)
        if length is not None and len(data) < length:
            raise MeshError(f"its {what} file {uri!r} holds {len(data)} bytes, fewer than "
                            f"the {length} it should have")
        return data


def _data_uri_bytes(uri: str, what: str) -> bytes:
    """The payload of a data: URI (its size is bounded by the JSON it sits in)."""
    header, _, payload = uri.partition(",")
    try:
        if header.endswith(";base64"):
            return base64.b64decode(payload, validate=True)
        return unquote(payload).encode("latin-1")
    except (binascii.Error, UnicodeEncodeError) as exc:
        raise MeshError(f"its {what} has a malformed data: URI ({exc})") from exc


def _load_buffers(document: dict, binary: bytes | None, files: _ReferencedFiles) -> list[bytes]:
    buffers = []
    for i, buffer in enumerate(document.get("buffers", ())):
        if not isinstance(buffer, dict):
            raise MeshError(f"its buffer {i} is not an object")
        length = _natural(buffer.get("byteLength"), f"buffer {i} byteLength")
        files.limits.check("max_file_bytes", length, f"bytes in buffer {i}")
        if "uri" in buffer:
            data = files.read(buffer["uri"], f"buffer {i}", length)
        elif i == 0 and binary is not None:
            data = binary  # the GLB's own BIN chunk
        else:
            raise MeshError(f"its buffer {i} has no uri and there is no GLB BIN chunk")
        if len(data) < length:
            raise MeshError(f"its buffer {i} holds {len(data)} bytes, "
                            f"fewer than its byteLength {length}")
        buffers.append(data)
    return buffers


def _view_bytes(buffers: list[bytes], view: dict, index: int) -> memoryview:
    if not isinstance(view, dict):
        raise MeshError(f"its bufferView {index} is not an object")
    start = _natural(view.get("byteOffset", 0), f"bufferView {index} byteOffset")
    end = start + _natural(view.get("byteLength"), f"bufferView {index} byteLength")
    buffer = view.get("buffer")
    if isinstance(buffer, bool) or not isinstance(buffer, int) or not 0 <= buffer < len(buffers):
        raise MeshError(f"its bufferView {index} refers to buffer {buffer!r}, which does not exist")
    data = buffers[buffer]
    if end > len(data):
        raise MeshError(f"its bufferView {index} runs past the end of buffer {buffer}")
    return memoryview(data)[start:end]


def _read_accessor(document: dict, views: list, index: int) -> np.ndarray:
    """Accessor ``index`` as a (count, width) array of its own dtype (sparse applied).

    Its count was checked against the limits by :func:`_check_declared`; here
    every byte range is checked against the data before it is touched.
    """
    accessor = _record(document, "accessors", index, "primitive")
    dtype = np.dtype(_COMPONENT_DTYPES[accessor["componentType"]])
    width = _TYPE_WIDTHS[accessor["type"]]
    count = _natural(accessor.get("count"), f"accessor {index} count")
    element = dtype.itemsize * width
    if "bufferView" in accessor and count:
        view = _record(document, "bufferViews", accessor["bufferView"], f"accessor {index}")
        data = views[accessor["bufferView"]]
        offset = _natural(accessor.get("byteOffset", 0), f"accessor {index} byteOffset")
        stride = _natural(view.get("byteStride", 0), f"bufferView {accessor['bufferView']} "
                                                     "byteStride") or element
        if stride < element:
            raise MeshError(f"its accessor {index} has elements of {element} bytes in a "
                            f"bufferView of stride {stride}")
        if offset + (count - 1) * stride + element > len(data):
            raise MeshError(f"its accessor {index} runs past the end of its bufferView")
        # a strided view over the interleaved bytes, copied into a compact array
        values = np.ndarray((count, width), dtype, buffer=data, offset=offset,
                            strides=(stride, dtype.itemsize)).copy()
    else:
        values = np.zeros((count, width), dtype)  # all zeros unless sparse says otherwise
    sparse = accessor.get("sparse")
    if sparse:
        n = _natural(sparse["count"], f"accessor {index} sparse count")
        if n > count:
            raise MeshError(f"its accessor {index} has {n} sparse values for {count} elements")
        where = sparse["indices"]
        _record(document, "bufferViews", where["bufferView"], f"accessor {index} sparse indices")
        _record(document, "bufferViews", sparse["values"]["bufferView"],
                f"accessor {index} sparse values")
        at = np.frombuffer(views[where["bufferView"]], _COMPONENT_DTYPES[where["componentType"]],
                           n, _natural(where.get("byteOffset", 0), "sparse byteOffset"))
        if n and (at.min() < 0 or at.max() >= count):
            raise MeshError(f"its accessor {index} has sparse indices outside its {count} elements")
        what = sparse["values"]
        values[at] = np.frombuffer(views[what["bufferView"]], dtype, n * width,
                                   _natural(what.get("byteOffset", 0), "sparse byteOffset")
                                   ).reshape(n, width)
    return values


def _as_float(values: np.ndarray, accessor: dict) -> np.ndarray:
    """float64 values of an attribute accessor, normalized integers mapped as the spec says."""
    if accessor.get("normalized"):
        scale = _NORMALIZED_SCALE[accessor["componentType"]]
        return np.maximum(values / scale, -1.0)
    return values.astype(np.float64)


def _local_matrix(node: dict) -> np.ndarray:
    """(4, 4) node transform: ``matrix`` times translation, rotation, scale (like trimesh)."""
    matrix = np.eye(4)
    if "matrix" in node:
        matrix = np.array(node["matrix"], dtype=np.float64).reshape(4, 4).T  # column-major
    if "translation" in node:
        step = np.eye(4)
        step[:3, 3] = node["translation"]
        matrix = matrix @ step
    if "rotation" in node:
        x, y, z, w = np.asarray(node["rotation"], dtype=np.float64)
        norm = x * x + y * y + z * z + w * w
        if norm > 1e-12:  # unnormalized quaternions are normalized; a zero one is no rotation
            s = 2.0 / norm
            step = np.eye(4)
            step[:3, :3] = [
                [1 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)],
                [s * (x * y + z * w), 1 - s * (x * x + z * z), s * (y * z - x * w)],
                [s * (x * z - y * w), s * (y * z + x * w), 1 - s * (x * x + y * y)],
            ]
            matrix = matrix @ step
    if "scale" in node:
        matrix = matrix @ np.diag([*node["scale"], 1.0])
    return matrix


def _mesh_instances(document: dict) -> list[tuple[int, np.ndarray]]:
    """(mesh index, (4, 4) world transform) of every node with a mesh in the default scene.

    Depth first with a stack, so the last root and the last child come first:
    the order trimesh places geometry in, which fixes the vertex order.
    """
    scenes = document.get("scenes")
    if not scenes:
        return []
    nodes = document.get("nodes", [])
    stack = [(root, np.eye(4)) for root in scenes[document.get("scene", 0)].get("nodes", ())]
    seen, instances = set(), []
    while stack:
        index, parent = stack.pop()
        if index in seen:
            continue  # glTF forbids a node with two parents; a cycle must not hang us
        seen.add(index)
        node = nodes[index]
        world = parent @ _local_matrix(node)
        if "mesh" in node:
            instances.append((node["mesh"], world))
        stack.extend((child, world) for child in node.get("children", ()))
    return instances


def _primitive_triangles(mode: int, indices: np.ndarray) -> np.ndarray:
    """(t, 3) int64 triangles of an index sequence drawn in ``mode`` (spec §3.7.2.1)."""
    if mode == TRIANGLES:
        if len(indices) % 3:
            raise MeshError(f"a triangle primitive has {len(indices)} indices, not a multiple of 3")
        return indices.reshape(-1, 3)
    i = np.arange(max(len(indices) - 2, 0))
    if mode == _TRIANGLE_STRIP:
        # odd triangles swap two corners so that every triangle keeps the strip's winding
        odd = i % 2
        return np.stack([indices[i], indices[i + 1 + odd], indices[i + 2 - odd]], axis=1)
    return np.stack([indices[i + 1], indices[i + 2], np.full_like(i, indices[0])], axis=1)


def read_gltf_meshes(path: Path, kind: str, *, root: Path | None = None,
                     limits: LoadLimits | None = None, honoured=()) -> dict:
    """Each glTF mesh of a .gltf or .glb file on its own, in its local space.

    The same reading, checks and primitive decoding as :func:`read_gltf`, but
    mesh by mesh with the identity transform instead of the default scene
    flattened, for :mod:`lodserver.io.scene`, which keeps the document.

    Returns
    -------
    dict
        ``document`` (the parsed JSON), ``meshes`` ({mesh index: the arrays
        :func:`read_gltf` returns, or a MeshError's message for a mesh without
        triangles}) for every mesh some node uses, ``materials`` (Materials
        or None, shared by every mesh: face_material indexes it) and
        ``accessor(index) -> (count, width) array`` of the accessor's own dtype
        (sparse applied), for data carried as it is (animations).

    An ``extensionsRequired`` entry not in ``honoured`` is a MeshError.
    """
    limits = limits or LoadLimits.unbounded()
    data = read_reference(path, path.name, "file", limit=limits.max_file_bytes)
    try:
        document, binary = _parse_container(data, limits)
        required = [name for name in document.get("extensionsRequired", ())
                    if name not in honoured]
        if required:
            raise MeshError(f"it requires the glTF extension {required[0]}, which lodserver "
                            "cannot honour")
        _check_declared(document, limits)
        files = _ReferencedFiles(path.parent, root, limits)
        buffers = _load_buffers(document, binary, files)
        views = [_view_bytes(buffers, view, i)
                 for i, view in enumerate(document.get("bufferViews", ()))]
        cache = {}

        def accessor(index):
            if index not in cache:
                cache[index] = _read_accessor(document, views, index)
            return cache[index]

        materials = _read_materials(document, views, files)
        used = sorted({node["mesh"] for node in document.get("nodes", ())
                       if isinstance(node, dict) and "mesh" in node})
        meshes = {}
        for index in used:
            _record(document, "meshes", index, "a node")
            try:
                meshes[index] = _flatten_scene(document, views, files,
                                               instances=[(index, np.eye(4))],
                                               materials=materials, accessor=accessor)
            except MeshError as exc:
                if not str(exc).startswith("it has no faces"):
                    raise
                meshes[index] = f"mesh {index} has no triangles (only points or lines)"
        return {"document": document, "meshes": meshes, "materials": materials,
                "accessor": accessor}
    except MeshError:
        raise
    except (KeyError, IndexError, TypeError, ValueError, OverflowError, struct.error) as exc:
        raise MeshError(
            f"it could not be parsed as {kind.upper()} ({type(exc).__name__}: {exc})"
        ) from exc


_READ = object()  # materials not given: read them


def _flatten_scene(document: dict, views: list, files: _ReferencedFiles, *,
                   instances=None, materials=_READ, accessor=None) -> dict:
    """Arrays of every placed triangle primitive (see :func:`read_gltf`).

    ``instances`` ((mesh index, (4, 4) transform) pairs) defaults to the
    default scene's; ``materials`` and ``accessor`` may be given when the
    caller reads several meshes of one document.
    """
    if accessor is None:
        cache = {}

        def accessor(index):
            if index not in cache:
                cache[index] = _read_accessor(document, views, index)
            return cache[index]

    placed = []  # (primitive, linear (3, 3), triangles, world positions)
    if instances is None:
        instances = _mesh_instances(document)
    for mesh_index, world in instances:
        for number, primitive in enumerate(document["meshes"][mesh_index]["primitives"]):
            mode = primitive.get("mode", TRIANGLES)
            if mode not in (TRIANGLES, _TRIANGLE_STRIP, _TRIANGLE_FAN):
                continue  # points and lines have no surface
            attributes = primitive["attributes"]
            position_index = attributes["POSITION"]
            local = _as_float(accessor(position_index), document["accessors"][position_index])
            if "indices" in primitive:
                indices = accessor(primitive["indices"]).ravel().astype(np.int64)
            else:
                indices = np.arange(len(local), dtype=np.int64)
            triangles = _primitive_triangles(mode, indices)
            if len(triangles) == 0:
                continue
            if triangles.max() >= len(local) or triangles.min() < 0:
                raise MeshError(f"primitive {number} of mesh {mesh_index} has indices past "
                                f"its {len(local)} vertices")
            linear = world[:3, :3]
            if np.linalg.det(linear) < 0:
                # A mirroring transform turns the winding, and so the normals, inside out.
                triangles = triangles[:, ::-1]
            placed.append((primitive, linear, triangles, local @ linear.T + world[:3, 3]))
    if not placed:
        raise MeshError("it has no faces (no node of its default scene places a triangle mesh)")

    positions = np.concatenate([world for *_, world in placed])
    starts = np.cumsum([0] + [len(world) for *_, world in placed])[:-1]
    faces = np.concatenate([triangles + start
                            for (_, _, triangles, _), start in zip(placed, starts)])

    names = {name for primitive, *_ in placed for name in primitive["attributes"]}
    layout = tuple((name, width) for name, width in ATTRIBUTE_WIDTHS.items() if name in names)
    dropped = sorted(names - set(ATTRIBUTE_WIDTHS) - {"POSITION"})
    corner_values = None
    if layout:
        corner_values = np.concatenate([
            _primitive_corners(primitive, linear, triangles, world, layout, accessor, document)
            for primitive, linear, triangles, world in placed])

    if materials is _READ:
        materials = _read_materials(document, views, files)
    face_material = None
    count = materials.count if materials is not None else 0
    if materials is not None or any("material" in primitive for primitive, *_ in placed):
        per_primitive = [primitive.get("material", -1) for primitive, *_ in placed]
        if any(not -1 <= m < count for m in per_primitive):
            raise MeshError(f"a primitive uses a material outside its {count} materials")
        face_material = np.repeat(np.array(per_primitive, dtype=np.int32),
                                  [len(triangles) for _, _, triangles, _ in placed])
    return {"positions": positions, "faces": faces, "corner_values": corner_values,
            "layout": layout, "face_material": face_material, "materials": materials,
            "dropped_attributes": dropped}


def _primitive_corners(primitive, linear, triangles, world, layout, accessor, document):
    """(t, 3, d) corner attribute vectors of one placed primitive, defaults where it has none."""
    attributes = primitive["attributes"]
    count = len(world)
    columns = []
    for name, width in layout:
        if name in attributes:
            record = _record(document, "accessors", attributes[name], f"primitive {name}")
            if record.get("count") != count:  # checked before reading: it could be huge
                raise MeshError(f"a primitive's {name} has {record.get('count')!r} values "
                                f"for {count} vertices")
            values = _as_float(accessor(attributes[name]), record)
            if len(values) != count:
                raise MeshError(f"a primitive's {name} has {len(values)} values "
                                f"for {count} vertices")
            if name == "NORMAL":
                values = transform_normals(values, linear)
            elif name == "COLOR_0" and values.shape[1] == 3:
                values = np.column_stack([values, np.ones(count)])  # RGB means opaque
            columns.append(values[triangles])
        elif name == "NORMAL":
            columns.append(np.repeat(face_normals(world, triangles)[:, None], 3, axis=1))
        else:
            fill = _DEFAULT_COLOR if name == "COLOR_0" else (0.0,) * width
            columns.append(np.broadcast_to(np.array(fill), (len(triangles), 3, width)))
    return np.concatenate(columns, axis=2)


def transform_normals(normals: np.ndarray, linear: np.ndarray) -> np.ndarray:
    """Normals (n, 3) under the linear map (3, 3): inverse transpose, renormalised.

    Normals must stay perpendicular to the surface, which a non-uniform scale
    would break if they were transformed like positions. Zero normals stay zero.
    """
    if np.allclose(linear, np.eye(3), rtol=0, atol=1e-15):
        return normals
    moved = normals @ np.linalg.pinv(linear)  # row form of inv(L).T @ n; pinv survives scale 0
    length = np.linalg.norm(moved, axis=1, keepdims=True)
    return np.divide(moved, length, out=np.zeros_like(moved), where=length > 0)


def face_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit normals (m, 3) of triangles (m, 3) by their winding; zero for zero-area faces."""
    corners = positions[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    length = np.linalg.norm(cross, axis=1, keepdims=True)
    return np.divide(cross, length, out=np.zeros_like(cross), where=length > 0)


def _read_materials(document: dict, views: list, files: _ReferencedFiles) -> Materials | None:
    """Every material, texture, sampler and image record, image bytes byte for byte.

    An image is kept only if its bytes are PNG, JPEG, WebP or KTX2, and its
    record's mimeType is the sniffed one whatever the document declared: a
    server sends the bytes with that type, and ``text/html`` is no texture.
    """
    if not any(document.get(key) for key in ("materials", "textures", "images")):
        return None
    images, records, by_view, total = [], [], {}, 0
    for i, image in enumerate(document.get("images", ())):
        if not isinstance(image, dict):
            raise MeshError(f"its image {i} is not an object")
        uri = image.get("uri", "")
        if not isinstance(uri, str):
            raise MeshError(f"its image {i} uri is not a string")
        # a file's name identifies the image; a data: URI is no name
        name = image.get("name") or ("" if uri[:5].lower() == "data:"
                                     else PurePosixPath(unquote(uri).replace("\\", "/")).name)
        name = str(name or f"image{i}")
        if "bufferView" in image:
            view = image["bufferView"]
            _record(document, "bufferViews", view, f"image {i}")
            if view not in by_view:  # many images on one view share its bytes, not copies
                by_view[view] = bytes(views[view])
            data = by_view[view]
        elif uri:
            data = files.read(uri, f"image {i}")
        else:
            raise MeshError(f"its image {i} has neither a uri nor a bufferView")
        # one image may be named a thousand times; each is written out again in a GLB
        total += len(data)
        files.limits.check("max_file_bytes", total, "bytes of images (counting repeats)")
        mime = image_type(data)
        if mime is None:
            raise MeshError(f"its image {i} ({name!r}) is not a PNG, JPEG, WebP or KTX2 image")
        record = {key: value for key, value in image.items() if key not in ("uri", "bufferView")}
        record.update(mimeType=mime, name=name)
        records.append(record)
        images.append(data)
    gltf = {key: document.get(key, []) for key in ("materials", "textures", "samplers")}
    gltf["images"] = records
    # extensions the source required and these records use must stay required
    used = extension_names(gltf)
    required = [name for name in document.get("extensionsRequired", ()) if name in used]
    if required:
        gltf["extensionsRequired"] = required
    return Materials(gltf, tuple(images))


def extension_names(tree) -> set[str]:
    """Names of every ``extensions`` entry anywhere in a JSON tree."""
    found = set()
    if isinstance(tree, dict):
        found.update(tree.get("extensions", {}) if isinstance(tree.get("extensions"), dict) else ())
        for value in tree.values():
            found |= extension_names(value)
    elif isinstance(tree, list):
        for value in tree:
            found |= extension_names(value)
    return found
