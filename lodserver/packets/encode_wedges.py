"""The wedge part of each record, compiled: the same predictions as ``reference.py``.

docs/packets.md, "The wedge part of split t" and steps 5-8 of "Collapse
records". Every float prediction here repeats, operation for operation, the
readable one in ``reference.py`` (:func:`~lodserver.packets.reference.split_ratio`,
``collapse_ratio``, ``fit_gradient``, ``extrapolated``, ``scaled``): a decoder
must reach the same integers, so the sums run in the same order and the 3x3
solve is the same cofactor expansion (``quadrics.symmetric_cofactors``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ..progressive.replay import ancestor_below
from ..simplify.quadrics import symmetric_cofactors
from .corners import HELD, distinct_prefix, put, search, sort_prefix, zz
from .format import GRADIENT_DAMPING, MAX_SPLIT_RATIO


@njit(cache=True, nogil=True, inline="always")
def _projected(u0, u1, w0, w1, empty, top):
    """``((w0 - w1) . (u0 - u1)) / |u0 - u1|^2`` clamped to [0, top], ``empty``
    when ``u0 == u1``: both ratios below, term by term as the reference computes
    them (the same float operations in the same order, so the same bits)."""
    a = 0.0
    b = 0.0
    for k in range(3):
        a += float(u0[k] - u1[k]) * float(u0[k] - u1[k])
    for k in range(3):
        b += float(w0[k] - w1[k]) * float(u0[k] - u1[k])
    ratio = b / a if a > 0 else empty
    return min(max(ratio, 0.0), top)


@njit(cache=True, nogil=True)
def _split_ratio(coarse, fine, new):
    """``reference.split_ratio``: where ``new`` lies along fine -> coarse, past coarse."""
    return _projected(coarse, fine, new, coarse, 1.0, MAX_SPLIT_RATIO)


@njit(cache=True, nogil=True)
def _collapse_ratio(fine, new, coarse):
    """``reference.collapse_ratio``: where ``coarse`` lies along fine -> new."""
    return _projected(new, fine, coarse, fine, 0.5, 1.0)


@njit(cache=True, nogil=True, inline="always")
def _scaled(ratio, d):
    """``reference.scaled``: ``floor(ratio * d + 0.5)``."""
    return np.int64(np.floor(ratio * d + 0.5))


@njit(cache=True, nogil=True)
def _fit_gradient(state, wedges, held, d, s, p, work):
    """``reference.fit_gradient`` of wedge ``p`` around ``s`` (corners ``held[:d]``
    ascending, vs at ``work.coarse``) into ``work.gradient`` (3, k); False where
    there is none. The same float operations in the same order."""
    faces, positions, corner, values = state.faces, state.positions, wedges.corner, wedges.values
    coarse, out, sums = work.coarse, work.gradient, work.sums
    k = values.shape[1]
    m00 = m01 = m02 = m11 = m12 = m22 = 0.0
    for j in range(k):
        sums[0, j] = 0.0
        sums[1, j] = 0.0
        sums[2, j] = 0.0
    edges = 0
    for i in range(d):
        c = held[i]
        if corner[c] != p:
            continue
        f3 = c - c % 3
        for step in range(1, 3):
            o = f3 + (c - f3 + step) % 3
            v = faces[o]
            if v == s:
                continue
            e0 = float(positions[v, 0] - coarse[0])
            e1 = float(positions[v, 1] - coarse[1])
            e2 = float(positions[v, 2] - coarse[2])
            w = corner[o]
            m00 += e0 * e0
            m01 += e0 * e1
            m02 += e0 * e2
            m11 += e1 * e1
            m12 += e1 * e2
            m22 += e2 * e2
            for j in range(k):
                dd = float(values[w, j] - values[p, j])
                sums[0, j] += e0 * dd
                sums[1, j] += e1 * dd
                sums[2, j] += e2 * dd
            edges += 1
    if edges < 2:
        return False
    damping = (m00 + m11 + m22) * GRADIENT_DAMPING + 1e-9
    c00, c01, c02, c11, c12, c22, det = symmetric_cofactors(m00 + damping, m01, m02,
                                                            m11 + damping, m12, m22 + damping)
    if not det > 0:
        return False
    i00, i01, i02 = c00 / det, c01 / det, c02 / det
    i11, i12, i22 = c11 / det, c12 / det, c22 / det
    for j in range(k):
        out[0, j] = i00 * sums[0, j] + i01 * sums[1, j] + i02 * sums[2, j]
        out[1, j] = i01 * sums[0, j] + i11 * sums[1, j] + i12 * sums[2, j]
        out[2, j] = i02 * sums[0, j] + i12 * sums[1, j] + i22 * sums[2, j]
    return True


@njit(cache=True, nogil=True)
def _extrapolated(gradient, j, value, d0, d1, d2, limit):
    """``reference.extrapolated``, the same float operations in the same order."""
    x = (float(value) + (float(d0) * gradient[0, j] + float(d1) * gradient[1, j]
                         + float(d2) * gradient[2, j])) + 0.5
    if not x >= 0:
        return np.int64(0)
    if x > limit:
        return np.int64(limit)
    return np.int64(np.floor(x))


@njit(cache=True, nogil=True)
def _distinct_wedges(corner, corners, n, below, out):
    """``out[:k]``: the distinct wedges of ``corners[:n]`` that are below ``below``,
    ascending; returns ``(out, k)`` (``out`` grown if needed)."""
    if n > out.shape[0]:
        out = np.empty(2 * n, dtype=np.int64)
    k = 0
    for i in range(n):
        w = corner[corners[i]]
        if w < below:
            out[k] = w
            k += 1
    sort_prefix(out, k)
    return out, distinct_prefix(out, k)


@njit(cache=True, nogil=True)
def _wedge_code(held, k, bottom, top, w):
    """``w``'s code relative to the candidate list of ``held[:k]`` (ascending)
    followed by the new wedges ``bottom .. top-1`` not among them
    (``reference.corner_candidates``)."""
    i = search(held, k, w)
    if i < k and held[i] == w:
        return i
    rank = k
    for x in range(bottom, top):
        j = search(held, k, x)
        if j < k and held[j] == x:
            continue
        if x == w:
            return rank
        rank += 1
    return rank + w


@njit(cache=True, nogil=True)
def split_wedges(state, pool, record, scratch, work, wedges, out, candidates):
    """The wedge part of split ``record.t`` (steps 8-11), after its geometry part.

    ``scratch`` holds ``held(s)`` (``record.held`` corners, as at the start of the
    record); ``work`` vs's coarse and fine and the new vertex's grid positions.
    Writes the wedge_count, wedge_parent, wedge_corner and value streams into
    ``out`` and updates ``wedges.corner`` and ``wedges.values``. Returns the
    candidate buffer (grown if needed).
    """
    faces, blocks = state.faces, state.blocks
    s, t, d = record.s, record.t, record.held
    coarse, fine, new, gradient = work.coarse, work.fine, work.new, work.gradient
    corner, values, wedge_parent = wedges.corner, wedges.values, wedges.parent
    offsets, limits = wedges.offsets, wedges.limits
    bottom, top = wedges.counts[record.j], wedges.counts[record.j + 1]
    used, value_streams, value_used = out.used, out.values, out.value_used
    held = scratch[HELD]
    used[0] = put(out.count, used[0], top - bottom)
    candidates, k = _distinct_wedges(corner, held, d, top, candidates)
    for x in range(bottom, top):
        p = wedge_parent[x]
        i = search(candidates, k, p)
        used[1] = put(out.parent, used[1], i if i < k and candidates[i] == p else k + p)
        row = x - wedges.first
        fitted = _fit_gradient(state, wedges, held, d, s, p, work)
        if not fitted:
            ratio = _split_ratio(coarse, fine, new)
        for a in range(offsets.shape[0] - 1):
            for col in range(offsets[a], offsets[a + 1]):
                c = values[p, col]
                guess = c
                if fitted:
                    guess = _extrapolated(gradient, col, c, fine[0] - coarse[0],
                                          fine[1] - coarse[1], fine[2] - coarse[2], limits[col])
                value_used[a] = put(value_streams[a], value_used[a],
                                    zz(wedges.fine[row, col] - guess))
            for col in range(offsets[a], offsets[a + 1]):
                c = values[p, col]
                if fitted:
                    guess = _extrapolated(gradient, col, c, new[0] - coarse[0],
                                          new[1] - coarse[1], new[2] - coarse[2], limits[col])
                else:
                    guess = c + _scaled(ratio, c - wedges.fine[row, col])
                value_used[a] = put(value_streams[a], value_used[a],
                                    zz(wedges.new[row, col] - guess))
        for col in range(offsets[-1]):
            values[p, col] = wedges.fine[row, col]
            values[x, col] = wedges.new[row, col]
    m = top - bottom
    for i in range(d):            # moved corners, ascending
        c = held[i]
        if faces[c] != t:
            continue
        y = corner[c]
        w = ancestor_below(wedge_parent, wedges.full_corners[c // 3, c % 3], top)
        guess = y
        for x in range(bottom, top):
            if wedge_parent[x] == y:
                guess = x
                break
        if w == guess:
            code = 0
        elif bottom <= w < top:
            code = 1 + w - bottom
        elif w == y:
            code = m + 1
        else:
            code = m + 2 + w
        used[2] = put(out.corner, used[2], code)
        corner[c] = w
    # the corners of the new faces, each relative to its vertex's wedges
    limit = 3 * record.first_face
    for f in range(record.first_face, record.face_count):
        for k in range(3):
            c = 3 * f + k
            v = faces[c]
            begin, n = blocks[v, 0], blocks[v, 1]
            if n > candidates.shape[0]:
                candidates = np.empty(2 * n, dtype=np.int64)
            size = 0
            for i in range(n):
                other = pool[begin + i]
                if other < limit:
                    candidates[size] = corner[other]
                    size += 1
            sort_prefix(candidates, size)
            distinct = distinct_prefix(candidates, size)
            w = wedges.birth_corners[record.first + f - record.first_face, k]
            used[2] = put(out.corner, used[2], _wedge_code(candidates, distinct, bottom, top, w))
            corner[c] = w
    return candidates


@njit(cache=True, nogil=True)
def collapse_wedges(state, pool, record, work, wedges, out, candidates):
    """The wedge part of collapse ``record.t`` into ``record.s`` (steps 5-8), after
    its geometry part: ``work.fine`` holds vs's grid position before the record,
    the state the merged one. Writes the wedge_count, wedge_parent and value
    streams into ``out``, updates ``wedges.corner`` and ``wedges.values``, and
    returns the candidate buffer (grown if needed)."""
    positions, s, t = state.positions, record.s, record.t
    corner, values, wedge_parent = wedges.corner, wedges.values, wedges.parent
    offsets = wedges.offsets
    used, value_streams, value_used = out.used, out.values, out.value_used
    ratio = _collapse_ratio(work.fine, positions[t], positions[s])
    bottom, top = wedges.counts[record.j], wedges.counts[record.j + 1]
    used[0] = put(out.count, used[0], top - bottom)
    first, d = state.blocks[s, 0], state.blocks[s, 1]
    candidates, k = _distinct_wedges(corner, pool[first:first + d], d, bottom, candidates)
    for x in range(top - 1, bottom - 1, -1):
        p = wedge_parent[x]
        r = search(candidates, k, p)
        used[1] = put(out.parent, used[1], r if r < k and candidates[r] == p else k + p)
        row = x - wedges.first
        for a in range(offsets.shape[0] - 1):
            for col in range(offsets[a], offsets[a + 1]):
                predicted = values[p, col] + _scaled(ratio, values[x, col] - values[p, col])
                value_used[a] = put(value_streams[a], value_used[a],
                                    zz(wedges.coarse[row, col] - predicted))
        for col in range(offsets[-1]):
            values[p, col] = wedges.coarse[row, col]
    for q in range(d):
        c = pool[first + q]
        corner[c] = ancestor_below(wedge_parent, corner[c], bottom)
    return candidates
