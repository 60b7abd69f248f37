"""Moving a level of a progressive mesh by replaying its records: the compiled
walks of vertex splits (forward) and edge collapses (backward), positions,
faces and wedges in place, and :class:`Cursor`, a level held in arrays and moved
with them. Removed vertices and faces keep their slots, so both directions are
exact. The layout the walks read is :class:`~lodserver.progressive.mesh.ProgressiveMesh`'s
(docs/how-it-works.md); this module does not import it, so that it can make its
cursor."""

from __future__ import annotations

import numpy as np
from numba import njit

from ..mesh import Mesh


@njit(cache=True, nogil=True, inline="always")
def ancestor_below(parent, x, level):
    """The vertex a full-detail corner ``x`` reads at ``level``: its first
    ancestor in the vertex hierarchy below ``level``."""
    while x >= level:
        x = parent[x]
    return x


@njit(cache=True, nogil=True, inline="always")
def _copy_row3(out, i, source, j):
    """``out[i] = source[j]`` for rows of three (a position or a face), unrolled."""
    out[i, 0] = source[j, 0]
    out[i, 1] = source[j, 1]
    out[i, 2] = source[j, 2]


@njit(cache=True, nogil=True, inline="always")
def _relabel(faces, moved_corners, first, last, label):
    """Corners ``moved_corners[first:last]`` (each ``3 * face + slot``) now read ``label``."""
    for k in range(first, last):
        c = moved_corners[k]
        faces[c // 3, c % 3] = label


@njit(cache=True, nogil=True)
def _apply_splits(positions, faces, level, target, base, parent, fine_position, new_position,
                  face_counts, birth_faces, moved_offsets, moved_corners):
    """Replay splits ``level .. target-1`` in place (vertex splits, forward)."""
    for t in range(level, target):
        j = t - base
        s = parent[t]
        _copy_row3(positions, s, fine_position, j)
        _copy_row3(positions, t, new_position, j)
        _relabel(faces, moved_corners, moved_offsets[j], moved_offsets[j + 1], t)
        for f in range(face_counts[j], face_counts[j + 1]):
            _copy_row3(faces, f, birth_faces, f)


@njit(cache=True, nogil=True)
def _apply_wedge_splits(values, corners, level, target, base, wedge_base, wedge_counts,
                        wedge_parent, fine_value, new_value, face_counts, birth_corners,
                        moved_offsets, moved_corners, full_corners):
    """The wedge side of ``_apply_splits``: new wedges appear, their parents
    take their finer values, and moved corners climb to their finer wedges."""
    for t in range(level, target):
        j = t - base
        top = wedge_counts[j + 1]
        for x in range(wedge_counts[j], top):
            i = x - wedge_base
            w = wedge_parent[x]
            for k in range(values.shape[1]):
                values[w, k] = fine_value[i, k]
                values[x, k] = new_value[i, k]
        for k in range(moved_offsets[j], moved_offsets[j + 1]):
            c = moved_corners[k]
            corners[c // 3, c % 3] = ancestor_below(wedge_parent, full_corners[c // 3, c % 3], top)
        for f in range(face_counts[j], face_counts[j + 1]):
            for k in range(3):
                corners[f, k] = birth_corners[f, k]


@njit(cache=True, nogil=True)
def _apply_wedge_collapses(values, corners, level, target, base, wedge_base, wedge_counts,
                           wedge_parent, coarse_value, moved_offsets, moved_corners, full_corners):
    """The wedge side of ``_apply_collapses``: merged wedges' parents take the
    merged values, moved corners climb to their coarser wedges."""
    for t in range(level - 1, target - 1, -1):
        j = t - base
        bottom = wedge_counts[j]
        for x in range(wedge_counts[j + 1] - 1, bottom - 1, -1):
            w = wedge_parent[x]
            for k in range(values.shape[1]):
                values[w, k] = coarse_value[x - wedge_base, k]
        for k in range(moved_offsets[j], moved_offsets[j + 1]):
            c = moved_corners[k]
            corners[c // 3, c % 3] = ancestor_below(wedge_parent, full_corners[c // 3, c % 3],
                                                     bottom)


@njit(cache=True, nogil=True)
def _apply_collapses(positions, faces, level, target, base, parent, coarse_position,
                     moved_offsets, moved_corners):
    """Undo splits ``level-1`` down to ``target`` in place (edge collapses, backward).
    Removed vertices and faces keep their slots; they fall outside the prefix."""
    for t in range(level - 1, target - 1, -1):
        j = t - base
        s = parent[t]
        _copy_row3(positions, s, coarse_position, j)
        _relabel(faces, moved_corners, moved_offsets[j], moved_offsets[j + 1], s)


class Cursor:
    """A level of a progressive mesh held in mutable arrays, moved one split
    or collapse at a time. Removed vertices keep their slots, so going back
    and forth is exact."""

    def __init__(self, pm: ProgressiveMesh, level: int):
        self.pm = pm
        level = pm.check_level(level)
        self.positions = np.empty_like(pm.positions)
        self.faces = np.empty_like(pm.faces)
        p, f = pm.arrays_at(level)
        self.positions[:level] = p
        self.faces[:len(f)] = f
        if pm.has_attributes:
            self.values = np.empty_like(pm.wedge_values)
            self.corners = np.empty_like(pm.corner_wedges)
            v, c = pm.wedges_at(level)
            self.values[:len(v)] = v
            self.corners[:len(c)] = c
        self.level = level

    def seek(self, level: int) -> Cursor:
        """Move to ``level`` by replaying splits (up) or collapses (down)."""
        pm = self.pm
        level = pm.check_level(level)
        if level > self.level:
            _apply_splits(self.positions, self.faces, self.level, level, pm.base_vertices,
                          pm.parent, pm.fine_position, pm.new_position, pm.face_counts,
                          pm.birth_faces, pm.moved_offsets, pm.moved_corners)
            if pm.has_attributes:
                _apply_wedge_splits(self.values, self.corners, self.level, level,
                                    pm.base_vertices, int(pm.wedge_counts[0]), pm.wedge_counts,
                                    pm.wedge_parent, pm.wedge_fine_value, pm.wedge_new_value,
                                    pm.face_counts, pm.birth_corners, pm.moved_offsets,
                                    pm.moved_corners, pm.corner_wedges)
        elif level < self.level:
            _apply_collapses(self.positions, self.faces, self.level, level, pm.base_vertices,
                             pm.parent, pm.coarse_position, pm.moved_offsets, pm.moved_corners)
            if pm.has_attributes:
                _apply_wedge_collapses(self.values, self.corners, self.level, level,
                                       pm.base_vertices, int(pm.wedge_counts[0]), pm.wedge_counts,
                                       pm.wedge_parent, pm.wedge_coarse_value, pm.moved_offsets,
                                       pm.moved_corners, pm.corner_wedges)
        self.level = level
        return self

    def arrays(self):
        """Copies of (positions (v, 3), faces (f, 3)) at the current level."""
        return (self.positions[:self.level].copy(),
                self.faces[:self.pm.faces_at_level(self.level)].copy())

    def wedges(self):
        """Copies of (values (w, d), corners (f, 3)) at the current level; (None, None)
        without attributes."""
        pm = self.pm
        if not pm.has_attributes:
            return None, None
        count = int(pm.wedge_counts[self.level - pm.base_vertices])
        return (self.values[:count].copy(), self.corners[:pm.faces_at_level(self.level)].copy())

    def mesh(self) -> Mesh:
        return self.pm.mesh_of(*self.arrays(), *self.wedges())
