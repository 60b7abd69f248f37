"""The indexed triangle mesh every stage of lodserver passes along.

A :class:`Mesh` is a thin, validated container of two arrays:

- ``positions`` : (n, 3) float64, vertex positions in the file's units.
- ``faces``     : (m, 3) int64, counter-clockwise vertex indices into ``positions``.

and, when the source has them, appearance data (Hoppe 1999's wedges):

- ``attributes`` : :class:`Attributes`, per-corner normals / UVs / colours,
  grouped into wedges: the corners of one vertex that share one attribute
  vector. A UV seam or a hard edge is a vertex with two or more wedges.
- ``face_material`` : (m,) int32, index into ``materials.gltf["materials"]``,
  -1 for "no material"; and ``materials`` : :class:`Materials`, the glTF
  material, texture, sampler and image records with the image bytes.

Topology (welding, manifoldness, the vertex hierarchy) lives on positions;
attributes ride on wedges, so seams cost nothing topologically.

Validation happens once, on construction, so the kernels downstream can trust
their input (finite coordinates, indices in range) without re-checking.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
from numba import njit


class MeshError(ValueError):
    """A mesh (or a file that should hold one) cannot be used; the message says why."""


# How each vertex attribute is simplified, by glTF semantic (a rules table, first match wins):
# (name pattern, width, kind, merge). Widths are fixed except for custom ``_NAME``
# attributes, whose width (1..4) the layout gives.
#
# kind SOLVED : an attribute quadric ranks the collapse and solves the merged value at the
#               new position (Hoppe 1999; ``simplify.wedges``)
# kind CARRIED: no part of the cost; a merged wedge takes the value interpolated along the
#               collapsed edge at the new position (``simplify.carried``). Skin and morph
#               errors are counted through pose quadrics instead (``simplify.poses``).
#
# merge: how a merged value is made valid again: "unit" renormalised, "clamp" kept in
# [0, 1], "value" as interpolated, "tangent" made orthogonal to the merged normal and
# unit with a handedness of +-1, "skin" the influences of both ends (every JOINTS_n/
# WEIGHTS_n set together) summed per joint, the largest kept, weights summing to 1;
# "vertex" as interpolated, for values that belong to the vertex rather than the corner
# (morph deltas, like skins, must agree on every wedge of a vertex or the surface tears
# when it moves: both blend only when that keeps the vertex's wedges in agreement).
#
# Morph targets are attributes too: ``TARGET{t}_POSITION`` (and ``_NORMAL``,
# ``_TANGENT``) holds target t's delta, carried per wedge like any value.
SOLVED, CARRIED = "solved", "carried"
ATTRIBUTE_RULES = (
    (r"NORMAL", 3, SOLVED, "unit"),
    (r"TEXCOORD_\d+", 2, SOLVED, "value"),
    (r"COLOR_\d+", 4, SOLVED, "clamp"),
    (r"TANGENT", 4, CARRIED, "tangent"),
    (r"JOINTS_\d+", 4, CARRIED, "skin"),
    (r"WEIGHTS_\d+", 4, CARRIED, "skin"),
    (r"TARGET\d+_(POSITION|NORMAL|TANGENT)", 3, CARRIED, "vertex"),
    (r"_[A-Za-z0-9_]{1,63}", None, CARRIED, "value"),
)
CUSTOM_WIDTHS = (1, 2, 3, 4)
# At most this many attributes a mesh: what a packet header can name (packets.format).
MAX_ATTRIBUTES = 255


def attribute_rule(name: str, width: int | None = None) -> tuple[int, str, str]:
    """``(width, kind, merge)`` of vertex attribute ``name`` (see ``ATTRIBUTE_RULES``).

    ``width`` is required for custom ``_NAME`` attributes and checked for the others;
    an unknown name or a wrong width is a MeshError.
    """
    for pattern, fixed, kind, merge in ATTRIBUTE_RULES:
        if re.fullmatch(pattern, name):
            if fixed is None:
                if width not in CUSTOM_WIDTHS:
                    raise MeshError(f"custom attribute {name!r} must have 1 to 4 components, "
                                    f"got {width}")
                return int(width), kind, merge
            if width is not None and int(width) != fixed:
                raise MeshError(f"attribute {name!r} has {fixed} components, got {width}")
            return fixed, kind, merge
    raise MeshError(f"unknown attribute {name!r}")


def attribute_width(name: str, width: int | None = None) -> int:
    """The number of floats of attribute ``name`` (``width`` for a custom one)."""
    return attribute_rule(name, width)[0]


def is_solved(name: str) -> bool:
    """True when attribute ``name`` has an attribute quadric (kind SOLVED)."""
    return any(re.fullmatch(pattern, name) and kind == SOLVED
               for pattern, _, kind, _ in ATTRIBUTE_RULES)


@dataclass(frozen=True, eq=False)
class Attributes:
    """Per-corner appearance attributes, grouped into wedges.

    layout : tuple of (name, width)
        The columns of ``values``, in order, named as glTF vertex attributes
        (:data:`ATTRIBUTE_RULES`): e.g. ``(("NORMAL", 3), ("TEXCOORD_0", 2))``.
        UVs are in glTF's convention (origin top-left, v down); colours are linear RGBA in
        0..1; ``TANGENT`` is xyz plus handedness w = +-1; ``JOINTS_n`` hold joint indices
        (into the skin's ``joints``) as exact integers, ``WEIGHTS_n`` their weights (all sets
        of a vertex summing to 1); ``TARGET{t}_*`` morph target t's deltas.
    values : (w, d) float64
        One attribute vector per wedge, ``d = sum(widths)``.
    corners : (m, 3) int64
        The wedge of every face corner; ``corners[f, k]`` belongs to vertex ``faces[f, k]``.
    """

    layout: tuple
    values: np.ndarray
    corners: np.ndarray

    def __post_init__(self):
        layout = tuple((str(name), int(width)) for name, width in self.layout)
        for name, width in layout:
            attribute_rule(name, width)
        if len(layout) > MAX_ATTRIBUTES:
            raise MeshError(f"the mesh has {len(layout)} vertex attributes; at most "
                            f"{MAX_ATTRIBUTES} are supported")
        if len({name for name, _ in layout}) != len(layout):
            raise MeshError("an attribute appears twice in the layout")
        d = sum(width for _, width in layout)
        values = np.ascontiguousarray(self.values, dtype=np.float64)
        # (w, 0) when no column is left (the solved part of a mesh with carried columns only)
        values = values.reshape(len(values) if d == 0 else -1, d)
        corners = np.ascontiguousarray(self.corners, dtype=np.int64)
        if not np.isfinite(values).all():
            raise MeshError("attribute values are NaN or infinite")
        if corners.ndim != 2 or corners.shape[1] != 3:
            raise MeshError(f"wedge corners must have shape (m, 3), got {corners.shape}")
        if corners.size and (corners.min() < 0 or corners.max() >= len(values)):
            raise MeshError("wedge indices out of range")
        values.setflags(write=False)
        corners.setflags(write=False)
        object.__setattr__(self, "layout", layout)
        object.__setattr__(self, "values", values)
        object.__setattr__(self, "corners", corners)

    def __setstate__(self, state):
        self.__dict__.update(_restore_read_only(state, ("values", "corners")))

    @property
    def width(self) -> int:
        return self.values.shape[1]

    @property
    def wedge_count(self) -> int:
        return len(self.values)

    def columns(self, name: str) -> slice | None:
        """The columns of ``values`` holding attribute ``name``, or None."""
        start = 0
        for other, width in self.layout:
            if other == name:
                return slice(start, start + width)
            start += width
        return None


@dataclass(frozen=True, eq=False)
class Materials:
    """Materials carried from input to output, as glTF 2.0 records.

    gltf : dict
        ``{"materials": [...], "textures": [...], "samplers": [...], "images": [...]}``
        as in a glTF document, except that each image record holds
        ``{"mimeType": ..., "name": ...}`` and no ``uri``/``bufferView``: its
        bytes are ``images[i]``. Texture ``source`` indices point into that list.
    images : tuple of bytes
        The encoded image files (PNG, JPEG), byte for byte as read.
    """

    gltf: dict
    images: tuple = ()

    @property
    def count(self) -> int:
        return len(self.gltf.get("materials", ()))


@dataclass(frozen=True, eq=False)
class Mesh:
    """Positions (n, 3) float64 and triangle faces (m, 3) int64, both read-only,
    with optional wedge attributes and per-face materials (see the module docstring)."""

    positions: np.ndarray
    faces: np.ndarray
    attributes: Attributes | None = None
    face_material: np.ndarray | None = None
    materials: Materials | None = None

    def __post_init__(self):
        self._adopt(checked=False)

    @classmethod
    def of_checked_arrays(cls, positions, faces, attributes: Attributes | None = None,
                          face_material=None, materials: Materials | None = None) -> Mesh:
        """A Mesh of ``positions`` (n, 3) float64 and ``faces`` (m, 3) int64 whose
        values the caller has already checked: finite coordinates, indices in
        [0, n). A level of a progressive mesh is such (its arrays were checked
        once when it was made, and every level is made of them), and skipping
        the scans of every coordinate and index is most of a level's cost after
        its kernels. Shapes, the wedges and the face materials are checked as
        by the constructor."""
        mesh = cls.__new__(cls)
        for name, value in (("positions", positions), ("faces", faces),
                            ("attributes", attributes), ("face_material", face_material),
                            ("materials", materials)):
            object.__setattr__(mesh, name, value)
        mesh._adopt(checked=True)
        return mesh

    def _adopt(self, checked: bool) -> None:
        """Check the fields (their values too unless ``checked``) and hold them read-only."""
        positions = np.ascontiguousarray(self.positions, dtype=np.float64)
        faces = np.asarray(self.faces)
        if positions.ndim != 2 or positions.shape[1] != 3:
            raise MeshError(f"positions must have shape (n, 3), got {positions.shape}")
        if faces.size == 0:
            faces = faces.reshape(0, 3)
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise MeshError(f"faces must have shape (m, 3), got {faces.shape}")
        if faces.size and not np.issubdtype(faces.dtype, np.integer):
            raise MeshError(f"faces must hold integer indices, got dtype {faces.dtype}")
        faces = np.ascontiguousarray(faces, dtype=np.int64)
        if len(faces) == 0:
            raise MeshError("the mesh has no faces")
        if not checked:
            _check_values(positions, faces)
        positions.setflags(write=False)
        faces.setflags(write=False)
        object.__setattr__(self, "positions", positions)
        object.__setattr__(self, "faces", faces)
        if self.attributes is not None:
            corners = self.attributes.corners
            if corners.shape != faces.shape:
                raise MeshError(f"wedge corners {corners.shape} do not match faces {faces.shape}")
            # every wedge belongs to exactly one vertex
            owner = np.full(self.attributes.wedge_count, -1, dtype=np.int64)
            owner[corners.ravel()] = faces.ravel()
            if not np.array_equal(owner[corners.ravel()], faces.ravel()):
                raise MeshError("a wedge is shared by corners of different vertices")
        if self.face_material is not None:
            material = np.ascontiguousarray(self.face_material, dtype=np.int32)
            count = self.materials.count if self.materials is not None else 0
            if material.shape != (len(faces),):
                raise MeshError(f"face_material must have shape ({len(faces)},), got {material.shape}")
            if material.size and (material.min() < -1 or material.max() >= count):
                raise MeshError(f"face materials must lie in [-1, {count - 1}]")
            material.setflags(write=False)
            object.__setattr__(self, "face_material", material)

    def __setstate__(self, state):
        self.__dict__.update(_restore_read_only(state, ("positions", "faces",
                                                        "face_material")))

    def wedge_vertices(self) -> np.ndarray:
        """(w,) int64: the vertex of every wedge (-1 for a wedge no corner uses)."""
        owner = np.full(self.attributes.wedge_count, -1, dtype=np.int64)
        owner[self.attributes.corners.ravel()] = self.faces.ravel()
        return owner

    @property
    def vertex_count(self) -> int:
        return len(self.positions)

    @property
    def face_count(self) -> int:
        return len(self.faces)

    @property
    def bounding_box_diagonal(self) -> float:
        """Length of the axis-aligned bounding box diagonal, in mesh units."""
        used = self.positions[np.unique(self.faces)]
        return float(np.linalg.norm(used.max(axis=0) - used.min(axis=0)))

    def __repr__(self) -> str:
        extra = ""
        if self.attributes is not None:
            names = ",".join(name for name, _ in self.attributes.layout)
            extra += f", wedges={self.attributes.wedge_count} [{names}]"
        if self.materials is not None:
            extra += f", materials={self.materials.count}"
        return f"Mesh(vertices={self.vertex_count}, faces={self.face_count}{extra})"


def unit_box(positions):
    """The frame in which kernels work: ``(lo (3,) float64, extent float)``,
    the smallest corner of the bounding box of ``positions`` (n, 3) and its
    longest side (1.0 for a single point), so that ``(positions - lo) / extent``
    lies in the unit cube. Tolerances are then scale-free and quadric
    coefficients stay where float64 cancellation is harmless.

    Plain numpy, called from Python (an njit twin would have to reproduce
    numpy's choice between -0.0 and 0.0 to keep outputs bit for bit)."""
    positions = np.asarray(positions, dtype=np.float64)
    lo = positions.min(axis=0)
    return lo, float((positions.max(axis=0) - lo).max()) or 1.0


def to_unit_box(positions, lo, extent):
    """``(positions - lo) / extent`` as a C-contiguous (n, 3) float64 array."""
    return np.ascontiguousarray((np.asarray(positions, dtype=np.float64) - lo) / extent)


def read_only(array, dtype=None) -> np.ndarray:
    """``array`` as a C-contiguous, read-only view (of ``dtype`` when given;
    copied only when its layout or type differ).

    numba types a read-only array apart from a writable one and compiles a
    kernel once for each; a kernel's input that it only reads is handed to it
    through this, whoever made the array, so that each kernel has one
    signature and the warm-up's compilation is the one a real build uses."""
    view = np.ascontiguousarray(array, dtype=dtype).view()
    view.flags.writeable = False
    return view


def _check_values(positions: np.ndarray, faces: np.ndarray) -> None:
    """MeshError unless every coordinate is finite and every index in [0, n)."""
    if not np.isfinite(positions).all():
        bad = int((~np.isfinite(positions).all(axis=1)).sum())
        raise MeshError(f"{bad} vertex positions are NaN or infinite")
    lo, hi = int(faces.min()), int(faces.max())
    if lo < 0 or hi >= len(positions):
        raise MeshError(
            f"face indices must lie in [0, {len(positions) - 1}], found {lo}..{hi}"
        )


def _restore_read_only(state: dict, names) -> dict:
    """``state`` (an unpickled ``__dict__``) with its arrays ``names`` made read-only:
    pickles before protocol 5, which multiprocessing uses to send a parsed
    mesh back, bring arrays back writable."""
    for name in names:
        if state.get(name) is not None:
            state[name] = read_only(state[name])
    return state


def take_rows(values, order) -> np.ndarray:
    """``values[order]`` for (n, d) ``values`` and (k,) int64 ``order``:
    (k, d) of ``values``' dtype, a new writable array."""
    return _take_rows(read_only(values), read_only(order, np.int64))


@njit(cache=True, nogil=True)
def _take_rows(values, order):
    """``take_rows``'s one compiled gather. numpy's fancy indexing of short
    rows is a loop per row, with its per-row overhead, which dominates on
    the millions of rows a progressive mesh reorders."""
    out = np.empty((order.shape[0], values.shape[1]), values.dtype)
    for i in range(order.shape[0]):
        for j in range(values.shape[1]):
            out[i, j] = values[order[i], j]
    return out


def split_layout(layout) -> tuple[np.ndarray, np.ndarray]:
    """The value columns of ``layout`` ((name, width), ...) that are SOLVED and CARRIED,
    as two int64 index arrays into an attribute vector."""
    solved, carried, start = [], [], 0
    for name, width in layout:
        columns = range(start, start + width)
        (solved if attribute_rule(name, width)[1] == SOLVED else carried).extend(columns)
        start += width
    return np.array(solved, dtype=np.int64), np.array(carried, dtype=np.int64)
