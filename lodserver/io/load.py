"""Reading a mesh file: its format's reader, the limits, the confinement, one kind of error.

:func:`load_mesh` picks the reader by extension (or ``file_type``): OBJ
(:mod:`.obj`), glTF/GLB (:mod:`.gltf`), PLY with triangle strips (:mod:`.ply`)
and, for the rest, ``trimesh.load_scene(..., process=False)`` so that trimesh
neither merges nor removes anything. Before trimesh sees a PLY, OFF or STL
file its declared counts are checked here against the limits and the file's
size (trimesh would allocate first). Whatever goes wrong becomes a
:class:`~lodserver.mesh.MeshError` (or its :class:`~.limits.LimitError`) of
one sentence naming the file by its name only.
"""

from __future__ import annotations

import os
import struct
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from ..mesh import Mesh, MeshError
from .clean import LoadReport, clean_mesh
from .gltf import read_gltf
from .limits import LimitError, LoadLimits, OutOfMemory
from .obj import read_obj
from .ply import (
    checked_ply_header,
    ply_attributes,
    ply_columns,
    ply_triangle_rows,
    read_ply_binary_triangles,
    read_ply_tristrips,
)

__all__ = ["SUPPORTED_INPUT", "LoadReport", "load_mesh"]


SUPPORTED_INPUT = ("obj", "ply", "stl", "off", "gltf", "glb")


def load_mesh(path, *, file_type: str | None = None, root=None,
              limits: LoadLimits | None = None) -> tuple[Mesh, LoadReport]:
    """Read a mesh file and clean it with :func:`clean_mesh`.

    Parameters
    ----------
    path : str or os.PathLike
        The file to read. A ``.gltf`` file finds its buffers and images
        relative to it, an OBJ its ``.mtl`` files and an MTL its textures.
    file_type : str, optional
        One of :data:`SUPPORTED_INPUT`, overriding the file's extension (for
        uploads saved under temporary names).
    root : str or os.PathLike, optional
        For files from someone else (an upload): every file ``path`` refers
        to must be a regular file inside this folder, reached without
        symlinks, ``..`` escapes or absolute paths
        (:func:`lodserver.references.resolve_reference`). Without it, names
        are taken relative to the referring file, as a user's own files are;
        devices, ``/proc`` and URLs are refused either way.
    limits : LoadLimits, optional
        Bounds on what the file may declare, checked before the memory is
        allocated. Default: :class:`LoadLimits` ``()`` when ``root`` is given,
        else :meth:`LoadLimits.unbounded` (the command line's trusted files).

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
        buffer or texture image that does not exist or may not be read. The
        message names the file by its name only (no folder: no server path).
    LimitError
        If it declares more than ``limits`` allow (a MeshError too).
    """
    path = Path(path)
    kind = file_kind(path, file_type, SUPPORTED_INPUT, "load")
    if limits is None:
        limits = LoadLimits() if root is not None else LoadLimits.unbounded()
    root = Path(root) if root is not None else None
    with file_errors(path):
        if not path.exists():
            raise MeshError("no such file")
        if not path.is_file():
            raise MeshError("it is not a regular file")
        size = path.stat().st_size
        if size == 0:
            raise MeshError("the file is empty")
        limits.check("max_file_bytes", size, "bytes (the file's size)")
        if kind == "obj":
            arrays = read_obj(path, root, limits)
        elif kind in ("gltf", "glb"):
            arrays = read_gltf(path, kind, root=root, limits=limits)
        elif kind == "ply":
            elements = checked_ply_header(path, size, limits)
            if "tristrips" in {name for name, _, _ in elements}:
                arrays = read_ply_tristrips(path)
            else:
                arrays = read_ply_binary_triangles(path) or _read_with_trimesh(path, kind)
        else:
            (_check_off if kind == "off" else _check_stl)(path, size, limits)
            arrays = _read_with_trimesh(path, kind)
        dropped = arrays.pop("dropped_attributes", [])
        missing = arrays.pop("missing_files", [])
        mesh, report = clean_mesh(**arrays)
        report.dropped_attributes, report.missing_files = list(dropped), list(missing)
        return mesh, report


@contextmanager
def file_errors(path: Path):
    """Whatever reading ``path`` raises, as one sentence naming the file by its name
    only: ``cannot load NAME: ...`` (MeshError, LimitError, or OutOfMemory when the
    process ran out of memory, so a parse worker knows to retire)."""
    try:
        yield
    except LimitError as exc:
        raise LimitError(f"cannot load {path.name}: {exc}") from exc
    except MeshError as exc:
        raise MeshError(f"cannot load {path.name}: {exc}") from exc
    except OSError as exc:
        raise MeshError(f"cannot load {path.name}: {exc.strerror or type(exc).__name__}") from exc
    except RecursionError:
        raise MeshError(f"cannot load {path.name}: it is nested too deeply to read") from None
    except MemoryError:
        raise OutOfMemory(f"cannot load {path.name}: reading it needs more memory than this "
                          "process may use") from None
    except Exception as exc:
        # A reader tripping over garbage (numpy, trimesh, a missing optional
        # dependency) is a bad file, not a server error; its message is kept
        # without the file's folder, which must not leak.
        detail = _without_folder(str(exc), path)
        raise MeshError(f"cannot load {path.name}: it could not be read "
                        f"({type(exc).__name__}: {detail})") from exc


def _without_folder(text: str, path: Path) -> str:
    """``text`` with every mention of the folder of ``path`` removed, shortened to one line."""
    for folder in {str(path.parent), str(path.resolve().parent)}:
        if folder not in ("", "."):
            text = text.replace(folder + os.sep, "").replace(folder, "")
    text = " ".join(text.split())
    return text[:200]


def file_kind(
    path: Path, file_type: str | None, supported: tuple[str, ...], verb: str
) -> str:
    """The lower-case format of ``path``, or a MeshError naming the supported ones."""
    kind = (file_type or path.suffix).lower().lstrip(".")
    if kind not in supported:
        what = f"file type '{kind}'" if kind else "file without an extension"
        raise MeshError(
            f"cannot {verb} {path.name}: unsupported {what}; "
            f"supported types are {', '.join(supported)}"
        )
    return kind


def _read_with_trimesh(path: Path, kind: str) -> dict:
    """Positions (n, 3) and triangles (m, 3) of every geometry instance in the file,
    plus a PLY's vertex normals, colours and UVs as corner values."""
    import trimesh      # here: only STL and OFF files need it, and its import is slow

    try:
        scene = trimesh.load_scene(str(path), file_type=kind, process=False)
    except Exception as exc:
        # trimesh raises anything from ValueError to IndexError (or an ImportError
        # for a missing optional dependency) on a file it cannot read.
        raise MeshError(f"it could not be parsed as {kind.upper()} "
                        f"({type(exc).__name__}: {_without_folder(str(exc), path)})") from exc
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
        vertex = ply_columns(raw["vertex"]["data"])
        face = ply_columns(raw["face"]["data"]) if "face" in raw else {}
        faces = arrays["faces"]
        if len(placed[0].vertices) != len(next(iter(vertex.values()))):
            # trimesh splits vertices along per-face UV seams; the file's own
            # triangles then say which vertex each corner is
            faces = ply_triangle_rows(face, len(faces))
        arrays.update(ply_attributes(vertex, faces, face))
    return arrays


def _check_off(path: Path, size: int, limits: LoadLimits) -> None:
    """Refuse an OFF header whose vertex or face count exceeds the limits or the file.

    An ASCII vertex line needs at least 6 bytes ("0 0 0\\n"), a triangle 8. A
    header this does not understand is left to trimesh to report.
    """
    with open(path, "rb") as file:
        head = file.read(4096).decode("ascii", errors="replace")
    words = []
    for line in head.splitlines():
        line = line.split("#", 1)[0].split()
        words.extend(line)
        if len(words) >= 4:
            break
    if not words or not words[0].upper().endswith("OFF") or "BINARY" in head[:64].upper():
        return
    try:
        vertices, faces = int(words[1]), int(words[2])
    except (IndexError, ValueError):
        return
    limits.check("max_vertices", vertices, "OFF vertices")
    limits.check("max_triangles", faces, "OFF faces")
    if vertices < 0 or faces < 0 or 6 * vertices + 8 * faces > size:
        raise MeshError(f"its OFF header declares {vertices} vertices and {faces} faces, more "
                        f"than its {size} bytes can hold")


def _check_stl(path: Path, size: int, limits: LoadLimits) -> None:
    """Tell binary from ASCII STL here, and check the triangle count of either.

    A binary STL is 84 bytes of header and count, then 50 bytes a triangle, so
    its size says whether the count is true. Anything else must be ASCII text
    starting with ``solid``, whose ``endfacet`` lines are counted in the bytes.
    (trimesh would otherwise guess an encoding for non-UTF-8 bytes with an
    optional dependency, and fail with ModuleNotFoundError.)
    """
    with open(path, "rb") as file:
        head = file.read(84)
        if len(head) == 84:
            (count,) = struct.unpack_from("<I", head, 80)
            if size == 84 + 50 * count:
                limits.check("max_triangles", count, "STL triangles")
                return
        if not head.lstrip()[:5].lower() == b"solid":
            declared = f"declares {count} triangles" if len(head) == 84 else "is too short"
            raise MeshError(f"it is neither binary STL (its header {declared} for {size} bytes) "
                            "nor ASCII STL (text starting with 'solid')")
        data = head + file.read()
    try:
        data.decode("utf-8")
    except UnicodeDecodeError:
        raise MeshError("it is not binary STL and not an ASCII STL in UTF-8 text") from None
    lower = data.lower()
    limits.check("max_triangles", lower.count(b"endfacet"), "STL facets")
