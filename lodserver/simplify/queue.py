"""The collapse queue: cheapest candidate first, stale entries dropped lazily.

A binary heap of every candidate would hold millions of entries, most of them
stale (a collapse re-ranks ~10 edges and strands the old entries), and each
pop would walk ~22 cache-missing levels. So only the cheapest slice lives in
the heap (keys <= ``tau``); the rest waits unsorted in a reservoir and moves
over, a slice at a time, when the heap runs dry. The pop order is still
exactly cheapest-first.

An entry is (key, ``a << 32 | b``, ``version[a] + version[b]``): versions only
grow, so the sum matches iff both endpoints are as they were when the entry
was queued (Garland & Heckbert's heap, with Hoppe's lazy re-ranking).

The queue is a ``Queue`` of arrays. No step that runs per candidate returns
arrays: returning a tuple of arrays from a compiled function costs several
times as much as the push itself, so the steps
only write into the arrays, and the pass loop makes room for the next ``k``
entries at safe points (``has_room`` / ``with_room``), before a step that
may push up to ``k``.

The reservoir's *logical* capacity (``size[CAPACITY]``) is what decides when
it is compacted and when it doubles, and so the order of its entries, which
the refill's sample sees; the arrays behind it are allocated larger, so that
a step never needs new ones in the middle.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

from .prefetch import prefetch

REFILL_SAMPLE = 4096       # reservoir keys sampled to choose the next tau
REFILL_MIN = 8192          # smallest slice moved into the heap at a refill

# heap_key / heap_pair / heap_version: the heap, ``size[HEAP]`` entries;
# key / pair / version: the reservoir, ``size[RESERVOIR]`` entries, full at
# ``size[CAPACITY]``; tau[0]: every heap key is <= tau, every reservoir key > tau.
Queue = namedtuple("Queue", "heap_key heap_pair heap_version key pair version size tau")
HEAP = 0
RESERVOIR = 1
CAPACITY = 2
# pop_fresh_from's answers besides a vertex id
EMPTY = -1          # no entry left
NEEDS_ROOM = -2     # the heap must hold the whole reservoir to refill: call with_room


@njit(cache=True, nogil=True, inline="always")
def new_queue(capacity):
    """An empty queue whose reservoir holds ``capacity`` entries before it
    is compacted (or grows)."""
    room = capacity + REFILL_MIN
    size = np.zeros(3, np.int64)
    size[CAPACITY] = capacity
    return Queue(np.empty(REFILL_MIN, np.float64), np.empty(REFILL_MIN, np.int64),
                 np.empty(REFILL_MIN, np.int64), np.empty(room, np.float64),
                 np.empty(room, np.int64), np.empty(room, np.int64), size, np.full(1, -np.inf))


@njit(cache=True, nogil=True, inline="always")
def clear_queue(queue):
    """Forget every entry (the start of a pass re-ranks everything)."""
    queue.size[HEAP] = 0
    queue.size[RESERVOIR] = 0
    queue.tau[0] = -np.inf


@njit(cache=True, nogil=True, inline="always")
def has_room(queue, k):
    """True if ``k`` pushes fit in the arrays as they are, whatever the reservoir does."""
    return (queue.size[HEAP] + k <= queue.heap_key.shape[0]
            and queue.size[CAPACITY] + k <= queue.key.shape[0])


@njit(cache=True, nogil=True)
def with_room(queue, heap_k, reservoir_k):
    """The queue with arrays large enough for ``heap_k`` more heap entries and
    ``reservoir_k`` more reservoir entries than its capacity (a refill needs
    ``heap_k`` = the reservoir's size)."""
    need = queue.size[HEAP] + heap_k
    hk, hab, hvs = queue.heap_key, queue.heap_pair, queue.heap_version
    if need > hk.shape[0]:
        hk = grow(hk, need)
        hab = grow(hab, need)
        hvs = grow(hvs, need)
    need = queue.size[CAPACITY] + reservoir_k
    rk, rab, rvs = queue.key, queue.pair, queue.version
    if need > rk.shape[0]:
        rk = grow(rk, need)
        rab = grow(rab, need)
        rvs = grow(rvs, need)
    return Queue(hk, hab, hvs, rk, rab, rvs, queue.size, queue.tau)


@njit(cache=True, nogil=True, inline="always")
def pair_key(a, b):
    """The queue's id of the pair (a, b), a < b: ``a << 32 | b``."""
    return (a << 32) | b


@njit(cache=True, nogil=True)
def grow(a, need):
    """``a``, or a copy at least twice as long if it holds fewer than ``need``."""
    if need <= a.shape[0]:
        return a
    b = np.empty(max(need, 2 * a.shape[0]), a.dtype)
    b[:a.shape[0]] = a
    return b


@njit(cache=True, nogil=True)
def _sift_down(keys, ab, vs, size, i):
    key = keys[i]
    e_ab = ab[i]
    e_vs = vs[i]
    while True:
        c = 2 * i + 1
        if c >= size:
            break
        if c + 1 < size and keys[c + 1] < keys[c]:
            c += 1
        if key <= keys[c]:
            break
        keys[i] = keys[c]
        ab[i] = ab[c]
        vs[i] = vs[c]
        i = c
    keys[i] = key
    ab[i] = e_ab
    vs[i] = e_vs


@njit(cache=True, nogil=True, inline="always")
def _heap_push(keys, ab, vs, size, key, e_ab, e_vs):
    i = size
    while i > 0:
        parent = (i - 1) >> 1
        if keys[parent] <= key:
            break
        keys[i] = keys[parent]
        ab[i] = ab[parent]
        vs[i] = vs[parent]
        i = parent
    keys[i] = key
    ab[i] = e_ab
    vs[i] = e_vs
    return size + 1


@njit(cache=True, nogil=True, inline="always")
def _heap_pop(keys, ab, vs, size):
    """Drop the root (read it first); returns the new size."""
    size -= 1
    if size > 0:
        keys[0] = keys[size]
        ab[0] = ab[size]
        vs[0] = vs[size]
        _sift_down(keys, ab, vs, size, np.int64(0))   # not a literal: one signature
    return size


@njit(cache=True, nogil=True, inline="always")
def _fresh(e_ab, e_vs, version, vertex_alive):
    a = e_ab >> 32
    b = e_ab & 0xFFFFFFFF
    return vertex_alive[a] and vertex_alive[b] and version[a] + version[b] == e_vs


@njit(cache=True, nogil=True)
def _refill(queue, version, vertex_alive):
    """Move the cheapest slice of the reservoir into the (empty) heap,
    dropping the stale entries of that slice on the way; the heap must have
    room for the whole reservoir. Returns how many were dropped; every
    reservoir key left is > the new tau."""
    rk, rab, rvs = queue.key, queue.pair, queue.version
    rsize = queue.size[RESERVOIR]
    want = max(REFILL_MIN, rsize // 16)
    if rsize <= want:
        tau = np.inf
    else:
        stride = max(1, rsize // REFILL_SAMPLE)
        sample = np.sort(rk[:rsize:stride])
        tau = sample[min(len(sample) - 1, (want * len(sample)) // rsize)]
    hk, hab, hvs = queue.heap_key, queue.heap_pair, queue.heap_version
    hsize = np.int64(0)
    kept = 0
    dropped = 0
    for i in range(rsize):
        if rk[i] <= tau:
            if _fresh(rab[i], rvs[i], version, vertex_alive):
                hk[hsize] = rk[i]
                hab[hsize] = rab[i]
                hvs[hsize] = rvs[i]
                hsize += 1
            else:
                dropped += 1
        else:
            rk[kept] = rk[i]
            rab[kept] = rab[i]
            rvs[kept] = rvs[i]
            kept += 1
    for i in range(hsize // 2 - 1, -1, -1):
        _sift_down(hk, hab, hvs, hsize, i)
    queue.size[HEAP] = hsize
    queue.size[RESERVOIR] = kept
    queue.tau[0] = tau
    return dropped


@njit(cache=True, nogil=True)
def _drop_stale(rk, rab, rvs, rsize, version, vertex_alive):
    """Compact the reservoir, dropping entries whose endpoints have changed."""
    kept = 0
    for i in range(rsize):
        if _fresh(rab[i], rvs[i], version, vertex_alive):
            rk[kept] = rk[i]
            rab[kept] = rab[i]
            rvs[kept] = rvs[i]
            kept += 1
    return kept


@njit(cache=True, nogil=True, inline="always")
def reservoir_append(rk, rab, rvs, size, key, e_ab, e_vs, version, vertex_alive):
    """Append an entry to the reservoir arrays (``Queue.key``, ``.pair``,
    ``.version``, ``.size``; they must have room, see ``with_room``).

    When the reservoir is full, its stale entries are dropped first; it
    doubles only if none was stale. Takes the arrays, not the ``Queue``: in
    a compiled loop every read of a namedtuple field takes and drops a
    reference (an atomic add each way), and this runs once per candidate.
    """
    rsize = size[RESERVOIR]
    capacity = size[CAPACITY]
    if rsize == capacity:
        rsize = _drop_stale(rk, rab, rvs, rsize, version, vertex_alive)
        if rsize + 1 > capacity:
            size[CAPACITY] = max(rsize + 1, 2 * capacity)
    rk[rsize] = key
    rab[rsize] = e_ab
    rvs[rsize] = e_vs
    size[RESERVOIR] = rsize + 1


@njit(cache=True, nogil=True, inline="always")
def queue_append(hk, hab, hvs, rk, rab, rvs, size, tau, key, e_ab, e_vs, version, vertex_alive):
    """``push`` on the queue's arrays (see ``reservoir_append`` for why arrays)."""
    if key <= tau[0]:
        size[HEAP] = _heap_push(hk, hab, hvs, size[HEAP], key, e_ab, e_vs)
    else:
        reservoir_append(rk, rab, rvs, size, key, e_ab, e_vs, version, vertex_alive)


@njit(cache=True, nogil=True)
def push_reservoir(queue, key, e_ab, e_vs, version, vertex_alive):
    """Append an entry to the reservoir (the arrays must have room, see ``with_room``)."""
    reservoir_append(queue.key, queue.pair, queue.version, queue.size, key, e_ab, e_vs, version,
                     vertex_alive)


@njit(cache=True, nogil=True)
def push(queue, key, e_ab, e_vs, version, vertex_alive):
    """Queue an entry: into the heap if it belongs to the current slice
    (key <= tau), else into the reservoir (the arrays must have room)."""
    queue_append(queue.heap_key, queue.heap_pair, queue.heap_version, queue.key, queue.pair,
                 queue.version, queue.size, queue.tau, key, e_ab, e_vs, version, vertex_alive)


@njit(cache=True, nogil=True, inline="always")
def next_key(queue):
    """The key the next pop would see at the earliest: the heap's root, or tau."""
    return queue.heap_key[0] if queue.size[HEAP] > 0 else queue.tau[0]


@njit(cache=True, nogil=True, inline="always")
def pop_fresh_from(hk, hab, hvs, size, queue, version, vertex_alive, rejected, stale):
    """Take the cheapest entry whose endpoints are as queued.

    The heap's arrays ``hk, hab, hvs`` and ``size`` of ``queue`` are passed as
    the pass loop holds them: inlined, every read of a field of ``queue`` would
    count a reference, and this runs once per candidate; ``queue`` itself is
    only read at a refill. Returns (a, b, entry version); a is EMPTY when the
    queue is, NEEDS_ROOM when the heap must first grow to hold the reservoir
    (``with_room(queue, queue.size[RESERVOIR], 0)``). Every stale entry met on
    the way adds one to ``rejected[stale]``.
    """
    while True:
        if size[HEAP] == 0:
            rsize = size[RESERVOIR]
            if rsize == 0:
                return EMPTY, EMPTY, EMPTY
            if hk.shape[0] < rsize:
                return NEEDS_ROOM, NEEDS_ROOM, NEEDS_ROOM
            rejected[stale] += _refill(queue, version, vertex_alive)
            continue
        e_ab = hab[0]
        e_vs = hvs[0]
        size[HEAP] = _heap_pop(hk, hab, hvs, size[HEAP])
        # Most entries popped are stale (4 to 8 to each fresh one), and the
        # freshness test reads two random versions: start those reads for the
        # next root now, so that they overlap this entry's work.
        if size[HEAP] > 0:
            prefetch(version, hab[0] >> 32)
            prefetch(version, hab[0] & 0xFFFFFFFF)
        if _fresh(e_ab, e_vs, version, vertex_alive):
            return e_ab >> 32, e_ab & 0xFFFFFFFF, e_vs
        rejected[stale] += 1
