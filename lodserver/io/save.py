"""Writing a mesh: the bytes of each output format, and files written atomically.

Precision when saving: PLY, GLB and STL store float32 coordinates (trimesh's
PLY exporter always writes ``float``; glTF and binary STL are float32 by
definition), so positions come back to within float32 rounding (about 6e-8
relative), and vertices closer than that would be welded on reload. OBJ and OFF
are text written with 17 decimals, exact for any coordinate of magnitude 0.1 or
more and within 5e-18 otherwise.

What each output format keeps: GLB everything (every attribute column of the
layout, materials, images; :func:`lodserver.io.glb.render_attributes`); OBJ
positions plus ``vt``/``vn`` per wedge from TEXCOORD_0 and NORMAL (no ``.mtl``:
the bytes API writes one file); PLY, OFF and STL positions and triangles only.
The columns a format cannot hold (TEXCOORD_1.., COLOR_n, TANGENT, joints and
weights, morph deltas, custom attributes) are left out without a word: the
format says what it keeps, and GLB is the one that keeps everything.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from ..mesh import Mesh, MeshError
from .files import write_atomic
from .glb import encode_glb
from .load import file_kind


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
    kind = file_kind(path, file_type, SUPPORTED_OUTPUT, "save")
    write_atomic(path, encode_mesh(mesh, kind))


def encode_mesh(mesh: Mesh, file_type: str) -> bytes:
    """The bytes of ``mesh`` as a file of ``file_type`` (one of :data:`SUPPORTED_OUTPUT`).

    GLB is packed by :func:`lodserver.io.glb.encode_glb`, straight from the
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

    One format call over the whole table: a Python loop per row would pay the
    interpreter's overhead on each of a million-face mesh's rows.
    """
    return (line * len(table)) % tuple(table.ravel().tolist())
