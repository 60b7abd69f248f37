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
vertex, the set of corners (``3 * face + slot``) that hold it. The decoder is
plain Python, written to be read as the reference for clients; the encoder runs
the same logic as numba kernels over arrays (see "encoding" below), checked
byte for byte against a pure-Python encoder kept in ``tests/naive_packets.py``.
"""

from __future__ import annotations

import struct
import threading
import weakref
import zlib
from dataclasses import dataclass

import numpy as np
from numba import njit

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
    lo, extent = _box_of(pm)
    step = extent / (2**bits - 1) if extent > 0 else 1.0
    return Grid(lo, step, bits)


# The box of each progressive mesh in use, so that a request on a big mesh does not
# scan every position again (a ProgressiveMesh is immutable).
_boxes: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_boxes_lock = threading.Lock()


def _box_of(pm: ProgressiveMesh) -> tuple[tuple[float, float, float], float]:
    """The smallest coordinate of any position at any level, per axis, and the
    largest extent over the axes."""
    with _boxes_lock:
        box = _boxes.get(pm)
    if box is None:
        points = np.concatenate([pm.positions, pm.coarse_position])
        lo = points.min(axis=0)
        box = tuple(float(x) for x in lo), float((points.max(axis=0) - lo).max())
        with _boxes_lock:
            _boxes[pm] = box
    return box


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


# ---- connectivity, as the reference decoder tracks it -------------------------
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


# ---- encoding ----------------------------------------------------------------
# The encoder's loops are numba kernels over plain arrays (``_``-prefixed, below
# ``encode_packet``). They write exactly the bytes of the straightforward encoder
# kept as the reference in ``tests/naive_packets.py``, which tracks corner sets
# with Python sets and dicts as the decoder above does. In the kernels:
#
# - ``faces`` is flat: corner ``c`` reads ``faces[c]``; face ``f`` is ``faces[3f:3f+3]``.
#   It and the corner lists are int32 when the ids fit (half the memory traffic:
#   on a big mesh the records touch vertices all over it, so memory latency rules).
# - ``corners(v)`` is a block of a pool (``_corner_blocks``), in no order: reading a
#   vertex's corners is one or two cache lines, not a chain of dependent loads.
# - A record copies what it needs about its vertex into a small scratch table
#   (``_gather``): ``held`` ascending, each corner's next and prev vertex, and the
#   neighbours ascending. Ranks are binary searches in it, and the fan walk's
#   lookups by next or prev vertex are binary searches over an argsort of those
#   columns, so a record costs O(d log d) for a vertex with d corners.
# - Each stream is a ``uint8`` buffer with room for its longest possible varints
#   (pages never written are never touched) and a used length; ``_put`` writes a varint.

# rows of the scratch table
_HELD, _NEXT, _PREV, _BY_NEXT, _BY_PREV, _IN_FAN, _MOVED, _AROUND = range(8)
_SCRATCH_ROWS = 8
# The longest varint: 64 bits in groups of 7.
_VARINT_MAX = 10
# Below this many items the kernels sort by insertion.
_INSERTION_SORT = 16
# Spare room in a vertex's block of corners at the start, and the smallest new block.
_SLACK, _BLOCK = 4, 8


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
    n0 = pm.base_vertices
    # room for both end levels; the kernels change these in place
    face_capacity = max(pm.faces_at_level(start), pm.faces_at_level(stop))
    index = _index_dtype(3 * face_capacity, pm.vertex_count)
    work_positions = np.zeros((max(start, stop), 3), dtype=np.int64)
    work_positions[:start] = grid.quantize(positions)
    work_faces = np.zeros(3 * face_capacity, dtype=index)
    work_faces[:faces.size] = faces.ravel()
    if stop > start:
        lo, hi = start - n0, stop - n0
        streams, error = _encode_splits(
            work_positions, work_faces, len(faces), start, stop, n0, pm.parent, pm.face_counts,
            pm.birth_faces, pm.moved_offsets, pm.moved_corners,
            grid.quantize(pm.fine_position[lo:hi]), grid.quantize(pm.new_position[lo:hi]))
        t, c, s = (int(x) for x in error)
        if t >= 0:
            raise PacketError(f"split {t} moves corner {c}, which does not hold vertex {s}")
    else:
        streams = _encode_collapses(work_positions, work_faces, len(faces), start, stop, n0,
                                    pm.parent, pm.face_counts,
                                    grid.quantize(pm.coarse_position[stop - n0:start - n0]))
    body = bytearray()
    for stream in streams:
        _put_varint(body, len(stream))
        body += memoryview(stream)
    header = _HEADER.pack(MAGIC, PACKET_VERSION, grid.bits, 0, start, stop,
                          pm.faces_at_level(start), pm.faces_at_level(stop),
                          *grid.origin, grid.step, len(body))
    return header + zlib.compress(bytes(body), 9)


def _index_dtype(corners: int, vertices: int):
    """The kernels' integer type for corner and vertex ids: int32 when they fit."""
    return np.int32 if max(corners, vertices) < 2**31 else np.int64


@njit(cache=True, nogil=True)
def _put(buf, used, value):
    """Write the unsigned varint of ``value >= 0`` at ``buf[used:]`` (the caller
    leaves room for ``_VARINT_MAX`` bytes); returns the new used length."""
    while value >= 0x80:
        buf[used] = (value & 0x7F) | 0x80
        used += 1
        value >>= 7
    buf[used] = value
    return used + 1


@njit(cache=True, nogil=True)
def _zz(value):
    """Signed -> unsigned, small magnitudes first: 0, -1, 1, -2, ... -> 0, 1, 2, 3, ..."""
    return 2 * value if value >= 0 else -2 * value - 1


@njit(cache=True, nogil=True)
def _sort(a, n):
    """Sort ``a[:n]`` in place."""
    if n > _INSERTION_SORT:
        a[:n] = np.sort(a[:n])
        return
    for i in range(1, n):
        x = a[i]
        k = i - 1
        while k >= 0 and a[k] > x:
            a[k + 1] = a[k]
            k -= 1
        a[k + 1] = x


@njit(cache=True, nogil=True)
def _argsort(keys, n, order):
    """``order[:n]``: the indices of ``keys[:n]`` by ascending key (ties in any order)."""
    if n > _INSERTION_SORT:
        order[:n] = np.argsort(keys[:n])
        return
    for i in range(n):
        x = i
        k = i - 1
        while k >= 0 and keys[order[k]] > keys[x]:
            order[k + 1] = order[k]
            k -= 1
        order[k + 1] = x


@njit(cache=True, nogil=True)
def _search(a, n, x):
    """The first ``i`` in ``[0, n]`` with ``a[i] >= x`` (``a[:n]`` ascending)."""
    lo, hi = 0, n
    while lo < hi:
        mid = (lo + hi) >> 1
        if a[mid] < x:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True, nogil=True)
def _lookup(keys, order, n, x):
    """The ``i`` with ``keys[i] == x`` (``keys`` ascending through ``order[:n]``):
    -1 when there is none, -2 when there are several."""
    lo, hi = 0, n
    while lo < hi:
        mid = (lo + hi) >> 1
        if keys[order[mid]] < x:
            lo = mid + 1
        else:
            hi = mid
    if lo == n or keys[order[lo]] != x:
        return -1
    if lo + 1 < n and keys[order[lo + 1]] == x:
        return -2
    return order[lo]


@njit(cache=True, nogil=True)
def _corner_blocks(faces, face_count, vertex_capacity):
    """The corner lists of the first ``face_count`` faces: ``(blocks, pool, end, slot)``.

    Vertex ``v``'s corners are ``pool[blocks[v, 0] : blocks[v, 0] + blocks[v, 1]]``
    (in no order), in a block of ``blocks[v, 2]`` entries; ``slot[c]`` is corner
    ``c``'s place in its block. Each block starts with some slack.
    """
    blocks = np.zeros((vertex_capacity, 3), dtype=np.int64)
    for c in range(3 * face_count):
        blocks[faces[c], 1] += 1
    at = 0
    for v in range(vertex_capacity):
        size = blocks[v, 1]
        blocks[v, 0] = at
        blocks[v, 2] = size + _SLACK if size else 0
        blocks[v, 1] = 0
        at += blocks[v, 2]
    pool = np.empty(max(2 * at, 1024), dtype=faces.dtype)
    slot = np.empty(faces.shape[0], dtype=faces.dtype)
    for c in range(3 * face_count):
        v = faces[c]
        k = blocks[v, 1]
        pool[blocks[v, 0] + k] = c
        slot[c] = k
        blocks[v, 1] = k + 1
    return blocks, pool, at, slot


@njit(cache=True, nogil=True)
def _add(blocks, pool, end, slot, v, c):
    """Add corner ``c`` to ``corners(v)``, moving the block to the end of the pool
    (``end``, its used length) when full. Returns ``(pool, end)``, the pool grown if needed."""
    size = blocks[v, 1]
    if size == blocks[v, 2]:
        room = max(_BLOCK, 2 * size)
        if end + room > pool.shape[0]:
            bigger = np.empty(2 * (end + room), dtype=pool.dtype)
            bigger[:end] = pool[:end]
            pool = bigger
        first = blocks[v, 0]
        for k in range(size):
            pool[end + k] = pool[first + k]
        blocks[v, 0] = end
        blocks[v, 2] = room
        end += room
    pool[blocks[v, 0] + size] = c
    slot[c] = size
    blocks[v, 1] = size + 1
    return pool, end


@njit(cache=True, nogil=True)
def _remove(blocks, pool, slot, v, c):
    """Remove corner ``c`` from ``corners(v)`` (it must be there): the block's last
    corner takes its slot."""
    first = blocks[v, 0]
    size = blocks[v, 1] - 1
    last = pool[first + size]
    pool[first + slot[c]] = last
    slot[last] = slot[c]
    blocks[v, 1] = size


@njit(cache=True, nogil=True)
def _gather(faces, blocks, pool, v, scratch):
    """Fill the scratch table for vertex ``v``: ``held(v)`` ascending, the next and
    prev vertex of each, and ``neighbours(v)`` ascending. Returns the (possibly
    grown) table, the number of corners and the number of neighbours."""
    first, d = blocks[v, 0], blocks[v, 1]
    if 2 * d > scratch.shape[1]:
        scratch = np.empty((_SCRATCH_ROWS, 2 * max(d, scratch.shape[1])), dtype=np.int64)
    held, nexts, prevs, around = scratch[_HELD], scratch[_NEXT], scratch[_PREV], scratch[_AROUND]
    for i in range(d):
        held[i] = pool[first + i]
    _sort(held, d)
    na = 0
    for i in range(d):
        c = held[i]
        f3 = c - c % 3
        nexts[i] = faces[f3 + (c - f3 + 1) % 3]
        prevs[i] = faces[f3 + (c - f3 + 2) % 3]
        if nexts[i] != v:
            around[na] = nexts[i]
            na += 1
        if prevs[i] != v:
            around[na] = prevs[i]
            na += 1
    _sort(around, na)
    distinct = 0
    for i in range(na):
        if distinct == 0 or around[i] != around[distinct - 1]:
            around[distinct] = around[i]
            distinct += 1
    return scratch, d, distinct


@njit(cache=True, nogil=True)
def _predicted_fan(scratch, d, s, t, birth_faces, first, last):
    """:func:`_predict_fan` on the scratch table of ``s``: the size of the fan,
    whose corners get ``scratch[_IN_FAN, i] = 1``, or -1 where there is no prediction."""
    vl = vr = -1                  # none (vertex ids are >= 0)
    for f in range(first, last):
        i = k = -1
        for x in range(3):
            if i < 0 and birth_faces[f, x] == s:
                i = x
            if k < 0 and birth_faces[f, x] == t:
                k = x
        if i < 0 or k < 0:
            return -1
        if (i + 1) % 3 == k:
            vl = birth_faces[f, (k + 1) % 3]
        else:
            vr = birth_faces[f, (i + 1) % 3]
    if vl >= 0:                   # look up corners by prev, step to next, stop at vr
        keys, order, step, y, end = scratch[_PREV], scratch[_BY_PREV], 1, vl, vr
    elif vr >= 0:                 # by next, step to prev, no stop
        keys, order, step, y, end = scratch[_NEXT], scratch[_BY_NEXT], 2, vr, -1
    else:
        return -1
    _argsort(keys, d, order)
    in_fan = scratch[_IN_FAN]
    in_fan[:d] = 0
    size = 0
    while True:
        i = _lookup(keys, order, d, y)
        if i == -1:
            return size
        if i == -2:
            return -1             # ambiguous: a non-manifold edge at s
        if in_fan[i]:
            return size
        in_fan[i] = 1
        size += 1
        y = scratch[_NEXT, i] if step == 1 else scratch[_PREV, i]
        if end >= 0 and y == end:
            return size


@njit(cache=True, nogil=True)
def _encode_splits(positions, faces, face_count, start, stop, base, parent, face_counts,
                   birth_faces, moved_offsets, moved_corners, fine, new):
    """The streams of split records ``start .. stop-1``.

    ``positions`` (v, 3) and flat ``faces`` hold the quantized state at ``start``
    (``face_count`` faces) with room for ``stop``, and are changed in place;
    ``fine`` and ``new`` are the quantized positions of splits ``start ..``.
    Returns the seven streams and ``(t, c, s)`` of the first moved corner that
    does not hold ``vs`` (all -1 when there is none; the streams are then complete).
    """
    blocks, pool, end, slot = _corner_blocks(faces, face_count, positions.shape[0])
    records = stop - start
    added = face_counts[stop - base] - face_counts[start - base]
    vertex = np.empty(_VARINT_MAX * records, dtype=np.uint8)
    count = np.empty(_VARINT_MAX * records, dtype=np.uint8)
    pattern = np.empty(added, dtype=np.uint8)
    other = np.empty(3 * _VARINT_MAX * added, dtype=np.uint8)
    fan = np.empty(records, dtype=np.uint8)
    mask = np.empty(64, dtype=np.uint8)          # grown when needed
    position = np.empty(6 * _VARINT_MAX * records, dtype=np.uint8)
    n_vertex = n_count = n_pattern = n_other = n_mask = n_position = 0
    error = np.full(3, -1, dtype=np.int64)
    scratch = np.empty((_SCRATCH_ROWS, 64), dtype=np.int64)

    for t in range(start, stop):
        j = t - base
        s = parent[t]
        n_vertex = _put(vertex, n_vertex, t - 1 - s)
        scratch, d, na = _gather(faces, blocks, pool, s, scratch)
        held, around = scratch[_HELD], scratch[_AROUND]

        first, last = face_counts[j], face_counts[j + 1]
        n_count = _put(count, n_count, last - first)
        for f in range(first, last):
            code = 0
            for k in range(3):
                v = birth_faces[f, k]
                if v == s:
                    kind = _IS_VS
                elif v == t:
                    kind = _IS_NEW
                else:
                    kind = _IS_OTHER
                    rank = _search(around, na, v)
                    n_other = _put(other, n_other,
                                   rank if rank < na and around[rank] == v else na + v)
                code = 3 * code + kind
            pattern[n_pattern] = code
            n_pattern += 1

        size = _predicted_fan(scratch, d, s, t, birth_faces, first, last)
        m0, m1 = moved_offsets[j], moved_offsets[j + 1]
        predicted = size >= 0
        if predicted:             # the fan equals the set of moved corners?
            in_fan, moved = scratch[_IN_FAN], scratch[_MOVED]
            moved[:d] = 0
            distinct = 0
            for x in range(m0, m1):
                c = moved_corners[x]
                i = _search(held, d, c)
                if i == d or held[i] != c or not in_fan[i]:
                    predicted = False
                    break
                if not moved[i]:
                    moved[i] = 1
                    distinct += 1
            predicted = predicted and distinct == size
        fan[t - start] = _FAN_PREDICTED if predicted else _FAN_LISTED
        if not predicted:
            width = (d + 7) // 8
            if n_mask + width > mask.shape[0]:
                bigger = np.empty(max(2 * mask.shape[0], n_mask + width), dtype=np.uint8)
                bigger[:n_mask] = mask[:n_mask]
                mask = bigger
            mask[n_mask:n_mask + width] = 0
            for x in range(m0, m1):
                c = moved_corners[x]
                i = _search(held, d, c)          # c's place in held(s)
                if i == d or held[i] != c:
                    error[0], error[1], error[2] = t, c, s
                    return (vertex[:n_vertex], count[:n_count], pattern[:n_pattern],
                            other[:n_other], fan[:t - start], mask[:n_mask],
                            position[:n_position]), error
                mask[n_mask + i // 8] |= 1 << (i % 8)
            n_mask += width
        for x in range(m0, m1):
            c = moved_corners[x]
            _remove(blocks, pool, slot, faces[c], c)
            faces[c] = t
            pool, end = _add(blocks, pool, end, slot, t, c)
        for f in range(first, last):
            for k in range(3):
                c = 3 * face_count + k
                faces[c] = birth_faces[f, k]
                pool, end = _add(blocks, pool, end, slot, faces[c], c)
            face_count += 1

        i = t - start
        # The collapse placed vs between the two, so new ~ 2 * coarse - fine.
        for a in range(3):
            n_position = _put(position, n_position, _zz(fine[i, a] - positions[s, a]))
        for a in range(3):
            n_position = _put(position, n_position,
                              _zz(new[i, a] + fine[i, a] - 2 * positions[s, a]))
        for a in range(3):
            positions[s, a] = fine[i, a]
            positions[t, a] = new[i, a]
    return (vertex[:n_vertex], count[:n_count], pattern[:n_pattern], other[:n_other],
            fan, mask[:n_mask], position[:n_position]), error


@njit(cache=True, nogil=True)
def _encode_collapses(positions, faces, face_count, start, stop, base, parent, face_counts,
                      coarse):
    """The streams of collapse records ``start-1`` down to ``stop``, as
    :func:`_encode_splits` (``coarse``: quantized positions of records ``stop ..``)."""
    blocks, pool, end, slot = _corner_blocks(faces, face_count, positions.shape[0])
    records = start - stop
    vertex = np.empty(_VARINT_MAX * records, dtype=np.uint8)
    count = np.empty(_VARINT_MAX * records, dtype=np.uint8)
    position = np.empty(3 * _VARINT_MAX * records, dtype=np.uint8)
    n_vertex = n_count = n_position = 0
    scratch = np.empty((_SCRATCH_ROWS, 64), dtype=np.int64)
    for t in range(start - 1, stop - 1, -1):
        j = t - base
        s = parent[t]
        scratch, _, na = _gather(faces, blocks, pool, t, scratch)
        rank = _search(scratch[_AROUND], na, s)
        found = rank < na and scratch[_AROUND, rank] == s
        n_vertex = _put(vertex, n_vertex, rank if found else na + s)
        removed = face_counts[j + 1] - face_counts[j]
        n_count = _put(count, n_count, removed)
        for _ in range(removed):
            face_count -= 1
            for k in range(3):
                c = 3 * face_count + k
                _remove(blocks, pool, slot, faces[c], c)
        for k in range(blocks[t, 1]):
            c = pool[blocks[t, 0] + k]
            faces[c] = s
            pool, end = _add(blocks, pool, end, slot, s, c)
        blocks[t, 1] = 0
        i = t - stop
        for a in range(3):
            middle = (positions[s, a] + positions[t, a]) >> 1
            n_position = _put(position, n_position, _zz(coarse[i, a] - middle))
        for a in range(3):
            positions[s, a] = coarse[i, a]
    empty = np.empty(0, dtype=np.uint8)
    return (vertex[:n_vertex], count[:n_count], empty, empty, empty, empty,
            position[:n_position])


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
