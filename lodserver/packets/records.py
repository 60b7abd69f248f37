"""Every record of a mesh encoded once; the server's packets are slices of them.

A record's bytes depend only on the level it starts from: the quantized state
of a level is the same whichever way a client reached it, and every prediction
reads only that state. So the packet ``A -> B`` is, stream by stream, a slice
of the streams of every split (or every collapse) of the mesh, and past a
chunk of records also a chain of pre-deflated segments (docs/packets.md, "How
the server cuts packets").

The records of the meshes in use are cached per mesh object, at the default
grid only (other grids are encoded per packet). :func:`prepare_records` encodes
them in the background, on one worker thread that is started on first use and
stopped by :func:`shutdown_background`.
"""

from __future__ import annotations

import struct
import threading
import weakref
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .corners import VARINT_MAX
from .encode import assemble_packet, encode_packet, encode_streams
from .format import pack_header, put_varint, stream_names
from .grids import attribute_grids_of, check_bits, default_bits, grid_of

if TYPE_CHECKING:
    from ..progressive.mesh import ProgressiveMesh

# Records per pre-deflated chunk of a stream. Smaller chunks cost more deflate block
# headers and lost matches (~0.5% of a full packet at 8192); larger ones leave more
# to deflate per packet at its two ends.
CHUNK_RECORDS = 8192


@dataclass(frozen=True, eq=False)
class RecordStreams:
    """The streams of every record of one direction, between the base and full detail.

    ``streams`` are the packet ``base -> full`` (``forward``) or ``full -> base``;
    the packet ``A -> B`` is records ``A .. B-1`` forward, ``A-1 .. B`` backward.

    ``chunks[k][i]`` is stream ``k``'s records ``i * chunk .. (i+1) * chunk - 1``
    as raw deflate ending in a sync flush (byte aligned, not final): deflate
    segments like these chain into one stream, so a long packet deflates only its
    two ends and copies the chunks between.
    """

    forward: bool
    streams: tuple          # uint8 arrays, body order
    marks: tuple            # per stream, (records + 1,): its length before each record
    chunk: int = CHUNK_RECORDS
    chunks: tuple = ()      # per stream, a tuple of bytes

    def slices(self, first: int, last: int) -> list:
        """The streams of records ``first .. last-1`` (counted in this direction)."""
        return [s[m[first]:m[last]] for s, m in zip(self.streams, self.marks)]

    def deflated_body(self, first: int, last: int) -> tuple[bytes, int]:
        """The zlib stream of the body of records ``first .. last-1``, and its inflated
        length, from the chunks inside the range and fresh segments around them."""
        pieces, adler, length = [b"\x78\x9c"], 1, 0    # zlib header: deflate, 32 KiB window

        def add(data, deflated=None):
            nonlocal adler, length
            if len(data):
                pieces.append(deflated if deflated is not None else _deflate_segment(data))
                adler = zlib.adler32(data, adler)
                length += len(data)

        whole_from, whole_to = -(-first // self.chunk), last // self.chunk
        for stream, marks, chunks in zip(self.streams, self.marks, self.chunks):
            start, stop = int(marks[first]), int(marks[last])
            prefix = bytearray()
            put_varint(prefix, stop - start)
            if whole_to <= whole_from:
                add(bytes(prefix) + stream[start:stop].tobytes())
                continue
            add(bytes(prefix) + stream[start:marks[whole_from * self.chunk]].tobytes())
            for i in range(whole_from, whole_to):
                add(stream[marks[i * self.chunk]:marks[(i + 1) * self.chunk]], chunks[i])
            add(stream[marks[whole_to * self.chunk]:stop].tobytes())
        pieces.append(b"\x03\x00")                   # an empty final block (fixed Huffman)
        pieces.append(struct.pack(">I", adler))
        return b"".join(pieces), length


def _deflate_segment(data, level: int = 6) -> bytes:
    """Raw deflate of ``data`` ending in a sync flush: chainable (see RecordStreams)."""
    deflater = zlib.compressobj(level, zlib.DEFLATED, -15)
    return deflater.compress(data) + deflater.flush(zlib.Z_SYNC_FLUSH)


def record_streams(pm: ProgressiveMesh, *, forward: bool, bits: int | None = None,
                   chunk: int | None = None) -> RecordStreams:
    """Encode every split (``forward``) or every collapse of ``pm`` once, at the
    default attribute grids, and deflate it in chunks of ``chunk`` records
    (default :data:`CHUNK_RECORDS`). Costs about one full packet; see
    :class:`RecordStreams`."""
    chunk = CHUNK_RECORDS if chunk is None else chunk
    grid = grid_of(pm, bits=bits)
    grids = attribute_grids_of(pm)
    n0, n = pm.base_vertices, pm.vertex_count
    start, stop = (n0, n) if forward else (n, n0)
    names = stream_names(grids, pm.face_material is not None)
    # Stream lengths fit 32 bits unless the mesh has hundreds of millions of vertices.
    wide = VARINT_MAX * 64 * (n - n0) >= 2**32
    marks = np.zeros((len(names), n - n0 + 1), dtype=np.int64 if wide else np.uint32)
    # own the bytes: the kernels' buffers are sized for the worst case
    streams = tuple(np.array(s, copy=True) for s in
                    encode_streams(pm, start, stop, grid, grids, marks))
    # A stream no record writes to (collapses have no faces to add, predicted fans
    # no masks) keeps a zero-stride row of zeros instead of 4 bytes per record.
    rows = tuple(row.copy() if row[-1] else np.broadcast_to(row.dtype.type(0), row.shape)
                 for row in marks)
    bounds = range(0, n - n0 - chunk + 1, chunk)
    chunks = tuple(tuple(_deflate_segment(stream[m[i]:m[i + chunk]]) for i in bounds)
                   for stream, m in zip(streams, rows))
    return RecordStreams(forward, streams, rows, chunk, chunks)


# The records of the progressive meshes in use, at their default grid only: per mesh,
# per direction, [lock, RecordStreams or None]. A ProgressiveMesh is immutable, and its
# records are dropped with it. Public so that tests can inspect and seed it.
record_cache: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_cache_lock = threading.Lock()


def cached_records(pm: ProgressiveMesh, forward: bool) -> RecordStreams:
    """``pm``'s :class:`RecordStreams` in one direction, encoded on first use."""
    with _cache_lock:
        slots = record_cache.setdefault(pm, {})
        slot = slots.setdefault(forward, [threading.Lock(), None])
    with slot[0]:               # one encoder per mesh and direction; the others wait for it
        if slot[1] is None:
            slot[1] = record_streams(pm, forward=forward)
        return slot[1]


def records_ready(pm: ProgressiveMesh, forward: bool | None = None) -> bool:
    """Whether ``pm``'s records are encoded in direction ``forward`` (True: splits),
    or both ways when ``forward`` is None."""
    with _cache_lock:
        slots = dict(record_cache.get(pm, {}))
    directions = (True, False) if forward is None else (forward,)
    return all(slots.get(d, (None, None))[1] is not None for d in directions)


def encode_records(pm: ProgressiveMesh) -> None:
    """Encode ``pm``'s records both ways now, at once (the kernels and deflate
    release the GIL), unless they are cached already; later packets are slices."""
    with ThreadPoolExecutor(2) as pool:
        for done in [pool.submit(cached_records, pm, forward) for forward in (True, False)]:
            done.result()


# One background encoder, started on first use (not at import: importing the
# package starts no thread), for records a request is likely to need soon.
_background: ThreadPoolExecutor | None = None
_scheduled: weakref.WeakSet = weakref.WeakSet()


def prepare_records(pm: ProgressiveMesh) -> None:
    """:func:`encode_records` in the background, once per mesh object: a client
    that fetched a level's json form asks for packets next, and after a restart
    nothing has prepared them."""
    global _background
    with _cache_lock:
        if pm in _scheduled:
            return
        _scheduled.add(pm)
        if _background is None:
            _background = ThreadPoolExecutor(max_workers=1, thread_name_prefix="packet-records")
        background = _background
    background.submit(encode_records, pm)


def shutdown_background(*, wait: bool = True) -> None:
    """Stop the background encoder: drop the preparations not started yet, finish
    (``wait``) or abandon the one running. A later :func:`prepare_records` starts
    a new one; meshes whose preparation was dropped are scheduled again then."""
    global _background
    with _cache_lock:
        background, _background = _background, None
        _scheduled.clear()
    if background is not None:
        background.shutdown(wait=wait, cancel_futures=True)


def packet_between(pm: ProgressiveMesh, start: int, stop: int, *,
                   bits: int | None = None) -> bytes:
    """The packet of :func:`encode_packet`, cut from :class:`RecordStreams`.

    At the default grid the first packet of a mesh in each direction encodes every
    record (about one full packet's time); later packets cost their slices and
    deflate, and past one chunk only the deflate of their two ends. Up to a chunk
    the bytes are :func:`encode_packet`'s; longer packets differ only in how the
    same body is deflated. Other grids are encoded directly.
    """
    start, stop = pm.check_level(start), pm.check_level(stop)
    if start == stop or (bits is not None and check_bits(bits) != default_bits(pm)):
        return encode_packet(pm, start, stop, bits=bits)
    records = cached_records(pm, stop > start)
    n0, n = pm.base_vertices, pm.vertex_count
    first, last = (start - n0, stop - n0) if stop > start else (n - start, n - stop)
    grid, grids = grid_of(pm), attribute_grids_of(pm)
    if last - first < records.chunk:
        return assemble_packet(pm, grid, grids, start, stop, records.slices(first, last))
    deflated, length = records.deflated_body(first, last)
    return pack_header(grid, grids, pm.face_material is not None, start, stop,
                       pm.faces_at_level(start), pm.faces_at_level(stop), length) + deflated
