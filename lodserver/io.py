"""Reading mesh files into a clean :class:`~lodserver.mesh.Mesh`, and writing them back.

Every reader below produces the same two arrays, which :func:`clean_mesh` then
welds and cleans:

- ``positions`` : (n, 3) float64, vertex positions in the file's units.
- ``faces``     : (m, 3) int64, triangle vertex indices into ``positions``.

Polygons are fan-triangulated. A glTF/GLB scene is flattened: every instance of
every triangle geometry is placed by its node transform. Only positions and
triangles are kept; UVs, normals, colours and materials are dropped.

Where the arrays come from:

- OBJ: a small reader in this module. trimesh's OBJ loader splits vertices
  along UV and normal seams and drops unreferenced vertices, so its vertex
  counts would not be the file's and the :class:`LoadReport` would not say
  what the cleaning did.
- PLY with a ``tristrips`` element: a reader in this module (trimesh loads such
  a file as a point cloud and ignores the strips).
- Everything else: ``trimesh.load_scene(..., process=False)``, so that trimesh
  neither merges nor removes anything.

Precision when saving: PLY, GLB and STL store float32 coordinates (trimesh's
PLY exporter always writes ``float``; glTF and binary STL are float32 by
definition), so positions come back to within float32 rounding (about 6e-8
relative), and vertices closer than that would be welded on reload. OBJ and OFF
are text written with 17 decimals, exact for any coordinate of magnitude 0.1 or
more and within 5e-18 otherwise.
"""

from __future__ import annotations

import json
import os
import re
import struct
import uuid
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import trimesh

from lodserver.mesh import Mesh, MeshError

SUPPORTED_INPUT = ("obj", "ply", "stl", "off", "gltf", "glb")
SUPPORTED_OUTPUT = ("ply", "obj", "glb", "off", "stl")

# Keyword arguments for trimesh's exporters: positions and triangles only, so
# nothing written (normals, colours, a header comment) changes what is read back.
_EXPORT_OPTIONS = {
    "ply": {"encoding": "binary", "vertex_normal": False, "include_attributes": False},
    "obj": {
        "include_normals": False,
        "include_color": False,
        "include_texture": False,
        "header": None,
        "digits": 17,
    },
    "off": {"digits": 17},
    "stl": {},
}

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip

_PLY_ENDIAN = {"binary_little_endian": "<", "binary_big_endian": ">"}


@dataclass
class LoadReport:
    """What :func:`clean_mesh` changed, in counts.

    The vertex counts add up:
    ``source_vertices == welded_vertices + unreferenced_vertices + mesh.vertex_count``.
    """

    source_vertices: int
    """Vertices as read from the file (after flattening a scene)."""
    welded_vertices: int
    """Vertices merged into an earlier vertex with an identical position."""
    unreferenced_vertices: int
    """Vertices used by no remaining face, dropped."""
    degenerate_faces: int
    """Faces with a repeated vertex after welding, dropped."""
    duplicate_faces: int
    """Faces on the same vertex set as an earlier face (either winding), dropped."""

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


def load_mesh(path, *, file_type: str | None = None) -> tuple[Mesh, LoadReport]:
    """Read a mesh file and clean it with :func:`clean_mesh`.

    Parameters
    ----------
    path : str or os.PathLike
        The file to read. A ``.gltf`` file finds its buffers relative to it.
    file_type : str, optional
        One of :data:`SUPPORTED_INPUT`, overriding the file's extension (for
        uploads saved under temporary names).

    Returns
    -------
    mesh : Mesh
        Welded positions (n, 3) float64 and triangles (m, 3) int64.
    report : LoadReport
        What the cleaning removed.

    Raises
    ------
    MeshError
        If the file is missing, unreadable, of an unsupported type, cannot be
        parsed, has no faces, has NaN or infinite coordinates or out-of-range
        face indices, or has only degenerate faces. The message names the file.
    """
    path = Path(path)
    kind = _file_kind(path, file_type, SUPPORTED_INPUT, "load")
    try:
        if not path.exists():
            raise MeshError("no such file")
        if not path.is_file():
            raise MeshError("it is not a regular file")
        if path.stat().st_size == 0:
            raise MeshError("the file is empty")
        if kind == "obj":
            positions, faces = _read_obj(path)
        elif kind == "ply" and "tristrips" in _ply_element_names(path):
            positions, faces = _read_ply_tristrips(path)
        else:
            positions, faces = _read_with_trimesh(path, kind)
        return clean_mesh(positions, faces)
    except MeshError as exc:
        raise MeshError(f"cannot load {path}: {exc}") from exc
    except OSError as exc:
        raise MeshError(f"cannot load {path}: {exc.strerror or exc}") from exc


def clean_mesh(positions, faces) -> tuple[Mesh, LoadReport]:
    """Weld coincident vertices and drop degenerate, duplicate and unused elements.

    In order: vertices with identical float64 positions are merged (``0.0`` and
    ``-0.0`` count as identical); faces with a repeated vertex are dropped; a
    face on the same three vertices as an earlier face, in either winding, is
    dropped; vertices no face uses are dropped and the indices compacted.
    Everything kept stays in the order of its first occurrence, so the result
    is deterministic.

    Parameters
    ----------
    positions : (n, 3) array_like of float
        Vertex positions.
    faces : (m, 3) array_like of int
        Triangle vertex indices into ``positions``.

    Returns
    -------
    mesh : Mesh
        The cleaned mesh, (n', 3) float64 positions and (m', 3) int64 faces.
    report : LoadReport
        How many vertices and faces each step removed.

    Raises
    ------
    MeshError
        On malformed arrays, NaN or infinite positions, out-of-range indices,
        no faces, or only degenerate faces.
    """
    positions = np.asarray(positions, dtype=np.float64)
    faces = np.asarray(faces)
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise MeshError(f"positions must have shape (n, 3), got {positions.shape}")
    if faces.size == 0:
        raise MeshError("it has no faces")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise MeshError(f"faces must have shape (m, 3), got {faces.shape}")
    if not np.issubdtype(faces.dtype, np.integer):
        raise MeshError(f"faces must hold integer indices, got dtype {faces.dtype}")
    bad_rows = int((~np.isfinite(positions).all(axis=1)).sum())
    if bad_rows:
        raise MeshError(
            f"{bad_rows} of its {len(positions)} vertices have NaN or infinite "
            "coordinates"
        )
    faces = faces.astype(np.int64)
    out_of_range = int(((faces < 0) | (faces >= len(positions))).any(axis=1).sum())
    if out_of_range:
        raise MeshError(
            f"{out_of_range} faces use vertex indices outside [0, {len(positions) - 1}]"
        )

    first, inverse = _first_occurrences(positions)
    welded = positions[first]
    faces = inverse[faces]

    degenerate = (
        (faces[:, 0] == faces[:, 1])
        | (faces[:, 1] == faces[:, 2])
        | (faces[:, 2] == faces[:, 0])
    )
    if degenerate.all():
        raise MeshError(
            f"all {len(faces)} faces are degenerate after welding coincident vertices"
        )
    faces = faces[~degenerate]

    first_face, _ = _first_occurrences(np.sort(faces, axis=1))
    duplicates = len(faces) - len(first_face)
    faces = faces[first_face]

    used = np.zeros(len(welded), dtype=bool)
    used[faces] = True
    new_index = np.cumsum(used) - 1
    mesh = Mesh(welded[used], new_index[faces])
    report = LoadReport(
        source_vertices=len(positions),
        welded_vertices=len(positions) - len(welded),
        unreferenced_vertices=len(welded) - mesh.vertex_count,
        degenerate_faces=int(degenerate.sum()),
        duplicate_faces=duplicates,
    )
    return mesh, report


def save_mesh(mesh: Mesh, path, *, file_type: str | None = None) -> None:
    """Write a mesh's positions and triangles to a file, atomically.

    The file is written under a temporary name in the same directory and then
    renamed over ``path``, so ``path`` never holds a partly written file.

    Parameters
    ----------
    mesh : Mesh
        Positions (n, 3) float64 and faces (m, 3) int64 to write.
    path : str or os.PathLike
        Destination; its extension picks the format unless ``file_type`` is given.
    file_type : str, optional
        One of :data:`SUPPORTED_OUTPUT`, overriding the extension.

    Raises
    ------
    MeshError
        If the format is unsupported (nothing is written then).
    OSError
        If the file cannot be written.
    """
    path = Path(path)
    kind = _file_kind(path, file_type, SUPPORTED_OUTPUT, "save")
    data = encode_mesh(mesh, kind)
    temporary = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    try:
        with open(temporary, "xb") as file:
            file.write(data)
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def encode_mesh(mesh: Mesh, file_type: str) -> bytes:
    """The bytes of ``mesh`` as a file of ``file_type`` (one of :data:`SUPPORTED_OUTPUT`).

    GLB is packed here (one float32 POSITION accessor, one uint32 index
    accessor), straight from the arrays, without building a trimesh scene.
    """
    if file_type not in SUPPORTED_OUTPUT:
        raise MeshError(f"cannot write {file_type!r}: supported are {', '.join(SUPPORTED_OUTPUT)}")
    if file_type == "glb":
        return _glb_bytes(mesh.positions, mesh.faces)
    data = trimesh.Trimesh(mesh.positions, mesh.faces, process=False).export(
        file_type=file_type, **_EXPORT_OPTIONS[file_type]
    )
    return data.encode("utf-8") if isinstance(data, str) else data


def _glb_bytes(positions, faces) -> bytes:
    """A binary glTF 2.0 file with one triangle mesh (positions float32, indices uint32)."""
    vertices = np.ascontiguousarray(positions, dtype="<f4")
    indices = np.ascontiguousarray(faces, dtype="<u4").ravel()
    vertex_bytes, index_bytes = vertices.nbytes, indices.nbytes
    document = {
        "asset": {"version": "2.0", "generator": "lodserver"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "mode": 4}]}],
        "accessors": [
            # glTF requires POSITION bounds, taken from the float32 values written
            {"bufferView": 0, "componentType": 5126, "count": len(vertices), "type": "VEC3",
             "min": vertices.min(axis=0).tolist(), "max": vertices.max(axis=0).tolist()},
            {"bufferView": 1, "componentType": 5125, "count": len(indices), "type": "SCALAR"},
        ],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": vertex_bytes, "target": 34962},
            {"buffer": 0, "byteOffset": vertex_bytes, "byteLength": index_bytes, "target": 34963},
        ],
        "buffers": [{"byteLength": vertex_bytes + index_bytes}],
    }
    header = json.dumps(document, separators=(",", ":")).encode()
    header += b" " * (-len(header) % 4)         # chunks are 4-byte aligned
    binary = vertices.tobytes() + indices.tobytes()  # both sizes are multiples of 4
    total = 12 + 8 + len(header) + 8 + len(binary)
    return b"".join([struct.pack("<4sII", b"glTF", 2, total),
                     struct.pack("<I4s", len(header), b"JSON"), header,
                     struct.pack("<I4s", len(binary), b"BIN\x00"), binary])


def _first_occurrences(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Group equal rows, numbering the groups in order of first appearance.

    Parameters
    ----------
    rows : (k, d) array
        Rows to compare (with ``==``, so ``0.0`` equals ``-0.0``).

    Returns
    -------
    first : (u,) int64
        Index of the first row of each group, ascending.
    inverse : (k,) int64
        Group of each row, so ``rows[first][inverse]`` equals ``rows``.
    """
    # lexsort is stable, so within a group of equal rows the earliest comes first.
    order = np.lexsort(rows.T[::-1])
    ordered = rows[order]
    starts = np.ones(len(rows), dtype=bool)
    starts[1:] = (ordered[1:] != ordered[:-1]).any(axis=1)
    group_first = order[starts]
    rank = np.empty(len(group_first), dtype=np.int64)
    rank[np.argsort(group_first)] = np.arange(len(group_first))
    inverse = np.empty(len(rows), dtype=np.int64)
    inverse[order] = rank[np.cumsum(starts) - 1]
    return np.sort(group_first), inverse


def _file_kind(
    path: Path, file_type: str | None, supported: tuple[str, ...], verb: str
) -> str:
    """The lower-case format of ``path``, or a MeshError naming the supported ones."""
    kind = (file_type or path.suffix).lower().lstrip(".")
    if kind not in supported:
        what = f"file type '{kind}'" if kind else "file without an extension"
        raise MeshError(
            f"cannot {verb} {path}: unsupported {what}; "
            f"supported types are {', '.join(supported)}"
        )
    return kind


def _read_with_trimesh(path: Path, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """Positions (n, 3) and triangles (m, 3) of every geometry instance in the file."""
    try:
        scene = trimesh.load_scene(str(path), file_type=kind, process=False)
    except Exception as exc:
        # trimesh raises anything from ValueError to IndexError (or an ImportError
        # for a missing optional dependency) on a file it cannot read.
        raise MeshError(
            f"it could not be parsed as {kind.upper()} ({type(exc).__name__}: {exc})"
        ) from exc
    all_positions, all_faces, offset = [], [], 0
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        geometry = scene.geometry[name]
        if not isinstance(geometry, trimesh.Trimesh) or len(geometry.faces) == 0:
            continue
        linear = transform[:3, :3]
        all_positions.append(
            np.asarray(geometry.vertices, dtype=np.float64) @ linear.T
            + transform[:3, 3]
        )
        faces = np.asarray(geometry.faces, dtype=np.int64)
        if np.linalg.det(linear) < 0:
            # A mirroring transform turns the winding, and so the normals, inside out.
            faces = faces[:, ::-1]
        all_faces.append(faces + offset)
        offset += len(geometry.vertices)
    if not all_faces:
        held = sorted({type(g).__name__ for g in scene.geometry.values()})
        found = f"only {', '.join(held)} geometry" if held else "nothing"
        raise MeshError(f"it has no faces (trimesh found {found})")
    return np.concatenate(all_positions), np.concatenate(all_faces)


def _read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Positions (n, 3) of the ``v`` lines and triangles (m, 3) of the ``f`` lines."""
    text = re.sub(r"\\\r?\n", " ", path.read_bytes().decode("utf-8", errors="replace"))
    rows, corners, sizes, defined_before = [], [], [], []
    for number, line in enumerate(text.splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "v":
            if len(parts) < 4:
                raise MeshError(
                    f"line {number} is a vertex with fewer than 3 coordinates"
                )
            rows.append(parts[1:4])
        elif parts[0] == "f":
            if len(parts) < 4:
                raise MeshError(f"line {number} is a face with fewer than 3 vertices")
            if "/" in line:  # v/vt/vn references: keep the position index
                corners.extend(part.split("/", 1)[0] for part in parts[1:])
            else:
                corners.extend(parts[1:])
            sizes.append(len(parts) - 1)
            defined_before.append(len(rows))
    if not sizes:
        raise MeshError(f"it has no faces ({len(rows)} vertices, no 'f' lines)")
    try:
        positions = np.array(rows, dtype=np.float64)
    except ValueError as exc:
        raise MeshError(f"a vertex coordinate is not a number ({exc})") from exc
    try:
        raw = np.array(corners).astype(np.int64)
    except ValueError as exc:
        raise MeshError(f"a face vertex index is not an integer ({exc})") from exc
    # OBJ indices are 1-based; negative ones count back from the last vertex so far.
    relative_base = np.repeat(np.array(defined_before, dtype=np.int64), sizes)
    indices = np.where(raw > 0, raw - 1, relative_base + raw)
    bad = (raw == 0) | (indices < 0) | (indices >= len(positions))
    if bad.any():
        raise MeshError(
            f"{int(bad.sum())} face corners refer to vertices that do not exist (the "
            f"file has {len(positions)} vertices; first bad index {int(raw[bad][0])})"
        )
    return positions, _fan_triangulate(indices, np.array(sizes, dtype=np.int64))


def _fan_triangulate(corners: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Triangles (t, 3) fanning out polygons given as corners (k,) and sizes (p,)."""
    fan = sizes - 2
    starts = np.repeat(np.cumsum(sizes) - sizes, fan)
    step = np.arange(fan.sum()) - np.repeat(np.cumsum(fan) - fan, fan) + 1
    return np.stack(
        [corners[starts], corners[starts + step], corners[starts + step + 1]], axis=1
    )


def _decode_tristrips(sequence: np.ndarray) -> np.ndarray:
    """Triangles (t, 3) of the triangle strips in ``sequence`` (k,), each ended by -1.

    Triangle i of a strip s is (s[i], s[i+1], s[i+2]) for even i and
    (s[i+1], s[i], s[i+2]) for odd i, so all share one winding. Triangles with a
    repeated index only stitch strips together and are dropped.
    """
    sequence = np.asarray(sequence, dtype=np.int64)
    if len(sequence) < 3:
        return np.empty((0, 3), dtype=np.int64)
    a, b, c = sequence[:-2], sequence[1:-1], sequence[2:]
    positions = np.arange(len(sequence))
    strip_start = np.maximum.accumulate(np.where(sequence < 0, positions + 1, 0))
    odd = (positions[:-2] - strip_start[:-2]) % 2 == 1
    triangles = np.where(
        odd[:, None], np.stack([b, a, c], axis=1), np.stack([a, b, c], axis=1)
    )
    keep = (a >= 0) & (b >= 0) & (c >= 0) & (a != b) & (b != c) & (c != a)
    return triangles[keep]


def _read_ply_header(
    file,
) -> tuple[str, list[tuple[str, int, list[tuple[str, str, str | None]]]]]:
    """Format and elements ``(name, count, [(property, type, list size type)])``.

    The list size type is None for a scalar property.

    Leaves ``file`` at the first byte after ``end_header``.
    """
    if file.readline(64).strip() != b"ply":
        raise MeshError("it is not a PLY file (no 'ply' magic line)")
    encoding, elements = None, []
    while True:
        line = file.readline(4096)
        if not line:
            raise MeshError("its PLY header has no 'end_header' line")
        words = line.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        try:
            if words[0] == "format":
                encoding = words[1]
            elif words[0] == "element":
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property" and words[1] == "list":
                elements[-1][2].append(
                    (words[4], _PLY_TYPES[words[3]], _PLY_TYPES[words[2]])
                )
            elif words[0] == "property":
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]], None))
        except (IndexError, KeyError, ValueError) as exc:
            raise MeshError(
                f"its PLY header line {line.strip()!r} is malformed"
            ) from exc
    if encoding not in ("ascii", *_PLY_ENDIAN):
        raise MeshError(f"its PLY format {encoding!r} is not ascii or binary")
    return encoding, elements


def _ply_element_names(path: Path) -> set[str]:
    """Element names in a PLY header; an empty set if there is no readable header."""
    try:
        with open(path, "rb") as file:
            return {name for name, _, _ in _read_ply_header(file)[1]}
    except MeshError:
        return set()  # let trimesh report what is wrong with the file


def _read_ply_tristrips(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Positions (n, 3) and triangles (m, 3) of ``tristrips`` and ``face`` elements."""
    with open(path, "rb") as file:
        encoding, elements = _read_ply_header(file)
        body = file.read()
    try:
        if encoding == "ascii":
            data = _ply_ascii_elements(body, elements)
        else:
            data = _ply_binary_elements(body, elements, _PLY_ENDIAN[encoding])
        vertex = data["vertex"]
        positions = np.column_stack([vertex[axis] for axis in "xyz"]).astype(np.float64)
        strips = _list_property(data["tristrips"])
    except (KeyError, IndexError, ValueError) as exc:
        raise MeshError(
            f"its PLY data is truncated or malformed ({type(exc).__name__}: {exc})"
        ) from exc
    separated = [np.append(np.asarray(strip, dtype=np.int64), -1) for strip in strips]
    triangles = [_decode_tristrips(np.concatenate(separated) if separated else [])]
    if "face" in data:
        polygons = [np.asarray(p, dtype=np.int64) for p in _list_property(data["face"])]
        if polygons:
            sizes = np.array([len(p) for p in polygons], dtype=np.int64)
            if (sizes < 3).any():
                raise MeshError("a PLY face has fewer than 3 vertices")
            triangles.append(_fan_triangulate(np.concatenate(polygons), sizes))
    return positions, np.concatenate(triangles)


def _list_property(element: dict) -> list:
    """The one list property of an element (named vertex_indices or vertex_index)."""
    for name in ("vertex_indices", "vertex_index"):
        if name in element:
            return element[name]
    raise KeyError("no vertex_indices list property")


def _ply_binary_elements(body: bytes, elements, endian: str) -> dict[str, dict]:
    """Binary PLY elements as ``{element: {property: (count,) array or arrays}}``."""
    data, offset = {}, 0
    for name, count, properties in elements:
        if all(list_type is None for _, _, list_type in properties):
            dtype = np.dtype([(prop, endian + kind) for prop, kind, _ in properties])
            table = np.frombuffer(body, dtype=dtype, count=count, offset=offset)
            offset += count * dtype.itemsize
            data[name] = {prop: table[prop] for prop, _, _ in properties}
            continue
        # Rows holding lists vary in size, so walk them one by one (slow, but such
        # elements are small in practice: the tristrips element has a single row).
        columns = {prop: [] for prop, _, _ in properties}
        for _ in range(count):
            for prop, kind, list_type in properties:
                length = 1
                if list_type is not None:
                    length = int(np.frombuffer(body, endian + list_type, 1, offset)[0])
                    offset += np.dtype(list_type).itemsize
                values = np.frombuffer(body, endian + kind, length, offset)
                offset += length * np.dtype(kind).itemsize
                columns[prop].append(values if list_type is not None else values[0])
        data[name] = columns
    return data


def _ply_ascii_elements(body: bytes, elements) -> dict[str, dict]:
    """ASCII PLY elements as ``{element: {property: (count,) array or arrays}}``."""
    tokens = body.split()
    data, at = {}, 0
    for name, count, properties in elements:
        if all(list_type is None for _, _, list_type in properties):
            width = len(properties)
            table = np.array(tokens[at : at + count * width], dtype=np.float64)
            at += count * width
            table = table.reshape(count, width)
            data[name] = {
                prop: table[:, i] for i, (prop, _, _) in enumerate(properties)
            }
            continue
        columns = {prop: [] for prop, _, _ in properties}
        for _ in range(count):
            for prop, _, list_type in properties:
                if list_type is None:
                    columns[prop].append(float(tokens[at]))
                    at += 1
                else:
                    length = int(tokens[at])
                    columns[prop].append(
                        np.array(tokens[at + 1 : at + 1 + length], dtype=np.int64)
                    )
                    at += 1 + length
        data[name] = columns
    return data
