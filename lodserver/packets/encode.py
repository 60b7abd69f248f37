"""The compiled encoder: the records between two levels, as packet streams.

:func:`encode_packet` is plain Python: it checks the levels, quantizes the
start level and the records' targets, packs the arrays into the small records
of ``kernel_types.py`` and calls one numba kernel per direction,
:func:`_encode_splits` or :func:`_encode_collapses`, which walk the records in
order and write each field to its stream (docs/packets.md, "Split records",
"Collapse records"). The kernels write exactly the bytes of the readable
encoder kept as the reference in ``tests/naive_packets.py``; the connectivity
they track is in ``corners.py``, the wedge part of each record in
``encode_wedges.py``.

``faces`` is flat in the kernels, and it and the corner lists are int32 when the
ids fit (:func:`index_dtype`): half the memory traffic, and on a big mesh the
records touch vertices all over it, so memory latency rules.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numba import njit

from .corners import (
    AROUND,
    HELD,
    IN_FAN,
    MOVED,
    SCRATCH_ROWS,
    VARINT_MAX,
    add_corner,
    corner_lists,
    gather,
    predicted_fan,
    put,
    remove_corner,
    search,
    zz,
)
from .encode_wedges import collapse_wedges, split_wedges
from .format import (
    FAN_LISTED,
    FAN_PREDICTED,
    IS_NEW,
    IS_OTHER,
    IS_VS,
    PacketError,
    deflate_body,
    pack_header,
    put_varint,
)
from .grids import Grid, attribute_grids_of, grid_of, quantize_wedges
from .kernel_types import (
    CollapseRecord,
    Hierarchy,
    Span,
    SplitRecord,
    Targets,
    WedgeStreams,
    Wedges,
    Work,
)

if TYPE_CHECKING:
    from ..progressive.mesh import ProgressiveMesh


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
    streams = encode_streams(pm, start, stop, grid, grids, _NO_MARKS)
    return assemble_packet(pm, grid, grids, start, stop, streams)


def assemble_packet(pm: ProgressiveMesh, grid: Grid, grids: tuple, start: int, stop: int,
                    streams: list) -> bytes:
    """Header, then the streams (each after its varint length), deflated."""
    body = bytearray()
    for stream in streams:
        put_varint(body, len(stream))
        body += memoryview(stream)
    header = pack_header(grid, grids, pm.face_material is not None, start, stop,
                         pm.faces_at_level(start), pm.faces_at_level(stop), len(body))
    return header + deflate_body(bytes(body))


def index_dtype(corners: int, vertices: int):
    """The kernels' integer type for corner and vertex ids: int32 when they fit."""
    return np.int32 if max(corners, vertices) < 2**31 else np.int64


# Stand-ins for the arrays a mesh without attributes lacks: read-only like the
# progressive mesh's own arrays, so that both run the same compiled kernel.
_READ_ONLY_INDEX = np.zeros(1, dtype=np.int64)
_READ_ONLY_INDEX.setflags(write=False)
_READ_ONLY_CORNERS = np.zeros((0, 3), dtype=np.int64)
_READ_ONLY_CORNERS.setflags(write=False)
_NO_MARKS = np.zeros((0, 0), dtype=np.uint32)
_NO_VALUES = np.zeros((0, 0), dtype=np.int64)


def encode_streams(pm: ProgressiveMesh, start: int, stop: int, grid: Grid, grids: tuple,
                   marks: np.ndarray) -> list:
    """The streams of the records from ``start`` to ``stop`` (uint8 arrays, body order).

    ``marks`` is empty, or (streams, records + 1) and gets each stream's length
    before every record and after the last.
    """
    has_materials = pm.face_material is not None
    positions, faces = pm.arrays_at(start)
    n0 = pm.base_vertices
    # room for both end levels; the kernels change these in place
    face_capacity = max(pm.faces_at_level(start), pm.faces_at_level(stop))
    index = index_dtype(3 * face_capacity, pm.vertex_count)
    work_positions = np.zeros((max(start, stop), 3), dtype=np.int64)
    work_positions[:start] = grid.quantize(positions)
    work_faces = np.zeros(3 * face_capacity, dtype=index)
    work_faces[:faces.size] = faces.ravel()
    hierarchy = Hierarchy(pm.parent, pm.face_counts, pm.birth_faces, pm.moved_offsets,
                          pm.moved_corners, pm.face_material.astype(np.int64) if has_materials
                          else np.zeros(0, dtype=np.int64))
    span = Span(start, stop, n0, len(faces))
    forward = stop > start
    wedges = _wedges(pm, start, stop, grids, index, face_capacity, forward)
    if forward:
        a, b = start - n0, stop - n0
        targets = Targets(grid.quantize(pm.fine_position[a:b]), grid.quantize(pm.new_position[a:b]),
                          np.zeros((0, 3), dtype=np.int64))
        streams, out, error = _encode_splits(work_positions, work_faces, span, hierarchy, targets,
                                             wedges, marks)
        t, c, s = (int(x) for x in error)
        if t >= 0:
            raise PacketError(f"split {t} moves corner {c}, which does not hold vertex {s}")
    else:
        empty = np.zeros((0, 3), dtype=np.int64)
        targets = Targets(empty, empty, grid.quantize(pm.coarse_position[stop - n0:start - n0]))
        streams, out = _encode_collapses(work_positions, work_faces, span, hierarchy, targets,
                                         wedges, marks)
    streams = list(streams)
    used = out.used
    if grids:
        streams += [out.count[:used[0]], out.parent[:used[1]], out.corner[:used[2]]]
        streams += [out.values[i, :out.value_used[i]] for i in range(len(grids))]
    if has_materials:
        streams.append(out.material[:used[3]])
    return streams


def _wedges(pm: ProgressiveMesh, start: int, stop: int, grids: tuple, index, face_capacity: int,
            forward: bool) -> Wedges:
    """The :class:`~lodserver.packets.kernel_types.Wedges` record of the packet
    ``start -> stop``: the quantized wedge state at ``start`` with room for both
    ends, and the quantized values its records write."""
    if not grids:
        return Wedges(np.zeros(0, dtype=index), _NO_VALUES, _READ_ONLY_INDEX, _READ_ONLY_INDEX,
                      _READ_ONLY_CORNERS, _READ_ONLY_CORNERS, np.zeros(1, dtype=np.int64),
                      np.zeros(0, dtype=np.int64), 0, _NO_VALUES, _NO_VALUES, _NO_VALUES)
    n0 = pm.base_vertices
    offsets = np.cumsum([0] + [g.components for g in grids]).astype(np.int64)
    limits = np.array([2**g.bits - 1 for g in grids for _ in range(g.components)],
                      dtype=np.int64)
    values, corners = pm.wedges_at(start)
    lo, hi = (int(pm.wedge_counts[level - n0]) for level in sorted((start, stop)))
    w0 = int(pm.wedge_counts[0])
    work_values = np.zeros((hi, offsets[-1]), dtype=np.int64)
    work_values[:len(values)] = quantize_wedges(grids, values)
    work_corner = np.zeros(3 * face_capacity, dtype=index)
    work_corner[:corners.size] = corners.ravel()
    # of wedges lo .. hi-1: the splits' new wedges, or the collapses' removed ones
    fine = new = coarse = _NO_VALUES
    if forward:
        fine = quantize_wedges(grids, pm.wedge_fine_value[lo - w0:hi - w0])
        new = quantize_wedges(grids, pm.wedge_new_value[lo - w0:hi - w0])
    else:
        coarse = quantize_wedges(grids, pm.wedge_coarse_value[lo - w0:hi - w0])
    return Wedges(work_corner, work_values, pm.wedge_counts, pm.wedge_parent, pm.birth_corners,
                  pm.corner_wedges, offsets, limits, lo, fine, new, coarse)


@njit(cache=True, nogil=True)
def _wedge_streams(records, wedges_written, values_per_wedge, corner_codes, material_codes,
                   wedges):
    """Empty wedge streams with room for the longest varints of ``records`` records
    writing ``wedges_written`` wedges of ``values_per_wedge`` values each (2 for a
    split's: the parent's and the new one's), ``corner_codes`` corner codes and
    ``material_codes`` materials."""
    attributes = wedges.offsets.shape[0] - 1
    widest = 0
    for a in range(attributes):
        widest = max(widest, wedges.offsets[a + 1] - wedges.offsets[a])
    value_room = values_per_wedge * widest * VARINT_MAX * wedges_written
    return WedgeStreams(np.empty(VARINT_MAX * records if attributes else 0, dtype=np.uint8),
                        np.empty(VARINT_MAX * wedges_written, dtype=np.uint8),
                        np.empty(VARINT_MAX * corner_codes, dtype=np.uint8),
                        np.empty(VARINT_MAX * material_codes, dtype=np.uint8),
                        np.zeros(4, dtype=np.int64),
                        np.empty((attributes, value_room), dtype=np.uint8),
                        np.zeros(attributes, dtype=np.int64))


@njit(cache=True, nogil=True)
def _mark(marks, i, lengths, out, has_materials):
    """Column ``i`` of ``marks``: every stream's length, in body order (``lengths``:
    the seven geometry streams')."""
    for k in range(7):
        marks[k, i] = lengths[k]
    attributes = out.value_used.shape[0]
    row = 7
    if attributes:
        marks[7, i], marks[8, i], marks[9, i] = out.used[0], out.used[1], out.used[2]
        for a in range(attributes):
            marks[10 + a, i] = out.value_used[a]
        row = 10 + attributes
    if has_materials:
        marks[row, i] = out.used[3]


@njit(cache=True, nogil=True)
def _encode_splits(positions, faces, span, hierarchy, targets, wedges, marks):
    """The streams of split records ``span.start .. span.stop-1``.

    ``positions`` (v, 3) and flat ``faces`` hold the quantized state at ``start``
    (``span.face_count`` faces) with room for ``stop``, and are changed in place,
    as are ``wedges.corner`` and ``wedges.values`` with attributes; ``targets``
    has the quantized fine and new positions of the splits. ``marks`` (empty, or
    streams x records + 1) gets the stream lengths before each record and after
    the last.

    Returns the seven geometry streams, the :class:`WedgeStreams` (wedge and
    material streams, filled to their used lengths), and ``(t, c, s)`` of the
    first moved corner that does not hold ``vs`` (all -1 when there is none; the
    streams are then complete).
    """
    state, pool = corner_lists(positions, faces, span.face_count)
    start, stop, base = span.start, span.stop, span.base
    parent, face_counts = hierarchy.parent, hierarchy.face_counts
    birth_faces = hierarchy.birth_faces
    moved_offsets, moved_corners = hierarchy.moved_offsets, hierarchy.moved_corners
    fine, new = targets.fine, targets.new
    records = stop - start
    added = face_counts[stop - base] - face_counts[start - base]
    vertex = np.empty(VARINT_MAX * records, dtype=np.uint8)
    count = np.empty(VARINT_MAX * records, dtype=np.uint8)
    pattern = np.empty(added, dtype=np.uint8)
    other = np.empty(3 * VARINT_MAX * added, dtype=np.uint8)
    fan = np.empty(records, dtype=np.uint8)
    mask = np.empty(64, dtype=np.uint8)          # grown when needed
    position = np.empty(6 * VARINT_MAX * records, dtype=np.uint8)
    n_vertex = n_count = n_pattern = n_other = n_mask = n_position = 0
    error = np.full(3, -1, dtype=np.int64)
    scratch = np.empty((SCRATCH_ROWS, 64), dtype=np.int64)

    attributes = wedges.offsets.shape[0] - 1
    has_materials = hierarchy.face_material.shape[0] > 0
    moved_total = moved_offsets[stop - base] - moved_offsets[start - base] if attributes else 0
    out = _wedge_streams(records, wedges.fine.shape[0], 2,
                         moved_total + 3 * added if attributes else 0,
                         added if has_materials else 0, wedges)
    candidates = np.empty(64, dtype=np.int64)
    face_count = span.face_count
    columns = wedges.offsets[-1]
    work = Work(np.empty(3, dtype=np.int64), np.empty(3, dtype=np.int64),
                np.empty(3, dtype=np.int64), np.empty((3, columns), dtype=np.float64),
                np.empty((3, columns), dtype=np.float64))

    for t in range(start, stop + 1):
        if marks.shape[0]:
            _mark(marks, t - start, (n_vertex, n_count, n_pattern, n_other, t - start, n_mask,
                                     n_position), out, has_materials)
        if t == stop:
            break
        j = t - base
        s = parent[t]
        n_vertex = put(vertex, n_vertex, t - 1 - s)
        scratch, d, na = gather(state, pool, s, scratch)
        held, around = scratch[HELD], scratch[AROUND]

        first, last = face_counts[j], face_counts[j + 1]
        n_count = put(count, n_count, last - first)
        for f in range(first, last):
            code = 0
            for k in range(3):
                v = birth_faces[f, k]
                if v == s:
                    kind = IS_VS
                elif v == t:
                    kind = IS_NEW
                else:
                    kind = IS_OTHER
                    rank = search(around, na, v)
                    n_other = put(other, n_other,
                                  rank if rank < na and around[rank] == v else na + v)
                code = 3 * code + kind
            pattern[n_pattern] = code
            n_pattern += 1

        size = predicted_fan(scratch, d, s, t, birth_faces, first, last)
        m0, m1 = moved_offsets[j], moved_offsets[j + 1]
        predicted = size >= 0
        if predicted:             # the fan equals the set of moved corners?
            in_fan, moved = scratch[IN_FAN], scratch[MOVED]
            moved[:d] = 0
            distinct = 0
            for x in range(m0, m1):
                c = moved_corners[x]
                i = search(held, d, c)
                if i == d or held[i] != c or not in_fan[i]:
                    predicted = False
                    break
                if not moved[i]:
                    moved[i] = 1
                    distinct += 1
            predicted = predicted and distinct == size
        fan[t - start] = FAN_PREDICTED if predicted else FAN_LISTED
        if not predicted:
            width = (d + 7) // 8
            if n_mask + width > mask.shape[0]:
                bigger = np.empty(max(2 * mask.shape[0], n_mask + width), dtype=np.uint8)
                bigger[:n_mask] = mask[:n_mask]
                mask = bigger
            mask[n_mask:n_mask + width] = 0
            for x in range(m0, m1):
                c = moved_corners[x]
                i = search(held, d, c)          # c's place in held(s)
                if i == d or held[i] != c:
                    error[0], error[1], error[2] = t, c, s
                    return ((vertex[:n_vertex], count[:n_count], pattern[:n_pattern],
                             other[:n_other], fan[:t - start], mask[:n_mask],
                             position[:n_position]), out, error)
                mask[n_mask + i // 8] |= 1 << (i % 8)
            n_mask += width
        first_face = face_count
        for x in range(m0, m1):
            c = moved_corners[x]
            remove_corner(state, pool, faces[c], c)
            faces[c] = t
            pool = add_corner(state, pool, t, c)
        for f in range(first, last):
            for k in range(3):
                c = 3 * face_count + k
                faces[c] = birth_faces[f, k]
                pool = add_corner(state, pool, faces[c], c)
            face_count += 1

        i = t - start
        # The collapse placed vs between the two, so new ~ 2 * coarse - fine.
        for a in range(3):
            n_position = put(position, n_position, zz(fine[i, a] - positions[s, a]))
        for a in range(3):
            n_position = put(position, n_position, zz(new[i, a] + fine[i, a] - 2 * positions[s, a]))
        for a in range(3):
            work.coarse[a] = positions[s, a]
            work.fine[a] = fine[i, a]
            work.new[a] = new[i, a]
            positions[s, a] = fine[i, a]
            positions[t, a] = new[i, a]
        if attributes:
            candidates = split_wedges(state, pool, SplitRecord(s, t, j, i, d, first_face,
                                                               face_count, first),
                                      scratch, work, wedges, out, candidates)
        if has_materials:
            for f in range(first, last):
                out.used[3] = put(out.material, out.used[3], hierarchy.face_material[f] + 1)
    return ((vertex[:n_vertex], count[:n_count], pattern[:n_pattern], other[:n_other],
             fan, mask[:n_mask], position[:n_position]), out, error)


@njit(cache=True, nogil=True)
def _encode_collapses(positions, faces, span, hierarchy, targets, wedges, marks):
    """The streams of collapse records ``span.start-1`` down to ``span.stop``, as
    :func:`_encode_splits` (``targets.coarse``: the quantized merged positions of
    records ``stop ..``; ``wedges.coarse``: the merged values of wedges
    ``wedges.first ..``). Returns the geometry streams and the WedgeStreams."""
    state, pool = corner_lists(positions, faces, span.face_count)
    start, stop, base = span.start, span.stop, span.base
    parent, face_counts, coarse = hierarchy.parent, hierarchy.face_counts, targets.coarse
    blocks = state.blocks
    face_count = span.face_count
    records = start - stop
    vertex = np.empty(VARINT_MAX * records, dtype=np.uint8)
    count = np.empty(VARINT_MAX * records, dtype=np.uint8)
    position = np.empty(3 * VARINT_MAX * records, dtype=np.uint8)
    n_vertex = n_count = n_position = 0
    scratch = np.empty((SCRATCH_ROWS, 64), dtype=np.int64)

    attributes = wedges.offsets.shape[0] - 1
    out = _wedge_streams(records, wedges.coarse.shape[0], 1, 0, 0, wedges)
    candidates = np.empty(64, dtype=np.int64)
    work = Work(np.empty(3, dtype=np.int64), np.empty(3, dtype=np.int64),
                np.empty(3, dtype=np.int64), np.empty((3, 0), dtype=np.float64),
                np.empty((3, 0), dtype=np.float64))

    for t in range(start - 1, stop - 2, -1):
        if marks.shape[0]:
            _mark(marks, start - 1 - t, (n_vertex, n_count, 0, 0, 0, 0, n_position), out, False)
        if t == stop - 1:
            break
        j = t - base
        s = parent[t]
        scratch, _, na = gather(state, pool, t, scratch)
        rank = search(scratch[AROUND], na, s)
        found = rank < na and scratch[AROUND, rank] == s
        n_vertex = put(vertex, n_vertex, rank if found else na + s)
        removed = face_counts[j + 1] - face_counts[j]
        n_count = put(count, n_count, removed)
        for _ in range(removed):
            face_count -= 1
            for k in range(3):
                c = 3 * face_count + k
                remove_corner(state, pool, faces[c], c)
        for k in range(blocks[t, 1]):
            c = pool[blocks[t, 0] + k]
            faces[c] = s
            pool = add_corner(state, pool, s, c)
        blocks[t, 1] = 0
        i = t - stop
        for a in range(3):
            middle = (positions[s, a] + positions[t, a]) >> 1
            n_position = put(position, n_position, zz(coarse[i, a] - middle))
        if not attributes:
            for a in range(3):
                positions[s, a] = coarse[i, a]
            continue
        for a in range(3):
            work.fine[a] = positions[s, a]
            positions[s, a] = coarse[i, a]
        candidates = collapse_wedges(state, pool, CollapseRecord(s, t, j, i), work, wedges, out,
                                     candidates)
    empty = np.empty(0, dtype=np.uint8)
    return ((vertex[:n_vertex], count[:n_count], empty, empty, empty, empty,
             position[:n_position]), out)
