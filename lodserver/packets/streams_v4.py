"""Version 4's symbol streams: what each field of the records becomes, and its context.

docs/packets.md, "Version 4". A version 4 packet carries the records of
version 3 (the same predictions, fans, wedges), but each field is coded as
integers with rANS (``rans.py``) in streams by kind, and two fields are
written differently:

- **where splits happen** (``batch``, ``vertex``): splits come in *batches*
  (runs of consecutive splits with one batch id, their vertices ``vs``
  ascending); ``batch`` holds each run's length less one, ``vertex`` the gaps
  between the ``vs`` of a run (the first ``vs`` itself, then
  ``vs - previous vs - 1``): about ``log2(e N / k)`` bits per split for ``k``
  splits among ``N`` vertices, where an index costs ``log2 N``.
- **positions** with :data:`~.format.EDGE_POSITIONS`: instead of version 3's
  ``d1`` (vs's move) and ``d2`` (the new vertex's offset from the mirror
  guess), the split edge ``E = d2 - 2 d1`` (the new vertex less vs's fine
  position), the place ``l`` in 16ths along it where the collapse put vs, and
  what is left: ``r = d1 + floor((l E + 8) / 16)`` per axis.

This module holds the rules both ends share: the streams and their shapes
(how many contexts, how a symbol's context follows from the symbols before
it) and the two transforms. Signed integers are zigzagged as in version 3.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from .format import EDGE_POSITIONS, MAGNITUDE_CONTEXTS, stream_names

# The magnitude classes of a classed stream's contexts (see Shape).
CLASSES = 8
# Places along the split edge are coded in 1/PLACES steps, 0 .. PLACES.
PLACES = 16
# Runs of a split packet: a vertex symbol is the first of its run (context 0) or a
# gap after another (context 1).
RUN_CONTEXTS = 2
# A pattern symbol's context: first of its record, or after one of the 27 patterns.
FACE_CONTEXTS = 28


@dataclass(frozen=True)
class Shape:
    """How a stream's symbols get their contexts.

    ``period`` symbols make a *group* (a record's position, a wedge's values);
    symbol ``i`` sits at ``j = i % period`` in its group. Unclassed: the context
    is ``j``. Classed: ``j * CLASSES + c``, ``c`` the :func:`magnitude_class` of
    the largest symbol of its group before it, or for the first of a group, of
    the previous group's (0 for the very first).
    ``runs``: the vertex stream of a split packet (:data:`RUN_CONTEXTS`).
    ``faces``: the pattern stream, whose context is 0 for a record's first new
    face and ``1 + p`` after a face of pattern ``p`` (:data:`FACE_CONTEXTS`).
    """

    period: int = 1
    classed: bool = False
    runs: bool = False
    faces: bool = False

    @property
    def contexts(self) -> int:
        if self.runs:
            return RUN_CONTEXTS
        if self.faces:
            return FACE_CONTEXTS
        return self.period * (CLASSES if self.classed else 1)


def stream_names_v4(attribute_grids: tuple, has_materials: bool) -> tuple[str, ...]:
    """The streams of a version 4 packet, in body order: ``batch``, then version 3's."""
    return ("batch",) + stream_names(attribute_grids, has_materials)


def shapes(attribute_grids: tuple, has_materials: bool, forward: bool, flags: int) -> list:
    """The :class:`Shape` of every stream of :func:`stream_names_v4`."""
    classed = bool(flags & MAGNITUDE_CONTEXTS)
    position = (7 if flags & EDGE_POSITIONS else 6) if forward else 3
    out = [Shape(), Shape(runs=forward), Shape(), Shape(faces=forward)] + [Shape()] * 4
    out[7] = Shape(position, classed)
    if attribute_grids:
        out += [Shape()] * 3
        out += [Shape((2 if forward else 1) * g.components, classed) for g in attribute_grids]
    if has_materials:
        out.append(Shape())
    return out


@njit(cache=True, nogil=True)
def magnitude_class(value):
    """The class of a symbol ``value >= 0``: 0 below 8, then one per power of two,
    the last for 512 and more."""
    n = 0
    while value >> n and n < CLASSES + 2:
        n += 1
    return min(max(n - 3, 0), CLASSES - 1)


def context_of(shape: Shape, i: int, decoded: list) -> int:
    """The context of symbol ``i`` of a stream of ``shape`` after ``decoded`` (the
    reference rule; :func:`contexts` is the same over a whole array)."""
    j = i % shape.period
    if not shape.classed:
        return j
    lo = i - j if j else i - shape.period
    largest = max(decoded[max(lo, 0):i], default=0)
    return j * CLASSES + magnitude_class(largest)


@njit(cache=True, nogil=True)
def _classed_contexts(values, period):
    out = np.empty(values.shape[0], dtype=np.int64)
    group = 0                       # the largest symbol of the group so far
    previous = 0                    # ... and of the group before
    for i in range(values.shape[0]):
        j = i % period
        if j == 0:
            previous, group = (group if i else 0), 0
            out[i] = magnitude_class(previous)
        else:
            out[i] = j * CLASSES + magnitude_class(group)
        group = max(group, values[i])
    return out


def face_contexts(counts, patterns) -> np.ndarray:
    """The contexts of a segment's pattern symbols, from its records' face counts."""
    return _face_contexts(np.ascontiguousarray(counts, dtype=np.int64),
                          np.ascontiguousarray(patterns, dtype=np.int64))


@njit(cache=True, nogil=True)
def _face_contexts(counts, patterns):
    out = np.empty(patterns.shape[0], dtype=np.int64)
    i = 0
    for k in counts:
        for f in range(k):
            out[i] = 0 if f == 0 else 1 + patterns[i - 1]
            i += 1
    return out


def contexts(shape: Shape, values: np.ndarray) -> np.ndarray:
    """The context of every symbol of ``values`` (not for ``runs`` or ``faces`` streams)."""
    if shape.classed:
        return _classed_contexts(np.ascontiguousarray(values, dtype=np.int64), shape.period)
    return np.arange(len(values), dtype=np.int64) % shape.period


# ---- zigzag ---------------------------------------------------------------------------
def zigzag(a: np.ndarray) -> np.ndarray:
    """Signed -> unsigned as version 3's signed varints: 0, -1, 1, -2 -> 0, 1, 2, 3."""
    a = np.asarray(a, dtype=np.int64)
    return np.where(a >= 0, 2 * a, -2 * a - 1)


def unzigzag(u: np.ndarray) -> np.ndarray:
    """The inverse of :func:`zigzag`."""
    u = np.asarray(u, dtype=np.int64)
    return (u >> 1) ^ -(u & 1)


# ---- the split edge -------------------------------------------------------------------
def to_edge(d: np.ndarray) -> np.ndarray:
    """(records, 7) signed: ``E``, ``l``, ``r`` from version 3's (records, 6) ``d1, d2``.

    ``l`` is the encoder's choice (the place nearest to the collapse's); any value in
    ``[0, PLACES]`` decodes to the same positions, as ``r`` absorbs the difference.
    """
    d1, d2 = d[:, :3], d[:, 3:]
    edge = d2 - 2 * d1
    length = (edge * edge).sum(1)
    along = -(d1 * edge).sum(1)
    place = np.full(len(d), PLACES // 2, dtype=np.int64)
    moved = length > 0
    place[moved] = np.clip(np.rint(PLACES * along[moved] / length[moved]), 0, PLACES)
    rest = d1 + (place[:, None] * edge + PLACES // 2) // PLACES
    return np.concatenate([edge, place[:, None], rest], axis=1)


# The column of the place in a record's position symbols: unsigned, not zigzagged.
PLACE_COLUMN = 3


def position_symbols(d: np.ndarray, edge: bool, ring: np.ndarray | None = None) -> np.ndarray:
    """The position stream's symbols of split records, from version 3's signed
    (records, 6) ``d1, d2``: zigzagged, through :func:`to_edge` when ``edge``, the
    edge less its prediction ``ring`` (records, 3) when given (``ring_v4.py``)."""
    if not edge:
        return zigzag(d).ravel()
    e = to_edge(d)
    if ring is not None:
        e[:, :3] -= ring
    out = zigzag(e)
    out[:, PLACE_COLUMN] = e[:, PLACE_COLUMN]
    return out.ravel()


def position_fields(symbols: np.ndarray, edge: bool) -> np.ndarray:
    """The inverse of :func:`position_symbols`: (records, 6) ``d1, d2``."""
    if not edge:
        return unzigzag(symbols).reshape(-1, 6)
    e = symbols.reshape(-1, 7)
    out = unzigzag(e)
    out[:, PLACE_COLUMN] = e[:, PLACE_COLUMN]
    return from_edge(out)


def from_edge(e: np.ndarray) -> np.ndarray:
    """Version 3's (records, 6) ``d1, d2`` from the (records, 7) of :func:`to_edge`."""
    edge, place, rest = e[:, :3], e[:, 3:4], e[:, 4:]
    d1 = rest - (place * edge + PLACES // 2) // PLACES
    return np.concatenate([d1, edge + 2 * d1], axis=1)
