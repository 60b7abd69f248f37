"""Reading mesh files into a clean :class:`~lodserver.mesh.Mesh`, and writing them back.

Every reader below produces the same arrays, which :func:`clean_mesh` then
welds and cleans:

- ``positions``     : (n, 3) float64, vertex positions in the file's units.
- ``faces``         : (m, 3) int64, triangle vertex indices into ``positions``.

and, where the file has appearance data:

- ``corner_values`` : (m, 3, d) float64, each face corner's attribute vector,
  columns named by ``layout`` (glTF names: NORMAL, TEXCOORD_0, TEXCOORD_1,
  COLOR_0; UVs with v down as glTF has them, colours linear RGBA in 0..1).
- ``face_material`` : (m,) int32 into ``materials`` (glTF records plus image bytes), -1 for none.

Polygons are fan-triangulated. A glTF/GLB scene is flattened: every instance of
every triangle geometry is placed by its node transform (normals by its
inverse transpose). :func:`clean_mesh` welds positions only, so the topology is
the positions' and attributes ride along as wedges (distinct attribute vectors
per vertex and material); a file without any attributes or materials yields
``attributes=None``, exactly as when lodserver kept positions only.

Where the arrays come from:

- OBJ: a small reader in this module (``v``, ``vt``, ``vn``, ``f``, ``usemtl``,
  ``mtllib``). trimesh's OBJ loader splits vertices along UV and normal seams
  and drops unreferenced vertices, so its vertex counts would not be the file's
  and the :class:`LoadReport` would not say what the cleaning did. ``vt`` v is
  flipped to glTF's convention (``v_gltf = 1 - v_obj``); MTL ``Kd``, ``d``/``Tr``
  and ``map_Kd`` become glTF metallic-roughness materials.
- glTF/GLB: :mod:`lodserver.gltf`, which keeps the image bytes as stored.
- PLY with a ``tristrips`` element: a reader in this module (trimesh loads such
  a file as a point cloud and ignores the strips).
- Everything else: ``trimesh.load_scene(..., process=False)``, so that trimesh
  neither merges nor removes anything; a PLY's vertex normals, colours and UVs
  (and MeshLab's per-face ``texcoord``) are taken from its raw properties.

PLY and OBJ vertex colours are display (sRGB) values by convention; they are
converted to linear, which is what glTF's COLOR_0 holds.

Precision when saving: PLY, GLB and STL store float32 coordinates (trimesh's
PLY exporter always writes ``float``; glTF and binary STL are float32 by
definition), so positions come back to within float32 rounding (about 6e-8
relative), and vertices closer than that would be welded on reload. OBJ and OFF
are text written with 17 decimals, exact for any coordinate of magnitude 0.1 or
more and within 5e-18 otherwise.

What each output format keeps: GLB everything (attributes, materials, images);
OBJ positions plus ``vt``/``vn`` per wedge (no ``.mtl``: the bytes API writes one
file); PLY, OFF and STL positions and triangles only.
"""

from __future__ import annotations

import os
import re
import uuid
from dataclasses import asdict, dataclass, field
from io import BytesIO
from pathlib import Path

import numpy as np
import trimesh

from lodserver.gltf import encode_glb, face_normals, image_mime_type, read_gltf
from lodserver.mesh import ATTRIBUTE_WIDTHS, Attributes, Materials, Mesh, MeshError

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

# PLY vertex properties lodserver keeps, by the names writers use for them.
_PLY_NORMAL = ("nx", "ny", "nz")
_PLY_COLOURS = (("red", "green", "blue", "alpha"), ("r", "g", "b", "a"),
                ("diffuse_red", "diffuse_green", "diffuse_blue", "diffuse_alpha"))
_PLY_UVS = (("s", "t"), ("u", "v"), ("texture_u", "texture_v"), ("texture_s", "texture_t"))
# MTL map options and how many values follow each (-o, -s, -t take up to 3).
_MTL_MAP_OPTIONS = {"-blendu": 1, "-blendv": 1, "-bm": 1, "-boost": 1, "-cc": 1, "-clamp": 1,
                    "-imfchan": 1, "-mm": 2, "-texres": 1, "-o": 3, "-s": 3, "-t": 3}


@dataclass
class LoadReport:
    """What :func:`clean_mesh` changed, in counts, and what the reader did not keep.

    The vertex counts add up:
    ``source_vertices == welded_vertices + unreferenced_vertices + mesh.vertex_count``.
    The fields after ``duplicate_faces`` keep their zero or empty defaults for a
    mesh without attributes or materials.
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
    wedges: int = 0
    """Distinct (vertex, attribute vector, material) corners kept; 0 without attributes."""
    seam_vertices: int = 0
    """Vertices with more than one wedge: on a UV seam, a crease or a material border."""
    materials: int = 0
    """Material records carried along (used by a face or not)."""
    dropped_attributes: list[str] = field(default_factory=list)
    """Per-vertex data in the file that is not kept (TANGENT, JOINTS_0, a PLY 'quality', ...)."""
    missing_files: list[str] = field(default_factory=list)
    """Companion files the mesh names but that do not exist (an OBJ's mtllib), ignored."""

    def as_dict(self) -> dict:
        return asdict(self)


def load_mesh(path, *, file_type: str | None = None) -> tuple[Mesh, LoadReport]:
    """Read a mesh file and clean it with :func:`clean_mesh`.

    Parameters
    ----------
    path : str or os.PathLike
        The file to read. A ``.gltf`` file finds its buffers and images
        relative to it, an OBJ its ``.mtl`` files and an MTL its textures.
    file_type : str, optional
        One of :data:`SUPPORTED_INPUT`, overriding the file's extension (for
        uploads saved under temporary names).

    Returns
    -------
    mesh : Mesh
        Welded positions (n, 3) float64 and triangles (m, 3) int64, with wedge
        attributes and materials where the file has them.
    report : LoadReport
        What the cleaning removed, the wedge counts, and what was not kept.

    Raises
    ------
    MeshError
        If the file is missing, unreadable, of an unsupported type, cannot be
        parsed, has no faces, has NaN or infinite coordinates or attributes or
        out-of-range face indices, has only degenerate faces, or names a
        buffer or texture image that does not exist. The message names the file.
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
            arrays = _read_obj(path)
        elif kind in ("gltf", "glb"):
            arrays = read_gltf(path, kind)
        elif kind == "ply" and "tristrips" in _ply_element_names(path):
            arrays = _read_ply_tristrips(path)
        else:
            arrays = _read_with_trimesh(path, kind)
        dropped = arrays.pop("dropped_attributes", [])
        missing = arrays.pop("missing_files", [])
        mesh, report = clean_mesh(**arrays)
        report.dropped_attributes, report.missing_files = list(dropped), list(missing)
        return mesh, report
    except MeshError as exc:
        raise MeshError(f"cannot load {path}: {exc}") from exc
    except OSError as exc:
        raise MeshError(f"cannot load {path}: {exc.strerror or exc}") from exc


def clean_mesh(positions, faces, *, corner_values=None, layout=(), face_material=None,
               materials: Materials | None = None) -> tuple[Mesh, LoadReport]:
    """Weld coincident vertices, drop degenerate, duplicate and unused elements, build wedges.

    In order: vertices with identical float64 positions are merged (``0.0`` and
    ``-0.0`` count as identical; attributes play no part, so a UV seam stays
    one vertex); faces with a repeated vertex are dropped; a face on the same
    three vertices as an earlier face, in either winding, is dropped (its corner
    attributes and material with it); vertices no face uses are dropped and the
    indices compacted. Then every corner gets a wedge: the corners of one vertex
    with the same attribute vector (exact float equality) and material share
    one. Everything kept stays in the order of its first occurrence, so the
    result is deterministic.

    Parameters
    ----------
    positions : (n, 3) array_like of float
        Vertex positions.
    faces : (m, 3) array_like of int
        Triangle vertex indices into ``positions``.
    corner_values : (m, 3, d) array_like of float, optional
        Each face corner's attribute vector, columns as in ``layout``.
    layout : tuple of (name, width)
        Attribute names (see :data:`~lodserver.mesh.ATTRIBUTE_WIDTHS`) and
        widths adding up to ``d``.
    face_material : (m,) array_like of int, optional
        Material index of each face into ``materials``, -1 for none.
    materials : Materials, optional
        The material records ``face_material`` refers to.

    Returns
    -------
    mesh : Mesh
        The cleaned mesh, (n', 3) float64 positions and (m', 3) int64 faces;
        ``attributes`` is None when no ``corner_values`` are given.
    report : LoadReport
        How many vertices and faces each step removed, and the wedge counts.

    Raises
    ------
    MeshError
        On malformed arrays, NaN or infinite positions or attribute values,
        out-of-range indices, no faces, or only degenerate faces.
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
    layout = tuple((str(name), int(width)) for name, width in layout)
    if corner_values is not None:
        corner_values = _checked_corner_values(corner_values, layout, len(faces))
    if face_material is not None:
        face_material = _checked_face_material(face_material, materials, len(faces))

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
    # the kept faces as rows of the input, to carry their corners and materials along
    kept = np.flatnonzero(~degenerate)[first_face]

    used = np.zeros(len(welded), dtype=bool)
    used[faces] = True
    new_index = np.cumsum(used) - 1
    faces = new_index[faces]
    if face_material is not None:
        face_material = face_material[kept]
    attributes, seams = None, 0
    if corner_values is not None:
        attributes, wedge_vertex = _build_wedges(faces, corner_values[kept], layout, face_material)
        seams = int((np.bincount(wedge_vertex, minlength=int(used.sum())) > 1).sum())
    mesh = Mesh(welded[used], faces, attributes, face_material, materials)
    report = LoadReport(
        source_vertices=len(positions),
        welded_vertices=len(positions) - len(welded),
        unreferenced_vertices=len(welded) - mesh.vertex_count,
        degenerate_faces=int(degenerate.sum()),
        duplicate_faces=duplicates,
        wedges=attributes.wedge_count if attributes is not None else 0,
        seam_vertices=seams,
        materials=materials.count if materials is not None else 0,
    )
    return mesh, report


def _checked_corner_values(corner_values, layout: tuple, face_count: int) -> np.ndarray:
    """``corner_values`` as (m, 3, d) float64, or a MeshError naming what is wrong."""
    width = sum(w for _, w in layout)
    values = np.asarray(corner_values, dtype=np.float64)
    if not layout or values.shape != (face_count, 3, width):
        raise MeshError(f"corner attribute values must have shape ({face_count}, 3, {width}) "
                        f"for layout {layout}, got {values.shape}")
    for name, width in layout:
        if ATTRIBUTE_WIDTHS.get(name) != width:
            raise MeshError(f"unknown attribute {name!r} of width {width}")
    finite = np.isfinite(values)
    if not finite.all():
        start, broken = 0, []
        for name, width in layout:
            count = int((~finite[:, :, start:start + width].all(axis=2)).sum())
            if count:
                broken.append(f"{count} {name}")
            start += width
        raise MeshError(f"face corners have NaN or infinite attribute values "
                        f"({', '.join(broken)} corners)")
    return values


def _checked_face_material(face_material, materials: Materials | None,
                           face_count: int) -> np.ndarray:
    """``face_material`` as (m,) int32 in [-1, count), or a MeshError."""
    values = np.asarray(face_material)
    count = materials.count if materials is not None else 0
    integers = values.size == 0 or np.issubdtype(values.dtype, np.integer)
    if values.shape != (face_count,) or not integers:
        raise MeshError(f"face materials must be ({face_count},) integers, got {values.shape} "
                        f"{values.dtype}")
    if values.size and (values.min() < -1 or values.max() >= count):
        raise MeshError(f"face materials must lie in [-1, {count - 1}] for its {count} materials, "
                        f"found {int(values.min())}..{int(values.max())}")
    return values.astype(np.int32)


def _build_wedges(faces: np.ndarray, corner_values: np.ndarray, layout: tuple,
                  face_material: np.ndarray | None) -> tuple[Attributes, np.ndarray]:
    """Wedges of cleaned faces (m, 3): one per distinct (vertex, material, attribute vector).

    The material is part of the key so that a primitive per material (as glTF
    draws them) never has to split a wedge. Returns the attributes and the
    vertex (w,) of each wedge.
    """
    width = corner_values.shape[2]
    key = [faces.reshape(-1, 1).astype(np.float64)]  # indices < 2**53 are exact in float64
    if face_material is not None:
        key.append(np.repeat(face_material, 3).astype(np.float64)[:, None])
    values = corner_values.reshape(-1, width)
    first, inverse = _first_occurrences(np.hstack([*key, values]))
    return Attributes(layout, values[first], inverse.reshape(-1, 3)), faces.ravel()[first]


def save_mesh(mesh: Mesh, path, *, file_type: str | None = None) -> None:
    """Write a mesh to a file, atomically (see :func:`encode_mesh` for what each format keeps).

    The file is written under a temporary name in the same directory and then
    renamed over ``path``, so ``path`` never holds a partly written file.

    Parameters
    ----------
    mesh : Mesh
        Positions (n, 3) float64 and faces (m, 3) int64 (and attributes) to write.
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
    write_atomic(path, encode_mesh(mesh, kind))


def write_atomic(path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename.

    A reader of ``path`` sees the old file or the whole new one, never a part;
    on failure the temporary file is removed and ``path`` is untouched.
    """
    path = Path(path)
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

    GLB is packed by :func:`lodserver.gltf.encode_glb`, straight from the
    arrays: attributes and materials when the mesh has them, else one float32
    POSITION and one uint32 index accessor. OBJ gets ``vt``/``vn`` lines per
    wedge when the mesh has TEXCOORD_0 or NORMAL. PLY, OFF and STL (and OBJ
    without those) hold positions and triangles only.
    """
    if file_type not in SUPPORTED_OUTPUT:
        raise MeshError(f"cannot write {file_type!r}: supported are {', '.join(SUPPORTED_OUTPUT)}")
    if file_type == "glb":
        return encode_glb(mesh)
    attributes = mesh.attributes
    if file_type == "obj" and attributes is not None and (
            attributes.columns("TEXCOORD_0") or attributes.columns("NORMAL")):
        return _obj_bytes(mesh)
    data = trimesh.Trimesh(mesh.positions, mesh.faces, process=False).export(
        file_type=file_type, **_EXPORT_OPTIONS[file_type]
    )
    return data.encode("utf-8") if isinstance(data, str) else data


def _obj_bytes(mesh: Mesh) -> bytes:
    """OBJ text: ``v`` per vertex, ``vt``/``vn`` per wedge, ``f v/vt/vn`` corners.

    Every wedge gets its own ``vt`` and ``vn`` line (no deduplication), so a
    corner's texture and normal index are both its wedge. v is flipped back to
    OBJ's v-up convention. Numbers use 17 significant digits: exact float64.
    """
    attributes = mesh.attributes
    uv_columns, normal_columns = attributes.columns("TEXCOORD_0"), attributes.columns("NORMAL")
    parts = [_format_rows("v %.17g %.17g %.17g\n", mesh.positions)]
    if uv_columns:
        uv = attributes.values[:, uv_columns] * [1.0, -1.0] + [0.0, 1.0]
        parts.append(_format_rows("vt %.17g %.17g\n", uv))
    if normal_columns:
        parts.append(_format_rows("vn %.17g %.17g %.17g\n", attributes.values[:, normal_columns]))
    vertex, wedge = mesh.faces + 1, attributes.corners + 1  # OBJ counts from 1
    if uv_columns and normal_columns:
        corner, table = "%d/%d/%d", np.stack([vertex, wedge, wedge], axis=2)
    elif uv_columns:
        corner, table = "%d/%d", np.stack([vertex, wedge], axis=2)
    else:
        corner, table = "%d//%d", np.stack([vertex, wedge], axis=2)
    parts.append(_format_rows("f " + " ".join([corner] * 3) + "\n", table.reshape(len(table), -1)))
    return "".join(parts).encode("utf-8")


def _format_rows(line: str, table: np.ndarray) -> str:
    """``line`` (a %-format of one row) applied to every row of ``table`` (k, c).

    One format call over the whole table: a Python loop per row would be ten
    times slower on a million-face mesh.
    """
    return (line * len(table)) % tuple(table.ravel().tolist())


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


def _read_with_trimesh(path: Path, kind: str) -> dict:
    """Positions (n, 3) and triangles (m, 3) of every geometry instance in the file,
    plus a PLY's vertex normals, colours and UVs as corner values."""
    try:
        scene = trimesh.load_scene(str(path), file_type=kind, process=False)
    except Exception as exc:
        # trimesh raises anything from ValueError to IndexError (or an ImportError
        # for a missing optional dependency) on a file it cannot read.
        raise MeshError(
            f"it could not be parsed as {kind.upper()} ({type(exc).__name__}: {exc})"
        ) from exc
    all_positions, all_faces, offset, placed = [], [], 0, []
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
        placed.append(geometry)
    if not all_faces:
        held = sorted({type(g).__name__ for g in scene.geometry.values()})
        found = f"only {', '.join(held)} geometry" if held else "nothing"
        raise MeshError(f"it has no faces (trimesh found {found})")
    arrays = {"positions": np.concatenate(all_positions), "faces": np.concatenate(all_faces)}
    raw = placed[0].metadata.get("_ply_raw") if kind == "ply" and len(placed) == 1 else None
    if raw and "vertex" in raw:
        vertex = _ply_columns(raw["vertex"]["data"])
        face = _ply_columns(raw["face"]["data"]) if "face" in raw else {}
        faces = arrays["faces"]
        if len(placed[0].vertices) != len(next(iter(vertex.values()))):
            # trimesh splits vertices along per-face UV seams; the file's own
            # triangles then say which vertex each corner is
            faces = _ply_triangle_rows(face, len(faces))
        arrays.update(_ply_attributes(vertex, faces, face))
    return arrays


def _ply_columns(data) -> dict:
    """A PLY element's properties as ``{name: (rows,) or (rows, k) array}``.

    trimesh holds binary elements as a structured array (a list property as a
    (count, values) record) and ASCII ones as a dict of (rows, 1) arrays; this
    module's reader as a dict of arrays or lists of arrays.
    """
    if isinstance(data, np.ndarray) and data.dtype.names:
        columns = {}
        for name in data.dtype.names:
            column = data[name]
            columns[name] = column[column.dtype.names[-1]] if column.dtype.names else column
        return columns
    columns = {}
    for name, column in data.items():
        try:
            column = np.asarray(column)
        except ValueError:
            continue  # lists of differing lengths: polygons, not a fixed table
        columns[name] = column[:, 0] if column.ndim == 2 and column.shape[1] == 1 else column
    return columns


def _ply_triangle_rows(face: dict, face_count: int) -> np.ndarray:
    """The (m, 3) vertex indices of a PLY face element of triangles."""
    for name in ("vertex_indices", "vertex_index"):
        rows = face.get(name)
        if rows is not None and rows.shape == (face_count, 3):
            return rows.astype(np.int64)
    raise MeshError("its PLY faces do not match the triangles read (polygons with per-face UVs?)")


def _ply_attributes(vertex: dict, faces: np.ndarray, face: dict | None = None) -> dict:
    """Corner values (m, 3, d) from PLY vertex normals, UVs and colours (or per-face UVs).

    Returns the ``corner_values``/``layout`` keywords of :func:`clean_mesh` (none
    when the file has no such property) and the properties not kept.
    """
    face = face or {}
    layout, columns, kept = [], [], {"x", "y", "z"}
    if all(name in vertex for name in _PLY_NORMAL):
        normals = np.column_stack([vertex[name] for name in _PLY_NORMAL]).astype(np.float64)
        layout.append(("NORMAL", 3))
        columns.append(normals[faces])
        kept.update(_PLY_NORMAL)
    uv = None
    for names in _PLY_UVS:
        if all(name in vertex for name in names):
            uv = np.column_stack([vertex[name] for name in names]).astype(np.float64)[faces]
            kept.update(names)
            break
    texcoord = face.get("texcoord")
    if uv is None and texcoord is not None and texcoord.shape == (len(faces), 6):
        uv = texcoord.astype(np.float64).reshape(-1, 3, 2)  # MeshLab: one (u, v) per corner
    if uv is not None:
        uv[..., 1] = 1.0 - uv[..., 1]  # PLY's v points up, glTF's down
        layout.append(("TEXCOORD_0", 2))
        columns.append(uv)
    for names in _PLY_COLOURS:
        if all(name in vertex for name in names[:3]):
            rgb = _srgb_to_linear(np.column_stack([_unit_colour(vertex[n]) for n in names[:3]]))
            alpha = _unit_colour(vertex[names[3]]) if names[3] in vertex else np.ones(len(rgb))
            layout.append(("COLOR_0", 4))
            columns.append(np.column_stack([rgb, alpha])[faces])
            kept.update(names)
            break
    dropped = sorted(set(vertex) - kept)
    dropped += [f"face {name}" for name in sorted(face)
                if name not in ("vertex_indices", "vertex_index")
                and not (name == "texcoord" and "TEXCOORD_0" in dict(layout))]
    if not layout:
        return {"dropped_attributes": dropped}
    return {"corner_values": np.concatenate(columns, axis=2), "layout": tuple(layout),
            "dropped_attributes": dropped}


def _unit_colour(values: np.ndarray) -> np.ndarray:
    """Colour channel values as floats in [0, 1]: integers by their type's range.

    A float channel above 1 (ASCII PLY, where the type is lost) is taken as 0..255.
    """
    values = np.asarray(values)
    if values.dtype.kind in "ui":
        return values / float(np.iinfo(values.dtype).max)
    values = values.astype(np.float64)
    if values.size and values.max() > 1.0:
        values = values / 255.0
    return np.clip(values, 0.0, 1.0)


def _srgb_to_linear(values: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] to linear light (the IEC 61966-2-1 curve).

    PLY and OBJ colours are what a screen showed; glTF's COLOR_0 and
    baseColorFactor are linear, and a renderer encodes them back for display.
    """
    values = np.asarray(values, dtype=np.float64)
    return np.where(values <= 0.04045, values / 12.92, ((values + 0.055) / 1.055) ** 2.4)


def _read_obj(path: Path) -> dict:
    """Positions (n, 3) of the ``v`` lines and triangles (m, 3) of the ``f`` lines,
    with per-corner ``vt``/``vn``, vertex colours and ``usemtl`` materials where present."""
    text = re.sub(r"\\\r?\n", " ", path.read_bytes().decode("utf-8", errors="replace"))
    rows, corners, sizes, defined_before = [], [], [], []
    uvs, normals, colours, material_runs, libraries = [], [], {}, [], []
    # (face, vt count, vn count) for faces with v/vt/vn references only, so that
    # files without them pay nothing for resolving relative vt/vn indices
    slashed = []
    for number, line in enumerate(text.splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        key = parts[0]
        if key == "v":
            if len(parts) < 4:
                raise MeshError(
                    f"line {number} is a vertex with fewer than 3 coordinates"
                )
            rows.append(parts[1:4])
            if len(parts) == 7:  # "v x y z r g b", the usual vertex colour extension
                colours[len(rows) - 1] = parts[4:7]
        elif key == "f":
            if len(parts) < 4:
                raise MeshError(f"line {number} is a face with fewer than 3 vertices")
            if "/" in line:
                slashed.append((len(sizes), len(uvs), len(normals)))
            corners.extend(parts[1:])
            sizes.append(len(parts) - 1)
            defined_before.append(len(rows))
        elif key == "vt":
            if len(parts) < 2:
                raise MeshError(f"line {number} is a texture coordinate without values")
            uvs.append(parts[1:3] if len(parts) > 2 else [parts[1], "0"])
        elif key == "vn":
            if len(parts) < 4:
                raise MeshError(f"line {number} is a normal with fewer than 3 coordinates")
            normals.append(parts[1:4])
        elif key == "usemtl":
            name = line.split(None, 1)[1].strip() if len(parts) > 1 else ""
            material_runs.append((len(sizes), name))
        elif key == "mtllib" and len(parts) > 1:
            libraries.append(line.split(None, 1)[1].strip())
    if not sizes:
        raise MeshError(f"it has no faces ({len(rows)} vertices, no 'f' lines)")
    try:
        positions = np.array(rows, dtype=np.float64)
    except ValueError as exc:
        raise MeshError(f"a vertex coordinate is not a number ({exc})") from exc
    sizes = np.array(sizes, dtype=np.int64)
    # OBJ indices are 1-based; negative ones count back from the last element so far.
    vertex_base = np.repeat(np.array(defined_before, dtype=np.int64), sizes)
    if not slashed:
        indices = _obj_indices(corners, vertex_base, len(positions), "vertices")
        arrays = {"positions": positions, "faces": _fan_triangulate(indices, sizes)}
        uv_index = normal_index = None
    else:
        fields = [corner.split("/") for corner in corners]
        indices = _obj_indices([f[0] for f in fields], vertex_base, len(positions), "vertices")
        face, uv_count, normal_count = np.array(slashed, dtype=np.int64).T
        uv_base, normal_base = np.zeros((2, len(sizes)), dtype=np.int64)
        uv_base[face], normal_base[face] = uv_count, normal_count
        uv_index = _obj_indices([f[1] if len(f) > 1 and f[1] else "0" for f in fields],
                                np.repeat(uv_base, sizes), len(uvs), "texture coordinates",
                                optional=True)
        normal_index = _obj_indices([f[2] if len(f) > 2 and f[2] else "0" for f in fields],
                                    np.repeat(normal_base, sizes), len(normals), "normals",
                                    optional=True)
        triangles = _fan_triangulate(np.arange(len(indices)), sizes)  # corner numbers
        arrays = {"positions": positions, "faces": indices[triangles]}
        uv_index, normal_index = uv_index[triangles], normal_index[triangles]
    arrays.update(_obj_corner_values(arrays["positions"], arrays["faces"], uv_index, uvs,
                                     normal_index, normals, colours))
    if material_runs or libraries:
        arrays.update(_obj_materials(material_runs, libraries, path.parent, sizes))
    return arrays


def _obj_indices(tokens: list, base: np.ndarray, count: int, what: str,
                 optional: bool = False) -> np.ndarray:
    """0-based indices (k,) of OBJ corner references; -1 where an optional one is absent (0)."""
    try:
        raw = np.array(tokens).astype(np.int64)
    except ValueError as exc:
        raise MeshError(f"a face {what} index is not an integer ({exc})") from exc
    indices = np.where(raw > 0, raw - 1, base + raw)
    absent = (raw == 0) if optional else np.zeros(len(raw), dtype=bool)
    bad = ~absent & ((raw == 0) | (indices < 0) | (indices >= count))
    if bad.any():
        raise MeshError(
            f"{int(bad.sum())} face corners refer to {what} that do not exist (the "
            f"file has {count} {what}; first bad index {int(raw[bad][0])})"
        )
    return np.where(absent, -1, indices)


def _obj_corner_values(positions, faces, uv_index, uvs, normal_index, normals, colours) -> dict:
    """``corner_values``/``layout`` from OBJ ``vn``, ``vt`` and ``v`` colours; {} if none.

    A corner without a ``vn`` gets its face's flat normal and one without a
    ``vt`` gets (0, 0), so that faces which have them keep them.
    """
    layout, columns, dropped = [], [], []
    if normal_index is not None and (normal_index >= 0).any():
        try:
            table = np.array(normals, dtype=np.float64)
        except ValueError as exc:
            raise MeshError(f"a normal coordinate is not a number ({exc})") from exc
        corner = table[normal_index]
        missing = normal_index < 0
        if missing.any():
            flat = np.broadcast_to(face_normals(positions, faces)[:, None], corner.shape)
            corner[missing] = flat[missing]
        layout.append(("NORMAL", 3))
        columns.append(corner)
    if uv_index is not None and (uv_index >= 0).any():
        try:
            table = np.array(uvs, dtype=np.float64)
        except ValueError as exc:
            raise MeshError(f"a texture coordinate is not a number ({exc})") from exc
        table[:, 1] = 1.0 - table[:, 1]  # OBJ's v points up, glTF's down
        corner = table[uv_index]
        corner[uv_index < 0] = 0.0
        layout.append(("TEXCOORD_0", 2))
        columns.append(corner)
    if colours and len(colours) == len(positions):
        try:
            rgb = np.array([colours[i] for i in range(len(positions))], dtype=np.float64)
        except ValueError as exc:
            raise MeshError(f"a vertex colour is not a number ({exc})") from exc
        if rgb.size and rgb.max() > 1.0:
            rgb = rgb / 255.0  # some writers use 0..255
        rgba = np.column_stack([_srgb_to_linear(np.clip(rgb, 0.0, 1.0)), np.ones(len(rgb))])
        layout.append(("COLOR_0", 4))
        columns.append(rgba[faces])
    elif colours:
        dropped.append("COLOR_0")  # colours on some vertices only: no colour for the rest
    arrays = {"dropped_attributes": dropped}
    if layout:
        arrays.update(corner_values=np.concatenate(columns, axis=2), layout=tuple(layout))
    return arrays


def _obj_materials(material_runs: list, libraries: list, folder: Path, sizes: np.ndarray) -> dict:
    """Materials of the ``mtllib`` files and the face material of each triangle.

    Every material of every library is kept, in file order, then any ``usemtl``
    name no library defines (as a plain material of that name). Faces before the
    first ``usemtl`` (or after ``usemtl`` with no name) have none (-1). A missing
    library is reported, not an error: the mesh is still usable. A missing
    texture is an error: its material would silently lose its look.
    """
    records, textures, images, image_index, missing = [], [], [], {}, []
    for library in libraries:
        for file in _mtl_files(library, folder, missing):
            for name, properties in _read_mtl(file):
                record = _mtl_record(name, properties)
                if "map_Kd" in properties:
                    key, data, label = _mtl_texture(properties["map_Kd"], file.parent, name)
                    if key not in image_index:
                        data, mime = _gltf_image(data, label)
                        image_index[key] = len(images)
                        images.append((data, {"mimeType": mime, "name": label}))
                        textures.append({"source": image_index[key]})
                    # one texture per image, so the two share an index
                    record["pbrMetallicRoughness"]["baseColorTexture"] = {"index": image_index[key]}
                records.append(record)
    index = {record["name"]: i for i, record in reversed(list(enumerate(records)))}
    for _, name in material_runs:
        if name and name not in index:
            index[name] = len(records)
            records.append(_mtl_record(name, {}))
    result = {"missing_files": missing}
    if not records:
        return result
    # a polygon takes the material of the last usemtl before it; run 0 is "before any"
    run_material = np.array([-1] + [index[name] if name else -1 for _, name in material_runs],
                            dtype=np.int32)
    starts = np.array([start for start, _ in material_runs], dtype=np.int64)
    polygon_material = run_material[np.searchsorted(starts, np.arange(len(sizes)), side="right")]
    gltf = {"materials": records, "textures": textures, "samplers": [],
            "images": [record for _, record in images]}
    result.update(materials=Materials(gltf, tuple(data for data, _ in images)),
                  face_material=np.repeat(polygon_material, sizes - 2).astype(np.int32))
    return result


def _mtl_files(library: str, folder: Path, missing: list) -> list[Path]:
    """The files an ``mtllib`` line names (several may share a line), noting missing ones."""
    whole = folder / library.replace("\\", "/")
    if whole.is_file():
        return [whole]
    found = []
    for name in library.split():
        file = folder / name.replace("\\", "/")
        if file.is_file():
            found.append(file)
        else:
            missing.append(name)
    return found


def _read_mtl(path: Path) -> list[tuple[str, dict]]:
    """``(name, {"Kd": [r, g, b], "d": a, "Tr": t, "map_Kd": [args]})`` per ``newmtl``."""
    materials = []
    for line in path.read_bytes().decode("utf-8", errors="replace").splitlines():
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "newmtl":
            materials.append((line.split(None, 1)[1].strip() if len(parts) > 1 else "", {}))
        elif materials and parts[0] in ("Kd", "d", "Tr") and len(parts) > 1:
            try:
                values = [float(value) for value in parts[1:4]]
            except ValueError:
                continue  # e.g. "Kd spectral file.rfl": not a colour we can use
            materials[-1][1][parts[0]] = values if parts[0] == "Kd" else values[0]
        elif materials and parts[0] == "map_Kd" and len(parts) > 1:
            materials[-1][1]["map_Kd"] = parts[1:]
    return materials


def _mtl_record(name: str, properties: dict) -> dict:
    """A glTF metallic-roughness material for MTL ``Kd`` and ``d``/``Tr`` (matte, not metal)."""
    kd = properties.get("Kd", [1.0, 1.0, 1.0])
    kd = (kd * 3)[:3] if len(kd) < 3 else kd  # "Kd 0.5" means grey
    alpha = properties.get("d", 1.0 - properties.get("Tr", 0.0))
    colour = [*_srgb_to_linear(np.clip(kd, 0.0, 1.0)).tolist(), float(np.clip(alpha, 0.0, 1.0))]
    record = {"name": name, "pbrMetallicRoughness": {
        "baseColorFactor": colour, "metallicFactor": 0.0, "roughnessFactor": 1.0}}
    if colour[3] < 1.0:
        record["alphaMode"] = "BLEND"
    return record


def _mtl_texture(arguments: list, folder: Path, material: str) -> tuple[Path, bytes, str]:
    """The resolved path, bytes and file name of a ``map_Kd`` (options skipped)."""
    at = 0
    while at < len(arguments) - 1 and arguments[at] in _MTL_MAP_OPTIONS:
        taken = 1
        # -o/-s/-t take one to three numbers; the others a fixed count
        while taken <= _MTL_MAP_OPTIONS[arguments[at]] and at + taken < len(arguments) - 1:
            if _MTL_MAP_OPTIONS[arguments[at]] == 3:
                try:
                    float(arguments[at + taken])
                except ValueError:
                    break
            taken += 1
        at += taken
    name = " ".join(arguments[at:]).replace("\\", "/")
    file = (folder / name).resolve()
    if not file.is_file():
        raise MeshError(f"its material {material!r} uses the texture {name!r}, which is missing "
                        f"(looked for {file})")
    return file, file.read_bytes(), Path(name).name


def _gltf_image(data: bytes, name: str) -> tuple[bytes, str]:
    """Image bytes glTF can carry (PNG or JPEG, byte for byte) and their mimeType.

    Other formats (TGA, BMP, ...) are re-encoded as PNG with Pillow, if installed.
    """
    mime = image_mime_type(data)
    if mime in ("image/png", "image/jpeg"):
        return data, mime
    try:
        from PIL import Image
    except ImportError:
        raise MeshError(f"its texture {name!r} is neither PNG nor JPEG, the formats glTF "
                        "carries; convert it, or install Pillow to have it converted") from None
    try:
        converted = BytesIO()
        Image.open(BytesIO(data)).save(converted, format="PNG")
    except Exception as exc:  # Pillow raises many kinds on an unreadable image
        raise MeshError(f"its texture {name!r} is neither PNG nor JPEG and could not be "
                        f"converted ({type(exc).__name__}: {exc})") from exc
    return converted.getvalue(), "image/png"


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


def _read_ply_tristrips(path: Path) -> dict:
    """Positions (n, 3) and triangles (m, 3) of ``tristrips`` and ``face`` elements,
    with vertex normals, colours and UVs as corner values."""
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
    faces = np.concatenate(triangles)
    return {"positions": positions, "faces": faces, **_ply_attributes(_ply_columns(vertex), faces)}


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
