"""The collapse log: every collapse, in order, as parallel arrays.

Two forms of one set of columns:

- ``CollapseLog``, what the simplifiers (``collapse.decimate``,
  ``octree.octree_log``) return and ``progressive.from_collapse_log`` turns
  into a progressive mesh: ids of the input mesh, errors in mesh units;
- ``LogColumns``, the edge-collapse kernel's log as it passes between
  ``collapse``, ``parts`` and ``submesh``: the same columns with the kernel's
  ``cost`` and ``area`` in place of ``error`` (``error = sqrt(cost / area)``,
  rescaled), and vertex ids of whichever mesh the kernel ran on.

``LogArrays`` is the kernel's room to write ``LogColumns`` in (the columns
plus their fill counts), ``log_arrays`` the octree kernel's.
"""

from __future__ import annotations

from collections import namedtuple
from dataclasses import dataclass

import numpy as np
from numba import njit


@dataclass(frozen=True)
class CollapseLog:
    """Every collapse, in order; row ``i`` is collapse ``i``. Vertex and face
    ids are those of the input mesh.

    Attributes
    ----------
    survivor : (k,) int64
        The vertex that stays (``vs`` of the split that undoes it).
    removed : (k,) int64
        The vertex that goes (``vt``); it is never used again.
    position : (k, 3) float64
        The survivor's position after the collapse, mesh units.
    error : (k,) float64
        sqrt(Q(p) / area) of the collapse: an RMS distance in mesh units.
    killed_offsets : (k + 1,) int64
        ``killed_faces[killed_offsets[i]:killed_offsets[i+1]]`` are the faces collapse i removes.
    killed_faces : (f,) int64
    moved_offsets : (k + 1,) int64
        ``moved_corners[moved_offsets[i]:moved_offsets[i+1]]`` are the corners
        (``3 * face + slot``) that collapse i relabels from ``removed`` to ``survivor``.
    moved_corners : (c,) int64
    merge_offsets : (k + 1,) int64
        ``merge_*[merge_offsets[i]:merge_offsets[i+1]]`` are the wedge merges of collapse i.
    merge_survivor, merge_removed : (g,) int64
        Wedge ``merge_removed`` (of the removed vertex) merges into
        ``merge_survivor`` (of the survivor); the removed wedge is never used again.
    merge_value : (g, d) float64
        The survivor wedge's attribute vector after the merge (input units).
    rejected : dict
        How many popped candidates were refused, by reason
        (``simplify.rules.REJECT_REASONS``).
    passes : int
    """

    survivor: np.ndarray
    removed: np.ndarray
    position: np.ndarray
    error: np.ndarray
    killed_offsets: np.ndarray
    killed_faces: np.ndarray
    moved_offsets: np.ndarray
    moved_corners: np.ndarray
    rejected: dict
    passes: int
    merge_offsets: np.ndarray | None = None
    merge_survivor: np.ndarray | None = None
    merge_removed: np.ndarray | None = None
    merge_value: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.survivor)


@njit(cache=True, nogil=True)
def log_arrays(n, m):
    """Room for the log of at most ``n`` collapses of an ``m``-face mesh:
    survivor, removed, position (n, 3), error, then the killed faces and the
    moved corners of each collapse as offsets (n + 1,) and values. The moved
    corners may outgrow ``3 m`` (a corner moves each time its vertex goes):
    writers grow that array."""
    return (np.empty(n, np.int64), np.empty(n, np.int64), np.empty((n, 3), np.float64),
            np.empty(n, np.float64), np.zeros(n + 1, np.int64), np.empty(m, np.int64),
            np.zeros(n + 1, np.int64), np.empty(3 * m, np.int64))


LogColumns = namedtuple("LogColumns", "survivor removed position cost area killed_offsets "
                                      "killed_faces moved_offsets moved_corners merge_offsets "
                                      "merge_survivor merge_removed merge_value")
LogColumns.__doc__ = """The edge-collapse kernel's log, one row per collapse (``k`` of them), as
it passes between modules (``filled``, ``parts.merge_phases``,
``submesh.map_log``); ``collapse.decimate`` turns it into a ``CollapseLog``.
Vertex, face and corner ids are those of the mesh the kernel ran on; wedge
ids are the input's.

survivor, removed : (k,) int64
    The vertex that stays and the one that goes.
position : (k, 3) float64
    The survivor's position after the collapse, mesh units.
cost : (k,) float64
    The quadric error of the collapse, in the unit box (squared distance
    times area).
area : (k,) float64
    The area the quadric is summed over, in the unit box.
killed_offsets : (k + 1,) int64, killed_faces : (f,) int64
    ``killed_faces[killed_offsets[i]:killed_offsets[i+1]]`` are the faces collapse i removes.
moved_offsets : (k + 1,) int64, moved_corners : (c,) int64
    ``moved_corners[moved_offsets[i]:moved_offsets[i+1]]`` are the corners
    (``3 * face + slot``) collapse i relabels from removed to survivor.
merge_offsets : (k + 1,) int64, merge_survivor, merge_removed : (g,) int64
    The wedge merges of collapse i, as in ``CollapseLog``.
merge_value : (g, d) float64
    The survivor wedge's value after each merge, scaled by sqrt(weight).
"""

# The kernel's room to write its log in: the columns of ``LogColumns``, then
# how many rows of each are filled, ``count[COLLAPSES, KILLED, MOVED, MERGED]``.
LogArrays = namedtuple("LogArrays", LogColumns._fields + ("count",))
COLLAPSES = 0
KILLED = 1
MOVED = 2
MERGED = 3


@njit(cache=True, nogil=True, inline="always")
def new_log(n, m, merges, width):
    """An empty ``LogArrays`` for at most ``n`` collapses of an ``m``-face mesh
    and ``merges`` wedge merges of ``width`` attribute scalars."""
    s, r, p, cost, killed_off, killed, moved_off, moved = log_arrays(n, m)
    return LogArrays(s, r, p, cost, np.empty(n, np.float64), killed_off, killed, moved_off, moved,
                     np.zeros(n + 1, np.int64), np.empty(merges, np.int64),
                     np.empty(merges, np.int64), np.empty((merges, width), np.float64),
                     np.zeros(4, np.int64))


@njit(cache=True, nogil=True, inline="always")
def filled(log):
    """The filled prefix of every column of ``log`` (views), as ``LogColumns``."""
    nk = log.count[COLLAPSES]
    nm = log.count[MERGED]
    return LogColumns(log.survivor[:nk], log.removed[:nk], log.position[:nk], log.cost[:nk],
                      log.area[:nk], log.killed_offsets[:nk + 1],
                      log.killed_faces[:log.count[KILLED]], log.moved_offsets[:nk + 1],
                      log.moved_corners[:log.count[MOVED]],
                      log.merge_offsets[:nk + 1], log.merge_survivor[:nm],
                      log.merge_removed[:nm], log.merge_value[:nm])


@njit(cache=True, nogil=True)
def with_room_for_moves(log, k):
    """``log`` with room for ``k`` more moved corners (a new ``LogArrays``
    only if ``moved_corners`` had to grow): a corner moves each time its vertex goes,
    so the total can outgrow ``3 m``."""
    need = log.count[MOVED] + k
    if need <= log.moved_corners.shape[0]:
        return log
    moved = np.empty(max(need, 2 * log.moved_corners.shape[0]), np.int64)
    moved[:log.count[MOVED]] = log.moved_corners[:log.count[MOVED]]
    return LogArrays(log.survivor, log.removed, log.position, log.cost, log.area,
                     log.killed_offsets, log.killed_faces, log.moved_offsets, moved,
                     log.merge_offsets, log.merge_survivor, log.merge_removed, log.merge_value,
                     log.count)
