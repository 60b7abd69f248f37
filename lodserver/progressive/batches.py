"""Splits in batches of independent ones (Pajarola & Rossignac's compressed
progressive meshes), by re-ordering a progressive mesh's recorded collapses.

Independent collapses commute, so the collapse log can be re-ordered after
the fact without running the simplifier again: the full and base meshes stay
the same, the levels in between change.

**Dependencies.** Replayed from full detail in the recorded order, collapse
``i`` (vertex ``r`` into ``s``) *reads* the faces around ``s`` and ``r`` (the
legality checks look at nothing else: link condition, border rule, normal
flips, wedges) and *touches* the faces it kills, moves or moves ``s`` within;
it also changes the face counts of the vertices of the faces it kills (the
"vertex left without faces" rule reads them). Collapse ``j`` depends on the
last earlier collapse that touched any face it reads, and on the last that
changed the face count of any vertex of a face it kills. Every order that
keeps these dependencies (a linear extension of the graph) shows every
collapse exactly the faces it saw when the simplifier chose it, so every
level of the re-ordered mesh is as valid as the recorded ones and ends in the
same state.

**Batches.** Going coarse to fine, a batch is every split whose predecessors
(the collapses that depend on it) are in earlier batches and whose recorded
place lies within reach of the first split not yet scheduled, ``P``: at most
``window`` times the current level size ahead, and no further than where the
level error curve (the worst collapse still applied) falls below
``error_ratio`` times its value at ``P``. A split thus moves at most that far
from its place in cost order, either way (``P`` is always ready, so a
waiting split is placed once ``P`` reaches it), and a level keeps the splits
the greedy order gave it but for some of nearly the same error: where errors
fall steeply (a CAD part's last sharp features) the reach shrinks to a few
splits, where they are flat it spans the window.

No two splits of a batch are joined by a path, so they read disjoint faces:
their split vertices are pairwise non-adjacent at the batch's start level,
and none references a vertex another creates or moves. Within a batch splits
are ordered by ascending split vertex (its id at the batch's start), the
order a decoder that reads one mark per vertex recovers; vertices are
renumbered so split ``t`` still creates vertex ``t``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from ..mesh import Attributes, Mesh
from .mesh import ProgressiveMesh, from_collapse_log

__all__ = ["Schedule", "schedule", "collapse_dependencies", "batch_order", "WINDOW",
           "ATTRIBUTE_WINDOW", "ERROR_RATIO"]

# How far (a fraction of the level's vertex count) a split may move ahead of
# the first split not yet scheduled: the trade between batch size (marks cost
# about log2(e N / k) bits a split) and how far a level strays from the
# greedy cost order. Tuned on bench/batches.py (bench/README.md): wider
# windows let some bench levels stray further from the greedy order's
# fidelity than the issue allows.
WINDOW = 0.1
# ... and with attributes: the level error is geometric while the greedy order
# ranks geometric and attribute error together, so the error reach below does
# not see attribute costs; measured, the attribute figures of a level stray
# less with the narrower window.
ATTRIBUTE_WINDOW = 0.05
# ... and no further than where the level error falls below this share of its
# value there, so no split of a distinctly larger error waits behind it.
ERROR_RATIO = 0.95


@dataclass(frozen=True)
class Schedule:
    """A progressive mesh whose splits come in batches of independent ones.

    pm : ProgressiveMesh
        The re-ordered mesh: same full and base meshes, split ``t`` creates vertex ``t``.
    batch : (k,) int32
        The batch of every split, non-decreasing in split order.
    order : (k,) int64
        The split of the unbatched mesh each split is: split ``n0 + p`` here
        creates the vertex that split ``n0 + order[p]`` created there.
    """

    pm: ProgressiveMesh
    batch: np.ndarray
    order: np.ndarray

    @property
    def batch_starts(self) -> np.ndarray:
        """(b + 1,) int64: split indices where each batch starts, then ``k``."""
        k = len(self.batch)
        if k == 0:
            return np.zeros(1, dtype=np.int64)
        edges = np.flatnonzero(np.diff(self.batch)) + 1
        return np.concatenate([[0], edges, [k]]).astype(np.int64)


@njit(cache=True, nogil=True, inline="always")
def _listed(preds, count, d, seen, i):
    """``preds`` with collapse ``d`` appended as a predecessor of ``i`` unless
    it is none (-1) or already listed for ``i`` (``seen``); grown when full."""
    if d >= 0 and seen[d] != i:
        seen[d] = i
        if count == preds.shape[0]:
            preds = np.concatenate((preds, np.empty(count, np.int64)))
        preds[count] = d
        count += 1
    return preds, count


@njit(cache=True, nogil=True)
def _dependencies(faces, parent, n0, face_counts, moved_offsets, moved_corners):
    """Replay the collapses (split ``n - 1`` first) and list each one's
    dependencies; see the module docstring. Returns (offsets (k + 1,),
    predecessors) in collapse indices ``i = n - 1 - t``."""
    n = parent.shape[0]
    m = faces.shape[0]
    k = n - n0
    label = faces.copy()
    alive = np.ones(m, np.bool_)
    head = np.full(n, -1, np.int64)
    nxt = np.full(3 * m, -1, np.int64)
    for c in range(3 * m - 1, -1, -1):
        v = label[c // 3, c % 3]
        nxt[c] = head[v]
        head[v] = c
    last_touch = np.full(m, -1, np.int64)
    last_count = np.full(n, -1, np.int64)
    seen = np.full(k, -1, np.int64)
    offsets = np.zeros(k + 1, np.int64)
    preds = np.empty(max(16, 8 * k), np.int64)
    count = 0
    for i in range(k):
        t = n - 1 - i
        j = t - n0
        s = parent[t]
        # faces around r (they are the killed and the moved ones) and s
        for v in (t, s):
            c = head[v]
            head[v] = -1
            while c >= 0:
                after = nxt[c]
                f = c // 3
                if alive[f] and label[f, c % 3] == v:
                    nxt[c] = head[v]
                    head[v] = c
                    preds, count = _listed(preds, count, last_touch[f], seen, i)
                c = after
        for f in range(face_counts[j], face_counts[j + 1]):
            for q in range(3):
                preds, count = _listed(preds, count, last_count[label[f, q]], seen, i)
        # perform: kill, move r's corners to s
        for f in range(face_counts[j], face_counts[j + 1]):
            alive[f] = False
            for q in range(3):
                last_count[label[f, q]] = i
        last_count[s] = i
        last_count[t] = i
        for x in range(moved_offsets[j], moved_offsets[j + 1]):
            c = moved_corners[x]
            label[c // 3, c % 3] = s
            nxt[c] = head[s]
            head[s] = c
        c = head[s]
        while c >= 0:
            if alive[c // 3]:
                last_touch[c // 3] = i
            c = nxt[c]
        head[t] = -1
        offsets[i + 1] = count
    return offsets, preds[:count].copy()


def collapse_dependencies(pm: ProgressiveMesh):
    """The dependency graph of ``pm``'s collapses (module docstring).

    Returns
    -------
    offsets : (k + 1,) int64, predecessors : (e,) int64
        Collapse ``i`` (it undoes split ``t = n - 1 - i``) depends on
        ``predecessors[offsets[i]:offsets[i + 1]]``, each an earlier collapse.
    """
    return _dependencies(pm.faces, pm.parent, pm.base_vertices, pm.face_counts,
                         pm.moved_offsets, pm.moved_corners)


@njit(cache=True, nogil=True)
def _batches(offsets, preds, n0, window, limit):
    """Split order (indices ``u = k - 1 - i`` of the recorded split order) and
    the batch of each, by the reach rule of the module docstring; ``limit[u]``
    (k,) is the end of the error reach from ``u``."""
    k = offsets.shape[0] - 1
    # a split waits for the splits of the collapses that depend on its collapse
    waiting = np.zeros(k, np.int64)
    for i in range(k):
        for x in range(offsets[i], offsets[i + 1]):
            waiting[k - 1 - preds[x]] += 1
    done = np.zeros(k, np.bool_)
    order = np.empty(k, np.int64)
    batch = np.empty(k, np.int32)
    chosen = np.empty(k, np.int64)
    placed = 0
    first = 0
    b = 0
    while placed < k:
        while done[first]:
            first += 1
        top = min(limit[first], first + max(int(window * (n0 + placed)), 1))
        count = 0
        for u in range(first, top):
            if not done[u] and waiting[u] == 0:
                chosen[count] = u
                count += 1
        for x in range(count):
            u = chosen[x]
            done[u] = True
            order[placed] = u
            batch[placed] = b
            placed += 1
        for x in range(count):
            i = k - 1 - chosen[x]
            for y in range(offsets[i], offsets[i + 1]):
                waiting[k - 1 - preds[y]] -= 1
        b += 1
    return order, batch


def batch_order(pm: ProgressiveMesh, window: float | None = None,
                error_ratio: float = ERROR_RATIO):
    """The batched split order of ``pm`` without re-ordering its arrays.

    Returns
    -------
    order : (k,) int64
        ``order[p]`` is the recorded split (``t - n0``) placed at ``p``; within a
        batch ascending by split vertex as numbered after re-ordering.
    batch : (k,) int32
        Non-decreasing batch ids.
    """
    if window is None:
        window = ATTRIBUTE_WINDOW if pm.has_attributes else WINDOW
    if not window >= 0 or not 0 <= error_ratio <= 1:
        raise ValueError(f"window must be >= 0 and error_ratio in [0, 1], got {window}, "
                         f"{error_ratio}")
    offsets, preds = collapse_dependencies(pm)
    # the error of level n0 + u, for split u: non-increasing
    curve = -pm.level_error[:pm.split_count]
    limit = np.searchsorted(curve, error_ratio * curve, side="right").astype(np.int64)
    order, batch = _batches(offsets, preds, pm.base_vertices, float(window), limit)
    return _by_split_vertex(order, batch, pm.parent, pm.base_vertices), batch


def _by_split_vertex(order, batch, parent, n0):
    """``order`` with each batch sorted by its split vertices' new ids: a
    vertex's new id is its split's new place (base vertices keep theirs)."""
    k = len(order)
    new_id = np.arange(n0 + k, dtype=np.int64)
    out = order.copy()
    starts = np.concatenate([[0], np.flatnonzero(np.diff(batch)) + 1, [k]]) if k else [0]
    for a, b in zip(starts[:-1], starts[1:]):
        members = out[a:b]
        # parents of a batch were created in earlier batches: their ids are final
        vs = new_id[parent[n0 + members]]
        members = members[np.argsort(vs, kind="stable")]
        out[a:b] = members
        new_id[n0 + members] = n0 + np.arange(a, b)
    return out


def reordered(pm: ProgressiveMesh, order: np.ndarray, batch=None) -> ProgressiveMesh:
    """``pm`` with its splits in ``order`` (recorded split indices, a linear
    extension of the dependencies), renumbered so split ``t`` creates vertex
    ``t``: the collapse log read back from ``pm`` in the new order, laid out
    again by ``from_collapse_log``; ``batch`` (k,) int32, optional, is kept as
    its ``split_batch``."""
    from ..simplify.log import CollapseLog

    n0 = pm.base_vertices
    # collapse order: the last split placed is collapsed first
    rows = np.asarray(order, dtype=np.int64)[::-1]
    t = n0 + rows

    def blocks(offsets, values):
        counts = np.diff(offsets)[rows]
        starts = offsets[:-1][rows]
        new_offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        index = np.repeat(starts - new_offsets[:-1], counts) + np.arange(new_offsets[-1])
        return new_offsets, values[index]

    killed_offsets, killed = blocks(pm.face_counts - pm.face_counts[0],
                                    np.arange(pm.face_counts[0], pm.face_count, dtype=np.int64))
    moved_offsets, moved = blocks(pm.moved_offsets, pm.moved_corners)
    merges = {}
    attributes = None
    if pm.has_attributes:
        w0 = int(pm.wedge_counts[0])
        merge_offsets, removed = blocks(pm.wedge_counts - w0,
                                        np.arange(w0, len(pm.wedge_values), dtype=np.int64))
        merges = dict(merge_offsets=merge_offsets, merge_removed=removed,
                      merge_survivor=pm.wedge_parent[removed],
                      merge_value=pm.wedge_coarse_value[removed - w0])
        attributes = Attributes(pm.attribute_layout, pm.wedge_values, pm.corner_wedges)
    log = CollapseLog(survivor=pm.parent[t], removed=t, position=pm.coarse_position[rows],
                      error=pm.error[rows], killed_offsets=killed_offsets, killed_faces=killed,
                      moved_offsets=moved_offsets, moved_corners=moved, rejected={}, passes=0,
                      **merges)
    full = Mesh(pm.positions, pm.faces, attributes, pm.face_material, pm.materials)
    return from_collapse_log(full, log, pm.metadata, batch)


def schedule(pm: ProgressiveMesh, window: float | None = None,
             error_ratio: float = ERROR_RATIO) -> Schedule:
    """``pm`` re-ordered into batches of independent splits (module docstring).

    Parameters
    ----------
    pm : ProgressiveMesh
    window : float, optional
        How far a split may move ahead of the first unscheduled one, as a
        fraction of the level's vertex count; None: ``WINDOW``, or
        ``ATTRIBUTE_WINDOW`` for a mesh with attributes.
    error_ratio : float
        In [0, 1]: no further than where the level error falls below this
        share of its value at the first unscheduled split (``ERROR_RATIO``);
        0 leaves only ``window``.

    Returns
    -------
    Schedule
        The re-ordered progressive mesh (its ``split_batch`` the batch ids),
        the batch id of each split and where each split came from.
    """
    order, batch = batch_order(pm, window, error_ratio)
    return Schedule(reordered(pm, order, batch), batch, order)
