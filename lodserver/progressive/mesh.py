"""The progressive mesh: a base mesh plus an ordered list of vertex splits.

Layout (Hoppe 1996, renumbered so that every level is a prefix):

- Vertices are numbered so the base mesh holds ids ``0 .. n0-1`` and the split
  that raises the vertex count from ``v`` to ``v + 1`` introduces vertex ``v``.
  A level is named by its vertex count ``v`` in ``[n0, n]``; it uses
  ``positions[:v]``.
- Faces are numbered so the base faces come first and each split appends the
  faces it creates (each starting at its corner on ``vs``: ``face_rotation``);
  level ``v`` uses the first ``face_counts[v - n0]`` faces.
- ``parent[t]`` is the vertex that split ``t`` splits (``vs``), always ``< t``;
  collapsing ``t`` merges it back into ``parent[t]``. The parents form Hoppe's
  vertex hierarchy: a face corner that reads ``x`` at full detail reads, at
  level ``v``, the first ancestor of ``x`` below ``v``. So any level can be
  computed directly (``at``), in time proportional to its size, and any level
  can be reached incrementally from any other (``Cursor``), both exactly.

Split record ``t`` (arrays indexed by ``t - n0``):

===================  ==========  ===================================================
field                dtype       meaning
===================  ==========  ===================================================
parent[t]            int64       ``vs``: the vertex split in two
coarse_position      (3,) f64    ``vs``'s position before the split (after the collapse)
fine_position        (3,) f64    ``vs``'s position after the split
new_position         (3,) f64    position of the new vertex ``t``
faces                int range   faces ``face_counts[t-n0] .. face_counts[t-n0+1]`` appear,
                                 with corners ``birth_faces`` at that range
moved corners        int64       ``3 * face + slot`` corners relabelled ``vs -> t``
error                f64         RMS quadric error of the collapse undone (mesh units)
===================  ==========  ===================================================

Wedges (appearance attributes, when the input has them) follow the same
scheme one level down: wedges are numbered so that level ``v`` uses wedges
``0 .. wedge_counts[v-n0]-1``; split ``t`` introduces the wedges its collapse
merged away, each a child of the wedge it merged into (``wedge_parent``). A
corner's wedge at a level is the first ancestor of its full-detail wedge below
that level's wedge count, and a wedge's attribute vector is the one left by
its most recent applied merge (``wedge_coarse_value``), exactly as for
positions. So attributes, too, are exact at every level, in both directions.
Face materials ride on the faces (``face_material``, renumbered with them),
batches of independent splits on the splits (``split_batch``, ``batches``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numba import njit

from ..heap import give_back
from ..mesh import Attributes, Materials, Mesh, take_rows
from ..overlap import both
from .artefact import (ARRAYS, STORED_FIELDS, WEDGE_ARRAYS, ArtefactError, decode_artefact,
                       encode_artefact, read_artefact, write_artefact)
from .face_rotation import new_face_turns, turned_corners, turned_rows
from .replay import Cursor, ancestor_below
from .renumber import (
    hierarchy,
    renumbered_faces,
    reverse_blocks,
    reversed_corners,
    split_face_order,
)

if TYPE_CHECKING:
    # only for annotations: a progressive mesh reads a collapse log's arrays, and
    # need not import the simplifier to do so
    from ..simplify.collapse import CollapseLog


def _faces_at(full_faces, parent, face_count: int, level: int, out) -> None:
    """Write the first ``face_count`` of ``full_faces`` (m, 3), as read at ``level``
    of the hierarchy ``parent`` (n,), into ``out`` (face_count, 3), any integer dtype.

    The same for wedges: ``corner_wedges``, ``wedge_parent`` and a wedge count.
    """
    n = len(parent)
    # int32 while ids fit: half the cache footprint of a table read at random
    dtype = np.int32 if n <= np.iinfo(np.int32).max else np.int64
    below = np.empty(max(n - level, 0) + 1, dtype=dtype)
    _faces_at_kernel(full_faces, parent, face_count, level, below, out)


@njit(cache=True, nogil=True)
def _faces_at_kernel(full_faces, parent, face_count, level, below, out):
    """Corners of the first ``face_count`` faces at level ``level``.

    Each full-detail corner reads its first ancestor below ``level``. Parents
    come before their children, so one pass finds the ancestor of every vertex
    from ``level`` on (``below[1 + x - level]``) and the corners are a gather:
    cheaper than walking up from each corner.

    Both loops are free of data-dependent branches: every corner reads the
    table (ids below ``level`` read the dummy ``below[0]``) and a select keeps
    either the id or what was read. At a middle level about half the corners
    are on each side, so a branch would mispredict on every other corner,
    which costs more than the extra read.

    below : (parent.shape[0] - level + 1,) scratch (see ``_faces_at``)
    out : (face_count, 3) any integer dtype
    """
    n = parent.shape[0]
    below[0] = 0
    for x in range(level, n):
        p = parent[x]
        y = below[max(p - level + 1, 0)]
        below[x - level + 1] = p if p < level else y
    for f in range(face_count):
        for k in range(3):
            x = full_faces[f, k]
            y = below[max(x - level + 1, 0)]
            out[f, k] = x if x < level else y


@njit(cache=True, nogil=True)
def _positions_at(full_positions, coarse_position, parent, base, level, out):
    """Positions of vertices ``0 .. level-1`` at ``level`` (or, for wedges,
    the attribute vectors of wedges ``0 .. level-1`` with ``level`` a wedge count).

    A vertex's position is the one left by its most recent collapse that is
    applied at this level: the smallest child ``t >= level``. Replaying the
    collapses from the last down to ``level`` leaves exactly that one.
    """
    for x in range(level):
        for j in range(out.shape[1]):
            out[x, j] = full_positions[x, j]
    for t in range(parent.shape[0] - 1, level - 1, -1):
        s = parent[t]
        if s < level:
            for j in range(out.shape[1]):
                out[s, j] = coarse_position[t - base, j]


@dataclass(frozen=True, eq=False)
class ProgressiveMesh:
    """Base mesh + vertex splits; see the module docstring for the layout.

    Stored fields (everything else is derived on construction):

    positions : (n, 3) float64      full-detail positions (the input, renumbered)
    faces : (m, 3) int64            full-detail faces (the input, renumbered)
    parent : (n,) int64             ``vs`` of the split introducing each vertex; -1 in the base
    base_vertices : int             ``n0``
    coarse_position : (n-n0, 3)     ``vs``'s position after collapsing ``t``
    error : (n-n0,) float64         RMS quadric error of collapsing ``t``, mesh units
    face_counts : (n-n0+1,) int64   faces at level ``v`` = ``face_counts[v - n0]``
    moved_offsets : (n-n0+1,) int64, moved_corners : (c,) int64
    metadata : dict                 JSON-able facts (source, options, load report)

    With attributes (all None / empty without):

    attribute_layout : tuple        ((name, width), ...) as ``mesh.Attributes.layout``
    wedge_values : (w, d) float64   full-detail attribute vectors (renumbered)
    corner_wedges : (m, 3) int64    full-detail wedge of every face corner
    wedge_parent : (w,) int64       the wedge each merged into; -1 in the base
    wedge_coarse_value : (w-w0, d)  the parent's vector after that merge
    wedge_counts : (n-n0+1,) int64  wedges at level ``v`` = ``wedge_counts[v - n0]``
    face_material : (m,) int32      per face (renumbered), or None
    materials : Materials           glTF materials and images, or None
    split_batch : (n-n0,) int32     batch of every split (``progressive.batches``), or None
    """

    positions: np.ndarray
    faces: np.ndarray
    parent: np.ndarray
    base_vertices: int
    coarse_position: np.ndarray
    error: np.ndarray
    face_counts: np.ndarray
    moved_offsets: np.ndarray
    moved_corners: np.ndarray
    metadata: dict = field(default_factory=dict)
    attribute_layout: tuple = ()
    wedge_values: np.ndarray | None = None
    corner_wedges: np.ndarray | None = None
    wedge_parent: np.ndarray | None = None
    wedge_coarse_value: np.ndarray | None = None
    wedge_counts: np.ndarray | None = None
    face_material: np.ndarray | None = None
    materials: Materials | None = None
    split_batch: np.ndarray | None = None

    @property
    def has_attributes(self) -> bool:
        return self.wedge_values is not None

    def __post_init__(self):
        n, n0 = len(self.positions), self.base_vertices
        k = n - n0
        if not (0 <= n0 <= n and len(self.parent) == n and len(self.coarse_position) == k
                and len(self.error) == k and len(self.face_counts) == k + 1
                and len(self.moved_offsets) == k + 1 and self.face_counts[-1] == len(self.faces)):
            raise ValueError("inconsistent progressive mesh arrays: sizes disagree")
        # The kernels index with these arrays unchecked, so a bad artefact must
        # stop here rather than read out of bounds.
        t = np.arange(n0, n)
        if (np.any(self.parent[n0:] < 0) or np.any(self.parent[n0:] >= t)
                or (len(self.faces) and (self.faces.min() < 0 or self.faces.max() >= n))
                or np.any(np.diff(self.face_counts) < 0) or self.face_counts[0] < 0
                or np.any(np.diff(self.moved_offsets) < 0) or self.moved_offsets[0] != 0
                or self.moved_offsets[-1] != len(self.moved_corners)
                or (len(self.moved_corners) and (self.moved_corners.min() < 0
                                                 or self.moved_corners.max() >= 3 * len(self.faces)))):
            raise ValueError("inconsistent progressive mesh arrays: indices out of range")
        if self.has_attributes:
            self._check_wedges()
        if self.face_material is not None and self.face_material.shape != (len(self.faces),):
            raise ValueError("inconsistent progressive mesh arrays: face_material size")
        # batches numbered from 0, one after another
        steps = None if self.split_batch is None else np.diff(self.split_batch, prepend=0)
        if steps is not None and (self.split_batch.shape != (k,) or np.any(steps[:1])
                                  or np.any(steps * (steps - 1))):
            raise ValueError("inconsistent progressive mesh arrays: split_batch numbering")
        for name in ARRAYS + WEDGE_ARRAYS + ("face_material", "split_batch"):
            if getattr(self, name) is not None:
                getattr(self, name).setflags(write=False)
        self._derive()

    def _check_wedges(self):
        w, k = len(self.wedge_values), self.split_count
        counts, parent = self.wedge_counts, self.wedge_parent
        width = sum(int(x) for _, x in self.attribute_layout)
        if (self.wedge_values.ndim != 2 or self.wedge_values.shape[1] != width
                or self.corner_wedges.shape != self.faces.shape or len(parent) != w
                or len(counts) != k + 1 or counts[-1] != w
                or self.wedge_coarse_value.shape != (w - counts[0], width)):
            raise ValueError("inconsistent progressive mesh arrays: wedge sizes disagree")
        x = np.arange(counts[0], w)
        if (np.any(np.diff(counts) < 0) or counts[0] < 0 or np.any(parent[:counts[0]] != -1)
                or np.any(parent[counts[0]:] < 0) or np.any(parent[counts[0]:] >= x)
                or (self.corner_wedges.size and (self.corner_wedges.min() < 0
                                                 or self.corner_wedges.max() >= w))):
            raise ValueError("inconsistent progressive mesh arrays: wedge indices out of range")

    # ---- derived arrays -------------------------------------------------
    def _derive(self):
        n, n0 = self.vertex_count, self.base_vertices
        m0 = int(self.face_counts[0])
        owner = np.repeat(np.arange(n0, n), np.diff(self.face_counts))

        def birth_faces():
            """Each face's corners at the first level it appears in."""
            birth = np.empty_like(self.faces)
            _faces_at(self.faces, self.parent, m0, n0, birth)
            # faces of split t live at level t+1: climb while >= t+1
            _faces_at_levels(self.faces, self.parent, m0, owner + 1, birth)
            return birth

        # two independent passes of random reads in compiled code that
        # releases the GIL: at once (``overlap``)
        birth, (fine, new) = both(
            birth_faces, lambda: hierarchy(self.parent, n0, self.positions, self.coarse_position))

        derived = dict(fine_position=fine, new_position=new, birth_faces=birth,
                       level_error=_level_error(self.error))
        if self.has_attributes:
            w0 = int(self.wedge_counts[0])
            derived["wedge_fine_value"], derived["wedge_new_value"] = hierarchy(
                self.wedge_parent, w0, self.wedge_values, self.wedge_coarse_value)
            # corners of each face at the level it appears in, as for birth_faces
            corners = np.empty_like(self.corner_wedges)
            _faces_at(self.corner_wedges, self.wedge_parent, m0, w0, corners)
            _faces_at_levels(self.corner_wedges, self.wedge_parent, m0,
                             self.wedge_counts[owner + 1 - n0], corners)
            derived["birth_corners"] = corners
        for key, value in derived.items():
            value.setflags(write=False)
            object.__setattr__(self, key, value)
        # every level's coordinates are rows of these two: finite here, finite at every level
        object.__setattr__(self, "levels_finite", bool(
            np.isfinite(self.positions).all() and np.isfinite(self.coarse_position).all()))

    # ---- sizes ----------------------------------------------------------
    # full detail's, read as a Mesh's are: the lengths of positions and faces
    vertex_count = Mesh.vertex_count
    face_count = Mesh.face_count

    @property
    def split_count(self) -> int:
        return self.vertex_count - self.base_vertices

    @property
    def levels(self) -> range:
        """Valid levels (vertex counts), coarsest first."""
        return range(self.base_vertices, self.vertex_count + 1)

    def faces_at_level(self, level: int) -> int:
        return int(self.face_counts[self.check_level(level) - self.base_vertices])

    def error_at_level(self, level: int) -> float:
        """Largest collapse error applied to reach ``level``; 0 at full detail."""
        return float(self.level_error[self.check_level(level) - self.base_vertices])

    def check_level(self, level) -> int:
        """``level`` as an int if it is one of :attr:`levels`, else ValueError."""
        level = int(level)
        if not self.base_vertices <= level <= self.vertex_count:
            raise ValueError(f"level {level} is outside [{self.base_vertices}, {self.vertex_count}]")
        return level

    # ---- choosing a level ------------------------------------------------
    def level_for(self, *, vertices=None, faces=None, ratio=None, error=None) -> int:
        """The level (vertex count) asked for by exactly one criterion.

        vertices : at most this many vertices (clamped to the base mesh).
        faces    : the finest level with at most this many faces.
        ratio    : faces = round(ratio * full face count), 0 < ratio <= 1.
        error    : the coarsest level whose error is at most this (mesh units).
        """
        given = [x is not None for x in (vertices, faces, ratio, error)]
        if sum(given) != 1:
            raise ValueError("give exactly one of vertices, faces, ratio or error")
        n0, n = self.base_vertices, self.vertex_count
        if vertices is not None:
            if vertices < 1:
                raise ValueError(f"vertices must be at least 1, got {vertices}")
            return int(min(max(int(vertices), n0), n))
        if ratio is not None:
            if not 0 < ratio <= 1:
                raise ValueError(f"ratio must be in (0, 1], got {ratio}")
            faces = max(1, int(round(ratio * self.face_count)))
        if faces is not None:
            if faces < 1:
                raise ValueError(f"faces must be at least 1, got {faces}")
            i = int(np.searchsorted(self.face_counts, faces, side="right")) - 1
            return n0 + max(i, 0)
        if not error >= 0:
            raise ValueError(f"error must be a non-negative number, got {error}")
        # level_error is non-increasing in the level
        i = int(np.searchsorted(-self.level_error, -error, side="left"))
        return n0 + min(i, self.split_count)

    # ---- extracting a level ---------------------------------------------
    def at(self, level=None, **criterion) -> Mesh:
        """The mesh at a level, computed directly (cost grows with its size).

        ``pm.at(1000)`` or ``pm.at(vertices=1000)``, ``pm.at(faces=2000)``,
        ``pm.at(ratio=0.1)``, ``pm.at(error=1e-3)``.
        """
        if level is None:
            level = self.level_for(**criterion)
        elif criterion:
            raise ValueError("give a level or one criterion, not both")
        positions, faces = self.arrays_at(level)
        return self._level_mesh(positions, faces, *self.wedges_at(level),
                                checked=self.levels_finite)

    def mesh_of(self, positions, faces, values=None, corners=None) -> Mesh:
        """A :class:`Mesh` of one level's arrays (as ``arrays_at`` and ``wedges_at``
        give them), with this mesh's attribute layout, face materials and materials."""
        return self._level_mesh(positions, faces, values, corners, checked=False)

    def _level_mesh(self, positions, faces, values, corners, checked: bool) -> Mesh:
        """``mesh_of``; with ``checked``, the arrays are this mesh's kernels' own (indices
        below the level by construction, coordinates finite by ``levels_finite``), so
        the Mesh does not scan them again."""
        attributes = None
        if self.has_attributes:
            attributes = Attributes(self.attribute_layout, values, corners)
        material = None
        if self.face_material is not None:
            material = self.face_material[:len(faces)]
        if checked:
            return Mesh.of_checked_arrays(positions, faces, attributes, material, self.materials)
        return Mesh(positions, faces, attributes, material, self.materials)

    def wedges_at(self, level: int):
        """(values (w, d) float64, corners (f, 3) int64) at ``level``; (None, None)
        without attributes."""
        if not self.has_attributes:
            return None, None
        level = self.check_level(level)
        count = int(self.wedge_counts[level - self.base_vertices])
        values = np.empty((count, self.wedge_values.shape[1]), dtype=np.float64)
        _positions_at(self.wedge_values, self.wedge_coarse_value, self.wedge_parent,
                      int(self.wedge_counts[0]), count, values)
        corners = np.empty((self.faces_at_level(level), 3), dtype=np.int64)
        _faces_at(self.corner_wedges, self.wedge_parent, len(corners), count, corners)
        return values, corners

    def arrays_at(self, level: int):
        """(positions (v, 3) float64, faces (f, 3) int64) at ``level``, freshly allocated."""
        level = self.check_level(level)
        positions = np.empty((level, 3), dtype=np.float64)
        _positions_at(self.positions, self.coarse_position, self.parent, self.base_vertices,
                      level, positions)
        faces = np.empty((self.faces_at_level(level), 3), dtype=np.int64)
        _faces_at(self.faces, self.parent, len(faces), level, faces)
        return positions, faces

    def write_level(self, level: int, positions: np.ndarray, faces: np.ndarray) -> None:
        """Write the arrays of ``level`` into ``positions`` (level, 3) and ``faces``
        (faces_at_level(level), 3), of any numeric dtype (cast on the way in)."""
        level = self.check_level(level)
        _positions_at(self.positions, self.coarse_position, self.parent, self.base_vertices,
                      level, positions)
        _faces_at(self.faces, self.parent, len(faces), level, faces)

    def cursor(self, level=None) -> Cursor:
        """A mutable view at ``level`` (default: the base) that moves by splits and collapses."""
        return Cursor(self, self.base_vertices if level is None else level)

    def summary(self) -> dict:
        """Counts, the full-detail bounding box (``bounds``: min and max corners,
        mesh units; what a viewer frames before it fetches a level) and the
        error curve at 25 face ratios from 1 to 0.001 (log-spaced, finest first,
        repeated levels once), JSON-able."""
        n0, n = self.base_vertices, self.vertex_count
        curve = []
        for ratio in np.geomspace(1.0, 1e-3, 25):
            level = self.level_for(ratio=float(ratio))
            if curve and curve[-1]["vertices"] == level:
                continue
            curve.append({"ratio": round(float(ratio), 6), "vertices": level,
                          "faces": self.faces_at_level(level), "error": self.error_at_level(level)})
        return {"vertices": n, "faces": self.face_count, "base_vertices": n0,
                "base_faces": int(self.face_counts[0]), "splits": n - n0,
                "max_error": float(self.level_error[0]) if n > n0 else 0.0,
                "bounds": {"min": self.positions.min(axis=0).tolist() if n else [0.0] * 3,
                           "max": self.positions.max(axis=0).tolist() if n else [0.0] * 3},
                "error_curve": curve, "metadata": self.metadata}

    # ---- persistence: the .pm file (progressive.artefact) ----------------
    def save(self, path) -> None:
        """Write the ``.pm`` artefact to ``path`` atomically."""
        save_progressive(self, path)

    @classmethod
    def load(cls, path) -> ProgressiveMesh:
        """Read a ``.pm`` artefact; ``ArtefactError`` if it is unreadable or damaged."""
        return load_progressive(path)


def encode_progressive(pm: ProgressiveMesh) -> bytes:
    """The whole ``.pm`` file of ``pm`` as bytes (``artefact.encode_artefact``)."""
    return encode_artefact({name: getattr(pm, name) for name in STORED_FIELDS})


def decode_progressive(data: bytes, *, source: str = "the artefact") -> ProgressiveMesh:
    """The progressive mesh in bytes written by ``encode_progressive``.

    Raises
    ------
    ArtefactError
        The bytes are damaged, or hold arrays that do not make a progressive
        mesh (a sentence naming ``source``).
    """
    fields = decode_artefact(data, source=source)
    try:
        pm = ProgressiveMesh(**fields)
    except (ValueError, KeyError, IndexError, TypeError) as exc:
        raise ArtefactError(f"{source} holds inconsistent arrays ({exc})") from exc
    page_in_levels(pm)
    return pm


def page_in_levels(pm: ProgressiveMesh) -> None:
    """What the first level asked of a freshly loaded ``pm`` would pay for
    once, paid at load: the level kernels' first call (numba's cache read and
    linked, on the base level's few rows) and the memory of a full-detail
    level's arrays, taken from the system and touched (the system zeroes each
    page on its first touch). glibc's malloc maps an array that large afresh
    and unmaps it when freed, until freeing one has raised its threshold past
    that size; from then on (up to its 32 MiB ceiling) such arrays come from,
    and go back to, the heap it keeps. So the full level's arrays are made
    twice: the first raises the threshold, the second leaves its touched
    pages in the heap for every level after. An array past the ceiling is
    mapped afresh every time whatever was done before, so it is not made
    here."""
    pm.arrays_at(pm.base_vertices)
    pm.wedges_at(pm.base_vertices)
    shapes = [(pm.vertex_count, 3), (pm.face_count, 3)]
    if pm.has_attributes:
        shapes += [pm.wedge_values.shape, (pm.face_count, 3)]
    shapes = [shape for shape in shapes if 8 * int(np.prod(shape)) <= _MALLOC_MMAP_CEILING]
    for _ in range(2):
        held = [np.ones(shape) for shape in shapes]
        del held


# glibc's largest dynamic mmap threshold on 64-bit systems (DEFAULT_MMAP_THRESHOLD_MAX)
_MALLOC_MMAP_CEILING = 32 * 2**20


def save_progressive(pm: ProgressiveMesh, path) -> None:
    """Write ``pm`` to ``path`` atomically (``artefact.write_artefact``)."""
    write_artefact(path, {name: getattr(pm, name) for name in STORED_FIELDS})


def load_progressive(path) -> ProgressiveMesh:
    """The progressive mesh stored at ``path``; ``ArtefactError`` if unreadable or damaged."""
    return decode_progressive(read_artefact(path), source=str(path))


@njit(cache=True, nogil=True)
def _faces_at_levels(full_faces, parent, start, levels, out):
    """Like ``_faces_at`` for faces ``start ..``, each at its own level."""
    for i in range(levels.shape[0]):
        f = start + i
        for k in range(3):
            out[f, k] = ancestor_below(parent, full_faces[f, k], levels[i])


def _level_error(error):
    """Error at each level v (index v - n0): the worst collapse applied to get
    there, i.e. the max over splits t >= v; 0 at full detail. Non-increasing."""
    out = np.zeros(len(error) + 1, dtype=np.float64)
    if len(error):
        out[:-1] = np.maximum.accumulate(error[::-1])[::-1]
    return out


def from_collapse_log(mesh: Mesh, log: CollapseLog, metadata=None,
                      split_batch=None) -> ProgressiveMesh:
    """Renumber ``mesh`` and its collapse log into the prefix layout.

    The vertex removed by collapse ``i`` (of ``k``) becomes vertex ``n - 1 - i``;
    vertices never removed keep their input order as ``0 .. n0-1``. Faces never
    removed come first, in input order, then each split's faces.
    ``split_batch`` (k,) int32, optional: the batch of every split, in split order.
    """
    n, m, k = mesh.vertex_count, mesh.face_count, len(log)
    n0 = n - k
    new_id = np.full(n, -1, dtype=np.int64)
    new_id[log.removed] = n - 1 - np.arange(k)
    kept = new_id < 0
    new_id[kept] = np.arange(n0)
    order = np.empty(n, dtype=np.int64)
    order[new_id] = np.arange(n)

    parent = np.full(n, -1, dtype=np.int64)
    parent[n - 1 - np.arange(k)] = new_id[log.survivor]
    # records are indexed by t - n0, i.e. collapse order reversed
    coarse_position = log.position[::-1].copy()
    error = log.error[::-1].copy()

    killed_counts = np.diff(log.killed_offsets)[::-1]          # per split t
    face_order, new_face = split_face_order(log.killed_faces, log.killed_offsets, m)
    base_count = m - len(log.killed_faces)
    face_counts = np.concatenate([[base_count], base_count + np.cumsum(killed_counts)])

    moved_counts = np.diff(log.moved_offsets)
    moved_offsets = np.concatenate([[0], np.cumsum(moved_counts[::-1])]).astype(np.int64)
    # two independent gathers at random, compiled and free of the GIL: at
    # once (``overlap``)
    faces, moved_corners = both(
        lambda: renumbered_faces(mesh.faces, face_order, new_id),
        lambda: reversed_corners(log.moved_corners, log.moved_offsets, new_face))
    # freed before the turned copies and the derived arrays are made
    del new_face, kept, new_id

    appearance = {}
    if mesh.attributes is not None:
        appearance = _renumber_wedges(mesh.attributes, log, face_order)
    # a codec then need not say where each new face starts
    turn = new_face_turns(faces, parent, face_counts, n0)
    # one after the other: each unturned array is freed before the next turned one is made
    faces = turned_rows(faces, turn)
    moved_corners = turned_corners(moved_corners, turn)
    if "corner_wedges" in appearance:
        appearance["corner_wedges"] = turned_rows(appearance["corner_wedges"], turn)
    if mesh.face_material is not None:
        appearance["face_material"] = mesh.face_material[face_order]
    positions = take_rows(mesh.positions, order)
    # the constructor's derived arrays are the last ones made, partly in
    # another thread's malloc arena: the temporaries' pages are returned first
    del turn, face_order, order
    give_back()
    return ProgressiveMesh(
        positions=positions,
        faces=faces,
        parent=parent, base_vertices=n0, coarse_position=coarse_position, error=error,
        face_counts=face_counts.astype(np.int64, copy=False), moved_offsets=moved_offsets,
        moved_corners=moved_corners.astype(np.int64, copy=False), metadata=dict(metadata or {}),
        materials=mesh.materials, split_batch=split_batch, **appearance)


def _renumber_wedges(attributes: Attributes, log: CollapseLog, face_order) -> dict:
    """The wedge arrays of the prefix layout, as ``from_collapse_log`` does for
    vertices: wedges never merged away keep their order as ``0 .. w0-1``, then
    each split's wedges follow in split order."""
    w = attributes.wedge_count
    removed = reverse_blocks(log.merge_removed, log.merge_offsets)
    survivor = reverse_blocks(log.merge_survivor, log.merge_offsets)
    value = reverse_blocks(log.merge_value, log.merge_offsets)
    w0 = w - len(removed)
    new_id = np.full(w, -1, dtype=np.int64)
    new_id[removed] = w0 + np.arange(len(removed))
    kept = new_id < 0
    new_id[kept] = np.arange(w0)
    order = np.empty(w, dtype=np.int64)
    order[new_id] = np.arange(w)
    parent = np.full(w, -1, dtype=np.int64)
    parent[w0:] = new_id[survivor]
    per_split = np.diff(log.merge_offsets)[::-1]
    counts = np.concatenate([[w0], w0 + np.cumsum(per_split)]).astype(np.int64)
    return dict(attribute_layout=attributes.layout,
                wedge_values=take_rows(attributes.values, order),
                corner_wedges=renumbered_faces(attributes.corners, face_order, new_id),
                wedge_parent=parent, wedge_coarse_value=np.ascontiguousarray(value),
                wedge_counts=counts)
