"""The version 4 encoder: version 3's records, their fields coded by kind with rANS.

docs/packets.md, "Version 4". :func:`encode_packet_v4` runs the compiled
version 3 encoder (``encode.py``: the same predictions, fans and wedges), reads
each field of its streams back as integers, rewrites where the splits happen
as batch runs and gaps and (optionally) the positions as the split edge
(``streams_v4.py``), and codes every stream with its contexts (``rans.py``).

Records are coded in *segments* that start at fixed record indices of the mesh
(every :data:`SEGMENT_RECORDS` records from the base, or from full detail for
collapses) and at the packet's ends, each with fresh models and rANS
states: a segment's bytes depend only on its records, so a server can code a
mesh's segments once and cut a packet from them as it does version 3's chunks.
"""

from __future__ import annotations

import struct
import zlib
from typing import TYPE_CHECKING

import numpy as np
from numba import njit

from .encode import encode_streams
from .format import (
    COUNT,
    EDGE_POSITIONS,
    FAN,
    MASK,
    PATTERN,
    POSITION,
    RING_POSITIONS,
    VERSION_4,
    pack_header,
    put_varint,
    stream_names,
)
from .grids import attribute_grids_of, grid_of
from .rans import encode_symbols
from .records import CHUNK_RECORDS
from .ring_v4 import ring_predictions
from .streams_v4 import contexts, face_contexts, position_symbols, shapes, unzigzag

if TYPE_CHECKING:
    from ..progressive.mesh import ProgressiveMesh

# Records per segment: the chunk of version 3's pre-deflated records, for the same reason.
SEGMENT_RECORDS = CHUNK_RECORDS
# The version 3 streams that hold bytes rather than varints.
BYTE_STREAMS = (PATTERN, FAN, MASK)
# The codings used unless asked otherwise: the split edge pays on meshes of tens of
# thousands of splits and costs little on small ones, and its prediction from the
# ring pays on every mesh measured; the magnitude classes do not earn their contexts'
# learning (bench/codec.py and bench/codec_levers.py measure each).
DEFAULT_FLAGS = EDGE_POSITIONS | RING_POSITIONS


def encode_packet_v4(pm: ProgressiveMesh, start: int, stop: int, *, bits: int | None = None,
                     attribute_bits: dict | None = None, batch: np.ndarray | None = None,
                     flags: int | None = None) -> bytes:
    """The version 4 packet taking the quantized form of level ``start`` to ``stop``.

    Parameters
    ----------
    pm, start, stop, bits, attribute_bits
        As for :func:`~lodserver.packets.encode.encode_packet`.
    batch : (pm.split_count,) int array, optional
        The batch of every split (non-decreasing; within a batch ``vs`` ascending):
        a run of one batch codes its ``vs`` as gaps. Default: the mesh's own
        schedule (``pm.split_batch``, a batched build), else every split its own batch.
    flags : int, optional
        Which codings to use: :data:`~.format.EDGE_POSITIONS`,
        :data:`~.format.MAGNITUDE_CONTEXTS`, :data:`~.format.RING_POSITIONS` (only
        with the edge; default :data:`DEFAULT_FLAGS`).

    Returns
    -------
    bytes
        Header, body and CRC-32 as in docs/packets.md, "Version 4".

    Raises
    ------
    ValueError
        When ``batch`` does not fit the mesh or a run's ``vs`` are not ascending, or
        ``flags`` ask for the ring without the edge.
    """
    start, stop = pm.check_level(start), pm.check_level(stop)
    flags = DEFAULT_FLAGS if flags is None else flags
    if flags & RING_POSITIONS and not flags & EDGE_POSITIONS:
        raise ValueError("RING_POSITIONS predicts the split edge: it needs EDGE_POSITIONS")
    grid = grid_of(pm, bits=bits)
    grids = attribute_grids_of(pm, attribute_bits=attribute_bits)
    has_materials = pm.face_material is not None
    forward = stop > start
    records = abs(stop - start)
    n0, n = pm.base_vertices, pm.vertex_count
    batch = pm.split_batch if batch is None else batch
    if batch is not None:
        batch = np.asarray(batch, dtype=np.int64)
        if batch.shape != (n - n0,) or (len(batch) > 1 and np.any(np.diff(batch) < 0)):
            raise ValueError(f"a batch schedule is one non-decreasing id per split "
                             f"({n - n0} splits)")
    segments = []
    if records:
        marks = np.zeros((len(stream_names(grids, has_materials)), records + 1), dtype=np.int64)
        streams = encode_streams(pm, start, stop, grid, grids, marks)
        first = start - n0 if forward else n - start
        layout = shapes(grids, has_materials, forward, flags)
        ring = (ring_predictions(pm, start, stop, grid)
                if forward and flags & RING_POSITIONS else None)
        for r0, r1 in segment_cuts(first, records):
            slices = [s[m[r0]:m[r1]] for s, m in zip(streams, marks)]
            ids = None if batch is None else batch[first + r0:first + r1]
            segments.append(segment_bytes(slices, start + r0 if forward else None, ids, flags,
                                          layout, None if ring is None else ring[r0:r1]))
    return assemble_v4(pm, grid, grids, start, stop, flags, segments)


def segment_cuts(first: int, records: int) -> list:
    """The segments ``[(r0, r1), ...]`` of a packet's ``records`` records, the first
    of them record ``first`` counted from the base (splits) or full detail (collapses):
    cut at every multiple of :data:`SEGMENT_RECORDS`."""
    cuts = [0] + [r for r in range(1, records) if (first + r) % SEGMENT_RECORDS == 0]
    return list(zip(cuts, cuts[1:] + [records]))


def segment_bytes(slices: list, t0: int | None, ids, flags: int, layout: list,
                  ring: np.ndarray | None = None) -> bytes:
    """One segment of the body: varint records, then every coded stream, from the
    segment's version 3 stream bytes ``slices`` (``t0``, ``ids``, ``ring``: as
    :func:`_segment_symbols`; ``layout``: :func:`~.streams_v4.shapes`)."""
    fields = [_integers(s, k in BYTE_STREAMS) for k, s in enumerate(slices)]
    out = bytearray()
    put_varint(out, len(fields[POSITION]) // (6 if t0 is not None else 3))
    for symbols, ctx, shape in zip(*_segment_symbols(fields, t0, ids, flags, layout, ring),
                                   layout):
        encode_symbols(out, symbols, ctx, shape.contexts)
    return bytes(out)


def assemble_v4(pm: ProgressiveMesh, grid, grids: tuple, start: int, stop: int, flags: int,
                segments: list) -> bytes:
    """Header, the body of ``segments`` (bytes of :func:`segment_bytes`), CRC-32."""
    body = bytearray()
    put_varint(body, len(segments))
    for segment in segments:
        body += segment
    header = pack_header(grid, grids, pm.face_material is not None, start, stop,
                         pm.faces_at_level(start), pm.faces_at_level(stop), len(body),
                         version=VERSION_4, flags=flags)
    packet = header + bytes(body)
    return packet + struct.pack("<I", zlib.crc32(packet))


def _segment_symbols(fields: list, t0: int | None, ids, flags: int, layout: list,
                     ring: np.ndarray | None = None):
    """The symbols and contexts of one segment's streams (version 4 body order), from
    the integers of its version 3 streams ``fields``. ``t0``: the first new vertex of
    a split segment (None for collapses); ``ids`` its splits' batch ids (None: one
    batch each); ``ring``: with :data:`~.format.RING_POSITIONS`, the predicted split
    edge of each split (records, 3; ``ring_v4.py``)."""
    symbols = list(fields)
    vertex_contexts = None
    if t0 is not None:
        d = fields[0]
        s = t0 + np.arange(len(d), dtype=np.int64) - 1 - d
        runs, gaps, first_of_run = batch_runs(s, ids)
        symbols[0] = gaps
        vertex_contexts = np.where(first_of_run, 0, 1)
        symbols[POSITION] = position_symbols(unzigzag(fields[POSITION]).reshape(-1, 6),
                                             bool(flags & EDGE_POSITIONS),
                                             ring if flags & RING_POSITIONS else None)
        symbols.insert(0, runs)
    else:
        symbols.insert(0, np.zeros(0, dtype=np.int64))
    ctx = [vertex_contexts if shape.runs else
           face_contexts(symbols[1 + COUNT], values) if shape.faces else contexts(shape, values)
           for values, shape in zip(symbols, layout)]
    return symbols, ctx


def batch_runs(s: np.ndarray, ids) -> tuple:
    """``(runs, gaps, first_of_run)`` of a segment's splits with vertices ``s``:
    each run's length less one, each split's gap (``vs`` for the first of a run,
    else ``vs - previous - 1``) and whether it starts a run."""
    first_of_run = np.ones(len(s), dtype=bool)
    if ids is not None:
        first_of_run[1:] = ids[1:] != ids[:-1]
    gaps = s.copy()
    gaps[1:] = np.where(first_of_run[1:], s[1:], s[1:] - s[:-1] - 1)
    if np.any(gaps < 0):
        raise ValueError("a batch's splits must have ascending vertices vs")
    starts = np.flatnonzero(first_of_run)
    runs = np.diff(np.append(starts, len(s))) - 1
    return runs, gaps, first_of_run


@njit(cache=True, nogil=True)
def _varints(data):
    out = np.empty(data.shape[0], dtype=np.int64)
    n = value = shift = 0
    for byte in data:
        value |= np.int64(byte & 0x7F) << shift
        if byte < 0x80:
            out[n] = value
            n += 1
            value = shift = 0
        else:
            shift += 7
    return out[:n]


def _integers(data, raw: bool) -> np.ndarray:
    """A version 3 stream's integers: its bytes, or its varints."""
    data = np.asarray(data, dtype=np.uint8)
    return data.astype(np.int64) if raw else _varints(data)
