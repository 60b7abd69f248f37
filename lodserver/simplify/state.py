"""The edge-collapse kernel's state: a few namedtuples of arrays that its
steps share, and how the steps that run per candidate are compiled.

Every array is allocated once per run (``new_state``, or in
``collapse._prepare``) and edited in place by the steps.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

from .topology import link_corners

# The steps run once per popped candidate (check, perform, re-rank) read the
# kernel's state out of namedtuples, and in compiled code every read of a
# field takes and drops a reference: two atomic operations, on every read,
# in the hottest loop of the decimation. These steps allocate
# nothing and keep no array past the call (the kernel holds every
# reference), so they are compiled without reference counting. ``_nrt`` is
# numba's own switch for that (CPUTargetOptions); where a numba lacks it the
# steps compile as usual, only slower.
NO_REFCOUNT = dict(cache=True, nogil=True)
try:
    from numba.core.cpu import CPUTargetOptions as _CPUTargetOptions
    if hasattr(_CPUTargetOptions, "_nrt"):
        NO_REFCOUNT["_nrt"] = False
except ImportError:      # pragma: no cover - numba internals moved
    pass


# The mesh as the kernel edits it: faces (m, 3) int32 (int32 ids halve the
# memory traffic of the corner walks, which dominate); corner lists
# vhead[v] -> c -> cnext[c] -> ... -> -1 over the corners c = 3 f + k of the
# faces at v (dead faces are unlinked lazily, when the survivor's list is next
# rebuilt); face_alive (m,); face_count (n,): live faces at each vertex;
# vertex_alive (n,).
Topology = namedtuple("Topology", "faces vhead cnext face_alive face_count vertex_alive")

# Per vertex: pos (n, 3) in the unit box and world (n, 3) the same in mesh
# units (origin + scale * pos, kept bit-exact for vertices that never move, so
# locked vertices log their input position exactly); quadrics (n, 11); kind
# (n,) int8; version (n,) int64, bumped at every change of the vertex (a queue
# entry is stale once either endpoint's has moved on). origin (3,), scale: the
# unit box.
Vertices = namedtuple("Vertices", "pos world quadrics kind version origin scale")

# Scratch every step reuses: q (11,) the candidate's summed quadric, p (3,) its
# placement, pairs (2, 2) its wedge pairs, opposite (2,) the vertices opposite
# its edge, gq (11,), plane (4,), and visit stamps mark, mark2 (n,).
Scratch = namedtuple("Scratch", "q p pairs opposite gq plane mark mark2")

# The caller's limits and switches.
Options = namedtuple("Options", "min_vertices max_collapses flip_cos pair_radius volume")


@njit(cache=True, nogil=True, inline="always")
def new_state(faces, n):
    """The ``Topology`` of ``faces`` (m, 3) int64 over ``n`` vertices, and an empty ``Scratch``."""
    m = faces.shape[0]
    faces = faces.astype(np.int32)
    vhead = np.full(n, -1, np.int32)
    cnext = np.full(3 * m, -1, np.int32)
    face_count = np.zeros(n, np.int64)
    link_corners(faces, vhead, cnext, face_count)
    topo = Topology(faces, vhead, cnext, np.ones(m, np.bool_), face_count, face_count > 0)
    return topo, new_scratch(n)


@njit(cache=True, nogil=True)
def new_topology(faces, n):
    """The ``Topology`` of ``faces`` (m, 3) int64 over ``n`` vertices (shared
    by the threads of a partitioned run, ``simplify.parts``)."""
    return new_state(faces, n)[0]


@njit(cache=True, nogil=True, inline="always")
def new_scratch(n):
    """An empty ``Scratch`` for ``n`` vertices (one per thread)."""
    return Scratch(np.empty(11), np.empty(3), np.full((2, 2), -1, np.int64),
                   np.empty(2, np.int64), np.empty(11, np.float64), np.empty(4, np.float64),
                   np.zeros(n, np.int64), np.zeros(n, np.int64))
