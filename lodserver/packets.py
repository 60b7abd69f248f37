"""Vertex-split packets: the bytes that take a client from one level to another.

A client holds one level of a progressive mesh in its *quantized form*
(:func:`quantized_level`, served by the LOD endpoint as ``format=json``):
integer grid positions and faces in the slots of the prefix layout
(``progressive.py``). A packet from level ``A`` to level ``B`` carries the
``|B - A|`` vertex splits (``B > A``) or edge collapses (``B < A``) between
them; applying it (:func:`apply_packet`) yields exactly the quantized form of
level ``B``: the same grid positions and the same faces in the same slots.

The byte layout is specified in ``docs/packets.md`` for clients in any language;
this module is the encoder and the reference decoder. In short:

- Positions live on a uniform grid over the bounding box of every position any
  level uses: ``x = origin + q * step`` with ``q`` in ``[0, 2**bits - 1]``.
- A split names ``vs`` by its distance below the new vertex, the corners that
  move to the new vertex as a bit mask over ``vs``'s corners, each new face's
  corners as ``vs`` / new vertex / a neighbour of ``vs`` by rank, and the two
  positions as residuals from the known position of ``vs`` (the collapse put
  ``vs`` between them). A collapse names ``vs`` by its rank among the new
  vertex's neighbours and the merged position as a residual from the midpoint.
- Each kind of field goes to its own stream of LEB128 varints or bytes, and
  the streams are deflated together (zlib), which entropy-codes each kind apart.

Neighbour ranks need connectivity, so both encoder and decoder track, for every
vertex, the set of corners (``3 * face + slot``) that hold it.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

import numpy as np

from .mesh import MeshError
from .progressive import ProgressiveMesh

MAGIC = b"LODV"
PACKET_VERSION = 1
MIN_BITS, MAX_BITS = 8, 24
# Grid steps per mean edge at full detail, as a power of two: see default_bits.
EDGE_BITS = 6

_HEADER = struct.Struct("<4sBBHIIII3ddI")
# Streams, in body order. A collapse packet leaves FAN, MASK, PATTERN and OTHER empty.
VERTEX, COUNT, PATTERN, OTHER, FAN, MASK, POSITION = range(7)
_STREAM_NAMES = ("vertex", "count", "pattern", "other", "fan", "mask", "position")
# FAN: whether a split's moved corners are the predicted fan (0) or listed in MASK (1).
_FAN_PREDICTED, _FAN_LISTED = 0, 1
# A face corner in a split's new face is vs, the new vertex, or another vertex.
_IS_VS, _IS_NEW, _IS_OTHER = 0, 1, 2


class PacketError(MeshError):
    """A packet cannot be decoded or does not fit the state it is applied to."""


@dataclass(frozen=True)
class Grid:
    """The quantization grid: ``position = origin + q * step`` per axis.

    origin : (3,) float64   smallest coordinate of any position at any level
    step : float            grid spacing, the same on all axes (mesh units)
    bits : int              grid coordinates lie in ``[0, 2**bits - 1]``
    """

    origin: tuple[float, float, float]
    step: float
    bits: int

    def quantize(self, points: np.ndarray) -> np.ndarray:
        """(k, 3) float positions -> (k, 3) int64 grid coordinates (nearest)."""
        q = np.rint((np.asarray(points, dtype=np.float64) - np.array(self.origin)) / self.step)
        return np.clip(q, 0, 2**self.bits - 1).astype(np.int64)

    def dequantize(self, q: np.ndarray) -> np.ndarray:
        """(k, 3) grid coordinates -> (k, 3) float64 positions, as a client computes them."""
        return np.array(self.origin) + np.asarray(q, dtype=np.float64) * self.step

    def as_dict(self) -> dict:
        return {"origin": list(self.origin), "step": self.step, "bits": self.bits}


def default_bits(pm: ProgressiveMesh) -> int:
    """Grid bits giving about ``2**EDGE_BITS`` steps along a full-detail edge.

    A mesh of ``n`` vertices spanning its box has edges of about
    ``extent / sqrt(n)``, so ``log2(n) / 2 + EDGE_BITS`` bits keep the rounding
    error at the same fraction of an edge on every mesh, and so the packet's
    bytes per split about the same too. Clamped to [10, 16].
    """
    return int(np.clip(np.ceil(np.log2(max(pm.vertex_count, 2)) / 2) + EDGE_BITS, 10, 16))


def grid_of(pm: ProgressiveMesh, *, bits: int | None = None) -> Grid:
    """The grid of ``pm`` at ``bits`` bits: a cube over every position any level uses.

    One step for all axes keeps the rounding error isotropic: at most
    ``step / 2`` per coordinate, ``step = extent / (2**bits - 1)``. ``bits``
    defaults to :func:`default_bits`.
    """
    bits = default_bits(pm) if bits is None else check_bits(bits)
    points = np.concatenate([pm.positions, pm.coarse_position])
    lo = points.min(axis=0)
    extent = float((points.max(axis=0) - lo).max())
    step = extent / (2**bits - 1) if extent > 0 else 1.0
    return Grid(tuple(float(x) for x in lo), step, bits)


def check_bits(bits) -> int:
    bits = int(bits)
    if not MIN_BITS <= bits <= MAX_BITS:
        raise ValueError(f"bits must be in [{MIN_BITS}, {MAX_BITS}], got {bits}")
    return bits


@dataclass(frozen=True, eq=False)
class LodState:
    """One level as a client holds it.

    positions : (v, 3) int64   grid coordinates of vertices ``0 .. v-1``
    faces : (f, 3) int64       the level's faces, in prefix-layout slots
    grid : Grid                how grid coordinates map to positions
    """

    positions: np.ndarray
    faces: np.ndarray
    grid: Grid

    @property
    def level(self) -> int:
        return len(self.positions)


def state_from_json(document: dict) -> LodState:
    """The state held by a client that fetched ``/lod?format=json`` (``export.encode_level``)."""
    grid = document["grid"]
    return LodState(np.array(document["positions"], dtype=np.int64).reshape(-1, 3),
                    np.array(document["faces"], dtype=np.int64).reshape(-1, 3),
                    Grid(tuple(float(x) for x in grid["origin"]), float(grid["step"]),
                         int(grid["bits"])))


def quantized_level(pm: ProgressiveMesh, level: int, grid: Grid) -> LodState:
    """The quantized form of ``level``: what the LOD endpoint serves as JSON."""
    positions, faces = pm.arrays_at(level)
    return LodState(grid.quantize(positions), faces, grid)


# ---- varints ----------------------------------------------------------------
def _put_varint(out: bytearray, value: int) -> None:
    """Unsigned LEB128: 7 bits per byte, low bits first, high bit = more follows."""
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)


def _zigzag(value: int) -> int:
    """Signed -> unsigned, small magnitudes first: 0, -1, 1, -2, ... -> 0, 1, 2, 3, ..."""
    return 2 * value if value >= 0 else -2 * value - 1


class _Reader:
    """Sequential reads from one stream; running past its end is a PacketError."""

    def __init__(self, data: bytes, name: str):
        self.data, self.at, self.name = data, 0, name

    def varint(self) -> int:
        value = shift = 0
        data, at = self.data, self.at
        while True:
            if at >= len(data):
                raise PacketError(f"the packet's {self.name} stream ends in the middle of a record")
            byte = data[at]
            at += 1
            value |= (byte & 0x7F) << shift
            if byte < 0x80:
                break
            shift += 7
            if shift > 63:
                raise PacketError(f"the packet's {self.name} stream holds an overlong varint")
        self.at = at
        return value

    def signed(self) -> int:
        u = self.varint()
        return (u >> 1) ^ -(u & 1)

    def take(self, size: int) -> bytes:
        if self.at + size > len(self.data):
            raise PacketError(f"the packet's {self.name} stream ends in the middle of a record")
        chunk = self.data[self.at:self.at + size]
        self.at += size
        return chunk

    def done(self) -> bool:
        return self.at == len(self.data)


# ---- connectivity shared by encoder and decoder ------------------------------
class _Corners:
    """For each vertex, the set of corners ``3 * face + slot`` that hold it.

    Built from the starting faces with one argsort; a vertex's set is made
    only when a record touches it, so the cost follows the packet, not the mesh.
    """

    def __init__(self, faces: np.ndarray, vertex_capacity: int):
        flat = faces.ravel()
        self._order = np.argsort(flat, kind="stable")
        self._offsets = np.zeros(vertex_capacity + 1, dtype=np.int64)
        np.cumsum(np.bincount(flat, minlength=vertex_capacity), out=self._offsets[1:])
        self._sets: dict[int, set[int]] = {}

    def of(self, v: int) -> set[int]:
        found = self._sets.get(v)
        if found is None:
            found = set(self._order[self._offsets[v]:self._offsets[v + 1]].tolist())
            self._sets[v] = found
        return found


class _Working:
    """Mutable arrays with room for both end levels, plus connectivity."""

    def __init__(self, positions: np.ndarray, faces: np.ndarray, vertex_capacity: int,
                 face_capacity: int):
        self.positions = np.zeros((max(vertex_capacity, len(positions)), 3), dtype=np.int64)
        self.positions[:len(positions)] = positions
        self.faces = np.zeros((max(face_capacity, len(faces)), 3), dtype=np.int64)
        self.faces[:len(faces)] = faces
        self.face_count = len(faces)
        self.corners = _Corners(np.asarray(faces, dtype=np.int64), len(self.positions))

    def neighbours(self, v: int) -> list[int]:
        """Vertices sharing a face with ``v``, ascending."""
        faces = self.faces
        found = set()
        for c in self.corners.of(v):
            f, k = divmod(c, 3)
            found.add(int(faces[f, (k + 1) % 3]))
            found.add(int(faces[f, (k + 2) % 3]))
        found.discard(v)
        return sorted(found)

    def set_corner(self, c: int, v: int) -> None:
        f, k = divmod(c, 3)
        self.corners.of(int(self.faces[f, k])).discard(c)
        self.faces[f, k] = v
        self.corners.of(v).add(c)

    def append_face(self, corners) -> None:
        f = self.face_count
        self.faces[f] = corners
        for k in range(3):
            self.corners.of(int(corners[k])).add(3 * f + k)
        self.face_count += 1

    def pop_face(self) -> None:
        self.face_count -= 1
        f = self.face_count
        for k in range(3):
            self.corners.of(int(self.faces[f, k])).discard(3 * f + k)


# ---- encoding ----------------------------------------------------------------
def encode_packet(pm: ProgressiveMesh, start: int, stop: int, *,
                  bits: int | None = None) -> bytes:
    """The packet taking the quantized form of level ``start`` to level ``stop``.

    Parameters
    ----------
    pm : ProgressiveMesh
    start, stop : int
        Levels (vertex counts) in ``pm.levels``; ``stop < start`` gives collapses.
    bits : int, optional
        Grid resolution, as for :func:`grid_of` (default :func:`default_bits`).

    Returns
    -------
    bytes
        Header and deflated streams as documented in ``docs/packets.md``.
    """
    start, stop = pm._check_level(start), pm._check_level(stop)
    grid = grid_of(pm, bits=bits)
    positions, faces = pm.arrays_at(start)
    state = _Working(grid.quantize(positions), faces, max(start, stop),
                     max(pm.faces_at_level(start), pm.faces_at_level(stop)))
    streams = [bytearray() for _ in _STREAM_NAMES]
    if stop > start:
        _encode_splits(pm, state, start, stop, grid, streams)
    else:
        _encode_collapses(pm, state, start, stop, grid, streams)
    body = bytearray()
    for stream in streams:
        _put_varint(body, len(stream))
        body += stream
    header = _HEADER.pack(MAGIC, PACKET_VERSION, grid.bits, 0, start, stop,
                          pm.faces_at_level(start), pm.faces_at_level(stop),
                          *grid.origin, grid.step, len(body))
    return header + zlib.compress(bytes(body), 9)


def _encode_splits(pm, state, start, stop, grid, streams):
    n0 = pm.base_vertices
    fine = grid.quantize(pm.fine_position[start - n0:stop - n0])
    new = grid.quantize(pm.new_position[start - n0:stop - n0])
    for t in range(start, stop):
        j = t - n0
        s = int(pm.parent[t])
        _put_varint(streams[VERTEX], t - 1 - s)
        held = sorted(state.corners.of(s))
        around = state.neighbours(s)

        first, last = int(pm.face_counts[j]), int(pm.face_counts[j + 1])
        _put_varint(streams[COUNT], last - first)
        rank = {v: i for i, v in enumerate(around)}
        added = pm.birth_faces[first:last].tolist()
        for corners in added:
            pattern = 0
            for v in corners:
                kind = _IS_VS if v == s else _IS_NEW if v == t else _IS_OTHER
                pattern = 3 * pattern + kind
                if kind == _IS_OTHER:
                    _put_varint(streams[OTHER], rank[v] if v in rank else len(around) + v)
            streams[PATTERN].append(pattern)

        moved = pm.moved_corners[pm.moved_offsets[j]:pm.moved_offsets[j + 1]].tolist()
        if _predict_fan(state, s, t, added) == set(moved):
            streams[FAN].append(_FAN_PREDICTED)
        else:
            streams[FAN].append(_FAN_LISTED)
            rank = {c: i for i, c in enumerate(held)}
            mask = bytearray((len(held) + 7) // 8)
            for c in moved:
                if c not in rank:
                    raise PacketError(f"split {t} moves corner {c}, which does not hold vertex {s}")
                mask[rank[c] // 8] |= 1 << (rank[c] % 8)
            streams[MASK] += mask
        for c in moved:
            state.set_corner(c, t)
        for corners in added:
            state.append_face(corners)

        coarse = state.positions[s]
        for d in (fine[j - (start - n0)] - coarse).tolist():
            _put_varint(streams[POSITION], _zigzag(d))
        # The collapse placed vs between the two, so new ~ 2 * coarse - fine.
        for d in (new[j - (start - n0)] + fine[j - (start - n0)] - 2 * coarse).tolist():
            _put_varint(streams[POSITION], _zigzag(d))
        state.positions[s] = fine[j - (start - n0)]
        state.positions[t] = new[j - (start - n0)]


def _predict_fan(state, s: int, t: int, added: list) -> set[int] | None:
    """The corners of ``s`` a split moves to ``t``, predicted from its new faces.

    On a consistently oriented manifold (Hoppe 1996, fig. 2) the new faces are
    ``(s, t, vl)`` and ``(t, s, vr)`` up to rotation, and the moved corners are
    the fan of faces around ``s`` from the edge ``(vl, s)`` to the edge
    ``(s, vr)``: walk it face by face across shared edges. With only one new
    face (a border) the walk runs to the border. Returns None where the walk is
    ambiguous (a non-manifold edge at ``s``) or there is no new face to start
    from; the encoder then lists the corners explicitly.
    """
    forward = backward = None   # vl and vr
    for corners in added:
        if s not in corners or t not in corners:
            return None
        i, k = corners.index(s), corners.index(t)
        if (i + 1) % 3 == k:
            forward = corners[(k + 1) % 3]
        else:
            backward = corners[(i + 1) % 3]
    faces = state.faces
    by_prev, by_next = {}, {}
    for c in state.corners.of(s):
        f, k = divmod(c, 3)
        for table, key in ((by_next, int(faces[f, (k + 1) % 3])),
                           (by_prev, int(faces[f, (k + 2) % 3]))):
            # -1 marks a key held by two corners: the fan splits there
            table[key] = -1 if key in table else c
    if forward is not None:
        table, step, y, end = by_prev, 1, forward, backward
    elif backward is not None:
        table, step, y, end = by_next, 2, backward, None
    else:
        return None
    fan = set()
    while True:
        c = table.get(y)
        if c is None or c in fan:
            return fan
        if c < 0:
            return None
        fan.add(c)
        f, k = divmod(c, 3)
        y = int(faces[f, (k + step) % 3])
        if y == end:
            return fan


def _encode_collapses(pm, state, start, stop, grid, streams):
    n0 = pm.base_vertices
    coarse = grid.quantize(pm.coarse_position[stop - n0:start - n0])
    for t in range(start - 1, stop - 1, -1):
        j = t - n0
        s = int(pm.parent[t])
        around = state.neighbours(t)
        code = around.index(s) if s in around else len(around) + s
        _put_varint(streams[VERTEX], code)
        first, last = int(pm.face_counts[j]), int(pm.face_counts[j + 1])
        _put_varint(streams[COUNT], last - first)
        for _ in range(last - first):
            state.pop_face()
        for c in list(state.corners.of(t)):
            state.set_corner(c, s)
        target = coarse[j - (stop - n0)]
        middle = (state.positions[s] + state.positions[t]) >> 1
        for d in (target - middle).tolist():
            _put_varint(streams[POSITION], _zigzag(d))
        state.positions[s] = target


# ---- decoding ----------------------------------------------------------------
@dataclass(frozen=True)
class Packet:
    """A parsed packet: header fields and its raw streams (not yet applied)."""

    start: int
    stop: int
    start_faces: int
    stop_faces: int
    grid: Grid
    streams: tuple[bytes, ...]

    @property
    def records(self) -> int:
        return abs(self.stop - self.start)


def decode_packet(data: bytes) -> Packet:
    """Parse a packet's header and inflate its streams.

    Raises
    ------
    PacketError
        On a bad magic, version, length, deflate stream or stream table.
    """
    data = bytes(data)
    if len(data) < _HEADER.size:
        raise PacketError(f"the packet is truncated: {len(data)} bytes is shorter than the header")
    (magic, version, bits, _reserved, start, stop, start_faces, stop_faces,
     ox, oy, oz, step, body_length) = _HEADER.unpack_from(data)
    if magic != MAGIC:
        raise PacketError("this is not a lodserver vsplit packet (bad magic bytes)")
    if version != PACKET_VERSION:
        raise PacketError(f"the packet has version {version}; this decoder reads {PACKET_VERSION}")
    try:
        body = zlib.decompress(data[_HEADER.size:])
    except zlib.error as exc:
        raise PacketError(f"the packet's body does not inflate ({exc})") from exc
    if len(body) != body_length:
        raise PacketError(f"the packet's body is {len(body)} bytes, the header says {body_length}")
    table = _Reader(body, "stream table")
    streams = []
    for _ in _STREAM_NAMES:
        streams.append(table.take(table.varint()))
    if not table.done():
        raise PacketError("the packet's body has bytes after its last stream")
    return Packet(start, stop, start_faces, stop_faces, Grid((ox, oy, oz), step, bits),
                  tuple(streams))


def apply_packet(state: LodState, packet) -> LodState:
    """The state at ``packet.stop``, from ``state`` at ``packet.start``.

    Parameters
    ----------
    state : LodState
        The client's level, as served by the LOD endpoint (or left by a packet).
    packet : Packet or bytes

    Returns
    -------
    LodState
        A new state; ``state`` is not changed.

    Raises
    ------
    PacketError
        If the packet is malformed or starts from another level, face count or grid.
    """
    if not isinstance(packet, Packet):
        packet = decode_packet(packet)
    if (state.level, len(state.faces)) != (packet.start, packet.start_faces):
        raise PacketError(f"the packet starts at level {packet.start} with {packet.start_faces} "
                          f"faces; the state is at level {state.level} with {len(state.faces)}")
    if state.grid != packet.grid:
        raise PacketError("the packet was made for another quantization grid than the state's")
    work = _Working(state.positions, state.faces, max(packet.start, packet.stop),
                    max(packet.start_faces, packet.stop_faces))
    readers = [_Reader(s, name) for s, name in zip(packet.streams, _STREAM_NAMES)]
    try:
        if packet.stop > packet.start:
            _apply_splits(work, packet.start, packet.stop, readers)
        else:
            _apply_collapses(work, packet.start, packet.stop, readers)
    except (IndexError, KeyError, ValueError) as exc:
        raise PacketError(f"the packet does not fit the state ({exc})") from exc
    if not all(r.done() for r in readers):
        raise PacketError("the packet's streams hold more than its records")
    if work.face_count != packet.stop_faces:
        raise PacketError(f"the packet left {work.face_count} faces, its header says "
                          f"{packet.stop_faces}")
    limit = 2**packet.grid.bits - 1
    positions = work.positions[:packet.stop].copy()
    if positions.min(initial=0) < 0 or positions.max(initial=0) > limit:
        raise PacketError("the packet moves a vertex off the grid")
    return LodState(positions, work.faces[:work.face_count].copy(), state.grid)


def _apply_splits(work: _Working, start, stop, readers):
    vertex, count, pattern, other, fan, mask, position = readers
    for t in range(start, stop):
        s = t - 1 - vertex.varint()
        if s < 0:
            raise PacketError(f"split {t} names a vertex below 0")
        held = sorted(work.corners.of(s))
        around = work.neighbours(s)
        added = []
        for _ in range(count.varint()):
            code = pattern.take(1)[0]
            corners = []
            for kind in (code // 9, code // 3 % 3, code % 3):
                if kind == _IS_VS:
                    corners.append(s)
                elif kind == _IS_NEW:
                    corners.append(t)
                else:
                    u = other.varint()
                    corners.append(around[u] if u < len(around) else u - len(around))
            if max(corners) > t:
                raise PacketError(f"split {t} adds a face on a vertex that does not exist yet")
            added.append(corners)

        if fan.take(1)[0] == _FAN_PREDICTED:
            moved = _predict_fan(work, s, t, added)
            if moved is None:
                raise PacketError(f"split {t} relies on a fan prediction that does not exist")
        else:
            bits = mask.take((len(held) + 7) // 8)
            moved = [c for i, c in enumerate(held) if bits[i // 8] >> (i % 8) & 1]
        for c in moved:
            work.set_corner(c, t)
        for corners in added:
            work.append_face(corners)

        coarse = work.positions[s].copy()
        fine = coarse + [position.signed() for _ in range(3)]
        work.positions[s] = fine
        work.positions[t] = 2 * coarse - fine + [position.signed() for _ in range(3)]


def _apply_collapses(work: _Working, start, stop, readers):
    vertex, count, _, _, _, _, position = readers
    for t in range(start - 1, stop - 1, -1):
        around = work.neighbours(t)
        u = vertex.varint()
        s = around[u] if u < len(around) else u - len(around)
        if not 0 <= s < t:
            raise PacketError(f"collapse of {t} names vertex {s}, which is not below it")
        removed = count.varint()
        if removed > work.face_count:
            raise PacketError(f"collapse of {t} removes more faces than the state holds")
        for _ in range(removed):
            work.pop_face()
        for c in list(work.corners.of(t)):
            work.set_corner(c, s)
        middle = (work.positions[s] + work.positions[t]) >> 1
        work.positions[s] = middle + [position.signed() for _ in range(3)]
