"""Reading glTF 2.0 (.gltf and .glb): the default scene flattened into arrays.

:func:`read_gltf` walks the default scene and places every triangle
primitive by its node's world transform, giving the arrays
:func:`lodserver.io.clean_mesh` takes:

- ``positions``     : (n, 3) float64, world-space vertex positions.
- ``faces``         : (m, 3) int64, triangles (strips and fans unrolled).
- ``corner_values`` : (m, 3, d) float64 or None, each face corner's attribute
  vector in ``layout`` order: NORMAL (world space, unit or zero), TEXCOORD_n (as
  stored: glTF's v-down convention), COLOR_n (linear RGBA), TANGENT (xyz by the
  world linear map, renormalised; w negated under a mirror) and custom ``_NAME``
  attributes (:mod:`.gltf_attributes`).
- ``face_material`` : (m,) int32 or None, the primitive's material, -1 for none.
- ``materials``     : :class:`~lodserver.mesh.Materials` or None, every material,
  texture, sampler and image of the document, the image bytes as stored.

The traversal is the one trimesh's loader uses (depth first, last child
first, one instance per node and primitive, winding reversed under a mirroring
transform), so vertices and faces come in the order trimesh's loader gives
them, and a file loads the same through either. Transforms are used as stored,
whereas trimesh snaps nearly rigid ones to exact rotations: positions can differ
from trimesh's by the float32 rounding of the stored matrices (4e-8 relative on
2CylinderEngine.glb), with the same weld and face counts. What means nothing
once flattened (JOINTS_n, WEIGHTS_n, morph targets) and what no rule knows
(matrix-typed custom attributes) is listed in ``dropped_attributes``;
:func:`read_gltf_meshes` keeps every attribute, the skin and the targets too.
Points and lines are skipped. Compressed and quantized geometry is decoded:
``EXT_meshopt_compression`` bufferViews (:mod:`.meshopt`),
``KHR_draco_mesh_compression`` primitives (:mod:`.draco`) and
``KHR_mesh_quantization``'s integer attributes (normalized ones mapped as §3.11
says, integer positions placed by the node transform that dequantizes them).

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
import struct
from pathlib import Path, PurePosixPath
from urllib.parse import unquote

import numpy as np

from ..mesh import Materials, MeshError
from .gltf_attributes import (as_float as _as_float, attribute_layout, check_attribute_size,
                              check_joints, primitive_corners)
# re-exported: readers (obj.py) and tests import them from this module
from .gltf_attributes import face_normals, transform_normals  # noqa: F401
from .images import image_type
from .gltf_document import (TRIANGLE_FAN as _TRIANGLE_FAN, TRIANGLE_STRIP as _TRIANGLE_STRIP,
                            TRIANGLES, accessor_identity, check_declared, natural,
                            parse_container, record)
from . import meshopt
from .draco import DracoAccessors
from .limits import LoadLimits
from .references import read_reference, resolve_reference

# glTF 2.0 accessor component types and element widths.
_COMPONENT_DTYPES = {5120: "<i1", 5121: "<u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}


_TYPE_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


FLOAT, UINT = 5126, 5125


ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963


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
        WebP or KTX2, a compressed view or Draco stream cannot be decoded
        (:mod:`.meshopt`, :mod:`.draco`), or it places no
        triangles.
    LimitError
        If what it declares exceeds ``limits``.
    """
    # every required extension either decodes (quantization, meshopt, Draco) or
    # concerns what a flattened mesh keeps as it is (materials, lights)
    return _read(path, kind, root, limits, lambda name: False, None,
                 lambda document, views, files, accessor: _flatten_scene(
                     document, views, files, accessor=accessor))


def _read(path, kind, root, limits, refused, refuse, then):
    """``then(document, views, files, accessor)`` of a glTF file read and checked
    (``accessor(index)``, :func:`_accessor_reader`, decodes Draco primitives): the one preamble
    of both readers. ``refuse(name)`` raises for the first ``extensionsRequired``
    entry that ``refused(name)``; a malformed document is a MeshError."""
    limits = limits or LoadLimits.unbounded()
    data = read_reference(path, path.name, "file", limit=limits.max_file_bytes)
    try:
        document, binary = parse_container(data, limits)
        required = [name for name in document.get("extensionsRequired", ()) if refused(name)]
        if required:
            refuse(required[0])
        check_declared(document, limits)
        files = _ReferencedFiles(path.parent, root, limits)
        buffers = _load_buffers(document, binary, files)
        views = [_view_bytes(buffers, view, i)
                 for i, view in enumerate(document.get("bufferViews", ()))]
        decoded = DracoAccessors(document, views)
        return then(document, views, files, _accessor_reader(document, views, decoded))
    except MeshError:
        raise
    except (KeyError, IndexError, TypeError, ValueError, OverflowError, struct.error) as exc:
        # a malformed document shows up as a missing key or a bad index somewhere
        raise MeshError(
            f"it could not be parsed as {kind.upper()} ({type(exc).__name__}: {exc})"
        ) from exc


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


def _load_buffers(document: dict, binary: bytes | None,
                  files: _ReferencedFiles) -> list[bytes | int]:
    """Each buffer's bytes; the byteLength alone of one without data (no uri, not the
    GLB's BIN chunk): the placeholder of ``EXT_meshopt_compression``, whose
    bufferViews are decoded from another buffer (:func:`_view_bytes`)."""
    buffers = []
    for i, buffer in enumerate(document.get("buffers", ())):
        if not isinstance(buffer, dict):
            raise MeshError(f"its buffer {i} is not an object")
        length = natural(buffer.get("byteLength"), f"buffer {i} byteLength")
        files.limits.check("max_file_bytes", length, f"bytes in buffer {i}")
        if "uri" in buffer:
            data = files.read(buffer["uri"], f"buffer {i}", length)
        elif i == 0 and binary is not None:
            data = binary  # the GLB's own BIN chunk
        else:
            buffers.append(length)
            continue
        if len(data) < length:
            raise MeshError(f"its buffer {i} holds {len(data)} bytes, "
                            f"fewer than its byteLength {length}")
        buffers.append(data)
    return buffers


def _view_bytes(buffers: list, view: dict, index: int) -> memoryview:
    """bufferView ``index``'s bytes: its range of its buffer, or decoded from the
    range its ``EXT_meshopt_compression`` names (:mod:`.meshopt`)."""
    if not isinstance(view, dict):
        raise MeshError(f"its bufferView {index} is not an object")
    start = natural(view.get("byteOffset", 0), f"bufferView {index} byteOffset")
    length = natural(view.get("byteLength"), f"bufferView {index} byteLength")
    data = _buffer_of(buffers, view.get("buffer"), f"bufferView {index}")
    # a placeholder buffer is its byteLength: the decoded views must fit in it all the same
    if start + length > (data if isinstance(data, int) else len(data)):
        raise MeshError(f"its bufferView {index} runs past the end of buffer {view['buffer']}")
    compressed = (view.get("extensions") or {}).get(meshopt.EXTENSION) \
        if isinstance(view.get("extensions"), dict) else None
    if compressed is not None:
        label = f"bufferView {index}"
        source = _buffer_of(buffers, compressed.get("buffer") if isinstance(compressed, dict)
                            else None, f"{label} {meshopt.EXTENSION}")
        at = natural(compressed.get("byteOffset", 0), f"{label} {meshopt.EXTENSION} byteOffset")
        size = natural(compressed.get("byteLength"), f"{label} {meshopt.EXTENSION} byteLength")
        if isinstance(source, int) or at + size > len(source):
            raise MeshError(f"its {label} has compressed bytes past the end of their buffer")
        return memoryview(meshopt.decode_view(compressed, memoryview(source)[at:at + size],
                                              length, label))
    if isinstance(data, int):
        raise MeshError(f"its buffer {view['buffer']} has no uri and there is no GLB BIN chunk")
    return memoryview(data)[start:start + length]


def _buffer_of(buffers: list, buffer, what: str):
    """``buffers[buffer]`` for a valid index, else a MeshError naming ``what``."""
    if isinstance(buffer, bool) or not isinstance(buffer, int) or not 0 <= buffer < len(buffers):
        raise MeshError(f"its {what} refers to buffer {buffer!r}, which does not exist")
    return buffers[buffer]


def _read_accessor(document: dict, views: list, index: int) -> np.ndarray:
    """Accessor ``index`` as a (count, width) array of its own dtype (sparse applied).

    Its count was checked against the limits by :func:`check_declared`; here
    every byte range is checked against the data before it is touched.
    """
    accessor = record(document, "accessors", index, "primitive")
    dtype = np.dtype(_COMPONENT_DTYPES[accessor["componentType"]])
    width = _TYPE_WIDTHS[accessor["type"]]
    count = natural(accessor.get("count"), f"accessor {index} count")
    element = dtype.itemsize * width
    if "bufferView" in accessor and count:
        view = record(document, "bufferViews", accessor["bufferView"], f"accessor {index}")
        data = views[accessor["bufferView"]]
        offset = natural(accessor.get("byteOffset", 0), f"accessor {index} byteOffset")
        stride = natural(view.get("byteStride", 0), f"bufferView {accessor['bufferView']} "
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
        n = natural(sparse["count"], f"accessor {index} sparse count")
        if n > count:
            raise MeshError(f"its accessor {index} has {n} sparse values for {count} elements")
        where = sparse["indices"]
        record(document, "bufferViews", where["bufferView"], f"accessor {index} sparse indices")
        record(document, "bufferViews", sparse["values"]["bufferView"],
                f"accessor {index} sparse values")
        at = np.frombuffer(views[where["bufferView"]], _COMPONENT_DTYPES[where["componentType"]],
                           n, natural(where.get("byteOffset", 0), "sparse byteOffset"))
        if n and (at.min() < 0 or at.max() >= count):
            raise MeshError(f"its accessor {index} has sparse indices outside its {count} elements")
        what = sparse["values"]
        values[at] = np.frombuffer(views[what["bufferView"]], dtype, n * width,
                                   natural(what.get("byteOffset", 0), "sparse byteOffset")
                                   ).reshape(n, width)
    return values


def _accessor_reader(document: dict, views: list, decoded: dict | None = None):
    """``accessor(index)``: accessor ``index``'s values (:func:`_read_accessor`), each
    read once, and accessors aliasing one byte range (:func:`.gltf_document.accessor_identity`)
    given the one array, so a thousand records naming the same bytes cost one copy.
    ``decoded`` gives the values of accessors a Draco primitive holds
    (:class:`.draco.DracoAccessors`)."""
    cache, by_identity = {}, {}

    def accessor(index):
        if decoded is not None and index in decoded:
            return decoded.get(index)
        if index not in cache:
            key = accessor_identity(record(document, "accessors", index, "primitive"))
            if key is None or key not in by_identity:
                values = _read_accessor(document, views, index)
                if key is not None:
                    by_identity[key] = values
            cache[index] = by_identity[key] if key is not None else values
        return cache[index]

    return accessor


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
                     limits: LoadLimits | None = None, honoured=(), check=None) -> dict:
    """Each glTF mesh of a .gltf or .glb file on its own, in its local space.

    The same reading, checks and primitive decoding as :func:`read_gltf`, but
    mesh by mesh with the identity transform instead of the default scene
    flattened, for :mod:`lodserver.io.scene`, which keeps the document.

    Returns
    -------
    dict
        ``document`` (the parsed JSON), ``meshes`` ({mesh index: the arrays
        :func:`read_gltf` returns, with every attribute (JOINTS_n, WEIGHTS_n and
        ``TARGET{t}_*`` morph deltas too, :mod:`.gltf_attributes`), or a
        MeshError's message for a mesh without triangles}) for every mesh some
        node uses, ``materials`` (Materials
        or None, shared by every mesh: face_material indexes it) and
        ``accessor(index) -> (count, width) array`` of the accessor's own dtype
        (sparse applied), for data carried as it is (animations).

    An ``extensionsRequired`` entry not in ``honoured`` is a MeshError, and so is a
    joint index outside the skin of a node that uses the mesh. ``check(document)``,
    when given, runs after the declared sizes are checked and before any accessor,
    image or mesh is read (the scene reader's bound on what it carries).
    """
    def refuse(required):
        raise MeshError(f"it requires the glTF extension {required}, which lodserver "
                        "cannot honour")

    def meshes(document, views, files, accessor):
        if check is not None:
            check(document)

        materials = _read_materials(document, views, files)
        used = sorted({node["mesh"] for node in document.get("nodes", ())
                       if isinstance(node, dict) and "mesh" in node})
        found = {}
        for index in used:
            record(document, "meshes", index, "a node")
            try:
                found[index] = _flatten_scene(document, views, files,
                                              instances=[(index, np.eye(4))],
                                              materials=materials, accessor=accessor,
                                              every=True)
            except MeshError as exc:
                if not str(exc).startswith("it has no faces"):
                    raise
                found[index] = f"mesh {index} has no triangles (only points or lines)"
                continue
            check_joints(document, index, found[index]["layout"],
                         found[index]["corner_values"])
        return {"document": document, "meshes": found, "materials": materials,
                "accessor": accessor}

    return _read(path, kind, root, limits, lambda name: name not in honoured, refuse, meshes)


_READ = object()  # materials not given: read them


def _flatten_scene(document: dict, views: list, files: _ReferencedFiles, *,
                   instances=None, materials=_READ, accessor=None, every=False) -> dict:
    """Arrays of every placed triangle primitive (see :func:`read_gltf`).

    ``instances`` ((mesh index, (4, 4) transform) pairs) defaults to the
    default scene's; ``materials`` and ``accessor`` may be given when the
    caller reads several meshes of one document. ``every`` keeps JOINTS_n,
    WEIGHTS_n and morph targets too (:mod:`.gltf_attributes`), for one mesh in
    its local space.
    """
    if accessor is None:
        accessor = _accessor_reader(document, views)

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

    layout, dropped = attribute_layout(document, [primitive for primitive, *_ in placed], every)
    corner_values = None
    if layout:
        check_attribute_size(files.limits if files is not None else None, 3 * len(faces), layout)
        corner_values = np.concatenate([
            primitive_corners(document, primitive, linear, triangles, world, layout, accessor,
                              every)
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
            record(document, "bufferViews", view, f"image {i}")
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
        kept = {key: value for key, value in image.items() if key not in ("uri", "bufferView")}
        kept.update(mimeType=mime, name=name)
        records.append(kept)
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
