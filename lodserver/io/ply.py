"""PLY: the header, its declared counts, triangle strips, and vertex attributes.

trimesh reads most PLY files (:mod:`.load`); it loads a file with a
``tristrips`` element as a point cloud and ignores the strips, so such files
are read here. The header is always parsed here first, so that its element
counts are checked against the limits and the body's size before trimesh or
this reader allocates anything. A PLY's vertex normals, colours and UVs (and
MeshLab's per-face ``texcoord``) become corner values; colours are display
(sRGB) values by convention and are converted to linear.
"""

from __future__ import annotations

import struct
import warnings
from array import array
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..mesh import MeshError
from .clean import fan_triangulate, srgb_to_linear
from .limits import LoadLimits


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


def checked_ply_header(path: Path, size: int, limits: LoadLimits) -> list:
    """The elements of a PLY header (as :func:`_read_ply_header`), their counts checked.

    Before trimesh or this module's reader allocates anything: every element's
    row count against the limits (vertices, faces and strips as such, any
    other element as vertices), and all rows against the bytes the body has.
    A binary row needs at least its scalars and its list lengths; an ASCII row
    at least two bytes (a digit and a separator) per property.
    """
    try:
        with open(path, "rb") as file:
            encoding, elements = _read_ply_header(file)
            body = size - file.tell()
    except MeshError as exc:
        raise MeshError(f"it could not be parsed as PLY ({exc})") from None
    least = 0
    for name, count, properties in elements:
        if name in ("face", "tristrips"):
            limits.check("max_triangles", count, f"PLY {name} rows")
        else:
            limits.check("max_vertices", count, f"PLY {name} rows")
        if encoding == "ascii":
            row = 2 * len(properties)
        else:
            row = sum(np.dtype(list_type or kind).itemsize for _, kind, list_type in properties)
        least += count * row
    if encoding == "ascii":
        least -= 1  # the last token needs no separator
    if least > body:
        raise MeshError(f"its PLY header declares rows that need at least {least} bytes, "
                        f"but the body has {body}")
    return elements


def read_ply_tristrips(path: Path) -> dict:
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
    except (KeyError, IndexError, ValueError, TypeError) as exc:
        raise MeshError(
            f"its PLY data is truncated or malformed ({type(exc).__name__}: {exc})"
        ) from exc
    # the strips end to end, each closed by -1: item j of row i moves up by i
    sequence = np.full(len(strips.values) + len(strips.lengths), -1, dtype=np.int64)
    rows = np.repeat(np.arange(len(strips.lengths)), strips.lengths)
    sequence[np.arange(len(strips.values)) + rows] = strips.values
    triangles = [_decode_tristrips(sequence)]
    if "face" in data:
        polygons = _list_property(data["face"])
        if len(polygons.lengths):
            if (polygons.lengths < 3).any():
                raise MeshError("a PLY face has fewer than 3 vertices")
            triangles.append(fan_triangulate(polygons.values, polygons.lengths))
    faces = np.concatenate(triangles)
    return {"positions": positions, "faces": faces, **ply_attributes(ply_columns(vertex), faces)}


def read_ply_binary_triangles(path: Path) -> dict | None:
    """Positions (n, 3) and triangles (m, 3) of a binary PLY whose rows all have one
    size, with vertex normals, colours and UVs as corner values; None for any other
    PLY (ASCII, polygons, lists of varying length), which trimesh reads.

    The common scan file (a vertex table, then faces of ``3 i j k``) is one
    fixed record per row, so numpy reads each element as one structured array
    instead of trimesh parsing it; the arrays are the ones trimesh's path
    hands :func:`~.clean.clean_mesh` (the file's triangles, no seam splits).
    The header's counts were checked against the body by
    :func:`checked_ply_header` before this is called.
    """
    with open(path, "rb") as file:
        encoding, elements = _read_ply_header(file)
        if encoding not in _PLY_ENDIAN:
            return None
        body = file.read()
    endian = _PLY_ENDIAN[encoding]
    data, offset = {}, 0
    for name, count, properties in elements:
        if count == 0:
            data[name] = {}
            continue
        dtype = _fixed_row_dtype(body, offset, properties, endian)
        if dtype is None or offset + count * dtype.itemsize > len(body):
            return None
        table = np.frombuffer(body, dtype=dtype, count=count, offset=offset)
        for prop, _, list_type in properties:
            if list_type is not None and (table[_LENGTH + prop] != table[prop].shape[1]).any():
                return None     # a row whose list is longer or shorter than the first's
        offset += count * dtype.itemsize
        data[name] = {prop: table[prop] for prop, _, _ in properties}
    vertex, face = data.get("vertex", {}), data.get("face", {})
    corners = next((face[n] for n in ("vertex_indices", "vertex_index") if n in face), None)
    if corners is None or corners.ndim != 2 or corners.shape[1] != 3 or not all(
            axis in vertex and vertex[axis].ndim == 1 for axis in "xyz"):
        return None
    positions = np.column_stack([vertex[axis] for axis in "xyz"]).astype(np.float64, copy=False)
    # the file's index type as it is: clean_mesh makes the one int64 copy
    faces = np.ascontiguousarray(corners)
    return {"positions": positions, "faces": faces, **ply_attributes(vertex, faces, face)}


# the field name under which a list property's per-row length sits in a fixed row
# (a header's property names are single words, so none has a space)
_LENGTH = "length of "


def _fixed_row_dtype(body: bytes, offset: int, properties, endian: str) -> np.dtype | None:
    """The structured dtype of a binary row whose lists are as long as in the row at
    ``offset`` (each list's length a field of its own), or None when a list's
    length or item is not an integer or a number, or the row runs past ``body``."""
    fields, at = [], offset
    for prop, kind, list_type in properties:
        item = np.dtype(endian + kind)
        if list_type is None:
            fields.append((prop, item))
            at += item.itemsize
            continue
        length = np.dtype(endian + list_type)
        if length.kind not in "iu" or at + length.itemsize > len(body):
            return None
        n = int(np.frombuffer(body, dtype=length, count=1, offset=at)[0])
        if n < 1:
            return None
        fields += [(_LENGTH + prop, length), (prop, item, (n,))]
        at += length.itemsize + n * item.itemsize
    try:
        return np.dtype(fields)
    except ValueError:      # a property named twice: trimesh's reader decides
        return None


@dataclass(frozen=True)
class _PlyLists:
    """A PLY list property of every row of an element: ``values`` (k,) int64, the
    lists end to end, and ``lengths`` (rows,) int64 (no array per row: a file of
    millions of empty rows must not cost an object each)."""

    values: np.ndarray
    lengths: np.ndarray


def _list_property(element: dict) -> _PlyLists:
    """The one list property of an element (named vertex_indices or vertex_index)."""
    for name in ("vertex_indices", "vertex_index"):
        if isinstance(element.get(name), _PlyLists):
            return element[name]
    raise KeyError("no vertex_indices list property")


def _item_index(starts: np.ndarray, lengths: np.ndarray, step: int) -> np.ndarray:
    """Where every item of every row is: ``start + i * step`` for ``i < length``, the rows
    end to end; ``step`` is the item size in bytes (binary) or 1 (ASCII tokens)."""
    before = np.cumsum(lengths) - lengths
    return np.repeat(starts - before * step, lengths) + np.arange(int(lengths.sum())) * step


def _row_starts(count: int, layout, at: int, read_list):
    """Where every value of ``count`` rows mixing scalar and list properties starts.

    ``layout`` is (property, item size, list header or None) a property, in row
    order; ``read_list(header, at)`` checks the length of the list at ``at`` and
    gives it and where its items start. Sizes and places count bytes (binary) or
    tokens (ASCII). Returns the starts and the list lengths a property, as typed
    arrays (8 bytes a value: a list would cost an int object each), and where
    the rows end."""
    starts = {prop: array("q") for prop, _, _ in layout}
    lengths = {prop: array("q") for prop, _, header in layout if header is not None}
    for _ in range(count):
        for prop, size, header in layout:
            if header is None:
                starts[prop].append(at)
                at += size
                continue
            n, at = read_list(header, at)
            starts[prop].append(at)
            lengths[prop].append(n)
            at += n * size
    return starts, lengths, at


def _ply_binary_elements(body: bytes, elements, endian: str) -> dict[str, dict]:
    """Binary PLY elements as ``{element: {property: (count,) array or _PlyLists}}``."""
    data, offset = {}, 0
    raw = np.frombuffer(body, dtype=np.uint8)

    def read_list(length, at):
        (n,) = length.unpack_from(body, at)  # struct.error past the end
        if n < 0:
            raise ValueError(f"a PLY list of length {n}")
        return n, at + length.size

    for name, count, properties in elements:
        if all(list_type is None for _, _, list_type in properties):
            dtype = np.dtype([(prop, endian + kind) for prop, kind, _ in properties])
            table = np.frombuffer(body, dtype=dtype, count=count, offset=offset)
            offset += count * dtype.itemsize
            data[name] = {prop: table[prop] for prop, _, _ in properties}
            continue
        # Rows holding lists vary in size: one pass over the rows finds where each
        # value starts (Python ints only), then numpy gathers every value at once.
        layout = []
        for prop, kind, list_type in properties:
            length = None
            if list_type is not None:
                if np.dtype(list_type).kind not in "iu":
                    raise ValueError(f"PLY list length type {list_type} is not an integer")
                length = struct.Struct(endian + np.dtype(list_type).char)
            layout.append((prop, np.dtype(endian + kind), length))
        starts, lengths, offset = _row_starts(
            count, [(prop, kind.itemsize, length) for prop, kind, length in layout], offset,
            read_list)
        if offset > len(body):
            raise ValueError(f"the {name} rows need {offset} bytes, the body has {len(body)}")
        columns = {}
        for prop, kind, length in layout:
            begin = np.array(starts[prop], dtype=np.int64)
            sizes = (np.array(lengths[prop], dtype=np.int64) if length is not None
                     else np.ones(count, dtype=np.int64))
            at = _item_index(begin, sizes, kind.itemsize)
            values = raw[at[:, None] + np.arange(kind.itemsize)].copy().view(kind).ravel()
            columns[prop] = (_PlyLists(values.astype(np.int64), sizes) if length is not None
                             else values)
        data[name] = columns
    return data


def _ply_ascii_elements(body: bytes, elements) -> dict[str, dict]:
    """ASCII PLY elements as ``{element: {property: (count,) array or _PlyLists}}``."""
    with warnings.catch_warnings():
        # numpy warns, and stops, at the first token that is not a number
        warnings.simplefilter("ignore", DeprecationWarning)
        tokens = np.fromstring(body, dtype=np.float64, sep=" ")
    data, at = {}, 0

    def read_list(_, at):
        n = tokens[at]  # IndexError past the end
        if n < 0 or n != int(n):
            raise ValueError(f"a PLY list of length {n}")
        return int(n), at + 1

    for name, count, properties in elements:
        if all(list_type is None for _, _, list_type in properties):
            width = len(properties)
            if at + count * width > len(tokens):
                raise ValueError(f"the {name} rows need {count * width} numbers, "
                                 f"{len(tokens) - at} are left")
            table = tokens[at : at + count * width].reshape(count, width)
            at += count * width
            data[name] = {prop: table[:, i] for i, (prop, _, _) in enumerate(properties)}
            continue
        starts, lengths, at = _row_starts(
            count, [(prop, 1, list_type) for prop, _, list_type in properties], at, read_list)
        if at > len(tokens):
            raise ValueError(f"the {name} rows need more numbers than the body has")
        columns = {}
        for prop, _, list_type in properties:
            begin = np.array(starts[prop], dtype=np.int64)
            if list_type is None:
                columns[prop] = tokens[begin]
                continue
            sizes = np.array(lengths[prop], dtype=np.int64)
            values = tokens[_item_index(begin, sizes, 1)]
            if (values != np.round(values)).any():
                raise ValueError(f"the {name} lists hold numbers that are not integers")
            columns[prop] = _PlyLists(values.astype(np.int64), sizes)
        data[name] = columns
    return data


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


def ply_columns(data) -> dict:
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
        if isinstance(column, _PlyLists):
            continue  # a list property: polygons, not a fixed table
        try:
            column = np.asarray(column)
        except ValueError:
            continue  # lists of differing lengths: polygons, not a fixed table
        columns[name] = column[:, 0] if column.ndim == 2 and column.shape[1] == 1 else column
    return columns


def ply_triangle_rows(face: dict, face_count: int) -> np.ndarray:
    """The (m, 3) vertex indices of a PLY face element of triangles."""
    for name in ("vertex_indices", "vertex_index"):
        rows = face.get(name)
        if rows is not None and rows.shape == (face_count, 3):
            return rows.astype(np.int64)
    raise MeshError("its PLY faces do not match the triangles read (polygons with per-face UVs?)")


def ply_attributes(vertex: dict, faces: np.ndarray, face: dict | None = None) -> dict:
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
            rgb = srgb_to_linear(np.column_stack([_unit_colour(vertex[n]) for n in names[:3]]))
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
