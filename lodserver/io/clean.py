"""Welding and cleaning the arrays every reader produces, and the wedges of their corners.

The readers (:mod:`.obj`, :mod:`.ply`, :mod:`.gltf`, trimesh for the rest) give
``positions`` (n, 3) float64 and ``faces`` (m, 3) int64 and, with appearance
data, ``corner_values`` (m, 3, d), ``face_material`` (m,) and ``materials``;
:func:`clean_mesh` turns them into a :class:`~lodserver.mesh.Mesh` and says in a
:class:`LoadReport` what it changed. The two small helpers at the end (fan
triangulation, sRGB to linear) are shared by the readers.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from numba import njit

from ..mesh import Attributes, Materials, Mesh, MeshError, attribute_rule, read_only


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
    """Per-vertex data in the file that is not kept (JOINTS_0 of a flattened glTF, a
    matrix-typed custom attribute, a PLY 'quality', ...)."""
    missing_files: list[str] = field(default_factory=list)
    """Companion files the mesh names but that do not exist (an OBJ's mtllib), ignored."""

    def as_dict(self) -> dict:
        return asdict(self)


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
    one. Every column counts, carried ones too: two corners whose joints, weights,
    tangent or one morph delta differ are two wedges (a skin seam is kept like a
    UV seam). Everything kept stays in the order of its first occurrence, so the
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
        Attribute names and widths (:data:`~lodserver.mesh.ATTRIBUTE_RULES`) adding
        up to ``d``.
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
    faces = faces.astype(np.int64, copy=False)     # nothing below writes into it
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
        try:
            attribute_rule(name, width)
        except MeshError as exc:
            raise MeshError(f"unknown attribute {name!r} of width {width}") from exc
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


def _first_occurrences(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Group equal rows, numbering the groups in order of first appearance.

    Parameters
    ----------
    rows : (k, d) float64 or integer array
        Rows to compare (with ``==``, so ``0.0`` equals ``-0.0`` and a row
        holding NaN equals no other row).

    Returns
    -------
    first : (u,) int64
        Index of the first row of each group, ascending.
    inverse : (k,) int64
        Group of each row, so ``rows[first][inverse]`` equals ``rows``.
    """
    rows = np.asarray(rows)
    if rows.ndim != 2:
        rows = rows.reshape(len(rows), -1)
    if np.issubdtype(rows.dtype, np.floating):
        rows = read_only(rows, np.float64)
        # adding 0.0 turns -0.0 into 0.0, so equal rows hash alike
        bits = read_only((rows + 0.0).view(np.int64))
    else:
        rows = read_only(rows, np.int64)
        bits = rows
    first, inverse, hashed = _group_rows(rows, bits, PROBES_PER_ROW)
    return (first, inverse) if hashed else _sorted_first_occurrences(rows)


# Hash-table probes per row (on average) past which grouping falls back to a
# sort: rows crafted to collide (a hostile upload) would otherwise make the
# table's pass quadratic, while a sort's cost does not depend on the values.
PROBES_PER_ROW = 32


def _sorted_first_occurrences(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``_first_occurrences`` by a lexsort of the rows (the same result)."""
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


@njit(cache=True, nogil=True)
def _group_rows(rows, bits, probes_per_row):
    """``_first_occurrences`` in one pass over the rows with a hash table
    (open addressing on ``bits``, each row's words as int64): a sort of the
    rows costs k log k comparisons of whole rows, this about one per row.
    Returns (first, inverse, True), or (_, _, False) once the probes pass
    ``probes_per_row`` per row (then the caller sorts instead)."""
    k, d = rows.shape
    size = 2
    while size < 2 * k:
        size *= 2
    mask = size - 1
    table = np.full(size, -1, np.int64)
    first = np.empty(k, np.int64)
    inverse = np.empty(k, np.int64)
    groups = 0
    probes = 0
    budget = probes_per_row * k + 1024
    for i in range(k):
        h = np.uint64(14695981039346656037)
        for c in range(d):
            h = (h ^ np.uint64(bits[i, c])) * np.uint64(1099511628211)
        h ^= h >> np.uint64(31)
        slot = np.int64(h & np.uint64(mask))
        while True:
            g = table[slot]
            if g < 0:
                table[slot] = groups
                first[groups] = i
                inverse[i] = groups
                groups += 1
                break
            j = first[g]
            equal = True
            for c in range(d):
                if rows[i, c] != rows[j, c]:
                    equal = False
                    break
            if equal:
                inverse[i] = g
                break
            slot = (slot + 1) & mask
            probes += 1
            if probes > budget:
                return first[:0].copy(), inverse, False
    return first[:groups].copy(), inverse, True


def fan_triangulate(corners: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Triangles (t, 3) fanning out polygons given as corners (k,) and sizes (p,)."""
    fan = sizes - 2
    starts = np.repeat(np.cumsum(sizes) - sizes, fan)
    step = np.arange(fan.sum()) - np.repeat(np.cumsum(fan) - fan, fan) + 1
    return np.stack(
        [corners[starts], corners[starts + step], corners[starts + step + 1]], axis=1
    )


def srgb_to_linear(values: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] to linear light (the IEC 61966-2-1 curve).

    PLY and OBJ colours are what a screen showed; glTF's COLOR_0 and
    baseColorFactor are linear, and a renderer encodes them back for display.
    """
    values = np.asarray(values, dtype=np.float64)
    return np.where(values <= 0.04045, values / 12.92, ((values + 0.055) / 1.055) ** 2.4)
