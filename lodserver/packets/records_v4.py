"""Version 4 packets cut from every record encoded once, as ``records.py`` does for version 3.

A version 4 segment's bytes depend only on its records (docs/packets.md,
"Version 4"), and every segment but a packet's first and last starts and ends
at a multiple of ``encode_v4.SEGMENT_RECORDS`` records. So the packet
``A -> B`` is its whole segments, each coded once per mesh and kept, between
two partial ones coded afresh from the slices of version 3's
:class:`~lodserver.packets.records.RecordStreams` (which hold every record's
fields). The bytes are those of :func:`~lodserver.packets.encode_v4.encode_packet_v4`
at the default grids, codings and batches (the mesh's own schedule).
"""

from __future__ import annotations

import threading
import weakref
from typing import TYPE_CHECKING

from . import encode_v4
from .format import RING_POSITIONS
from .grids import attribute_grids_of, check_bits, default_bits, grid_of
from .records import cached_records
from .ring_v4 import ring_predictions
from .streams_v4 import shapes

if TYPE_CHECKING:
    from ..progressive.mesh import ProgressiveMesh

# Per progressive mesh, per direction: {segment index: bytes}, the whole segments
# coded so far (at the default grid and codings). Dropped with the mesh.
segment_cache: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
# Per progressive mesh: the ring prediction of every split at the default grid
# (ring_v4.ring_predictions from the base to full detail), for RING_POSITIONS.
ring_cache: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_lock = threading.Lock()


def packet_between_v4(pm: ProgressiveMesh, start: int, stop: int, *,
                      bits: int | None = None) -> bytes:
    """The version 4 packet ``start -> stop`` of :func:`~.encode_v4.encode_packet_v4`
    (default codings, the mesh's own batches), from cached records and segments.
    Other grids are encoded directly."""
    start, stop = pm.check_level(start), pm.check_level(stop)
    flags = encode_v4.DEFAULT_FLAGS
    if start == stop or (bits is not None and check_bits(bits) != default_bits(pm)):
        return encode_v4.encode_packet_v4(pm, start, stop, bits=bits, flags=flags)
    forward = stop > start
    records = cached_records(pm, forward)
    n0, n = pm.base_vertices, pm.vertex_count
    first, last = (start - n0, stop - n0) if forward else (n - start, n - stop)
    grid, grids = grid_of(pm), attribute_grids_of(pm)
    batch = pm.split_batch
    layout = shapes(grids, pm.face_material is not None, forward, flags)
    size = encode_v4.SEGMENT_RECORDS
    with _lock:
        kept = segment_cache.setdefault(pm, {}).setdefault((forward, size, flags), {})
    segments = []
    for r0, r1 in encode_v4.segment_cuts(first, last - first):
        a, b = first + r0, first + r1
        whole = a % size == 0 and b - a == size
        coded = kept.get(a // size) if whole else None
        if coded is None:
            ids = None if batch is None or not forward else batch[a:b]
            ring = _ring(pm, grid)[a:b] if forward and flags & RING_POSITIONS else None
            coded = encode_v4.segment_bytes(records.slices(a, b), n0 + a if forward else None,
                                            ids, flags, layout, ring)
            if whole:
                kept[a // size] = coded      # the same bytes whichever thread wins
        segments.append(coded)
    return encode_v4.assemble_v4(pm, grid, grids, start, stop, flags, segments)


def _ring(pm: ProgressiveMesh, grid):
    """Every split's ring prediction at the default ``grid``, computed once per mesh."""
    with _lock:
        ring = ring_cache.get(pm)
    if ring is None:
        ring = ring_predictions(pm, pm.base_vertices, pm.vertex_count, grid)
        with _lock:
            ring = ring_cache.setdefault(pm, ring)   # the same array whichever thread wins
    return ring
