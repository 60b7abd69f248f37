"""The original pure-Python packet encoder, kept as the byte-for-byte reference.

This is the encoder of ``lodserver/packets`` as it was before its hot loops were
compiled with numba (commit c8f1e29, when the package was one module):
per-vertex corner *sets*, dict lookups for neighbour ranks and the fan walk,
and ``bytearray`` streams. It is slow
(seconds for the Stanford bunny) and obviously right; ``tests/packets/test_packets.py``
checks that the compiled encoder produces exactly these bytes. The corner
sets (``Working``), the fan prediction and the wedge predictions are the
reference decoder's own public functions, imported from
``lodserver.packets.reference``: a packet must be decoded the way it was
predicted when encoded. Neither file uses the other's private helpers.

Wedges (packet version 2, meshes with attributes) were written here first, in
the same style, then compiled: per record, the new or removed wedges, their
parents by rank among ``vs``'s wedges, their quantized values as residuals,
and each changed corner's wedge as a code (docs/packets.md).
"""

from __future__ import annotations

from lodserver.packets import (COUNT, FAN, MASK, OTHER, PATTERN, POSITION, VERTEX, WEDGE_CORNER,
                               WEDGE_COUNT, WEDGE_PARENT, PacketError, attribute_grids_of,
                               deflate_body, grid_of, pack_header, quantize_wedges,
                               stream_names)
from lodserver.packets.format import FAN_LISTED, FAN_PREDICTED, IS_NEW, IS_OTHER, IS_VS, put_varint
from lodserver.packets.reference import (
    Working,
    collapse_ratio,
    corner_candidates,
    moved_prediction,
    predict_fan,
    scaled,
    split_guesses,
)
from lodserver.progressive.mesh import ProgressiveMesh


# ---- varints ----------------------------------------------------------------
def _zigzag(value: int) -> int:
    """Signed -> unsigned, small magnitudes first: 0, -1, 1, -2, ... -> 0, 1, 2, 3, ..."""
    return 2 * value if value >= 0 else -2 * value - 1


def encode_packet(pm: ProgressiveMesh, start: int, stop: int, *,
                  bits: int | None = None, attribute_bits: dict | None = None) -> bytes:
    """The packet taking the quantized form of level ``start`` to level ``stop``.

    Parameters
    ----------
    pm : ProgressiveMesh
    start, stop : int
        Levels (vertex counts) in ``pm.levels``; ``stop < start`` gives collapses.
    bits : int, optional
        Grid resolution, as for :func:`grid_of` (default :func:`default_bits`).
    attribute_bits : dict, optional
        Attribute grid resolutions, as for :func:`attribute_grids_of`.

    Returns
    -------
    bytes
        Header and deflated streams as documented in ``docs/packets.md``.
    """
    start, stop = pm.check_level(start), pm.check_level(stop)
    grid = grid_of(pm, bits=bits)
    grids = attribute_grids_of(pm, attribute_bits=attribute_bits)
    has_materials = pm.face_material is not None
    positions, faces = pm.arrays_at(start)
    state = Working(grid.quantize(positions), faces, max(start, stop),
                     max(pm.faces_at_level(start), pm.faces_at_level(stop)))
    values, corners = pm.wedges_at(start)
    state.attach_wedges(None if values is None else quantize_wedges(grids, values), corners,
                        pm.face_material[:len(faces)] if has_materials else None)
    streams = [bytearray() for _ in stream_names(grids, has_materials)]
    if stop > start:
        _encode_splits(pm, state, start, stop, grid, grids, streams)
    else:
        _encode_collapses(pm, state, start, stop, grid, grids, streams)
    body = bytearray()
    for stream in streams:
        put_varint(body, len(stream))
        body += stream
    header = pack_header(grid, grids, has_materials, start, stop, pm.faces_at_level(start),
                         pm.faces_at_level(stop), len(body))
    return header + deflate_body(bytes(body))   # the deflate level is not the format's


def _ancestor_below(parent, x: int, count: int) -> int:
    while x >= count:
        x = int(parent[x])
    return x


def _encode_splits(pm, state, start, stop, grid, grids, streams):
    n0 = pm.base_vertices
    fine = grid.quantize(pm.fine_position[start - n0:stop - n0])
    new = grid.quantize(pm.new_position[start - n0:stop - n0])
    wedge_fine = wedge_new = None
    if grids:   # by wedge id - wedge_counts[0]
        wedge_fine = quantize_wedges(grids, pm.wedge_fine_value)
        wedge_new = quantize_wedges(grids, pm.wedge_new_value)
    for t in range(start, stop):
        j = t - n0
        s = int(pm.parent[t])
        put_varint(streams[VERTEX], t - 1 - s)
        held = sorted(state.corners.of(s))
        around = state.neighbours(s)

        first, last = int(pm.face_counts[j]), int(pm.face_counts[j + 1])
        put_varint(streams[COUNT], last - first)
        rank = {v: i for i, v in enumerate(around)}
        added = pm.birth_faces[first:last].tolist()
        for corners in added:
            pattern = 0
            for v in corners:
                kind = IS_VS if v == s else IS_NEW if v == t else IS_OTHER
                pattern = 3 * pattern + kind
                if kind == IS_OTHER:
                    put_varint(streams[OTHER], rank[v] if v in rank else len(around) + v)
            streams[PATTERN].append(pattern)

        moved = pm.moved_corners[pm.moved_offsets[j]:pm.moved_offsets[j + 1]].tolist()
        if predict_fan(state, s, t, added) == set(moved):
            streams[FAN].append(FAN_PREDICTED)
        else:
            streams[FAN].append(FAN_LISTED)
            rank = {c: i for i, c in enumerate(held)}
            mask = bytearray((len(held) + 7) // 8)
            for c in moved:
                if c not in rank:
                    raise PacketError(f"split {t} moves corner {c}, which does not hold vertex {s}")
                mask[rank[c] // 8] |= 1 << (rank[c] % 8)
            streams[MASK] += mask
        first_face = state.face_count
        for c in moved:
            state.set_corner(c, t)
        for corners in added:
            state.append_face(corners)

        coarse = state.positions[s].copy()
        for d in (fine[j - (start - n0)] - coarse).tolist():
            put_varint(streams[POSITION], _zigzag(d))
        # The collapse placed vs between the two, so new ~ 2 * coarse - fine.
        for d in (new[j - (start - n0)] + fine[j - (start - n0)] - 2 * coarse).tolist():
            put_varint(streams[POSITION], _zigzag(d))
        state.positions[s] = fine[j - (start - n0)]
        state.positions[t] = new[j - (start - n0)]
        if grids:
            geometry = (coarse.tolist(), state.positions[s].tolist(), state.positions[t].tolist())
            _encode_split_wedges(pm, state, s, t, held, set(moved), first_face, geometry,
                                 wedge_fine, wedge_new, grids, streams)
        if pm.face_material is not None:
            for f in range(first, last):
                put_varint(streams[-1], int(pm.face_material[f]) + 1)
                state.face_material[f] = pm.face_material[f]


def _encode_collapses(pm, state, start, stop, grid, grids, streams):
    n0 = pm.base_vertices
    coarse = grid.quantize(pm.coarse_position[stop - n0:start - n0])
    wedge_coarse = quantize_wedges(grids, pm.wedge_coarse_value) if grids else None
    for t in range(start - 1, stop - 1, -1):
        j = t - n0
        s = int(pm.parent[t])
        around = state.neighbours(t)
        code = around.index(s) if s in around else len(around) + s
        put_varint(streams[VERTEX], code)
        first, last = int(pm.face_counts[j]), int(pm.face_counts[j + 1])
        put_varint(streams[COUNT], last - first)
        for _ in range(last - first):
            state.pop_face()
        for c in list(state.corners.of(t)):
            state.set_corner(c, s)
        target = coarse[j - (stop - n0)]
        middle = (state.positions[s] + state.positions[t]) >> 1
        for d in (target - middle).tolist():
            put_varint(streams[POSITION], _zigzag(d))
        if grids:
            ratio = collapse_ratio(state.positions[s].tolist(), state.positions[t].tolist(),
                                    target.tolist())
        state.positions[s] = target
        if grids:
            _encode_collapse_wedges(pm, state, t, s, ratio, wedge_coarse, grids, streams)


def _encode_split_wedges(pm, state, s, t, held, moved, first, geometry, fine, new, grids,
                         streams):
    """The wedge part of split ``t``: its new wedges (parent, values) and the wedge
    of every moved corner and every corner of its new faces."""
    n0, base = pm.base_vertices, int(pm.wedge_counts[0])
    bottom, top = int(pm.wedge_counts[t - n0]), int(pm.wedge_counts[t - n0 + 1])
    put_varint(streams[WEDGE_COUNT], top - bottom)
    candidates = state.wedges_held(held)
    parents = []
    for x in range(bottom, top):
        p = int(pm.wedge_parent[x])
        put_varint(streams[WEDGE_PARENT],
                    candidates.index(p) if p in candidates else len(candidates) + p)
        parents.append(p)
        guess_fine, guess_new = split_guesses(state, s, held, p, geometry, grids)
        f, n, at = fine[x - base].tolist(), new[x - base].tolist(), 0
        for i, g in enumerate(grids):
            columns = range(at, at + g.components)
            at += g.components
            residuals = [f[j] - guess_fine[j] for j in columns]
            residuals += [n[j] - guess_new(j, f[j]) for j in columns]
            for d in residuals:
                put_varint(streams[WEDGE_CORNER + 1 + i], _zigzag(d))
        state.wedge_values[p] = fine[x - base].tolist()
        state.wedge_values.append(new[x - base].tolist())
    m = top - bottom
    for c in held:
        if c not in moved:
            continue
        y = state.wedge_of(c)
        w = _ancestor_below(pm.wedge_parent, int(pm.corner_wedges[c // 3, c % 3]), top)
        if w == moved_prediction(parents, bottom, y):
            code = 0
        elif bottom <= w < top:
            code = 1 + w - bottom
        elif w == y:
            code = m + 1
        else:
            code = m + 2 + w
        put_varint(streams[WEDGE_CORNER], code)
        state.set_wedge(c, w)
    for f in range(first, state.face_count):
        for k in range(3):
            w = int(pm.birth_corners[f, k])
            candidates = corner_candidates(state, int(state.faces[f, k]), 3 * first, bottom, top)
            put_varint(streams[WEDGE_CORNER],
                        candidates.index(w) if w in candidates else len(candidates) + w)
            state.set_wedge(3 * f + k, w)


def _encode_collapse_wedges(pm, state, t, s, ratio, coarse, grids, streams):
    """The wedge part of collapse ``t``: how many wedges go, and for each (last first)
    its parent and the parent's merged value."""
    n0, base = pm.base_vertices, int(pm.wedge_counts[0])
    bottom, top = int(pm.wedge_counts[t - n0]), int(pm.wedge_counts[t - n0 + 1])
    put_varint(streams[WEDGE_COUNT], top - bottom)
    candidates = [w for w in state.wedges_held(state.corners.of(s)) if w < bottom]
    for x in range(top - 1, bottom - 1, -1):
        p = int(pm.wedge_parent[x])
        put_varint(streams[WEDGE_PARENT],
                    candidates.index(p) if p in candidates else len(candidates) + p)
        merged = coarse[x - base].tolist()
        predicted = [a + scaled(ratio, b - a)
                     for a, b in zip(state.wedge_values[p], state.wedge_values[x])]
        at = 0
        for i, g in enumerate(grids):
            for d, e in zip(merged[at:at + g.components], predicted[at:at + g.components]):
                put_varint(streams[WEDGE_CORNER + 1 + i], _zigzag(d - e))
            at += g.components
        state.wedge_values[p] = merged
    for c in state.corners.of(s):
        state.set_wedge(c, _ancestor_below(pm.wedge_parent, state.wedge_of(c), bottom))
    del state.wedge_values[bottom:]
