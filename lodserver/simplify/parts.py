"""Partitioned decimation: the cheap bulk of the collapses on every core.

A greedy collapse order is sequential, but two collapses far apart touch
disjoint data and commute. So the mesh is cut into ``parts`` parts of equal
vertex count (median cuts along the longest side, recursively); every
vertex of a face that straddles a cut, and every neighbour of such a vertex,
is *frozen*; and each part is decimated by its own kernel
(``collapse._decimate_kernel`` with the part's label) on its own dense copy
(``simplify.submesh``), as many at once as there are threads. A collapse of
a part then only reads and writes vertices, faces and wedges that no other
part's collapse touches (the two rings of frozen vertices are what makes the
faces and counters of the vertices opposite an edge private too), so the
parts need no locks and each part's result does not depend on how the
threads are scheduled.

The parts' logs are merged into one order by their keys (each log's running
maximum, so that every log keeps its own order, which its collapses depend
on; ties go to the lower part). Collapses of different parts commute, so
the merged log is a valid sequence and its prefixes are the levels.

A frozen strip stays at the resolution its phase started with, so the run
goes in short phases (``PHASES``), each cutting the live mesh anew, every
other one along a turned frame so that its cuts cross the last phase's
strips instead of lying on them; a level taken during a phase has the last
strips already decimated and the phase's own at most a few times finer than
the mesh around them. One whole-mesh kernel, on a dense copy too, builds the
last 3% or so of the hierarchy (0.6 x 0.25 x 0.2, and the last strips).

The result depends on ``parts``, not on the number of threads that run them:
the same mesh gives the same artefact on every machine.

``memory_order`` is the other half of locality: a Morton renumbering of a
large mesh's vertices, so that the rows a collapse reads lie close in memory
(and a part's vertices in a few ranges of it, which its copy keeps in order).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ..heap import give_back
from .log import LogColumns

# Parts of a partitioned run: as many as give each part about PART_VERTICES
# vertices (a power of two, at least 2, at most MAX_PARTS), so that a part's
# dense copy stays about as large, near cache size, whatever the mesh's
# size: a collapse on rows that fit in cache is cheaper than one on a large
# mesh's shared arrays (``simplify.submesh``), and a fixed part count would
# make the time per face grow with the mesh. The count depends on the mesh
# alone, never on the machine's cores, so the artefact is the same
# everywhere.
PART_VERTICES = 70_000
MAX_PARTS = 256
# Meshes with fewer vertices are decimated whole: threads would gain little,
# and a small mesh's artefact is that of the plain whole-mesh kernel.
PARALLEL_MIN_VERTICES = 100_000
# The phases of a partitioned run: each cuts the live mesh anew into
# ``parts // divisor`` parts (``turned``: along the axes of a turned frame,
# so that its cuts cross the previous phase's instead of lying along them,
# and the strip that phase left at its resolution is decimated inside the
# parts) and decimates every part down to ``fraction`` of its live vertices.
# The rest of the hierarchy is built by one whole-mesh kernel.
#
# A phase's strip waits at the resolution the phase started with, so the
# phases are short, and the last one has few cuts: a strip is two rings of
# the live mesh wide, so the coarser the mesh, the more of it a strip holds.
# Many cuts late in the hierarchy leave its coarse levels with a larger share
# of vertices held back at a finer resolution, which costs surface error; so
# the last phase cuts into fewer parts.
PHASES = ((False, 0.6, 1), (True, 0.25, 1), (False, 0.2, 4))
# Label of a frozen vertex (in no part).
FROZEN = -1
# Meshes with this many vertices or more are decimated with their vertices
# renumbered along a Morton curve (``memory_order``): past a few tens of MB
# the kernel's per-vertex rows (quadrics, positions, corner lists) no longer
# fit in cache, and the neighbours a collapse reads then sit on the same or
# nearby cache lines and pages. Smaller meshes fit in cache and are
# decimated in their input order.
REORDER_MIN_VERTICES = 100_000
# Bits per axis of the Morton code (3 x 21 = 63 bits of an int64).
_MORTON_BITS = 21


@njit(cache=True, nogil=True, inline="always")
def _spread_bits(x):
    """The low 21 bits of ``x`` (uint64) moved to every third bit."""
    x &= np.uint64(0x1FFFFF)
    x = (x | (x << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
    x = (x | (x << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
    x = (x | (x << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
    x = (x | (x << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
    x = (x | (x << np.uint64(2))) & np.uint64(0x1249249249249249)
    return x


@njit(cache=True, nogil=True)
def _bounds(positions):
    """(lo (3,), hi (3,), all finite) of ``positions`` (n, 3), n > 0, in one
    pass (numpy's column reductions of an (n, 3) array read it six times)."""
    lo = positions[0].copy()
    hi = positions[0].copy()
    finite = True
    for i in range(positions.shape[0]):
        for j in range(3):
            x = positions[i, j]
            finite &= np.isfinite(x)
            lo[j] = min(lo[j], x)
            hi[j] = max(hi[j], x)
    return lo, hi, finite


@njit(cache=True, nogil=True)
def _morton_codes(positions, lo, scale):
    """(n,) uint64 Morton code of every position: its cell ``(p - lo) * scale``
    (truncated), the bits of x, y and z interleaved."""
    code = np.empty(positions.shape[0], np.uint64)
    for i in range(positions.shape[0]):
        c = np.uint64(0)
        for j in range(3):
            cell = np.uint64(np.int64((positions[i, j] - lo[j]) * scale))
            c |= _spread_bits(cell) << np.uint64(j)
        code[i] = c
    return code


def memory_order(positions):
    """A renumbering of the vertices along a Morton (Z-order) curve.

    Parameters
    ----------
    positions : (n, 3) float64

    Returns
    -------
    order : (n,) int64 or None
        ``order[new] = old``: vertices close in space get close ids. Ties keep
        the input order, so the result is deterministic. None when a
        position is not finite (nothing to order by; the caller's checks
        report it).
    """
    positions = np.ascontiguousarray(positions, dtype=np.float64)
    if len(positions) == 0:
        return None
    lo, hi, finite = _bounds(positions)
    if not finite:
        return None
    span = float((hi - lo).max())
    scale = (2**_MORTON_BITS - 1) / span if span > 0 else 0.0
    return np.argsort(_morton_codes(positions, lo, scale), kind="stable")


@njit(cache=True, nogil=True)
def renumbered(faces, new_id):
    """``new_id[faces]`` (m, 3) int64, in one compiled pass."""
    out = np.empty((faces.shape[0], 3), np.int64)
    for f in range(faces.shape[0]):
        for k in range(3):
            out[f, k] = new_id[faces[f, k]]
    return out


# The turned frame of a ``turned`` phase: a rotation by 45 degrees about z,
# then by atan(1/sqrt(2)) about x, so that no cut plane of one frame is
# parallel to a cut plane of the other.
_TURN = (np.array([[1.0, 0.0, 0.0],
                   [0.0, np.sqrt(2.0 / 3.0), -np.sqrt(1.0 / 3.0)],
                   [0.0, np.sqrt(1.0 / 3.0), np.sqrt(2.0 / 3.0)]])
         @ np.array([[np.sqrt(0.5), -np.sqrt(0.5), 0.0],
                     [np.sqrt(0.5), np.sqrt(0.5), 0.0],
                     [0.0, 0.0, 1.0]]))


def default_parts(n):
    """The parts of a partitioned run of a mesh of ``n`` vertices (1: whole)."""
    if n < PARALLEL_MIN_VERTICES:
        return 1
    return int(min(MAX_PARTS, max(2, 2 ** round(np.log2(n / PART_VERTICES)))))


def phase_parts(parts, divisor):
    """The parts of a phase of ``PHASES`` in a run of ``parts`` parts."""
    return max(1, parts // divisor)


def kernel_count(parts):
    """How many kernels a run of ``parts`` parts starts (each has a progress counter)."""
    return 1 if parts == 1 else sum(phase_parts(parts, d) for _, _, d in PHASES) + 1


def partition(positions, faces, alive, parts, turned=False):
    """Label every vertex with its part, or FROZEN.

    Parameters
    ----------
    positions : (n, 3) float64
    faces : (m, 3) int64
    alive : (n,) bool
        Vertices with faces; the others are labelled FROZEN.
    parts : int
        A power of two: the vertices are halved ``log2(parts)`` times, each
        time at the median along the longest side of the half's bounding box.
    turned : bool
        Cut along the axes of the turned frame ``_TURN`` instead.

    Returns
    -------
    label : (n,) int32
        The part of every vertex, FROZEN for the vertices of a face whose
        vertices lie in different parts and for their neighbours.
    """
    if parts < 1 or parts & (parts - 1):
        raise ValueError(f"parts must be a power of two, got {parts}")
    n = len(positions)
    if turned:
        positions = np.ascontiguousarray(positions @ _TURN.T)
    label = np.full(n, FROZEN, dtype=np.int32)
    groups = [np.nonzero(alive)[0]]
    while len(groups) < parts:
        halves = []
        for group in groups:
            axis = _longest_side(positions, group)
            # a selection, not a sort (O(n)); deterministic, ties included
            half = len(group) // 2
            order = group[np.argpartition(positions[group, axis], half)] if half else group
            halves += [order[:half], order[half:]]
        groups = halves
    for part, group in enumerate(groups):
        label[group] = part
    _freeze(np.ascontiguousarray(faces), label)
    return label


# Vertices of a group sampled to find its longest side: the box of an even
# sample of a surface is its box to within a sample's spacing, and reading
# every vertex of a large mesh at random is a cache miss per vertex.
_SIDE_SAMPLE = 65_536


@njit(cache=True, nogil=True)
def _longest_side(positions, group):
    """The axis (0, 1 or 2) along which the bounding box of ``positions[group]``
    is longest (the first of equals; 0 for an empty group), from at most about
    ``_SIDE_SAMPLE`` of them evenly spread through ``group``. One pass,
    where numpy's column reductions of a narrow (n, 3) array would make one
    strided pass per column and a gathered copy first."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for i in range(0, group.shape[0], max(1, group.shape[0] // _SIDE_SAMPLE)):
        for j in range(3):
            x = positions[group[i], j]
            lo[j] = min(lo[j], x)
            hi[j] = max(hi[j], x)
    axis = 0
    for j in range(1, 3):
        if hi[j] - lo[j] > hi[axis] - lo[axis]:
            axis = j
    return axis


@njit(cache=True, nogil=True)
def _freeze(faces, label):
    """Label FROZEN, in place, every vertex of a face whose vertices lie in
    different parts, and every neighbour of such a vertex (the second ring:
    a collapse's opposite vertices are then never frozen ones, whose face
    counts and wedges two parts would both update)."""
    first = np.zeros(label.shape[0], np.bool_)
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        if label[a] != label[b] or label[a] != label[c]:
            first[a] = True
            first[b] = True
            first[c] = True
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        if first[a] or first[b] or first[c]:
            label[a] = FROZEN
            label[b] = FROZEN
            label[c] = FROZEN


@njit(cache=True, nogil=True)
def _gather_blocks(values, offsets, order):
    """Blocks ``values[offsets[i]:offsets[i+1]]`` in the row order ``order``:
    (values, offsets) of the reordered blocks; ``values`` is 1-D. One pass
    and no temporaries (numpy's repeat-and-index builds index arrays as
    long as ``values``)."""
    new_offsets = np.empty(order.shape[0] + 1, np.int64)
    new_offsets[0] = 0
    for i in range(order.shape[0]):
        row = order[i]
        new_offsets[i + 1] = new_offsets[i] + offsets[row + 1] - offsets[row]
    out = np.empty(new_offsets[-1], values.dtype)
    for i in range(order.shape[0]):
        row = order[i]
        at = new_offsets[i]
        for x in range(offsets[row], offsets[row + 1]):
            out[at] = values[x]
            at += 1
    return out, new_offsets


def merge_logs(columns, keys, tail=None):
    """One log from the parts' logs, merged by key, then ``tail`` appended.

    Parameters
    ----------
    columns : list of LogColumns
        Every part's filled log (``simplify.log.filled``).
    keys : list of (k_i,) float64
        The queue key of each part's collapses, in its order.
    tail : LogColumns, optional
        A log that follows all of them.

    Returns
    -------
    LogColumns
        The merged log.
    """
    return merge_phases([(columns, keys)], tail)


def merge_phases(phases, tail=None):
    """One log from phases run one after another: each phase's parts' logs
    merged by key (as ``merge_logs``), the phases in order, then ``tail``.
    ``phases`` is a list of (columns, keys) as ``merge_logs`` takes them.
    One gather of every column, whatever the number of phases; the tail is
    appended (``concatenate_logs``), so that the phases can be merged while
    the tail is still being built. ``phases`` is emptied: each column of the
    parts' logs is freed once gathered (if nothing else holds it)."""
    logs, order, start = [], [], 0
    for columns, keys in phases:
        # a running maximum keeps each part's own order under a stable sort
        envelope = [np.maximum.accumulate(k) if len(k) else k for k in keys]
        by_key = np.argsort(np.concatenate(envelope), kind="stable") if envelope else []
        order.append(start + np.asarray(by_key, dtype=np.int64))
        logs += [dict(log._asdict()) for log in columns]
        start += sum(len(k) for k in keys)
    phases.clear()
    merged = _take(logs, np.concatenate(order))
    return merged if tail is None else concatenate_logs([merged, tail])


# The columns with one entry per collapse, and the block columns (values
# ``killed_faces[killed_offsets[i]:killed_offsets[i + 1]]`` per collapse i) with
# their offsets; the three merge columns share ``merge_offsets``.
_ROWS = ("survivor", "removed", "position", "cost", "area")
_MERGE_VALUES = ("merge_survivor", "merge_removed", "merge_value")


def concatenate_logs(logs):
    """The logs ``logs`` (a list of ``LogColumns``) one after another, as one
    ``LogColumns``. ``logs`` is emptied: each column of the inputs is freed
    once it is joined (if nothing else holds it), so the join needs room for
    one column twice, not for the whole log twice."""
    columns = [dict(log._asdict()) for log in logs]
    logs.clear()
    joined = {}
    for values, offsets in (("killed_faces", "killed_offsets"), ("moved_corners", "moved_offsets"),
                            ("merge_survivor", "merge_offsets")):
        joined[values], joined[offsets] = _concatenate_blocks(columns, offsets, values)
        for log in columns:
            del log[values], log[offsets]
    for name in _ROWS + _MERGE_VALUES[1:]:
        joined[name] = np.concatenate([log.pop(name) for log in columns])
    return LogColumns(**joined)


def _take(logs, order):
    """The rows ``order`` of the logs ``logs`` (dicts of ``LogColumns``'
    columns) put one after another, as ``LogColumns``. Each column is taken
    out of the dicts as it is gathered and its memory given back (the parts'
    logs were made in the worker threads' arenas, which this thread's
    gathers cannot reuse; ``heap``), so the merge needs room for the log
    and one column, not for the log twice."""
    def joined(name):
        return np.concatenate([log.pop(name) for log in logs])

    rows = {name: joined(name)[order] for name in _ROWS}
    give_back()
    killed, killed_offsets = _gather_blocks(
        *_concatenate_blocks(logs, "killed_offsets", "killed_faces"), order)
    for log in logs:
        del log["killed_offsets"], log["killed_faces"]
    give_back()
    moved, moved_offsets = _gather_blocks(
        *_concatenate_blocks(logs, "moved_offsets", "moved_corners"), order)
    for log in logs:
        del log["moved_offsets"], log["moved_corners"]
    give_back()
    # the three merge columns share offsets: gather an index once
    merges, merge_offsets = _concatenate_blocks(logs, "merge_offsets", "merge_survivor")
    index, merge_offsets = _gather_blocks(np.arange(len(merges)), merge_offsets, order)
    merge_survivor, merge_removed, merge_value = (joined(name)[index] for name in _MERGE_VALUES)
    return LogColumns(**rows, killed_offsets=killed_offsets, killed_faces=killed,
                      moved_offsets=moved_offsets, moved_corners=moved, merge_offsets=merge_offsets,
                      merge_survivor=merge_survivor, merge_removed=merge_removed,
                      merge_value=merge_value)


def _concatenate_blocks(logs, offsets_name, values_name):
    """(values, offsets) of the block column ``values_name`` of every log
    (``LogColumns`` or dicts of their columns), one after another (its offsets
    ``offsets_name`` shifted to match)."""
    logs = [log if isinstance(log, dict) else log._asdict() for log in logs]
    offsets, shift = [], 0
    for log in logs:
        column = log[offsets_name]
        offsets.append(column[:-1] + shift)
        shift += int(column[-1])
    offsets.append(np.array([shift], dtype=np.int64))
    return np.concatenate([log[values_name] for log in logs]), np.concatenate(offsets)
