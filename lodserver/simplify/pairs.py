"""Close pairs: vertices that share no edge but lie close together.

Garland & Heckbert 1997 (section 3) call these "valid pairs" besides the
edges: contracting one joins two parts or sheets, which edge collapse alone
never does. It removes no face, and the progressive mesh records it like any
other collapse (a vertex split that adds no face).
"""

from __future__ import annotations

import numpy as np
from numba import njit

# At most this many candidates per vertex and per pass, so a dense cloud
# cannot blow up memory.
MAX_PAIRS_PER_VERTEX = 8


@njit(cache=True, nogil=True)
def close_pairs(pos, topo, radius, mark, stamp):
    """Pairs (a < b) of live vertices at most ``radius`` apart that share no edge.

    A uniform grid of cells ``radius`` wide is the spatial index: rebuilt from
    the current positions at each pass (vertices move as they absorb others),
    every vertex looks at its 27 surrounding cells. At most
    MAX_PAIRS_PER_VERTEX candidates per vertex, nearest cells first.

    ``topo`` is the kernel's ``Topology``. Returns (pairs (k, 2) int64, the
    last stamp used in ``mark``).
    """
    faces, vhead, cnext = topo.faces, topo.vhead, topo.cnext
    face_alive, vertex_alive = topo.face_alive, topo.vertex_alive
    n = pos.shape[0]
    cells = int(np.ceil(1.0 / radius)) + 3
    keys = np.full(n, np.iinfo(np.int64).max, np.int64)
    for v in range(n):
        if vertex_alive[v]:
            keys[v] = ((int(pos[v, 0] / radius) + 1) * cells
                       + int(pos[v, 1] / radius) + 1) * cells + int(pos[v, 2] / radius) + 1
    order = np.argsort(keys)
    sorted_keys = keys[order]
    pairs = np.empty((16, 2), np.int64)
    count = 0
    r2 = radius * radius
    for a in range(n):
        if not vertex_alive[a]:
            continue
        # mark a's neighbours: an existing edge is not a close pair
        stamp += 1
        c = vhead[a]
        while c >= 0:
            f = c // 3
            if face_alive[f]:
                for t in range(3):
                    mark[faces[f, t]] = stamp
            c = cnext[c]
        found = 0
        for dx in (0, -1, 1):
            for dy in (0, -1, 1):
                for dz in (0, -1, 1):
                    key = keys[a] + (dx * cells + dy) * cells + dz
                    i = np.searchsorted(sorted_keys, key)
                    while i < n and sorted_keys[i] == key and found < MAX_PAIRS_PER_VERTEX:
                        b = order[i]
                        i += 1
                        if b <= a or mark[b] == stamp:
                            continue
                        d0 = pos[a, 0] - pos[b, 0]
                        d1 = pos[a, 1] - pos[b, 1]
                        d2 = pos[a, 2] - pos[b, 2]
                        if d0 * d0 + d1 * d1 + d2 * d2 <= r2:
                            if count == pairs.shape[0]:
                                grown = np.empty((2 * count, 2), np.int64)
                                grown[:count] = pairs
                                pairs = grown
                            pairs[count, 0] = a
                            pairs[count, 1] = b
                            count += 1
                            found += 1
    return pairs[:count], stamp
