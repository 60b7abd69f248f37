"""The progressive mesh: a base mesh plus an ordered list of vertex splits.

Layout (Hoppe 1996, renumbered so that every level is a prefix):

- Vertices are numbered so the base mesh holds ids ``0 .. n0-1`` and the split
  that raises the vertex count from ``v`` to ``v + 1`` introduces vertex ``v``.
  A level is named by its vertex count ``v`` in ``[n0, n]``; it uses
  ``positions[:v]``.
- Faces are numbered so the base faces come first and each split appends the
  faces it creates; level ``v`` uses the first ``face_counts[v - n0]`` faces.
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
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit

from .decimate import CollapseLog
from .mesh import Mesh


@njit(cache=True, nogil=True, inline="always")
def _ancestor_below(parent, x, level):
    """The vertex a full-detail corner ``x`` reads at ``level``: its first
    ancestor in the vertex hierarchy below ``level``."""
    while x >= level:
        x = parent[x]
    return x


@njit(cache=True, nogil=True)
def _faces_at(full_faces, parent, face_count, level, out):
    """Corners of the first ``face_count`` faces at level ``level``."""
    for f in range(face_count):
        for k in range(3):
            out[f, k] = _ancestor_below(parent, full_faces[f, k], level)


@njit(cache=True, nogil=True)
def _positions_at(full_positions, coarse_position, child_offsets, children, base, level, out):
    """Positions of vertices ``0 .. level-1`` at ``level``.

    A vertex's position is the one left by its most recent collapse that is
    applied at this level: the smallest child ``t >= level`` (collapses are
    applied from ``n-1`` down to ``level``). Children lists are sorted.
    """
    for x in range(level):
        lo = child_offsets[x]
        hi = child_offsets[x + 1]
        # binary search for the first child >= level
        while lo < hi:
            mid = (lo + hi) >> 1
            if children[mid] < level:
                lo = mid + 1
            else:
                hi = mid
        if lo < child_offsets[x + 1]:
            t = children[lo]
            out[x, 0] = coarse_position[t - base, 0]
            out[x, 1] = coarse_position[t - base, 1]
            out[x, 2] = coarse_position[t - base, 2]
        else:
            out[x, 0] = full_positions[x, 0]
            out[x, 1] = full_positions[x, 1]
            out[x, 2] = full_positions[x, 2]


@njit(cache=True, nogil=True)
def _apply_splits(positions, faces, level, target, base, parent, fine_position, new_position,
                  face_counts, birth_faces, moved_offsets, moved_corners):
    """Replay splits ``level .. target-1`` in place (vertex splits, forward)."""
    for t in range(level, target):
        j = t - base
        s = parent[t]
        positions[s, 0] = fine_position[j, 0]
        positions[s, 1] = fine_position[j, 1]
        positions[s, 2] = fine_position[j, 2]
        positions[t, 0] = new_position[j, 0]
        positions[t, 1] = new_position[j, 1]
        positions[t, 2] = new_position[j, 2]
        for k in range(moved_offsets[j], moved_offsets[j + 1]):
            c = moved_corners[k]
            faces[c // 3, c % 3] = t
        for f in range(face_counts[j], face_counts[j + 1]):
            faces[f, 0] = birth_faces[f, 0]
            faces[f, 1] = birth_faces[f, 1]
            faces[f, 2] = birth_faces[f, 2]


@njit(cache=True, nogil=True)
def _apply_collapses(positions, faces, level, target, base, parent, coarse_position,
                     moved_offsets, moved_corners):
    """Undo splits ``level-1`` down to ``target`` in place (edge collapses, backward).
    Removed vertices and faces keep their slots; they fall outside the prefix."""
    for t in range(level - 1, target - 1, -1):
        j = t - base
        s = parent[t]
        positions[s, 0] = coarse_position[j, 0]
        positions[s, 1] = coarse_position[j, 1]
        positions[s, 2] = coarse_position[j, 2]
        for k in range(moved_offsets[j], moved_offsets[j + 1]):
            c = moved_corners[k]
            faces[c // 3, c % 3] = s


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
        for name in ("positions", "faces", "parent", "coarse_position", "error", "face_counts",
                     "moved_offsets", "moved_corners"):
            getattr(self, name).setflags(write=False)
        self._derive()

    # ---- derived arrays -------------------------------------------------
    def _derive(self):
        n, n0 = self.vertex_count, self.base_vertices
        t = np.arange(n0, n)
        par = self.parent[n0:]
        # children of every vertex, ascending (CSR): the vertex hierarchy
        order = np.argsort(par, kind="stable")     # t is ascending already
        children = t[order]
        child_offsets = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(np.bincount(par, minlength=n), out=child_offsets[1:])

        # fine_position[t]: vs's position just after split t = the position
        # left by vs's next collapse above t (its next child), else its input position.
        sorted_par = par[order]
        next_sibling = np.full(len(t), -1, dtype=np.int64)
        same = sorted_par[1:] == sorted_par[:-1]
        next_sibling[order[:-1][same]] = children[1:][same]
        fine = self.positions[par].copy()
        has = next_sibling >= 0
        fine[has] = self.coarse_position[next_sibling[has] - n0]
        # new_position[t]: t's own position at level t+1 = left by its first child.
        first_child = np.full(n, -1, dtype=np.int64)
        nonempty = child_offsets[1:] > child_offsets[:-1]
        first_child[nonempty] = children[child_offsets[:-1][nonempty]]
        new = self.positions[n0:].copy()
        fc = first_child[n0:]
        new[fc >= 0] = self.coarse_position[fc[fc >= 0] - n0]

        # birth_faces: each face's corners at the first level it appears in.
        birth = np.empty_like(self.faces)
        m0 = int(self.face_counts[0])
        _faces_at(self.faces, self.parent, m0, n0, birth)
        owner = np.repeat(np.arange(n0, n), np.diff(self.face_counts))
        # faces of split t live at level t+1: climb while >= t+1
        _faces_at_levels(self.faces, self.parent, m0, owner + 1, birth)

        derived = dict(children=children, child_offsets=child_offsets, fine_position=fine,
                       new_position=new, birth_faces=birth,
                       level_error=_level_error(self.error))
        for key, value in derived.items():
            value.setflags(write=False)
            object.__setattr__(self, key, value)

    # ---- sizes ----------------------------------------------------------
    @property
    def vertex_count(self) -> int:
        return len(self.positions)

    @property
    def face_count(self) -> int:
        return len(self.faces)

    @property
    def split_count(self) -> int:
        return self.vertex_count - self.base_vertices

    @property
    def levels(self) -> range:
        """Valid levels (vertex counts), coarsest first."""
        return range(self.base_vertices, self.vertex_count + 1)

    def faces_at_level(self, level: int) -> int:
        return int(self.face_counts[self._check_level(level) - self.base_vertices])

    def error_at_level(self, level: int) -> float:
        """Largest collapse error applied to reach ``level``; 0 at full detail."""
        return float(self.level_error[self._check_level(level) - self.base_vertices])

    def _check_level(self, level) -> int:
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
        return Mesh(positions, faces)

    def arrays_at(self, level: int):
        """(positions (v, 3) float64, faces (f, 3) int64) at ``level``, freshly allocated."""
        level = self._check_level(level)
        positions = np.empty((level, 3), dtype=np.float64)
        _positions_at(self.positions, self.coarse_position, self.child_offsets, self.children,
                      self.base_vertices, level, positions)
        faces = np.empty((self.faces_at_level(level), 3), dtype=np.int64)
        _faces_at(self.faces, self.parent, len(faces), level, faces)
        return positions, faces

    def cursor(self, level=None) -> "Cursor":
        """A mutable view at ``level`` (default: the base) that moves by splits and collapses."""
        return Cursor(self, self.base_vertices if level is None else level)

    def summary(self) -> dict:
        """Counts and the error curve at 25 face ratios from 1 to 0.001
        (log-spaced, finest first, repeated levels once), JSON-able."""
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
                "error_curve": curve, "metadata": self.metadata}

    # ---- persistence ----------------------------------------------------
    def save(self, path) -> None:
        from .codec import save_progressive
        save_progressive(self, path)

    @classmethod
    def load(cls, path) -> "ProgressiveMesh":
        from .codec import load_progressive
        return load_progressive(path)


@njit(cache=True, nogil=True)
def _faces_at_levels(full_faces, parent, start, levels, out):
    """Like ``_faces_at`` for faces ``start ..``, each at its own level."""
    for i in range(levels.shape[0]):
        f = start + i
        for k in range(3):
            out[f, k] = _ancestor_below(parent, full_faces[f, k], levels[i])


def _level_error(error):
    """Error at each level v (index v - n0): the worst collapse applied to get
    there, i.e. the max over splits t >= v; 0 at full detail. Non-increasing."""
    out = np.zeros(len(error) + 1, dtype=np.float64)
    if len(error):
        out[:-1] = np.maximum.accumulate(error[::-1])[::-1]
    return out


class Cursor:
    """A level of a progressive mesh held in mutable arrays, moved one split
    or collapse at a time. Removed vertices keep their slots, so going back
    and forth is exact."""

    def __init__(self, pm: ProgressiveMesh, level: int):
        self.pm = pm
        level = pm._check_level(level)
        self.positions = np.empty_like(pm.positions)
        self.faces = np.empty_like(pm.faces)
        p, f = pm.arrays_at(level)
        self.positions[:level] = p
        self.faces[:len(f)] = f
        self.level = level

    def seek(self, level: int) -> "Cursor":
        """Move to ``level`` by replaying splits (up) or collapses (down)."""
        pm = self.pm
        level = pm._check_level(level)
        if level > self.level:
            _apply_splits(self.positions, self.faces, self.level, level, pm.base_vertices,
                          pm.parent, pm.fine_position, pm.new_position, pm.face_counts,
                          pm.birth_faces, pm.moved_offsets, pm.moved_corners)
        elif level < self.level:
            _apply_collapses(self.positions, self.faces, self.level, level, pm.base_vertices,
                             pm.parent, pm.coarse_position, pm.moved_offsets, pm.moved_corners)
        self.level = level
        return self

    def arrays(self):
        """Copies of (positions (v, 3), faces (f, 3)) at the current level."""
        return (self.positions[:self.level].copy(),
                self.faces[:self.pm.faces_at_level(self.level)].copy())

    def mesh(self) -> Mesh:
        return Mesh(*self.arrays())


def _reverse_blocks(values, offsets):
    """Concatenate the blocks ``values[offsets[i]:offsets[i+1]]`` last block
    first, each block keeping its inner order (collapse order -> split order)."""
    counts = np.diff(offsets)
    block = np.repeat(np.arange(len(counts)), counts)
    # element j of block i lands at (total - end of block i) + (j - start of block i)
    destination = (offsets[-1] - offsets[1:])[block] + (np.arange(len(values)) - offsets[:-1][block])
    out = np.empty_like(values)
    out[destination] = values
    return out


def from_collapse_log(mesh: Mesh, log: CollapseLog, metadata=None) -> ProgressiveMesh:
    """Renumber ``mesh`` and its collapse log into the prefix layout.

    The vertex removed by collapse ``i`` (of ``k``) becomes vertex ``n - 1 - i``;
    vertices never removed keep their input order as ``0 .. n0-1``. Faces never
    removed come first, in input order, then each split's faces.
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
    face_alive = np.ones(m, dtype=bool)
    face_alive[log.killed_faces] = False
    base_faces = np.nonzero(face_alive)[0]
    split_faces = _reverse_blocks(log.killed_faces, log.killed_offsets)
    face_order = np.concatenate([base_faces, split_faces]).astype(np.int64)
    new_face = np.empty(m, dtype=np.int64)
    new_face[face_order] = np.arange(m)
    face_counts = np.concatenate([[len(base_faces)], len(base_faces) + np.cumsum(killed_counts)])

    moved_counts = np.diff(log.moved_offsets)
    moved_offsets = np.concatenate([[0], np.cumsum(moved_counts[::-1])]).astype(np.int64)
    moved = _reverse_blocks(log.moved_corners, log.moved_offsets)
    moved_corners = 3 * new_face[moved // 3] + moved % 3

    return ProgressiveMesh(
        positions=np.ascontiguousarray(mesh.positions[order]),
        faces=np.ascontiguousarray(new_id[mesh.faces[face_order]]),
        parent=parent, base_vertices=n0, coarse_position=coarse_position, error=error,
        face_counts=face_counts.astype(np.int64), moved_offsets=moved_offsets,
        moved_corners=moved_corners.astype(np.int64), metadata=dict(metadata or {}))
