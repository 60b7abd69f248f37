"""The version 4 reference decoder: plain Python, the reference for clients.

docs/packets.md, "Version 4". :func:`decode_packet_v4` checks the CRC-32 and
the header, decodes every segment's streams with ``rans.py``'s
:class:`~lodserver.packets.rans.SymbolReader` (each symbol's context from the
symbols before it, ``streams_v4.py``), undoes the batch runs and the split edge,
and hands the records' fields as version 3 streams to ``reference.py``, whose
:func:`~lodserver.packets.reference.apply_packet` applies them: the records
themselves are version 3's. :func:`decode_any` reads every version.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

from .format import (
    COUNT,
    EDGE_POSITIONS,
    FAN,
    HAS_MATERIALS,
    HEADER,
    MAGNITUDE_CONTEXTS,
    MASK,
    PATTERN,
    POSITION,
    RING_POSITIONS,
    VERSION_4,
    PacketError,
    Reader,
    put_varint,
    unpack_header,
)
from .grids import AttributeGrid, Grid
from .rans import SymbolReader
from .reference import Packet, decode_packet
from .streams_v4 import (
    FACE_CONTEXTS,
    PLACE_COLUMN,
    context_of,
    position_fields,
    shapes,
    stream_names_v4,
    unzigzag,
)

# At most this many symbols per record of a segment, and this many more, in any stream
# but the position's (whose count is fixed): bounds a damaged packet's work.
SYMBOLS_PER_RECORD, SYMBOLS_SLACK = 64, 2**16
CRC = struct.Struct("<I")


def decode_any(data: bytes) -> Packet:
    """A packet of any version, parsed (versions 1-3 by ``reference.decode_packet``)."""
    data = bytes(data)
    if len(data) > 4 and data[4] == VERSION_4:
        return decode_packet_v4(data)
    return decode_packet(data)


def decode_packet_v4(data: bytes) -> Packet:
    """Parse a version 4 packet into the records' fields as version 3 streams.

    Raises
    ------
    PacketError
        On a bad checksum, header or segment, a stream that does not decode or does
        not end where its symbols do, or fields that cannot be a record's.
    """
    data = bytes(data)
    if len(data) < HEADER.size + CRC.size:
        raise PacketError(f"the packet is truncated: {len(data)} bytes is shorter than the header")
    if CRC.unpack_from(data, len(data) - CRC.size)[0] != zlib.crc32(data[:-CRC.size]):
        raise PacketError("the packet's checksum does not match: it is damaged or truncated")
    data = data[:-CRC.size]
    fields, records, at = unpack_header(data, (VERSION_4,), HAS_MATERIALS | EDGE_POSITIONS
                                        | MAGNITUDE_CONTEXTS | RING_POSITIONS)
    body = data[at:]
    if len(body) != fields["body_length"]:
        raise PacketError(f"the packet's body is {len(body)} bytes, the header says "
                          f"{fields['body_length']}")
    grids = tuple(AttributeGrid(name, encoding, origin, step, bits, width)
                  for name, width, encoding, origin, step, bits in records)
    start, stop, flags = fields["start"], fields["stop"], fields["flags"]
    if flags & RING_POSITIONS and not flags & EDGE_POSITIONS:
        raise PacketError("the packet predicts the split edge from the ring (flag 8) without "
                          "coding the edge (flag 2)")
    ring = bool(flags & RING_POSITIONS) and stop > start
    has_materials = bool(flags & HAS_MATERIALS)
    forward = stop > start
    layout = shapes(grids, has_materials, forward, flags)
    names = stream_names_v4(grids, has_materials)
    out = [bytearray() for _ in names[1:]]
    edges: list = []       # with the ring: each split's (E - P, l, r), resolved when applied
    reader = Reader(body, "segment table")
    done = 0
    for _ in range(reader.varint()):
        size = reader.varint()
        if not 0 < size <= abs(stop - start) - done:
            raise PacketError("the packet's segments do not add up to its records")
        decoded = _segment(reader, names, layout, size, forward, flags)
        if ring:
            edges.append(_edge_symbols(decoded[1 + POSITION]))
            decoded[1 + POSITION] = []
        _fields(decoded, out, start + done if forward else None, flags)
        done += size
    if done != abs(stop - start) or not reader.done():
        raise PacketError("the packet's segments do not add up to its records")
    return Packet(start, stop, fields["start_faces"], fields["stop_faces"],
                  Grid(fields["origin"], fields["step"], fields["bits"]),
                  tuple(bytes(s) for s in out), grids, has_materials,
                  np.concatenate(edges) if ring else None)


def _edge_symbols(symbols: list) -> np.ndarray:
    """(records, 7) signed ``E - P, l, r`` from a segment's position symbols."""
    e = np.array(symbols, dtype=np.int64).reshape(-1, 7)
    out = unzigzag(e)
    out[:, PLACE_COLUMN] = e[:, PLACE_COLUMN]
    return out


def _segment(reader: Reader, names, layout, size: int, forward: bool, flags: int) -> list:
    """Every stream of one segment of ``size`` records, as lists of symbols."""
    decoded = []
    run_starts: list = []      # the first split of each batch run, ascending
    for k, (name, shape) in enumerate(zip(names, layout)):
        stream = SymbolReader(reader, shape.contexts, name)
        period = shape.period
        if k == 1 + POSITION:            # positions: a fixed count per record
            if stream.count != size * period:
                raise PacketError(f"the packet's {name} stream holds {stream.count} symbols "
                                  f"for {size} records")
        elif stream.count > SYMBOLS_PER_RECORD * size + SYMBOLS_SLACK:
            raise PacketError(f"the packet's {name} stream holds more symbols than its "
                              "records can read")
        values: list = []
        if shape.runs:
            if stream.count != size:
                raise PacketError("the packet's vertex stream does not hold one gap per split")
            starts = iter(run_starts)
            start = next(starts, None)
            for i in range(size):
                first = i == start
                if first:
                    start = next(starts, None)
                values.append(stream.read(0 if first else 1))
        elif shape.faces:               # patterns: by their place in their record
            if stream.count != sum(decoded[1 + COUNT]):
                raise PacketError("the packet's pattern stream does not hold one pattern per "
                                  "new face")
            for faces in decoded[1 + COUNT]:
                for f in range(faces):
                    values.append(stream.read(0 if f == 0 else 1 + values[-1]))
                    if values[-1] >= FACE_CONTEXTS - 1:
                        raise PacketError(f"the packet holds a pattern above "
                                          f"{FACE_CONTEXTS - 2}")
        else:
            for i in range(stream.count):
                values.append(stream.read(context_of(shape, i, values)))
        stream.check_done()
        if k == 0 and not forward and values:
            raise PacketError("the packet's batch stream holds runs, but it collapses")
        if k == 0 and forward:           # batch runs: which splits start a run
            # kept as the runs' starts, not a flag per split: a damaged segment can
            # declare billions of splits in a few bytes
            covered = 0
            for length in values:
                if covered + 1 + length > size:
                    raise PacketError("the packet's batch runs hold more splits than its segment")
                run_starts.append(covered)
                covered += 1 + length
            if covered != size:
                raise PacketError("the packet's batch runs do not cover its segment")
        decoded.append(values)
    return decoded


def _fields(decoded: list, out: list, t0: int | None, flags: int) -> None:
    """Append one segment's fields to the version 3 streams ``out``, undoing the batch
    runs (``t0``: its first new vertex; None for collapses) and the split edge."""
    streams = decoded[1:]
    if t0 is not None:
        streams[0] = _vertex_codes(decoded[0], streams[0], t0)
        d = position_fields(np.array(streams[POSITION], dtype=np.int64),
                            bool(flags & EDGE_POSITIONS))
        streams[POSITION] = [int(u) for u in np.where(d >= 0, 2 * d, -2 * d - 1).ravel()]
    for k, values in enumerate(streams):
        if k in (PATTERN, FAN, MASK):
            if any(v > 255 for v in values):
                raise PacketError("the packet holds a pattern, fan or mask symbol above 255")
            out[k] += bytes(values)
        else:
            for v in values:
                put_varint(out[k], v)


def _vertex_codes(runs: list, gaps: list, t0: int) -> list:
    """Version 3's vertex codes ``t - 1 - vs`` of a segment's splits from its runs."""
    codes, i = [], 0
    for length in runs:
        s = -1
        for k in range(length + 1):
            s = gaps[i] if k == 0 else s + 1 + gaps[i]
            t = t0 + i
            if s >= t:
                raise PacketError(f"split {t} names vertex {s}, which does not exist yet")
            codes.append(t - 1 - s)
            i += 1
    return codes
