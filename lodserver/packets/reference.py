"""The reference decoder: plain Python, written to be read, for clients in any language.

:func:`decode_packet` parses a packet's header and inflates its streams;
:func:`apply_packet` applies its records to a client's :class:`LodState` and
yields exactly the quantized form of the level it ends at (docs/packets.md,
"Exactness"). Everything a record's prediction reads is here, in the order the
format fixes: the connectivity a decoder tracks (:class:`Working`: for every
vertex the set of corners ``3 * face + slot`` holding it), the predicted fan
(:func:`predict_fan`), and the wedge predictions (:func:`split_ratio`,
:func:`collapse_ratio`, :func:`fit_gradient`, :func:`extrapolated`).

The compiled encoder (``encode.py``) runs the same predictions as numba kernels
over arrays; the readable encoder ``tests/naive_packets.py`` calls these very
functions, so that a packet is predicted when encoded exactly as it is when
decoded, and the compiled encoder is checked byte for byte against it.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass

import numpy as np

from .format import (
    FAN_PREDICTED,
    GRADIENT_DAMPING,
    HAS_MATERIALS,
    IS_NEW,
    IS_VS,
    MAX_SPLIT_RATIO,
    RING_SCALE,
    TANGENT,
    PacketError,
    Reader,
    stream_names,
    unpack_header,
)
from .grids import AttributeGrid, Grid, LodState


# ---- connectivity, as the reference decoder tracks it -------------------------
class Corners:
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


class Working:
    """Mutable arrays with room for both end levels, plus connectivity."""

    def __init__(self, positions: np.ndarray, faces: np.ndarray, vertex_capacity: int,
                 face_capacity: int):
        self.positions = np.zeros((max(vertex_capacity, len(positions)), 3), dtype=np.int64)
        self.positions[:len(positions)] = positions
        self.faces = np.zeros((max(face_capacity, len(faces)), 3), dtype=np.int64)
        self.faces[:len(faces)] = faces
        self.face_count = len(faces)
        self.corners = Corners(np.asarray(faces, dtype=np.int64), len(self.positions))

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

    # ---- wedges (with attributes) ----
    def attach_wedges(self, wedges, corners, face_material) -> None:
        """Hold wedge values (a list of int lists, grown and shrunk at the end), the
        wedge of every corner, and the face materials (each may be None)."""
        self.wedge_values = None if wedges is None else [list(map(int, w)) for w in wedges]
        self.corner_wedges = None
        if corners is not None:
            self.corner_wedges = np.zeros(self.faces.shape, dtype=np.int64)
            self.corner_wedges[:len(corners)] = corners
        self.face_material = None
        if face_material is not None:
            self.face_material = np.zeros(len(self.faces), dtype=np.int64)
            self.face_material[:len(face_material)] = face_material

    def wedge_of(self, c: int) -> int:
        return int(self.corner_wedges[c // 3, c % 3])

    def set_wedge(self, c: int, w: int) -> None:
        self.corner_wedges[c // 3, c % 3] = w

    def wedges_held(self, corners) -> list[int]:
        """The distinct wedges of ``corners``, ascending."""
        return sorted({self.wedge_of(c) for c in corners})


# ---- predictions: what encoder and decoder both compute from the state -------
# (docs/packets.md, "Predicted fan" and "The wedge part of split t"; the
# compiled encoder repeats each in corners.py and encode_wedges.py)
def corner_candidates(work: Working, v: int, limit: int, bottom: int, top: int) -> list[int]:
    """The wedges a new face's corner on ``v`` may take: those of ``v``'s corners
    below corner ``limit`` (the faces before the record), ascending, then the
    record's new wedges ``bottom .. top-1`` not among them."""
    held = work.wedges_held(c for c in work.corners.of(v) if c < limit)
    known = set(held)
    return held + [x for x in range(bottom, top) if x not in known]


def split_ratio(coarse, fine, new) -> float:
    """How far the new vertex lies beyond ``coarse`` (vs before the split), in units
    of ``coarse - fine``: ``(new - coarse) . (coarse - fine) / |coarse - fine|^2``,
    clamped to ``[0, 4]``; 1 (the mirror image) when vs did not move. Integer grid
    positions, so both dot products are exact in float64: every decoder gets
    the same float."""
    a = sum(float(c - f) * float(c - f) for c, f in zip(coarse, fine))
    b = sum(float(n - c) * float(c - f) for c, f, n in zip(coarse, fine, new))
    ratio = b / a if a > 0 else 1.0
    return min(max(ratio, 0.0), MAX_SPLIT_RATIO)


def collapse_ratio(fine, new, coarse) -> float:
    """Where the merged position lies between vs's (``fine``) and the removed vertex's
    (``new``): ``(coarse - fine) . (new - fine) / |new - fine|^2`` clamped to
    ``[0, 1]``; 1/2 when the two coincide."""
    a = sum(float(n - f) * float(n - f) for f, n in zip(fine, new))
    b = sum(float(c - f) * float(n - f) for f, n, c in zip(fine, new, coarse))
    ratio = b / a if a > 0 else 0.5
    return min(max(ratio, 0.0), 1.0)


def fit_gradient(work: Working, s: int, held: list, p: int, coarse) -> list | None:
    """The gradient ``J`` (3 rows of ``k`` floats) of wedge ``p``'s values against
    position around vertex ``s`` (at grid position ``coarse``): the damped least
    squares fit of ``value(w) - value(p) ~ J . (position(v) - coarse)`` over the
    edges from ``s`` to the other corners ``(v, w)`` of the faces whose corner on
    ``s`` (from ``held``, ascending) holds ``p``. None with fewer than two edges.

    Every decoder must get the same floats: the sums run in this order (corners
    ascending, each face's next corner before its prev) and the 3x3 solve is
    written out; with integer inputs the sums are exact anyway below 2^53.
    """
    k = len(work.wedge_values[p])
    value = work.wedge_values[p]
    m00 = m01 = m02 = m11 = m12 = m22 = 0.0
    b0, b1, b2 = [0.0] * k, [0.0] * k, [0.0] * k
    edges = 0
    for c in held:
        if work.wedge_of(c) != p:
            continue
        f3 = c - c % 3
        for o in (f3 + (c - f3 + 1) % 3, f3 + (c - f3 + 2) % 3):
            v = int(work.faces[o // 3, o % 3])
            if v == s:
                continue
            e0 = float(int(work.positions[v, 0]) - coarse[0])
            e1 = float(int(work.positions[v, 1]) - coarse[1])
            e2 = float(int(work.positions[v, 2]) - coarse[2])
            other = work.wedge_values[work.wedge_of(o)]
            m00 += e0 * e0
            m01 += e0 * e1
            m02 += e0 * e2
            m11 += e1 * e1
            m12 += e1 * e2
            m22 += e2 * e2
            for j in range(k):
                d = float(other[j] - value[j])
                b0[j] += e0 * d
                b1[j] += e1 * d
                b2[j] += e2 * d
            edges += 1
    if edges < 2:
        return None
    damping = (m00 + m11 + m22) * GRADIENT_DAMPING + 1e-9
    m00 += damping
    m11 += damping
    m22 += damping
    c00 = m11 * m22 - m12 * m12
    c01 = m02 * m12 - m01 * m22
    c02 = m01 * m12 - m02 * m11
    c11 = m00 * m22 - m02 * m02
    c12 = m01 * m02 - m00 * m12
    c22 = m00 * m11 - m01 * m01
    det = m00 * c00 + m01 * c01 + m02 * c02
    if not det > 0:
        return None
    i00, i01, i02 = c00 / det, c01 / det, c02 / det
    i11, i12, i22 = c11 / det, c12 / det, c22 / det
    return [[i00 * b0[j] + i01 * b1[j] + i02 * b2[j] for j in range(k)],
            [i01 * b0[j] + i11 * b1[j] + i12 * b2[j] for j in range(k)],
            [i02 * b0[j] + i12 * b1[j] + i22 * b2[j] for j in range(k)]]


def extrapolated(gradient: list, j: int, value: int, delta, limit: int) -> int:
    """``value`` moved by ``gradient`` over the position change ``delta`` (integers),
    rounded, within ``[0, limit]``: ``floor(value + J . delta + 0.5)``."""
    x = (float(value) + (float(delta[0]) * gradient[0][j] + float(delta[1]) * gradient[1][j]
                         + float(delta[2]) * gradient[2][j])) + 0.5
    if not x >= 0:        # also NaN
        return 0
    if x > limit:
        return limit
    return math.floor(x)


def split_guesses(work: Working, s: int, held: list, p: int, geometry, grids):
    """The predictions of split values for the new wedge of parent ``p``:
    ``(guess_fine, guess_new)``, the parent's finer value (a list) and a function
    ``guess_new(j, fine_j)`` of component ``j`` of the new wedge's value.

    With a :func:`fit_gradient` around ``s``, both extrapolate ``p``'s current value
    over the moves from vs's coarse position to its fine one and to the new
    vertex's. Without one, the parent keeps its value and the new wedge lies
    beyond it as the new vertex does (:func:`split_ratio`).
    """
    coarse, fine, new = geometry
    current = work.wedge_values[p]
    gradient = fit_gradient(work, s, held, p, coarse)
    if gradient is None:
        ratio = split_ratio(coarse, fine, new)
        return list(current), lambda j, f: current[j] + scaled(ratio, current[j] - f)
    limits = [2**g.bits - 1 for g in grids for _ in range(g.components)]
    to_fine = [a - b for a, b in zip(fine, coarse)]
    to_new = [a - b for a, b in zip(new, coarse)]
    guess_fine = [extrapolated(gradient, j, current[j], to_fine, limits[j])
                  for j in range(len(current))]
    guess_new = [extrapolated(gradient, j, current[j], to_new, limits[j])
                 for j in range(len(current))]
    return guess_fine, lambda j, f: guess_new[j]


def scaled(ratio: float, d: int) -> int:
    """``floor(ratio * d + 0.5)``: the rounding every decoder does the same way."""
    return math.floor(ratio * d + 0.5)


def ring_prediction(work: Working, s: int, t: int) -> list[int]:
    """``P``, the split edge predicted from the rings (docs/packets.md, "Positions
    from the ring"), in the state after split ``t``'s faces, before its positions."""
    sums, counts = [], []
    for v, other in ((s, t), (t, s)):
        ring = []                  # with repeats: the other two corners of each corner of v
        for c in work.corners.of(v):
            f, k = divmod(c, 3)
            ring += [int(work.faces[f, (k + j) % 3]) for j in (1, 2)]
        ring = [u for u in ring if u not in (v, other)]
        sums.append([float(sum(int(work.positions[u, a]) for u in ring)) for a in range(3)])
        counts.append(len(ring))
    (ss, st), (ns, nt) = sums, counts
    if ns == 0 or nt == 0:
        return [0, 0, 0]
    return [math.floor((st[a] / nt - ss[a] / ns) * RING_SCALE + 0.5) for a in range(3)]


def ring_edge_fields(work: Working, s: int, t: int, symbols) -> tuple[list, list]:
    """Version 3's ``d1``, ``d2`` of split ``t`` from its signed position symbols
    ``E - P, l, r`` (7) and the ring's ``P``: ``E``, then ``d1 = r - floor((l E + 8) /
    16)`` and ``d2 = E + 2 d1`` per axis (docs/packets.md, "Version 4", "Records")."""
    predicted = ring_prediction(work, s, t)
    place = int(symbols[3])
    edge = [int(symbols[a]) + predicted[a] for a in range(3)]
    d1 = [int(symbols[4 + a]) - (place * edge[a] + 8) // 16 for a in range(3)]
    return d1, [edge[a] + 2 * d1[a] for a in range(3)]


def moved_prediction(parents: list[int], bottom: int, y: int) -> int:
    """The predicted finer wedge of a moved corner holding ``y``: the first new wedge
    (``bottom + i``, parent ``parents[i]``) that is a child of ``y``, else ``y``."""
    for i, parent in enumerate(parents):
        if parent == y:
            return bottom + i
    return y


def predict_fan(state, s: int, t: int, added: list) -> set[int] | None:
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


# ---- decoding ------------------------------------------------------------------
@dataclass(frozen=True)
class Packet:
    """A parsed packet: header fields and its raw streams (not yet applied)."""

    start: int
    stop: int
    start_faces: int
    stop_faces: int
    grid: Grid
    streams: tuple[bytes, ...]
    attribute_grids: tuple = ()
    has_materials: bool = False
    # Version 4 with RING_POSITIONS only: every split's position symbols, (records, 7)
    # signed ``E - P, l, r``, resolved as each split is applied (the prediction ``P``
    # reads the state after its faces); the position stream is then empty.
    ring_edges: np.ndarray | None = None

    @property
    def records(self) -> int:
        return abs(self.stop - self.start)


def decode_packet(data: bytes) -> Packet:
    """Parse a packet's header and inflate its streams.

    Raises
    ------
    PacketError
        On a bad magic, version, length, attribute record, deflate stream or stream table.
    """
    data = bytes(data)
    fields, records, at = unpack_header(data)
    grids = tuple(AttributeGrid(name, encoding, origin, step, bits, width)
                  for name, width, encoding, origin, step, bits in records)
    try:
        body = zlib.decompress(data[at:])
    except zlib.error as exc:
        raise PacketError(f"the packet's body does not inflate ({exc})") from exc
    if len(body) != fields["body_length"]:
        raise PacketError(f"the packet's body is {len(body)} bytes, the header says "
                          f"{fields['body_length']}")
    table = Reader(body, "stream table")
    has_materials = bool(fields["flags"] & HAS_MATERIALS)
    streams = []
    for _ in stream_names(grids, has_materials):
        streams.append(table.take(table.varint()))
    if not table.done():
        raise PacketError("the packet's body has bytes after its last stream")
    return Packet(fields["start"], fields["stop"], fields["start_faces"], fields["stop_faces"],
                  Grid(fields["origin"], fields["step"], fields["bits"]), tuple(streams), grids,
                  has_materials)


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
    if tuple(state.attribute_grids) != packet.attribute_grids:
        raise PacketError("the packet was made for other attributes or attribute grids than "
                          "the state's")
    if (state.face_material is not None) != packet.has_materials:
        raise PacketError("the packet and the state disagree on face materials")
    work = Working(state.positions, state.faces, max(packet.start, packet.stop),
                    max(packet.start_faces, packet.stop_faces))
    work.attach_wedges(state.wedges, state.corners, state.face_material)
    names = stream_names(packet.attribute_grids, packet.has_materials)
    readers = [Reader(s, name) for s, name in zip(packet.streams, names)]
    try:
        if packet.stop > packet.start:
            _apply_splits(work, packet.start, packet.stop, readers, packet.attribute_grids,
                          packet.ring_edges)
        else:
            _apply_collapses(work, packet.start, packet.stop, readers, packet.attribute_grids)
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
    wedges = corners = material = None
    if packet.attribute_grids:
        k = sum(g.components for g in packet.attribute_grids)
        wedges = np.array(work.wedge_values, dtype=np.int64).reshape(-1, k)
        corners = work.corner_wedges[:work.face_count].copy()
        start = 0
        for g in packet.attribute_grids:
            column = wedges[:, start:start + g.components]
            start += g.components
            if column.min(initial=0) < 0 or column.max(initial=0) > 2**g.bits - 1:
                raise PacketError(f"the packet moves a {g.name} value off its grid")
            if g.encoding == TANGENT and column[:, 2].max(initial=0) > 1:
                raise PacketError("the packet gives a TANGENT a handedness other than -1 or +1")
        if corners.min(initial=0) < 0 or corners.max(initial=-1) >= len(wedges):
            raise PacketError("the packet leaves a corner on a wedge that does not exist")
    if packet.has_materials:
        material = work.face_material[:work.face_count].copy()
    return LodState(positions, work.faces[:work.face_count].copy(), state.grid, wedges, corners,
                    state.attribute_grids, material)


def _apply_splits(work: Working, start, stop, readers, grids, ring_edges=None):
    vertex, count, pattern, other, fan, mask, position = readers[:7]
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
                if kind == IS_VS:
                    corners.append(s)
                elif kind == IS_NEW:
                    corners.append(t)
                else:
                    u = other.varint()
                    corners.append(around[u] if u < len(around) else u - len(around))
            if max(corners) > t:
                raise PacketError(f"split {t} adds a face on a vertex that does not exist yet")
            added.append(corners)

        if fan.take(1)[0] == FAN_PREDICTED:
            moved = predict_fan(work, s, t, added)
            if moved is None:
                raise PacketError(f"split {t} relies on a fan prediction that does not exist")
        else:
            bits = mask.take((len(held) + 7) // 8)
            moved = [c for i, c in enumerate(held) if bits[i // 8] >> (i % 8) & 1]
        first = work.face_count
        for c in moved:
            work.set_corner(c, t)
        for corners in added:
            work.append_face(corners)

        coarse = work.positions[s].copy()
        if ring_edges is None:
            d1 = [position.signed() for _ in range(3)]
            d2 = [position.signed() for _ in range(3)]
        else:
            d1, d2 = ring_edge_fields(work, s, t, ring_edges[t - start])
        fine = coarse + d1
        work.positions[s] = fine
        work.positions[t] = 2 * coarse - fine + d2
        if grids:
            geometry = (coarse.tolist(), fine.tolist(), work.positions[t].tolist())
            _split_wedges(work, s, t, held, set(moved), first, geometry, readers, grids)
        if work.face_material is not None:
            material = readers[-1]
            for f in range(first, work.face_count):
                work.face_material[f] = material.varint() - 1


def _split_wedges(work: Working, s, t, held, moved, first, geometry, readers, grids):
    """The wedge part of split ``t`` (docs/packets.md), after its geometry part:
    ``held`` is ``held(s)``, ``moved`` the corners moved to ``t``, ``first`` the
    first new face, ``geometry`` the grid positions ``(coarse, fine, new)``."""
    wedge_count, wedge_parent, wedge_corner = readers[7:10]
    values = readers[10:10 + len(grids)]
    bottom = len(work.wedge_values)
    top = bottom + wedge_count.varint()
    candidates = work.wedges_held(held)
    parents = []
    for x in range(bottom, top):
        u = wedge_parent.varint()
        p = candidates[u] if u < len(candidates) else u - len(candidates)
        if not 0 <= p < x:
            raise PacketError(f"split {t} gives wedge {x} the parent {p}, which is not below it")
        parents.append(p)
        guess_fine, guess_new = split_guesses(work, s, held, p, geometry, grids)
        fine, new, at = [], [], 0
        for grid, stream in zip(grids, values):
            columns = range(at, at + grid.components)
            at += grid.components
            fine += [guess_fine[j] + stream.signed() for j in columns]
            new += [guess_new(j, fine[j]) + stream.signed() for j in columns]
        work.wedge_values[p] = fine
        work.wedge_values.append(new)
    m = top - bottom
    for c in held:
        if c not in moved:
            continue
        y = work.wedge_of(c)
        u = wedge_corner.varint()
        if u == 0:
            w = moved_prediction(parents, bottom, y)
        elif u <= m:
            w = bottom + u - 1
        elif u == m + 1:
            w = y
        else:
            w = u - m - 2
        work.set_wedge(c, w)
    for f in range(first, work.face_count):
        for k in range(3):
            candidates = corner_candidates(work, int(work.faces[f, k]), 3 * first, bottom, top)
            u = wedge_corner.varint()
            work.set_wedge(3 * f + k, candidates[u] if u < len(candidates) else u - len(candidates))


def _apply_collapses(work: Working, start, stop, readers, grids):
    vertex, count, _, _, _, _, position = readers[:7]
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
        fine = work.positions[s].tolist()
        middle = (work.positions[s] + work.positions[t]) >> 1
        work.positions[s] = middle + [position.signed() for _ in range(3)]
        if grids:
            ratio = collapse_ratio(fine, work.positions[t].tolist(), work.positions[s].tolist())
            _collapse_wedges(work, t, s, ratio, readers, grids)


def _collapse_wedges(work: Working, t, s, ratio, readers, grids):
    """The wedge part of collapse ``t`` into ``s``, after its geometry part
    (``ratio``: the :func:`collapse_ratio` of the positions)."""
    wedge_count, wedge_parent = readers[7:9]
    values = readers[10:10 + len(grids)]
    top = len(work.wedge_values)
    bottom = top - wedge_count.varint()
    if bottom < 0:
        raise PacketError(f"collapse of {t} removes more wedges than the state holds")
    candidates = [w for w in work.wedges_held(work.corners.of(s)) if w < bottom]
    parents = {}
    for x in range(top - 1, bottom - 1, -1):
        u = wedge_parent.varint()
        p = candidates[u] if u < len(candidates) else u - len(candidates)
        if not 0 <= p < x:
            raise PacketError(f"collapse of {t} merges wedge {x} into {p}, which is not below it")
        parents[x] = p
        merged, at = [], 0
        for grid, stream in zip(grids, values):
            # the merged value: between the two as the positions are, plus a residual
            for a, b in zip(work.wedge_values[p][at:at + grid.components],
                            work.wedge_values[x][at:at + grid.components]):
                merged.append(a + scaled(ratio, b - a) + stream.signed())
            at += grid.components
        work.wedge_values[p] = merged
    for c in work.corners.of(s):
        w = work.wedge_of(c)
        while w >= bottom:
            w = parents[w]
        work.set_wedge(c, w)
    del work.wedge_values[bottom:]
