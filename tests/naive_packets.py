"""The original pure-Python packet encoder, kept as the byte-for-byte reference.

This is ``lodserver/packets.py``'s encoder as it was before its hot loops were
compiled with numba (commit c8f1e29): per-vertex corner *sets*, dict lookups
for neighbour ranks and the fan walk, and ``bytearray`` streams. It is slow
(seconds for the Stanford bunny) and obviously right; ``tests/test_packets.py``
checks that the compiled encoder produces exactly these bytes.
"""

from __future__ import annotations

import zlib

import numpy as np

from lodserver.packets import (
    _FAN_LISTED,
    _FAN_PREDICTED,
    _HEADER,
    _IS_NEW,
    _IS_OTHER,
    _IS_VS,
    _STREAM_NAMES,
    COUNT,
    FAN,
    MAGIC,
    MASK,
    OTHER,
    PACKET_VERSION,
    PATTERN,
    POSITION,
    VERTEX,
    PacketError,
    grid_of,
)
from lodserver.progressive import ProgressiveMesh


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
