"""glTF 2.0 in and out: a scene flattened into arrays, meshes and LOD chains written as GLB.

Reading (:func:`read_gltf`) walks the default scene and places every triangle
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

Writing (:func:`encode_glb`, :func:`encode_lod_chain`) makes one primitive per
material, one render vertex per wedge that primitive uses (glTF has a single
index per corner, so a seam vertex is written once per wedge), float32
attributes, uint32 indices, the images embedded as bufferViews, and every
bufferView 4-byte aligned. A mesh without attributes and materials takes a
separate, faster path whose bytes have not changed since lodserver wrote
positions only.

The ``Materials.gltf`` dict holds ``materials``, ``textures``, ``samplers`` and
``images`` lists as in a glTF document (images as ``{"mimeType", "name"}``,
bytes in ``Materials.images``) and, when the source required extensions used by
those records, ``extensionsRequired``.
"""

from __future__ import annotations

import base64
import binascii
import itertools
import json
import struct
from pathlib import Path
from urllib.parse import unquote

import numpy as np

from .mesh import ATTRIBUTE_WIDTHS, Materials, Mesh, MeshError

# glTF 2.0 accessor component types and element widths.
_COMPONENT_DTYPES = {5120: "<i1", 5121: "<u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
_TYPE_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
# Normalized integers map to [0, 1] (unsigned) or [-1, 1] (signed, -128 clamped): spec §3.11.
_NORMALIZED_SCALE = {5120: 127.0, 5121: 255.0, 5122: 32767.0, 5123: 65535.0}
_FLOAT, _UINT = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_TRIANGLES, _TRIANGLE_STRIP, _TRIANGLE_FAN = 4, 5, 6
# Geometry compressed by these has no plain accessor data to fall back on.
_UNDECODABLE = ("KHR_draco_mesh_compression", "EXT_meshopt_compression")
# What a primitive without the attribute looks like (spec §3.7.2.1: flat normals,
# and COLOR_0 multiplies the base colour, so white changes nothing).
_DEFAULT_COLOR = (1.0, 1.0, 1.0, 1.0)
_IMAGE_SIGNATURES = ((b"\x89PNG\r\n\x1a\n", "image/png"), (b"\xff\xd8\xff", "image/jpeg"),
                     (b"\xabKTX 20\xbb", "image/ktx2"))


# --- reading ----------------------------------------------------------------------------


def read_gltf(path: Path, kind: str) -> dict:
    """The triangles of a .gltf or .glb file's default scene, flattened.

    Parameters
    ----------
    path : Path
        The file; a ``.gltf`` finds its buffers and images relative to it.
    kind : str
        ``"gltf"`` or ``"glb"``, for messages (the container is sniffed).

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
        If the file is not glTF, a buffer or image it names is missing, an
        accessor runs past its data, it needs a compression extension, or it
        places no triangles.
    """
    data = path.read_bytes()
    try:
        document, binary = _parse_container(data)
        required = [name for name in document.get("extensionsRequired", ()) if name in _UNDECODABLE]
        if required:
            raise MeshError(f"it requires the glTF extension {required[0]}, which lodserver "
                            "cannot decode (export it without mesh compression)")
        buffers = _load_buffers(document, binary, path.parent)
        views = [_view_bytes(buffers, view, i)
                 for i, view in enumerate(document.get("bufferViews", ()))]
        return _flatten_scene(document, views, path.parent)
    except MeshError:
        raise
    except (KeyError, IndexError, TypeError, ValueError, struct.error) as exc:
        # a malformed document shows up as a missing key or a bad index somewhere
        raise MeshError(
            f"it could not be parsed as {kind.upper()} ({type(exc).__name__}: {exc})"
        ) from exc


def _parse_container(data: bytes) -> tuple[dict, bytes | None]:
    """The JSON document and the BIN chunk (None if absent) of GLB or .gltf bytes."""
    if data[:4] != b"glTF":
        return json.loads(data.decode("utf-8")), None
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
    return json.loads(chunks[b"JSON"].decode("utf-8")), chunks.get(b"BIN\x00")


def _load_buffers(document: dict, binary: bytes | None, folder: Path) -> list[bytes]:
    buffers = []
    for i, buffer in enumerate(document.get("buffers", ())):
        if "uri" in buffer:
            data = _uri_bytes(buffer["uri"], folder, f"buffer {i}")
        elif i == 0 and binary is not None:
            data = binary  # the GLB's own BIN chunk
        else:
            raise MeshError(f"its buffer {i} has no uri and there is no GLB BIN chunk")
        if len(data) < buffer["byteLength"]:
            raise MeshError(f"its buffer {i} holds {len(data)} bytes, "
                            f"fewer than its byteLength {buffer['byteLength']}")
        buffers.append(data)
    return buffers


def _uri_bytes(uri: str, folder: Path, what: str) -> bytes:
    """The bytes behind a data: URI or a file path relative to the document."""
    if uri.startswith("data:"):
        header, _, payload = uri.partition(",")
        try:
            if header.endswith(";base64"):
                return base64.b64decode(payload, validate=True)
            return unquote(payload).encode("latin-1")
        except (binascii.Error, UnicodeEncodeError) as exc:
            raise MeshError(f"its {what} has a malformed data: URI ({exc})") from exc
    file = folder / unquote(uri)
    if not file.is_file():
        raise MeshError(f"its {what} file {uri!r} is missing (looked for {file})")
    return file.read_bytes()


def _view_bytes(buffers: list[bytes], view: dict, index: int) -> memoryview:
    start = view.get("byteOffset", 0)
    end = start + view["byteLength"]
    data = buffers[view["buffer"]]
    if end > len(data):
        raise MeshError(f"its bufferView {index} runs past the end of buffer {view['buffer']}")
    return memoryview(data)[start:end]


def _read_accessor(document: dict, views: list, index: int) -> np.ndarray:
    """Accessor ``index`` as a (count, width) array of its own dtype (sparse applied)."""
    accessor = document["accessors"][index]
    dtype = np.dtype(_COMPONENT_DTYPES[accessor["componentType"]])
    width, count = _TYPE_WIDTHS[accessor["type"]], accessor["count"]
    if "bufferView" in accessor and count:
        view = document["bufferViews"][accessor["bufferView"]]
        data = views[accessor["bufferView"]]
        offset = accessor.get("byteOffset", 0)
        stride = view.get("byteStride") or dtype.itemsize * width
        if count and offset + (count - 1) * stride + dtype.itemsize * width > len(data):
            raise MeshError(f"its accessor {index} runs past the end of its bufferView")
        # a strided view over the interleaved bytes, copied into a compact array
        values = np.ndarray((count, width), dtype, buffer=data, offset=offset,
                            strides=(stride, dtype.itemsize)).copy()
    else:
        values = np.zeros((count, width), dtype)  # all zeros unless sparse says otherwise
    sparse = accessor.get("sparse")
    if sparse:
        n = sparse["count"]
        where = sparse["indices"]
        at = np.frombuffer(views[where["bufferView"]], _COMPONENT_DTYPES[where["componentType"]],
                           n, where.get("byteOffset", 0))
        what = sparse["values"]
        values[at] = np.frombuffer(views[what["bufferView"]], dtype, n * width,
                                   what.get("byteOffset", 0)).reshape(n, width)
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
    if mode == _TRIANGLES:
        if len(indices) % 3:
            raise MeshError(f"a triangle primitive has {len(indices)} indices, not a multiple of 3")
        return indices.reshape(-1, 3)
    i = np.arange(max(len(indices) - 2, 0))
    if mode == _TRIANGLE_STRIP:
        # odd triangles swap two corners so that every triangle keeps the strip's winding
        odd = i % 2
        return np.stack([indices[i], indices[i + 1 + odd], indices[i + 2 - odd]], axis=1)
    return np.stack([indices[i + 1], indices[i + 2], np.full_like(i, indices[0])], axis=1)


def _flatten_scene(document: dict, views: list, folder: Path) -> dict:
    """Arrays of every placed triangle primitive (see :func:`read_gltf`)."""
    cache = {}

    def accessor(index):
        if index not in cache:
            cache[index] = _read_accessor(document, views, index)
        return cache[index]

    placed = []  # (primitive, linear (3, 3), triangles, world positions)
    for mesh_index, world in _mesh_instances(document):
        for number, primitive in enumerate(document["meshes"][mesh_index]["primitives"]):
            mode = primitive.get("mode", _TRIANGLES)
            if mode not in (_TRIANGLES, _TRIANGLE_STRIP, _TRIANGLE_FAN):
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
            if triangles.max() >= len(local):
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

    materials = _read_materials(document, views, folder)
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
            values = _as_float(accessor(attributes[name]), document["accessors"][attributes[name]])
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


def _read_materials(document: dict, views: list, folder: Path) -> Materials | None:
    """Every material, texture, sampler and image record, image bytes byte for byte."""
    if not any(document.get(key) for key in ("materials", "textures", "images")):
        return None
    images, records = [], []
    for i, image in enumerate(document.get("images", ())):
        uri = image.get("uri", "")
        # a file's name identifies the image; a data: URI is no name
        name = image.get("name") or ("" if uri.startswith("data:") else Path(unquote(uri)).name)
        name = name or f"image{i}"
        if "bufferView" in image:
            data = bytes(views[image["bufferView"]])
        elif uri:
            data = _uri_bytes(uri, folder, f"image {i}")
        else:
            raise MeshError(f"its image {i} has neither a uri nor a bufferView")
        # a bufferView image states its mimeType; a uri one may leave it to the bytes
        mime = image.get("mimeType") or image_mime_type(data)
        if mime is None:
            raise MeshError(f"its image {i} ({name!r}) is not PNG, JPEG, WebP or KTX2 "
                            "and has no mimeType")
        record = {key: value for key, value in image.items() if key not in ("uri", "bufferView")}
        record.update(mimeType=mime, name=name)
        records.append(record)
        images.append(data)
    gltf = {key: document.get(key, []) for key in ("materials", "textures", "samplers")}
    gltf["images"] = records
    # extensions the source required and these records use must stay required
    used = _extension_names(gltf)
    required = [name for name in document.get("extensionsRequired", ()) if name in used]
    if required:
        gltf["extensionsRequired"] = required
    return Materials(gltf, tuple(images))


def image_mime_type(data: bytes) -> str | None:
    """The glTF mimeType of encoded image bytes, from their signature; None if unknown."""
    for signature, mime in _IMAGE_SIGNATURES:
        if data.startswith(signature):
            return mime
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "image/webp"
    return None


def _extension_names(tree) -> set[str]:
    """Names of every ``extensions`` entry anywhere in a JSON tree."""
    found = set()
    if isinstance(tree, dict):
        found.update(tree.get("extensions", {}) if isinstance(tree.get("extensions"), dict) else ())
        for value in tree.values():
            found |= _extension_names(value)
    elif isinstance(tree, list):
        for value in tree:
            found |= _extension_names(value)
    return found


# --- writing ----------------------------------------------------------------------------


def encode_glb(mesh: Mesh) -> bytes:
    """A binary glTF 2.0 file of one mesh, with its attributes and materials.

    One node, one mesh, one primitive per material used (faces without a
    material in a primitive of their own); every image, texture and material of
    ``mesh.materials`` is written, used or not. A mesh with neither attributes
    nor materials is written by the positions-only fast path.
    """
    if mesh.attributes is None and mesh.face_material is None and mesh.materials is None:
        return geometry_glb(mesh.positions, mesh.faces)
    writer = _GlbWriter(mesh.materials)
    writer.add_mesh(mesh)
    return writer.finish([{"mesh": 0}], scene_nodes=[0])


def encode_lod_chain(meshes: list[Mesh], screen_coverage: list[float]) -> bytes:
    """One GLB holding levels of detail, finest first, linked by the ``MSFT_lod`` extension.

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

    Returns
    -------
    bytes
        Node i draws mesh i; node 0, the only one in the scene (so a viewer
        without the extension shows the finest level), carries
        ``extensions.MSFT_lod.ids = [1, ..., n - 1]`` and
        ``extras.MSFT_screencoverage``.
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
    materials = meshes[0].materials
    count = materials.count if materials is not None else 0
    writer = _GlbWriter(materials)
    nodes = []
    for level, mesh in enumerate(meshes):
        used = mesh.face_material
        if used is not None and used.size and used.max() >= count:
            raise MeshError(f"level {level} uses material {int(used.max())}, "
                            f"but the first level has {count} materials")
        writer.add_mesh(mesh)
        nodes.append({"name": f"LOD{level}", "mesh": level})
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


class _GlbWriter:
    """Accumulates the binary chunk, bufferViews, accessors and meshes of one GLB."""

    def __init__(self, materials: Materials | None):
        self.blobs, self.size = [], 0
        self.views, self.accessors, self.meshes = [], [], []
        self.materials = materials

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
                     target: int = _ARRAY_BUFFER) -> int:
        """An accessor over ``values`` (float32 or uint32), min/max when ``bounds``."""
        component = _FLOAT if values.dtype == np.float32 else _UINT
        values = np.ascontiguousarray(values, dtype="<f4" if component == _FLOAT else "<u4")
        accessor = {"bufferView": self.add_view(values.tobytes(), target),
                    "componentType": component, "count": len(values), "type": kind}
        if bounds:
            accessor["min"], accessor["max"] = _bounds(values)
        self.accessors.append(accessor)
        return len(self.accessors) - 1

    def add_mesh(self, mesh: Mesh) -> int:
        """A glTF mesh of ``mesh``'s primitives; its index."""
        primitives = []
        for material, vertices, attributes, indices in render_primitives(mesh):
            # glTF requires POSITION bounds, taken from the float32 values written
            record = {"attributes": {"POSITION": self.add_accessor(vertices.astype(np.float32),
                                                                   "VEC3", bounds=True)}}
            for name, values in attributes.items():
                kind = f"VEC{values.shape[1]}"
                record["attributes"][name] = self.add_accessor(values, kind)
            record["indices"] = self.add_accessor(indices.ravel(), "SCALAR",
                                                  target=_ELEMENT_ARRAY_BUFFER)
            if material >= 0:
                record["material"] = material
            record["mode"] = _TRIANGLES
            primitives.append(record)
        self.meshes.append({"primitives": primitives})
        return len(self.meshes) - 1

    def finish(self, nodes: list, *, scene_nodes: list, extensions=()) -> bytes:
        document = {"asset": {"version": "2.0", "generator": "lodserver"}, "scene": 0,
                    "scenes": [{"nodes": scene_nodes}], "nodes": nodes, "meshes": self.meshes}
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
            used += sorted(_extension_names(records) - set(used))
            if gltf.get("extensionsRequired"):
                document["extensionsRequired"] = list(gltf["extensionsRequired"])
        document.update(accessors=self.accessors, bufferViews=self.views,
                        buffers=[{"byteLength": self.size + (-self.size % 4)}])
        if used:
            document["extensionsUsed"] = used
        self.blobs.append(b"\0" * (-self.size % 4))
        return _pack_glb(document, *self.blobs)


def render_primitives(mesh: Mesh):
    """Per material, the arrays a renderer draws: one vertex per wedge used.

    Yields
    ------
    material : int
        Index into ``mesh.materials``, -1 for faces without one.
    positions : (r, 3) float64
        The render vertices' positions, ``positions[wedge vertex]``.
    attributes : dict of str to (r, k) float32
        NORMAL (unit length), TEXCOORD_n, COLOR_0 (RGBA in [0, 1]).
    indices : (f, 3) uint32
        The primitive's triangles over its render vertices, in mesh face order.
    """
    faces = mesh.faces
    # without attributes a render vertex is a mesh vertex; with them, a wedge
    keys = mesh.attributes.corners if mesh.attributes is not None else faces
    owner = mesh.wedge_vertices() if mesh.attributes is not None else None
    if mesh.face_material is None:
        groups = [(-1, np.arange(len(faces)))]
    else:
        order = np.argsort(mesh.face_material, kind="stable")  # keeps face order within a group
        materials, starts = np.unique(mesh.face_material[order], return_index=True)
        groups = zip(materials.tolist(), np.split(order, starts[1:]))
    for material, rows in groups:
        used, local = np.unique(keys[rows], return_inverse=True)
        indices = local.reshape(-1, 3).astype(np.uint32)
        vertices = used if owner is None else owner[used]
        attributes = {}
        if mesh.attributes is not None:
            for name, _ in mesh.attributes.layout:
                values = mesh.attributes.values[used, mesh.attributes.columns(name)]
                if name == "NORMAL":
                    values = _unit_normals(values, mesh.positions[vertices], indices)
                elif name == "COLOR_0":
                    values = np.clip(values, 0.0, 1.0)  # glTF colours are in [0, 1]
                attributes[name] = values.astype(np.float32)
        yield material, mesh.positions[vertices], attributes, indices


def _unit_normals(normals: np.ndarray, positions: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Normals (r, 3) scaled to unit length, as glTF requires.

    A zero normal (from a zero-area face in the source, say) has no direction to
    keep: it takes the area-weighted normal of the triangles around its render
    vertex, or +Z if those have no area either.
    """
    normals = np.array(normals, dtype=np.float64)
    zero = np.linalg.norm(normals, axis=1) < 1e-12
    if zero.any():
        corners = positions[triangles]
        weighted = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        around = np.zeros_like(normals)
        np.add.at(around, triangles.ravel(), np.repeat(weighted, 3, axis=0))
        normals[zero] = around[zero]
        normals[np.linalg.norm(normals, axis=1) == 0] = (0.0, 0.0, 1.0)
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


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
    return _pack_glb(document, memoryview(vertices).cast("B"), memoryview(indices).cast("B"))


def _geometry_document(vertex_count: int, face_count: int, lo: list, hi: list) -> dict:
    """The glTF document of one triangle mesh: POSITION (float32, bounds ``lo``,
    ``hi``) then uint32 indices, back to back in buffer 0."""
    vertex_bytes, index_bytes = 12 * vertex_count, 12 * face_count
    return {
        "asset": {"version": "2.0", "generator": "lodserver"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "mode": 4}]}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": vertex_count, "type": "VEC3",
             "min": lo, "max": hi},
            {"bufferView": 1, "componentType": 5125, "count": 3 * face_count, "type": "SCALAR"},
        ],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": vertex_bytes, "target": 34962},
            {"buffer": 0, "byteOffset": vertex_bytes, "byteLength": index_bytes, "target": 34963},
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


def _bounds(values: np.ndarray) -> tuple[list, list]:
    """Per-column min and max of (n, k) ``values``, as lists.

    Column by column: numpy's ``min(axis=0)`` on a narrow (n, 3) array is ~20x
    slower, which showed on the million-face levels the server writes.
    """
    columns = values.reshape(len(values), -1).T
    return [c.min().item() for c in columns], [c.max().item() for c in columns]


def _pack_glb(document: dict, *binary) -> bytes:
    """The GLB container: 12-byte header, JSON chunk (space padded), BIN chunk
    (the concatenation of ``binary``, byte buffers; copied once)."""
    header = json.dumps(document, separators=(",", ":")).encode()
    header += b" " * (-len(header) % 4)  # chunks are 4-byte aligned
    size = sum(len(b) for b in binary)
    total = 12 + 8 + len(header) + 8 + size
    return b"".join([struct.pack("<4sII", b"glTF", 2, total),
                     struct.pack("<I4s", len(header), b"JSON"), header,
                     struct.pack("<I4s", size, b"BIN\x00"), *binary])
