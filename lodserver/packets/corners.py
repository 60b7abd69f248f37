"""The encoder's compiled connectivity: corner lists, one vertex's scratch table, the fan.

The reference decoder (``reference.py``) tracks, for every vertex, the *set* of
corners ``3 * face + slot`` that hold it; the kernels here keep the same sets
as arrays (docs/packets.md, "The client's state"):

- ``corners(v)`` is a block of a pool (:func:`corner_lists`), in no order:
  reading a vertex's corners is one or two cache lines, not a chain of
  dependent loads (on a big mesh the records touch vertices all over it, so
  memory latency rules).
- A record copies what it needs about its vertex into a small scratch table
  (:func:`gather`): ``held`` ascending, each corner's next and prev vertex,
  and the neighbours ascending. Ranks are binary searches in it, and the fan
  walk's lookups by next or prev vertex are binary searches over an argsort of
  those columns, so a record costs O(d log d) for a vertex with d corners.
- Each stream is a ``uint8`` buffer with room for its longest possible varints
  (pages never written are never touched) and a used length; :func:`put`
  writes a varint.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .kernel_types import State

# rows of the scratch table
HELD, NEXT, PREV, BY_NEXT, BY_PREV, IN_FAN, MOVED, AROUND = range(8)
SCRATCH_ROWS = 8
# The longest varint: 64 bits in groups of 7.
VARINT_MAX = 10
# Below this many items the kernels sort by insertion.
INSERTION_SORT = 16
# Spare room in a vertex's block of corners at the start, and the smallest new block.
SLACK, BLOCK = 4, 8


@njit(cache=True, nogil=True)
def put(buf, used, value):
    """Write the unsigned varint of ``value >= 0`` at ``buf[used:]`` (the caller
    leaves room for ``VARINT_MAX`` bytes); returns the new used length."""
    while value >= 0x80:
        buf[used] = (value & 0x7F) | 0x80
        used += 1
        value >>= 7
    buf[used] = value
    return used + 1


@njit(cache=True, nogil=True)
def zz(value):
    """Signed -> unsigned, small magnitudes first: 0, -1, 1, -2, ... -> 0, 1, 2, 3, ..."""
    return 2 * value if value >= 0 else -2 * value - 1


@njit(cache=True, nogil=True)
def sort_prefix(a, n):
    """Sort ``a[:n]`` in place."""
    if n > INSERTION_SORT:
        a[:n] = np.sort(a[:n])
        return
    for i in range(1, n):
        x = a[i]
        k = i - 1
        while k >= 0 and a[k] > x:
            a[k + 1] = a[k]
            k -= 1
        a[k + 1] = x


@njit(cache=True, nogil=True)
def argsort_prefix(keys, n, order):
    """``order[:n]``: the indices of ``keys[:n]`` by ascending key (ties in any order)."""
    if n > INSERTION_SORT:
        order[:n] = np.argsort(keys[:n])
        return
    for i in range(n):
        x = i
        k = i - 1
        while k >= 0 and keys[order[k]] > keys[x]:
            order[k + 1] = order[k]
            k -= 1
        order[k + 1] = x


@njit(cache=True, nogil=True)
def search(a, n, x):
    """The first ``i`` in ``[0, n]`` with ``a[i] >= x`` (``a[:n]`` ascending)."""
    lo, hi = 0, n
    while lo < hi:
        mid = (lo + hi) >> 1
        if a[mid] < x:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True, nogil=True)
def lookup(keys, order, n, x):
    """The ``i`` with ``keys[i] == x`` (``keys`` ascending through ``order[:n]``):
    -1 when there is none, -2 when there are several."""
    lo, hi = 0, n
    while lo < hi:
        mid = (lo + hi) >> 1
        if keys[order[mid]] < x:
            lo = mid + 1
        else:
            hi = mid
    if lo == n or keys[order[lo]] != x:
        return -1
    if lo + 1 < n and keys[order[lo + 1]] == x:
        return -2
    return order[lo]


@njit(cache=True, nogil=True)
def distinct_prefix(a, n):
    """Drop repeats from ``a[:n]`` (ascending) in place; returns how many are left."""
    distinct = 0
    for i in range(n):
        if distinct == 0 or a[i] != a[distinct - 1]:
            a[distinct] = a[i]
            distinct += 1
    return distinct


@njit(cache=True, nogil=True)
def corner_lists(positions, faces, face_count):
    """The state over ``positions`` (v, 3) and flat ``faces``, with the corner lists
    of its first ``face_count`` faces: ``(State, pool)``.

    Vertex ``v``'s corners are ``pool[blocks[v, 0] : blocks[v, 0] + blocks[v, 1]]``
    (in no order), in a block of ``blocks[v, 2]`` entries; ``slot[c]`` is corner
    ``c``'s place in its block; ``end[0]`` is the pool's used length. Each block
    starts with some slack, and the pool with room for as much again.
    """
    vertex_capacity = positions.shape[0]
    blocks = np.zeros((vertex_capacity, 3), dtype=np.int64)
    for c in range(3 * face_count):
        blocks[faces[c], 1] += 1
    at = 0
    for v in range(vertex_capacity):
        size = blocks[v, 1]
        blocks[v, 0] = at
        blocks[v, 2] = size + SLACK if size else 0
        blocks[v, 1] = 0
        at += blocks[v, 2]
    pool = np.empty(max(2 * at, 1024), dtype=faces.dtype)
    slot = np.empty(faces.shape[0], dtype=faces.dtype)
    for c in range(3 * face_count):
        v = faces[c]
        k = blocks[v, 1]
        pool[blocks[v, 0] + k] = c
        slot[c] = k
        blocks[v, 1] = k + 1
    end = np.full(1, at, dtype=np.int64)
    return State(positions, faces, blocks, slot, end), pool


# add_corner and remove_corner run several times a record: inlined (numba IR), so
# that the State record is not passed field by field on every call, a real share
# of the encoder's work if they were calls.
@njit(cache=True, nogil=True, inline="always")
def add_corner(state, pool, v, c):
    """Add corner ``c`` to ``corners(v)``, moving the block to the end of the pool
    when full. Returns the pool, grown if needed."""
    blocks, end = state.blocks, state.end
    size = blocks[v, 1]
    if size == blocks[v, 2]:
        room = max(BLOCK, 2 * size)
        if end[0] + room > pool.shape[0]:
            bigger = np.empty(2 * (end[0] + room), dtype=pool.dtype)
            bigger[:end[0]] = pool[:end[0]]
            pool = bigger
        first = blocks[v, 0]
        for k in range(size):
            pool[end[0] + k] = pool[first + k]
        blocks[v, 0] = end[0]
        blocks[v, 2] = room
        end[0] += room
    pool[blocks[v, 0] + size] = c
    state.slot[c] = size
    blocks[v, 1] = size + 1
    return pool


@njit(cache=True, nogil=True, inline="always")
def remove_corner(state, pool, v, c):
    """Remove corner ``c`` from ``corners(v)`` (it must be there): the block's last
    corner takes its slot."""
    blocks, slot = state.blocks, state.slot
    first = blocks[v, 0]
    size = blocks[v, 1] - 1
    last = pool[first + size]
    pool[first + slot[c]] = last
    slot[last] = slot[c]
    blocks[v, 1] = size


@njit(cache=True, nogil=True)
def gather(state, pool, v, scratch):
    """Fill the scratch table for vertex ``v``: ``held(v)`` ascending, the next and
    prev vertex of each, and ``neighbours(v)`` ascending. Returns the (possibly
    grown) table, the number of corners and the number of neighbours."""
    faces = state.faces
    first, d = state.blocks[v, 0], state.blocks[v, 1]
    if 2 * d > scratch.shape[1]:
        scratch = np.empty((SCRATCH_ROWS, 2 * max(d, scratch.shape[1])), dtype=np.int64)
    held, nexts, prevs, around = scratch[HELD], scratch[NEXT], scratch[PREV], scratch[AROUND]
    for i in range(d):
        held[i] = pool[first + i]
    sort_prefix(held, d)
    na = 0
    for i in range(d):
        c = held[i]
        f3 = c - c % 3
        nexts[i] = faces[f3 + (c - f3 + 1) % 3]
        prevs[i] = faces[f3 + (c - f3 + 2) % 3]
        if nexts[i] != v:
            around[na] = nexts[i]
            na += 1
        if prevs[i] != v:
            around[na] = prevs[i]
            na += 1
    sort_prefix(around, na)
    return scratch, d, distinct_prefix(around, na)


@njit(cache=True, nogil=True)
def predicted_fan(scratch, d, s, t, birth_faces, first, last):
    """``reference.predict_fan`` on the scratch table of ``s`` (``d`` corners) for
    the split ``t`` whose new faces are rows ``first .. last-1`` of ``birth_faces``:
    the size of the fan, whose corners get ``scratch[IN_FAN, i] = 1``, or -1 where
    there is no prediction."""
    vl = vr = -1                  # none (vertex ids are >= 0)
    for f in range(first, last):
        i = k = -1
        for x in range(3):
            if i < 0 and birth_faces[f, x] == s:
                i = x
            if k < 0 and birth_faces[f, x] == t:
                k = x
        if i < 0 or k < 0:
            return -1
        if (i + 1) % 3 == k:
            vl = birth_faces[f, (k + 1) % 3]
        else:
            vr = birth_faces[f, (i + 1) % 3]
    if vl >= 0:                   # look up corners by prev, step to next, stop at vr
        keys, order, step, y, end = scratch[PREV], scratch[BY_PREV], 1, vl, vr
    elif vr >= 0:                 # by next, step to prev, no stop
        keys, order, step, y, end = scratch[NEXT], scratch[BY_NEXT], 2, vr, -1
    else:
        return -1
    argsort_prefix(keys, d, order)
    in_fan = scratch[IN_FAN]
    in_fan[:d] = 0
    size = 0
    while True:
        i = lookup(keys, order, d, y)
        if i == -1:
            return size
        if i == -2:
            return -1             # ambiguous: a non-manifold edge at s
        if in_fan[i]:
            return size
        in_fan[i] = 1
        size += 1
        y = scratch[NEXT, i] if step == 1 else scratch[PREV, i]
        if end >= 0 and y == end:
            return size
