"""Partitioned decimation: the cheap bulk of the collapses on every core.

A greedy collapse order is sequential, but two collapses far apart touch
disjoint data and commute. So the mesh is cut into ``parts`` slabs of equal
vertex count (median cuts along the longest side, recursively); every
vertex of a face that straddles a cut, and every neighbour of such a vertex,
is *frozen*; and each part is decimated by its own kernel in its own thread
(``collapse._decimate_kernel`` with the part's label) down to
``TAIL_FRACTION`` of its vertices. A collapse of a part then only reads and
writes vertices, faces and wedges that no other part's collapse touches
(the two rings of frozen vertices are what makes the faces and counters of
the vertices opposite an edge private too), so the parts need no locks and
each part's result does not depend on how the threads are scheduled.

The parts' logs are merged into one order by their keys (each log's running
maximum, so that every log keeps its own order, which its collapses depend
on; ties go to the lower part). Collapses of different parts commute, so
the merged log is a valid sequence and its prefixes are the levels. The
frozen strip and the rest are then decimated by one whole-mesh kernel, which
starts with the strip's cheap collapses: a level taken during the parts'
phase has the strip at full resolution, a fraction of a percent of its
vertices.

The result depends on ``parts``, not on the number of threads that run them:
the same mesh gives the same artefact on every machine.

``memory_order`` is the other half of locality: a Morton renumbering of a
large mesh's vertices, so that the rows a collapse reads lie close in memory
(and a part's vertices in a few ranges of it).
"""

from __future__ import annotations

import numpy as np

# Parts of a partitioned run (a fixed number, so that the artefact does not
# depend on the machine's core count; a power of two).
DEFAULT_PARTS = 2
# Meshes with fewer vertices are decimated whole: threads would gain little,
# and small meshes keep the artefacts they always had.
PARALLEL_MIN_VERTICES = 100_000
# Each part is decimated down to this fraction of its vertices; the rest of
# the hierarchy is built by the whole-mesh kernel. Lower gives the parts
# more of the work; the frozen strip is at full resolution until then.
TAIL_FRACTION = 0.15
# Label of a frozen vertex (in no part).
FROZEN = -1
# Meshes with this many vertices or more are decimated with their vertices
# renumbered along a Morton curve (``memory_order``): past a few tens of MB
# the kernel's per-vertex rows (quadrics, positions, corner lists) no longer
# fit in cache, and the neighbours a collapse reads then sit on the same or
# nearby cache lines and pages (1.1M bunny: about 15% less CPU time).
# Smaller meshes fit in cache and keep the artefacts they always had.
REORDER_MIN_VERTICES = 100_000
# Bits per axis of the Morton code (3 x 21 = 63 bits of an int64).
_MORTON_BITS = 21


def _spread_bits(x):
    """(k,) uint64 with the low 21 bits of ``x`` moved to every third bit."""
    x = x.astype(np.uint64) & np.uint64(0x1FFFFF)
    for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                        (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


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
    positions = np.asarray(positions, dtype=np.float64)
    if len(positions) == 0 or not np.isfinite(positions).all():
        return None
    lo = positions.min(axis=0)
    span = float((positions.max(axis=0) - lo).max())
    scale = (2**_MORTON_BITS - 1) / span if span > 0 else 0.0
    cells = ((positions - lo) * scale).astype(np.int64)
    code = (_spread_bits(cells[:, 0]) | (_spread_bits(cells[:, 1]) << np.uint64(1))
            | (_spread_bits(cells[:, 2]) << np.uint64(2)))
    return np.argsort(code, kind="stable")


def partition(positions, faces, alive, parts):
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

    Returns
    -------
    label : (n,) int32
        The part of every vertex, FROZEN for the vertices of a face whose
        vertices lie in different parts and for their neighbours.
    """
    if parts < 1 or parts & (parts - 1):
        raise ValueError(f"parts must be a power of two, got {parts}")
    n = len(positions)
    label = np.full(n, FROZEN, dtype=np.int32)
    groups = [np.nonzero(alive)[0]]
    while len(groups) < parts:
        halves = []
        for group in groups:
            points = positions[group]
            axis = int(np.argmax(points.max(axis=0) - points.min(axis=0))) if len(group) else 0
            # a selection, not a sort (O(n)); deterministic, ties included
            half = len(group) // 2
            order = group[np.argpartition(points[:, axis], half)] if half else group
            halves += [order[:half], order[half:]]
        groups = halves
    for part, group in enumerate(groups):
        label[group] = part
    corner = label[faces]
    straddles = (corner != corner[:, :1]).any(axis=1)
    frozen = np.zeros(n, dtype=bool)
    frozen[faces[straddles].ravel()] = True
    # the second ring: a collapse's opposite vertices are then never frozen
    # ones, whose face counts and wedges two parts would both update
    frozen[faces[frozen[faces].any(axis=1)].ravel()] = True
    label[frozen] = FROZEN
    return label


def _gather_blocks(values, offsets, order):
    """Blocks ``values[offsets[i]:offsets[i+1]]`` in the row order ``order``:
    (values, offsets) of the reordered blocks."""
    counts = np.diff(offsets)[order]
    new_offsets = np.zeros(len(order) + 1, dtype=np.int64)
    np.cumsum(counts, out=new_offsets[1:])
    index = np.repeat(offsets[:-1][order] - new_offsets[:-1], counts) + np.arange(new_offsets[-1])
    return values[index], new_offsets


def merge_logs(columns, keys, tail=None):
    """One log from the parts' logs, merged by key, then ``tail`` appended.

    Parameters
    ----------
    columns : list of tuples
        Every part's filled log columns (``simplify.log.filled``): survivor,
        removed, position, cost, area, killed_offsets, killed, moved_offsets,
        moved, merge_offsets, merge_survivor, merge_removed, merge_value.
    keys : list of (k_i,) float64
        The queue key of each part's collapses, in its order.
    tail : tuple, optional
        Columns of a log that follows all of them.

    Returns
    -------
    The merged columns, in the same layout.
    """
    logs = list(columns) + ([tail] if tail is not None else [])
    # a running maximum keeps each part's own order under a stable sort
    envelope = [np.maximum.accumulate(k) if len(k) else k for k in keys]
    order = np.argsort(np.concatenate(envelope), kind="stable")
    if tail is not None:
        order = np.concatenate([order, len(order) + np.arange(len(tail[0]))])
    rows = [np.concatenate([log[i] for log in logs])[order] for i in range(5)]
    killed, killed_offsets = _gather_blocks(*_concatenate_blocks(logs, 5, 6), order)
    moved, moved_offsets = _gather_blocks(*_concatenate_blocks(logs, 7, 8), order)
    # the three merge columns share offsets: gather an index once
    merges, merge_offsets = _concatenate_blocks(logs, 9, 10)
    index, merge_offsets = _gather_blocks(np.arange(len(merges)), merge_offsets, order)
    merge_s, merge_r, merge_v = (np.concatenate([log[i] for log in logs])[index]
                                 for i in (10, 11, 12))
    return (*rows, killed_offsets, killed, moved_offsets, moved, merge_offsets, merge_s, merge_r,
            merge_v)


def _concatenate_blocks(logs, at_offsets, at_values):
    """(values, offsets) of the block column ``at_values`` of every log, one
    after another (offsets shifted to match)."""
    offsets, shift = [], 0
    for log in logs:
        offsets.append(log[at_offsets][:-1] + shift)
        shift += int(log[at_offsets][-1])
    offsets.append(np.array([shift], dtype=np.int64))
    return np.concatenate([log[at_values] for log in logs]), np.concatenate(offsets)
