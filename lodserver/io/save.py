"""Writing a mesh: the output formats, the bytes of each, and files written atomically.

:data:`OUTPUT_FORMATS` lists every output format once (name, file suffix, media
type, what it keeps, its writer); the CLI's output files, the server's level
formats and :func:`save_mesh` all read it, so a format is added here and
nowhere else.

Precision when saving: PLY, GLB and STL store float32 coordinates (trimesh's
PLY exporter always writes ``float``; glTF and binary STL are float32 by
definition), so positions come back to within float32 rounding (about 6e-8
relative), and vertices closer than that would be welded on reload. OBJ and OFF
are text written with 17 decimals, exact for any coordinate of magnitude 0.1 or
more and within 5e-18 otherwise.

GLB may be written quantized (KHR_mesh_quantization) or meshopt-compressed
(EXT_meshopt_compression), its primitives in vertex cache and fetch order
(``compress=``, :class:`lodserver.io.glb.GlbWriter`); positions then come back
within half a step of a 14-bit grid over the mesh's largest side.

What each output format keeps: GLB everything (every attribute column of the
layout, materials, images; :func:`lodserver.io.glb.render_attributes`); OBJ
positions plus ``vt``/``vn`` per wedge from TEXCOORD_0 and NORMAL (no ``.mtl``:
the bytes API writes one file); PLY, OFF and STL positions and triangles only.
The columns a format cannot hold (TEXCOORD_1.., COLOR_n, TANGENT, joints and
weights, morph deltas, custom attributes) are left out without a word: the
format says what it keeps, and GLB is the one that keeps everything.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..mesh import Mesh, MeshError
from .files import write_atomic
from .glb import COMPRESSIONS, encode_glb
from .load import file_kind


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


def save_mesh(mesh: Mesh, path, *, file_type: str | None = None,
              compress: str = "none") -> None:
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
    compress : str
        One of the format's ``compressions`` (:func:`encode_mesh`).

    Raises
    ------
    MeshError
        If the format is unsupported (nothing is written then).
    OSError
        If the file cannot be written.
    """
    path = Path(path)
    kind = file_kind(path, file_type, SUPPORTED_OUTPUT, "save")
    write_atomic(path, encode_mesh(mesh, kind, compress=compress))


def encode_mesh(mesh: Mesh, file_type: str, *, compress: str = "none") -> bytes:
    """The bytes of ``mesh`` as a file of ``file_type`` (one of :data:`SUPPORTED_OUTPUT`).

    GLB is packed by :func:`lodserver.io.glb.encode_glb`, straight from the
    arrays: attributes and materials when the mesh has them, else one float32
    POSITION and one uint32 index accessor. OBJ gets ``vt``/``vn`` lines per
    wedge when the mesh has TEXCOORD_0 or NORMAL. PLY, OFF and STL (and OBJ
    without those) hold positions and triangles only. ``compress`` is one of the
    format's ``compressions``: for GLB ``"quantize"`` or ``"meshopt"``
    (:data:`lodserver.io.glb.COMPRESSIONS`), ``"none"`` for every format.
    """
    if file_type not in SUPPORTED_OUTPUT:
        raise MeshError(f"cannot write {file_type!r}: supported are {', '.join(SUPPORTED_OUTPUT)}")
    output = OUTPUT_FORMATS[file_type]
    if compress not in output.compressions:
        raise MeshError(f"{file_type} cannot be written with compress={str(compress)[:40]!r}: "
                        f"it takes {', '.join(output.compressions)}")
    return output.writer(mesh) if compress == "none" else output.writer(mesh, compress)


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


def _trimesh_writer(file_type: str) -> Callable[[Mesh], bytes]:
    """A writer of positions and triangles through trimesh's exporter of ``file_type``."""
    def write(mesh: Mesh) -> bytes:
        # here, not on import: the package's heaviest import, which most saves skip
        import trimesh

        data = trimesh.Trimesh(mesh.positions, mesh.faces, process=False).export(
            file_type=file_type, **_EXPORT_OPTIONS[file_type])
        return data.encode("utf-8") if isinstance(data, str) else data
    return write


def _obj_writer(mesh: Mesh) -> bytes:
    """OBJ with ``vt``/``vn`` lines when the mesh has TEXCOORD_0 or NORMAL, else
    positions and triangles through trimesh."""
    attributes = mesh.attributes
    if attributes is not None and (attributes.columns("TEXCOORD_0")
                                   or attributes.columns("NORMAL")):
        return _obj_bytes(mesh)
    return _trimesh_writer("obj")(mesh)


@dataclass(frozen=True)
class OutputFormat:
    """One output format: what it is called, what it keeps, what writes it.

    Attributes
    ----------
    name : str
        The format's name, as ``file_type``, the CLI's suffix and the server's
        ``format=`` say it.
    suffix : str
        The file suffix, with its dot.
    media_type : str
        The ``Content-Type`` the server answers it with.
    materials : bool
        Whether it carries the mesh's materials (and images, or a link to them).
    attributes : str
        Which wedge attributes it carries: ``"all"``, ``"TEXCOORD_0, NORMAL"`` or
        ``"none"``.
    writer : callable or None
        ``writer(mesh) -> bytes``; None for ``json``, the quantized form of a
        level, which ``service/levels.py`` writes (it needs the packets' grids).
    served : bool
        Whether the server answers levels in it (``GET /meshes/{id}/lod?format=``).
    compressions : tuple of str
        How it may be compressed (``compress=``, ``--compress``): ``writer(mesh,
        compress)`` for any but ``"none"``.
    """

    name: str
    suffix: str
    media_type: str
    materials: bool
    attributes: str
    writer: Callable[[Mesh], bytes] | None
    served: bool
    compressions: tuple[str, ...] = ("none",)


# Every output format once. The order is the order the server's formats are
# listed in (its 422 messages and its OpenAPI document name them in this order).
OUTPUT_FORMATS = {f.name: f for f in (
    OutputFormat("glb", ".glb", "model/gltf-binary", materials=True, attributes="all",
                 writer=encode_glb, served=True, compressions=COMPRESSIONS),
    OutputFormat("obj", ".obj", "model/obj", materials=False, attributes="TEXCOORD_0, NORMAL",
                 writer=_obj_writer, served=True),
    OutputFormat("ply", ".ply", "application/octet-stream", materials=False, attributes="none",
                 writer=_trimesh_writer("ply"), served=True),
    OutputFormat("json", ".json", "application/json", materials=True, attributes="all",
                 writer=None, served=True),
    OutputFormat("off", ".off", "application/octet-stream", materials=False, attributes="none",
                 writer=_trimesh_writer("off"), served=False),
    OutputFormat("stl", ".stl", "model/stl", materials=False, attributes="none",
                 writer=_trimesh_writer("stl"), served=False),
)}

# The formats a mesh file can be written in (save_mesh, encode_mesh, the CLI).
SUPPORTED_OUTPUT = tuple(name for name, f in OUTPUT_FORMATS.items() if f.writer is not None)
# The formats the server answers a level in, with their media types.
SERVED_FORMATS = {name: f.media_type for name, f in OUTPUT_FORMATS.items() if f.served}
