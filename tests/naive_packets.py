"""The original pure-Python packet encoder, kept as the byte-for-byte reference.

This is ``lodserver/packets.py``'s encoder as it was before its hot loops were
compiled with numba (commit c8f1e29): per-vertex corner *sets*, dict lookups
for neighbour ranks and the fan walk, and ``bytearray`` streams. It is slow
(seconds for the Stanford bunny) and obviously right; ``tests/test_packets.py``
checks that the compiled encoder produces exactly these bytes. The corner
sets (``_Working``) and the fan prediction are the reference decoder's own,
imported from ``lodserver.packets``: a packet must be decoded the way it was
predicted when encoded.
"""

from __future__ import annotations

import zlib

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
    _predict_fan,
    _put_varint,
    _Working,
    grid_of,
)
from lodserver.progressive import ProgressiveMesh


# ---- varints ----------------------------------------------------------------
def _zigzag(value: int) -> int:
    """Signed -> unsigned, small magnitudes first: 0, -1, 1, -2, ... -> 0, 1, 2, 3, ..."""
    return 2 * value if value >= 0 else -2 * value - 1


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
