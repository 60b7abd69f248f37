"""The encoder kernels' inputs and state as small typed records of arrays.

numba compiles a ``collections.namedtuple`` of arrays and scalars into a
struct passed by value: reading a field costs nothing, and a kernel's
signature names a handful of records instead of two dozen arrays. The
records hold no logic; the kernels (``encode.py``, ``encode_wedges.py``,
``corners.py``) document what they read and change.

In every record ``faces`` (and the per-corner wedge array) is *flat*: corner
``c = 3 * face + slot`` reads ``faces[c]``. Corner and vertex ids are int32
when they fit (see ``encode.index_dtype``), the rest int64.
"""

from __future__ import annotations

from collections import namedtuple

# The quantized state a packet's records change in place, and its corner lists.
# positions (v, 3) int64: grid coordinates, room for both end levels
# faces (3 f,) index: vertex of every corner, room for both end levels
# blocks (v, 3) int64, slot (3 f,) index, end (1,) int64: corners(v) as blocks
#   of a pool (see corners.corner_lists); the pool itself is passed apart, as it grows
State = namedtuple("State", "positions faces blocks slot end")

# Which records: splits start .. stop-1 or collapses start-1 .. stop; base = n0;
# face_count = faces at ``start``.
Span = namedtuple("Span", "start stop base face_count")

# The progressive mesh's vertex hierarchy and face records (progressive/mesh.py):
# parent (n,), face_counts (n-n0+1,), birth_faces (m, 3), moved_offsets (n-n0+1,),
# moved_corners (c,), all int64; face_material (m,) int64, or empty without materials.
Hierarchy = namedtuple("Hierarchy",
                       "parent face_counts birth_faces moved_offsets moved_corners face_material")

# The quantized positions the records write, one row per record in the span:
# fine, new (records, 3) for splits (empty for collapses); coarse (records, 3) for
# collapses (empty for splits).
Targets = namedtuple("Targets", "fine new coarse")

# The wedge state and the wedge records (all empty without attributes):
# corner (3 f,) index: the wedge of every corner (state, changed in place)
# values (w, k) int64: quantized wedge values, room for both end levels (state)
# counts (n-n0+1,), parent (w,): pm.wedge_counts, pm.wedge_parent
# birth_corners, full_corners (m, 3): pm.birth_corners, pm.corner_wedges
# offsets (a+1,): the columns of each attribute in ``values``; limits (k,): per column,
#   the largest grid value (2**bits - 1)
# first: the wedge id of row 0 of fine/new/coarse, the quantized values the span's
#   records write: fine, new (splits), coarse (collapses), (rows, k) int64
Wedges = namedtuple("Wedges", "corner values counts parent birth_corners full_corners offsets "
                              "limits first fine new coarse")

# The wedge streams as they fill: count, parent, corner, material (uint8 buffers, room
# for their longest varints), used (4,) int64 their used lengths; values (a, size) uint8,
# a buffer row per attribute, and value_used (a,) int64.
WedgeStreams = namedtuple("WedgeStreams", "count parent corner material used values value_used")

# One split: vs ``s``, new vertex ``t``, record ``j = t - n0``, row ``i`` of the span;
# ``held``: corners of s in the scratch table; new faces first_face .. face_count-1 of
# the state, from row ``first`` of birth_faces / birth_corners.
SplitRecord = namedtuple("SplitRecord", "s t j i held first_face face_count first")

# One collapse of ``t`` into ``s``: record ``j = t - n0``, row ``i`` of the span.
CollapseRecord = namedtuple("CollapseRecord", "s t j i")

# Per-record float and position scratch, allocated once per packet:
# coarse, fine, new (3,) int64: vs before / after, the new vertex (grid positions);
# gradient, sums (3, k) float64: the attribute gradient fit.
Work = namedtuple("Work", "coarse fine new gradient sums")
