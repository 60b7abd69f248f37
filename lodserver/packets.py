"""Vertex-split packets: the bytes that take a client from one level to another.

A client holds one level of a progressive mesh in its *quantized form*
(:func:`quantized_level`, served by the LOD endpoint as ``format=json``):
integer grid positions and faces in the slots of the prefix layout
(``progressive.py``). A packet from level ``A`` to level ``B`` carries the
``|B - A|`` vertex splits (``B > A``) or edge collapses (``B < A``) between
them; applying it (:func:`apply_packet`) yields exactly the quantized form of
level ``B``: the same grid positions and the same faces in the same slots
(and the same wedge values, corner wedges and face materials).

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
- With attributes (version 2), the state also holds wedges: grid values per
  attribute (:class:`AttributeGrid`: linear, or octahedral for normals) and the
  wedge of every corner. A split then names how many wedges it adds, each one's
  parent by rank among ``vs``'s wedges and its two values (the parent's finer
  one, the new wedge's) as residuals from their extrapolation along the
  attribute gradient fitted around ``vs``; and the wedge of each moved corner
  and new-face corner as a small code (nearly always 0, the predicted one). A
  collapse names how many wedges go, their parents, and the merged values as
  residuals from between the two. Packets also carry each new face's material.
- Each kind of field goes to its own stream of LEB128 varints or bytes, and
  the streams are deflated together (zlib), which entropy-codes each kind apart.

Neighbour ranks need connectivity, so both encoder and decoder track, for every
vertex, the set of corners (``3 * face + slot``) that hold it. The decoder is
plain Python, written to be read as the reference for clients; the encoder runs
the same logic as numba kernels over arrays (see "encoding" below), checked
byte for byte against a pure-Python encoder kept in ``tests/naive_packets.py``.
"""

from __future__ import annotations

import math
import struct
import threading
import weakref
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numba import njit

from .mesh import ATTRIBUTE_WIDTHS, MeshError
from .progressive import ProgressiveMesh, _ancestor_below
from .quadrics import symmetric_cofactors

MAGIC = b"LODV"
PACKET_VERSION = 2
# Versions decode_packet reads: a version 1 packet is a geometry-only version 2 one.
READABLE_VERSIONS = (1, 2)
MIN_BITS, MAX_BITS = 8, 24
# Grid steps per mean edge at full detail, as a power of two: see default_bits.
EDGE_BITS = 6

# magic, version, bits, attribute count, flags, from, to, faces at from, faces at to,
# origin, step, body length; then one _ATTRIBUTE record (+ origin) per attribute.
_HEADER = struct.Struct("<4sBBBBIIII3ddI")
_ATTRIBUTE = struct.Struct("<BBBBd")
# flags
_HAS_MATERIALS = 1
# Streams, in body order. A collapse packet leaves FAN, MASK, PATTERN and OTHER empty.
VERTEX, COUNT, PATTERN, OTHER, FAN, MASK, POSITION = range(7)
_STREAM_NAMES = ("vertex", "count", "pattern", "other", "fan", "mask", "position")
# With attributes, these follow (then one value stream per attribute, then MATERIAL
# when the mesh has face materials; MATERIAL alone when it has materials only).
WEDGE_COUNT, WEDGE_PARENT, WEDGE_CORNER = range(7, 10)
_WEDGE_STREAM_NAMES = ("wedge_count", "wedge_parent", "wedge_corner")
# FAN: whether a split's moved corners are the predicted fan (0) or listed in MASK (1).
_FAN_PREDICTED, _FAN_LISTED = 0, 1
# A face corner in a split's new face is vs, the new vertex, or another vertex.
_IS_VS, _IS_NEW, _IS_OTHER = 0, 1, 2

# Attributes in packet headers: glTF semantic <-> id, and the encodings of their grids.
ATTRIBUTE_IDS = {"NORMAL": 0, "TEXCOORD_0": 1, "TEXCOORD_1": 2, "COLOR_0": 3}
_ATTRIBUTE_NAMES = {v: k for k, v in ATTRIBUTE_IDS.items()}
LINEAR, OCTAHEDRAL = "linear", "octahedral"
_ENCODING_IDS = {LINEAR: 0, OCTAHEDRAL: 1}
# Default grid bits per attribute (see attribute_grids_of). Normals: octahedral,
# 10 bits per component (at most 0.25 degrees off); UVs: 12 bits over their range
# (a quarter texel on a 1024-texel texture spanning it); colours: 10 bits.
DEFAULT_ATTRIBUTE_BITS = {"NORMAL": 10, "TEXCOORD_0": 12, "TEXCOORD_1": 12, "COLOR_0": 10}


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


@dataclass(frozen=True)
class AttributeGrid:
    """The quantization of one appearance attribute (a glTF vertex attribute).

    name : str          ``NORMAL``, ``TEXCOORD_0``, ``TEXCOORD_1`` or ``COLOR_0``
    encoding : str      ``linear``: ``value = origin + q * step`` per component;
                        ``octahedral`` (normals): two coordinates ``origin + q * step``
                        on the octahedron, unfolded to a unit vector (:func:`unfold_octahedral`)
    origin : tuple      per component of the encoding
    step : float        the same for all components
    bits : int          grid coordinates lie in ``[0, 2**bits - 1]``
    """

    name: str
    encoding: str
    origin: tuple
    step: float
    bits: int

    @property
    def width(self) -> int:
        """Floats per value (the attribute's glTF width)."""
        return ATTRIBUTE_WIDTHS[self.name]

    @property
    def components(self) -> int:
        """Integers per quantized value."""
        return 2 if self.encoding == OCTAHEDRAL else self.width

    def quantize(self, values: np.ndarray) -> np.ndarray:
        """(k, width) float values -> (k, components) int64 grid coordinates (nearest)."""
        values = np.asarray(values, dtype=np.float64).reshape(-1, self.width)
        if self.encoding == OCTAHEDRAL:
            values = fold_octahedral(values)
        q = np.rint((values - np.array(self.origin)) / self.step)
        return np.clip(q, 0, 2**self.bits - 1).astype(np.int64)

    def dequantize(self, q: np.ndarray) -> np.ndarray:
        """(k, components) grid coordinates -> (k, width) float64 values, as a client computes them."""
        x = np.array(self.origin) + np.asarray(q, dtype=np.float64) * self.step
        return unfold_octahedral(x) if self.encoding == OCTAHEDRAL else x

    def as_dict(self) -> dict:
        return {"encoding": self.encoding, "origin": list(self.origin), "step": self.step,
                "bits": self.bits}


def fold_octahedral(normals: np.ndarray) -> np.ndarray:
    """(k, 3) directions -> (k, 2) points of the square [-1, 1]^2 (Meyer et al. 2010):
    project onto the octahedron ``|x| + |y| + |z| = 1`` and fold its lower half
    out over the corners. A zero vector maps to (0, 0), which unfolds to +z."""
    n = np.asarray(normals, dtype=np.float64)
    l1 = np.abs(n).sum(axis=1)
    n = n / np.where(l1 > 0, l1, 1.0)[:, None]
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    sx, sy = np.where(x >= 0, 1.0, -1.0), np.where(y >= 0, 1.0, -1.0)
    lower = z < 0
    return np.stack([np.where(lower, (1 - np.abs(y)) * sx, x),
                     np.where(lower, (1 - np.abs(x)) * sy, y)], axis=1)


def unfold_octahedral(points: np.ndarray) -> np.ndarray:
    """(k, 2) points of [-1, 1]^2 -> (k, 3) unit vectors: the inverse of :func:`fold_octahedral`."""
    p = np.asarray(points, dtype=np.float64)
    x, y = p[:, 0], p[:, 1]
    z = 1 - np.abs(x) - np.abs(y)
    lower = z < 0
    sx, sy = np.where(x >= 0, 1.0, -1.0), np.where(y >= 0, 1.0, -1.0)
    n = np.stack([np.where(lower, (1 - np.abs(y)) * sx, x),
                  np.where(lower, (1 - np.abs(x)) * sy, y), z], axis=1)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def default_bits(pm: ProgressiveMesh) -> int:
    """Grid bits giving the same number of steps along a full-detail edge on every mesh.

    A mesh of ``n`` vertices spanning its box has edges of about
    ``extent / sqrt(n)``, so ``log2(n) / 2 + EDGE_BITS`` bits keep the rounding
    error at the same fraction of an edge on every mesh, and so the packet's
    bytes per split about the same too. Clamped to [10, 16]. That estimate is
    short: measured, a full-detail edge is 114 steps long on spot and 155 on
    the Stanford bunny rather than ``2**EDGE_BITS`` (docs/packets.md).
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


def attribute_grids_of(pm: ProgressiveMesh, *, attribute_bits: dict | None = None) -> tuple:
    """The grids of ``pm``'s attributes, in layout order (empty without attributes).

    Normals use an octahedral grid with ``origin = (-1, -1)`` and
    ``step = 2 / (2**bits - 2)``, so that ``q = 2**(bits-1) - 1`` is exactly 0
    (axis-aligned normals stay exact). Other attributes use a linear grid over
    every value any level uses, one step for all components, like positions.
    ``attribute_bits`` maps attribute names to bits (default
    :data:`DEFAULT_ATTRIBUTE_BITS`).
    """
    if not pm.has_attributes:
        return ()
    attribute_bits = dict(attribute_bits or {})
    unknown = set(attribute_bits) - {name for name, _ in pm.attribute_layout}
    if unknown:
        raise ValueError(f"the mesh has no attribute named {', '.join(sorted(unknown))}")
    grids = []
    for i, (name, _) in enumerate(pm.attribute_layout):
        bits = check_bits(attribute_bits.get(name, DEFAULT_ATTRIBUTE_BITS[name]))
        if name == "NORMAL":
            grids.append(AttributeGrid(name, OCTAHEDRAL, (-1.0, -1.0), 2 / (2**bits - 2), bits))
            continue
        lo, extent = _attribute_box_of(pm)[i]
        grids.append(AttributeGrid(name, LINEAR, lo, extent / (2**bits - 1) if extent > 0 else 1.0,
                                   bits))
    return tuple(grids)


def _attribute_box_of(pm: ProgressiveMesh) -> list:
    """Per attribute: the smallest value of any wedge at any level per component, and the
    largest extent over the components."""
    with _boxes_lock:
        boxes = _attribute_boxes.get(pm)
    if boxes is None:
        values = np.concatenate([pm.wedge_values, pm.wedge_coarse_value])
        boxes, start = [], 0
        for _, width in pm.attribute_layout:
            column = values[:, start:start + width]
            start += width
            lo = column.min(axis=0) if len(column) else np.zeros(width)
            hi = column.max(axis=0) if len(column) else np.zeros(width)
            boxes.append((tuple(float(x) for x in lo), float((hi - lo).max())))
        with _boxes_lock:
            _attribute_boxes[pm] = boxes
    return boxes


_attribute_boxes: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def quantize_wedges(grids: tuple, values: np.ndarray) -> np.ndarray:
    """(k, d) wedge values -> (k, sum of components) int64, attribute after attribute."""
    values = np.asarray(values, dtype=np.float64)
    columns, start = [], 0
    for grid in grids:
        columns.append(grid.quantize(values[:, start:start + grid.width]))
        start += grid.width
    if not columns:
        return np.zeros((len(values), 0), dtype=np.int64)
    return np.ascontiguousarray(np.concatenate(columns, axis=1))


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

    With attributes (None / empty without):

    wedges : (w, k) int64      grid coordinates of wedges ``0 .. w-1``, attribute
                               after attribute (``k`` = the grids' components)
    corners : (f, 3) int64     the wedge of every face corner
    attribute_grids : tuple    an :class:`AttributeGrid` per attribute, in layout order
    face_material : (f,) int64 the material of every face (-1: none), or None
    """

    positions: np.ndarray
    faces: np.ndarray
    grid: Grid
    wedges: np.ndarray | None = None
    corners: np.ndarray | None = None
    attribute_grids: tuple = ()
    face_material: np.ndarray | None = None

    @property
    def level(self) -> int:
        return len(self.positions)

    @property
    def components(self) -> int:
        return sum(g.components for g in self.attribute_grids)


def state_from_json(document: dict) -> LodState:
    """The state held by a client that fetched ``/lod?format=json`` (``export.encode_level``)."""
    grid = document["grid"]
    faces = np.array(document["faces"], dtype=np.int64).reshape(-1, 3)
    grids, wedges, corners = (), None, None
    if document.get("layout"):
        grids = tuple(AttributeGrid(name, document["attribute_grid"][name]["encoding"],
                                    tuple(float(x) for x in document["attribute_grid"][name]["origin"]),
                                    float(document["attribute_grid"][name]["step"]),
                                    int(document["attribute_grid"][name]["bits"]))
                      for name, _ in document["layout"])
        k = sum(g.components for g in grids)
        wedges = np.array(document["wedges"], dtype=np.int64).reshape(-1, k)
        corners = np.array(document["corners"], dtype=np.int64).reshape(-1, 3)
    material = document.get("face_material")
    return LodState(np.array(document["positions"], dtype=np.int64).reshape(-1, 3), faces,
                    Grid(tuple(float(x) for x in grid["origin"]), float(grid["step"]),
                         int(grid["bits"])),
                    wedges, corners, grids,
                    None if material is None else np.array(material, dtype=np.int64).reshape(-1))


def quantized_level(pm: ProgressiveMesh, level: int, grid: Grid,
                    attribute_grids: tuple | None = None) -> LodState:
    """The quantized form of ``level``: what the LOD endpoint serves as JSON.
    ``attribute_grids`` defaults to :func:`attribute_grids_of`."""
    positions, faces = pm.arrays_at(level)
    wedges = corners = material = None
    grids = ()
    if pm.has_attributes:
        grids = attribute_grids_of(pm) if attribute_grids is None else tuple(attribute_grids)
        values, corners = pm.wedges_at(level)
        wedges = quantize_wedges(grids, values)
    if pm.face_material is not None:
        material = pm.face_material[:len(faces)].astype(np.int64)
    return LodState(grid.quantize(positions), faces, grid, wedges, corners, grids, material)


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


def _corner_candidates(work: _Working, v: int, limit: int, bottom: int, top: int) -> list[int]:
    """The wedges a new face's corner on ``v`` may take: those of ``v``'s corners
    below corner ``limit`` (the faces before the record), ascending, then the
    record's new wedges ``bottom .. top-1`` not among them."""
    held = work.wedges_held(c for c in work.corners.of(v) if c < limit)
    known = set(held)
    return held + [x for x in range(bottom, top) if x not in known]


# The split's new wedge is predicted beyond the parent's coarse value by the
# ratio the new vertex lies beyond vs's coarse position, clamped to this.
_MAX_SPLIT_RATIO = 4.0


def _split_ratio(coarse, fine, new) -> float:
    """How far the new vertex lies beyond ``coarse`` (vs before the split), in units
    of ``coarse - fine``: ``(new - coarse) . (coarse - fine) / |coarse - fine|^2``,
    clamped to ``[0, 4]``; 1 (the mirror image) when vs did not move. Integer grid
    positions, so both dot products are exact in float64: every decoder gets
    the same float."""
    a = sum(float(c - f) * float(c - f) for c, f in zip(coarse, fine))
    b = sum(float(n - c) * float(c - f) for c, f, n in zip(coarse, fine, new))
    ratio = b / a if a > 0 else 1.0
    return min(max(ratio, 0.0), _MAX_SPLIT_RATIO)


def _collapse_ratio(fine, new, coarse) -> float:
    """Where the merged position lies between vs's (``fine``) and the removed vertex's
    (``new``): ``(coarse - fine) . (new - fine) / |new - fine|^2`` clamped to
    ``[0, 1]``; 1/2 when the two coincide."""
    a = sum(float(n - f) * float(n - f) for f, n in zip(fine, new))
    b = sum(float(c - f) * float(n - f) for f, n, c in zip(fine, new, coarse))
    ratio = b / a if a > 0 else 0.5
    return min(max(ratio, 0.0), 1.0)


# The fit of a wedge's attribute gradient is damped by this fraction of the trace.
_GRADIENT_DAMPING = 1e-3


def _gradient(work: _Working, s: int, held: list, p: int, coarse) -> list | None:
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
    damping = (m00 + m11 + m22) * _GRADIENT_DAMPING + 1e-9
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


def _extrapolated(gradient: list, j: int, value: int, delta, limit: int) -> int:
    """``value`` moved by ``gradient`` over the position change ``delta`` (integers),
    rounded, within ``[0, limit]``: ``floor(value + J . delta + 0.5)``."""
    x = (float(value) + (float(delta[0]) * gradient[0][j] + float(delta[1]) * gradient[1][j]
                         + float(delta[2]) * gradient[2][j])) + 0.5
    if not x >= 0:        # also NaN
        return 0
    if x > limit:
        return limit
    return math.floor(x)


def _split_guesses(work: _Working, s: int, held: list, p: int, geometry, grids):
    """The predictions of split values for the new wedge of parent ``p``:
    ``(guess_fine, guess_new)``, the parent's finer value (a list) and a function
    ``guess_new(j, fine_j)`` of component ``j`` of the new wedge's value.

    With a :func:`_gradient` around ``s``, both extrapolate ``p``'s current value
    over the moves from vs's coarse position to its fine one and to the new
    vertex's. Without one, the parent keeps its value and the new wedge lies
    beyond it as the new vertex does (:func:`_split_ratio`).
    """
    coarse, fine, new = geometry
    current = work.wedge_values[p]
    gradient = _gradient(work, s, held, p, coarse)
    if gradient is None:
        ratio = _split_ratio(coarse, fine, new)
        return list(current), lambda j, f: current[j] + _scaled(ratio, current[j] - f)
    limits = [2**g.bits - 1 for g in grids for _ in range(g.components)]
    to_fine = [a - b for a, b in zip(fine, coarse)]
    to_new = [a - b for a, b in zip(new, coarse)]
    guess_fine = [_extrapolated(gradient, j, current[j], to_fine, limits[j])
                  for j in range(len(current))]
    guess_new = [_extrapolated(gradient, j, current[j], to_new, limits[j])
                 for j in range(len(current))]
    return guess_fine, lambda j, f: guess_new[j]


def _scaled(ratio: float, d: int) -> int:
    """``floor(ratio * d + 0.5)``: the rounding every decoder does the same way."""
    return math.floor(ratio * d + 0.5)


def _moved_prediction(parents: list[int], bottom: int, y: int) -> int:
    """The predicted finer wedge of a moved corner holding ``y``: the first new wedge
    (``bottom + i``, parent ``parents[i]``) that is a child of ``y``, else ``y``."""
    for i, parent in enumerate(parents):
        if parent == y:
            return bottom + i
    return y


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
    start, stop = pm._check_level(start), pm._check_level(stop)
    grid = grid_of(pm, bits=bits)
    grids = attribute_grids_of(pm, attribute_bits=attribute_bits)
    streams = _encode_streams(pm, start, stop, grid, grids, _NO_MARKS)
    return _assemble(pm, grid, grids, start, stop, streams)


def _assemble(pm: ProgressiveMesh, grid: Grid, grids: tuple, start: int, stop: int,
              streams: list) -> bytes:
    """Header, then the streams (each after its varint length), deflated."""
    body = bytearray()
    for stream in streams:
        _put_varint(body, len(stream))
        body += memoryview(stream)
    header = pack_header(grid, grids, pm.face_material is not None, start, stop,
                         pm.faces_at_level(start), pm.faces_at_level(stop), len(body))
    return header + deflate_body(bytes(body))


def deflate_body(body: bytes) -> bytes:
    """The zlib stream of a packet body. The level is not part of the format:
    on a 5.6 MB body 9 packed 0.24% tighter than 6, in 1.75 times as long."""
    return zlib.compress(body, 9 if len(body) < 2**20 else 6)


def _encode_streams(pm: ProgressiveMesh, start: int, stop: int, grid: Grid, grids: tuple,
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
    index = _index_dtype(3 * face_capacity, pm.vertex_count)
    work_positions = np.zeros((max(start, stop), 3), dtype=np.int64)
    work_positions[:start] = grid.quantize(positions)
    work_faces = np.zeros(3 * face_capacity, dtype=index)
    work_faces[:faces.size] = faces.ravel()
    offsets = np.cumsum([0] + [g.components for g in grids]).astype(np.int64)
    material = (pm.face_material.astype(np.int64) if has_materials
                else np.zeros(0, dtype=np.int64))
    if grids:
        values, corners = pm.wedges_at(start)
        lo, hi = (int(pm.wedge_counts[level - n0]) for level in sorted((start, stop)))
        w0 = int(pm.wedge_counts[0])
        work_values = np.zeros((hi, offsets[-1]), dtype=np.int64)
        work_values[:len(values)] = quantize_wedges(grids, values)
        work_wedges = np.zeros(3 * face_capacity, dtype=index)
        work_wedges[:corners.size] = corners.ravel()
        wedge_counts, wedge_parent = pm.wedge_counts, pm.wedge_parent
        birth_corners, full_corners = pm.birth_corners, pm.corner_wedges
    else:
        lo = hi = w0 = 0
        work_values = np.zeros((0, 0), dtype=np.int64)
        work_wedges = np.zeros(0, dtype=index)
        # read-only like the progressive mesh's arrays: the same compiled kernel
        wedge_counts = wedge_parent = _READ_ONLY_INDEX
        birth_corners = full_corners = _READ_ONLY_CORNERS
    if stop > start:
        a, b = start - n0, stop - n0
        wedge_fine = wedge_new = np.zeros((0, 0), dtype=np.int64)
        if grids:   # of wedges lo .. hi-1, the splits' new wedges
            wedge_fine = quantize_wedges(grids, pm.wedge_fine_value[lo - w0:hi - w0])
            wedge_new = quantize_wedges(grids, pm.wedge_new_value[lo - w0:hi - w0])
        streams, wedge_streams, value_streams, error = _encode_splits(
            work_positions, work_faces, len(faces), start, stop, n0, pm.parent, pm.face_counts,
            pm.birth_faces, pm.moved_offsets, pm.moved_corners,
            grid.quantize(pm.fine_position[a:b]), grid.quantize(pm.new_position[a:b]),
            work_wedges, work_values, wedge_counts, wedge_parent, wedge_fine, wedge_new, lo,
            birth_corners, full_corners, offsets,
            np.array([2**g.bits - 1 for g in grids], dtype=np.int64), material, marks)
        t, c, s = (int(x) for x in error)
        if t >= 0:
            raise PacketError(f"split {t} moves corner {c}, which does not hold vertex {s}")
    else:
        wedge_coarse = np.zeros((0, 0), dtype=np.int64)
        if grids:   # of wedges lo .. hi-1, the collapses' removed wedges
            wedge_coarse = quantize_wedges(grids, pm.wedge_coarse_value[lo - w0:hi - w0])
        streams, wedge_streams, value_streams = _encode_collapses(
            work_positions, work_faces, len(faces), start, stop, n0, pm.parent, pm.face_counts,
            grid.quantize(pm.coarse_position[stop - n0:start - n0]),
            work_wedges, work_values, wedge_counts, wedge_parent, wedge_coarse, lo, offsets,
            marks)
    streams = list(streams)
    if grids:
        buffers, used = value_streams
        streams += list(wedge_streams[:3]) + [buffers[i, :used[i]] for i in range(len(grids))]
    if has_materials:
        streams.append(wedge_streams[3])
    return streams


# ---- every record, encoded once ---------------------------------------------
# Records per pre-deflated chunk of a stream. Smaller chunks cost more deflate block
# headers and lost matches (~0.5% of a full packet at 8192); larger ones leave more
# to deflate per packet at its two ends.
CHUNK_RECORDS = 8192


@dataclass(frozen=True, eq=False)
class RecordStreams:
    """The streams of every record of one direction, between the base and full detail.

    A record's bytes depend only on the level it starts from: the quantized state
    of a level is the same whichever way a client reached it, and every
    prediction reads only that state. So the packet ``A -> B`` is, stream by
    stream, a slice of these: records ``A .. B-1`` forward, ``A-1 .. B`` backward.

    ``chunks[k][i]`` is stream ``k``'s records ``i * chunk .. (i+1) * chunk - 1``
    as raw deflate ending in a sync flush (byte aligned, not final): deflate
    segments like these chain into one stream, so a long packet deflates only its
    two ends and copies the chunks between.
    """

    forward: bool
    streams: tuple          # uint8 arrays, body order
    marks: tuple            # per stream, (records + 1,): its length before each record
    chunk: int = CHUNK_RECORDS
    chunks: tuple = ()      # per stream, a tuple of bytes

    def slices(self, first: int, last: int) -> list:
        """The streams of records ``first .. last-1`` (counted in this direction)."""
        return [s[m[first]:m[last]] for s, m in zip(self.streams, self.marks)]

    def deflated_body(self, first: int, last: int) -> tuple[bytes, int]:
        """The zlib stream of the body of records ``first .. last-1``, and its inflated
        length, from the chunks inside the range and fresh segments around them."""
        pieces, adler, length = [b"\x78\x9c"], 1, 0    # zlib header: deflate, 32 KiB window

        def add(data, deflated=None):
            nonlocal adler, length
            if len(data):
                pieces.append(deflated if deflated is not None else _deflate_segment(data))
                adler = zlib.adler32(data, adler)
                length += len(data)

        whole_from, whole_to = -(-first // self.chunk), last // self.chunk
        for stream, marks, chunks in zip(self.streams, self.marks, self.chunks):
            start, stop = int(marks[first]), int(marks[last])
            prefix = bytearray()
            _put_varint(prefix, stop - start)
            if whole_to <= whole_from:
                add(bytes(prefix) + stream[start:stop].tobytes())
                continue
            add(bytes(prefix) + stream[start:marks[whole_from * self.chunk]].tobytes())
            for i in range(whole_from, whole_to):
                add(stream[marks[i * self.chunk]:marks[(i + 1) * self.chunk]], chunks[i])
            add(stream[marks[whole_to * self.chunk]:stop].tobytes())
        pieces.append(b"\x03\x00")                   # an empty final block (fixed Huffman)
        pieces.append(struct.pack(">I", adler))
        return b"".join(pieces), length


def _deflate_segment(data, level: int = 6) -> bytes:
    """Raw deflate of ``data`` ending in a sync flush: chainable (see RecordStreams)."""
    deflater = zlib.compressobj(level, zlib.DEFLATED, -15)
    return deflater.compress(data) + deflater.flush(zlib.Z_SYNC_FLUSH)


def record_streams(pm: ProgressiveMesh, *, forward: bool, bits: int | None = None,
                   chunk: int | None = None) -> RecordStreams:
    """Encode every split (``forward``) or every collapse of ``pm`` once, at the
    default attribute grids, and deflate it in chunks of ``chunk`` records
    (default :data:`CHUNK_RECORDS`). Costs about one full packet; see
    :class:`RecordStreams`."""
    chunk = CHUNK_RECORDS if chunk is None else chunk
    grid = grid_of(pm, bits=bits)
    grids = attribute_grids_of(pm)
    n0, n = pm.base_vertices, pm.vertex_count
    start, stop = (n0, n) if forward else (n, n0)
    names = stream_names(grids, pm.face_material is not None)
    # Stream lengths fit 32 bits unless the mesh has hundreds of millions of vertices.
    wide = _VARINT_MAX * 64 * (n - n0) >= 2**32
    marks = np.zeros((len(names), n - n0 + 1), dtype=np.int64 if wide else np.uint32)
    # own the bytes: the kernels' buffers are sized for the worst case
    streams = tuple(np.array(s, copy=True) for s in
                    _encode_streams(pm, start, stop, grid, grids, marks))
    # A stream no record writes to (collapses have no faces to add, predicted fans
    # no masks) keeps a zero-stride row of zeros instead of 4 bytes per record.
    rows = tuple(row.copy() if row[-1] else np.broadcast_to(row.dtype.type(0), row.shape)
                 for row in marks)
    bounds = range(0, n - n0 - chunk + 1, chunk)
    chunks = tuple(tuple(_deflate_segment(stream[m[i]:m[i + chunk]]) for i in bounds)
                   for stream, m in zip(streams, rows))
    return RecordStreams(forward, streams, rows, chunk, chunks)


# The records of the progressive meshes in use, at their default grid only (other
# grids are encoded per packet): a ProgressiveMesh is immutable, and dropped with it.
_records: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_records_lock = threading.Lock()


def _cached_records(pm: ProgressiveMesh, forward: bool) -> RecordStreams:
    with _records_lock:
        slots = _records.setdefault(pm, {})
        slot = slots.setdefault(forward, [threading.Lock(), None])
    with slot[0]:               # one encoder per mesh and direction; the others wait for it
        if slot[1] is None:
            slot[1] = record_streams(pm, forward=forward)
        return slot[1]


def encode_records(pm: ProgressiveMesh) -> None:
    """Encode ``pm``'s records both ways now, at once (the kernels and deflate
    release the GIL), unless they are cached already; later packets are slices."""
    with ThreadPoolExecutor(2) as pool:
        for done in [pool.submit(_cached_records, pm, forward) for forward in (True, False)]:
            done.result()


# One background encoder: records are prepared where a request is likely to need them.
_background = ThreadPoolExecutor(max_workers=1, thread_name_prefix="packet-records")
_scheduled: weakref.WeakSet = weakref.WeakSet()


def prepare_records(pm: ProgressiveMesh) -> None:
    """:func:`encode_records` in the background, once per mesh object: a client
    that fetched a level's json form asks for packets next, and after a restart
    nothing has prepared them."""
    with _records_lock:
        if pm in _scheduled:
            return
        _scheduled.add(pm)
    _background.submit(encode_records, pm)


def packet_between(pm: ProgressiveMesh, start: int, stop: int, *,
                   bits: int | None = None) -> bytes:
    """The packet of :func:`encode_packet`, cut from :class:`RecordStreams`.

    At the default grid the first packet of a mesh in each direction encodes every
    record (about one full packet's time); later packets cost their slices and
    deflate, and past one chunk only the deflate of their two ends. Up to a chunk
    the bytes are :func:`encode_packet`'s; longer packets differ only in how the
    same body is deflated. Other grids are encoded directly.
    """
    start, stop = pm._check_level(start), pm._check_level(stop)
    if start == stop or (bits is not None and check_bits(bits) != default_bits(pm)):
        return encode_packet(pm, start, stop, bits=bits)
    records = _cached_records(pm, stop > start)
    n0, n = pm.base_vertices, pm.vertex_count
    first, last = (start - n0, stop - n0) if stop > start else (n - start, n - stop)
    grid, grids = grid_of(pm), attribute_grids_of(pm)
    if last - first < records.chunk:
        return _assemble(pm, grid, grids, start, stop, records.slices(first, last))
    deflated, length = records.deflated_body(first, last)
    return pack_header(grid, grids, pm.face_material is not None, start, stop,
                       pm.faces_at_level(start), pm.faces_at_level(stop), length) + deflated


_READ_ONLY_INDEX = np.zeros(1, dtype=np.int64)
_READ_ONLY_INDEX.setflags(write=False)
_READ_ONLY_CORNERS = np.zeros((0, 3), dtype=np.int64)
_READ_ONLY_CORNERS.setflags(write=False)
_NO_MARKS = np.zeros((0, 0), dtype=np.uint32)


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
                   birth_faces, moved_offsets, moved_corners, fine, new,
                   wedges, values, wedge_counts, wedge_parent, wedge_fine, wedge_new, wedge_from,
                   birth_corners, full_corners, offsets, bit_limits, material, marks):
    """The streams of split records ``start .. stop-1``.

    ``positions`` (v, 3) and flat ``faces`` hold the quantized state at ``start``
    (``face_count`` faces) with room for ``stop``, and are changed in place;
    ``fine`` and ``new`` are the quantized positions of splits ``start ..``.
    With attributes (``offsets``: the columns of each attribute in ``values``,
    more than one entry; ``bit_limits``: the largest grid value of each) the flat
    ``wedges`` (wedge per corner) and ``values`` (quantized, room for ``stop``)
    are the wedge state, changed in place too;
    ``wedge_fine`` and ``wedge_new`` are the quantized values of wedges
    ``wedge_from ..``. ``material`` (per face, or empty) adds the material stream.
    ``marks`` (empty, or streams x records + 1) gets the stream lengths before
    each record and after the last.

    Returns the seven streams, the wedge_count, wedge_parent, wedge_corner and
    material streams, the value streams (a buffer row and a length per attribute),
    and ``(t, c, s)`` of the first moved corner that does not hold ``vs`` (all -1
    when there is none; the streams are then complete).
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

    attributes = offsets.shape[0] - 1
    has_materials = material.shape[0] > 0
    new_wedges = wedge_fine.shape[0]
    moved_total = moved_offsets[stop - base] - moved_offsets[start - base] if attributes else 0
    wedge_streams = (np.empty(_VARINT_MAX * records if attributes else 0, dtype=np.uint8),
                     np.empty(_VARINT_MAX * new_wedges, dtype=np.uint8),
                     np.empty(_VARINT_MAX * (moved_total + 3 * added) if attributes else 0,
                              dtype=np.uint8),
                     np.empty(_VARINT_MAX * added if has_materials else 0, dtype=np.uint8))
    used = np.zeros(4, dtype=np.int64)          # of the wedge streams
    widest = 0
    for a in range(attributes):
        widest = max(widest, offsets[a + 1] - offsets[a])
    value_streams = np.empty((attributes, 2 * widest * _VARINT_MAX * new_wedges), dtype=np.uint8)
    value_used = np.zeros(attributes, dtype=np.int64)
    candidates = np.empty(64, dtype=np.int64)
    coarse = np.empty(3, dtype=np.int64)
    columns = offsets[-1]
    gradient = np.empty((3, columns), dtype=np.float64)
    sums = np.empty((3, columns), dtype=np.float64)
    limits = np.empty(columns, dtype=np.int64)
    for a in range(attributes):
        limits[offsets[a]:offsets[a + 1]] = bit_limits[a]

    for t in range(start, stop + 1):
        if marks.shape[0]:
            _mark(marks, t - start, n_vertex, n_count, n_pattern, n_other, t - start, n_mask,
                  n_position, used, value_used, attributes, has_materials)
        if t == stop:
            break
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
                    return ((vertex[:n_vertex], count[:n_count], pattern[:n_pattern],
                             other[:n_other], fan[:t - start], mask[:n_mask],
                             position[:n_position]), wedge_streams,
                            (value_streams, value_used), error)
                mask[n_mask + i // 8] |= 1 << (i % 8)
            n_mask += width
        first_face = face_count
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
            coarse[a] = positions[s, a]
            positions[s, a] = fine[i, a]
            positions[t, a] = new[i, a]
        if attributes:
            candidates = _split_wedges_kernel(
                faces, positions, blocks, pool, s, t, scratch, d, first_face, face_count, first,
                coarse, fine[i], new[i], limits, gradient, sums, wedges, values,
                wedge_counts[j], wedge_counts[j + 1], wedge_parent, wedge_fine, wedge_new,
                wedge_from, birth_corners, full_corners, offsets, wedge_streams, used,
                value_streams, value_used, candidates)
        if has_materials:
            for f in range(first, last):
                used[3] = _put(wedge_streams[3], used[3], material[f] + 1)
    return ((vertex[:n_vertex], count[:n_count], pattern[:n_pattern], other[:n_other],
             fan, mask[:n_mask], position[:n_position]),
            (wedge_streams[0][:used[0]], wedge_streams[1][:used[1]], wedge_streams[2][:used[2]],
             wedge_streams[3][:used[3]]), (value_streams, value_used), error)


@njit(cache=True, nogil=True)
def _split_ratio_kernel(coarse, fine, new):
    """:func:`_split_ratio`, the same float operations in the same order."""
    a = 0.0
    b = 0.0
    for k in range(3):
        a += float(coarse[k] - fine[k]) * float(coarse[k] - fine[k])
    for k in range(3):
        b += float(new[k] - coarse[k]) * float(coarse[k] - fine[k])
    ratio = b / a if a > 0 else 1.0
    return min(max(ratio, 0.0), _MAX_SPLIT_RATIO)


@njit(cache=True, nogil=True)
def _collapse_ratio_kernel(fine, new, coarse):
    """:func:`_collapse_ratio`, the same float operations in the same order."""
    a = 0.0
    b = 0.0
    for k in range(3):
        a += float(new[k] - fine[k]) * float(new[k] - fine[k])
    for k in range(3):
        b += float(coarse[k] - fine[k]) * float(new[k] - fine[k])
    ratio = b / a if a > 0 else 0.5
    return min(max(ratio, 0.0), 1.0)


@njit(cache=True, nogil=True, inline="always")
def _scaled_kernel(ratio, d):
    return np.int64(np.floor(ratio * d + 0.5))


@njit(cache=True, nogil=True)
def _gradient_kernel(faces, positions, wedges, values, held, d, s, p, coarse, out, sums):
    """:func:`_gradient` into ``out`` (3, k); False where there is none. The same
    float operations in the same order."""
    k = values.shape[1]
    m00 = m01 = m02 = m11 = m12 = m22 = 0.0
    for j in range(k):
        sums[0, j] = 0.0
        sums[1, j] = 0.0
        sums[2, j] = 0.0
    edges = 0
    for i in range(d):
        c = held[i]
        if wedges[c] != p:
            continue
        f3 = c - c % 3
        for step in range(1, 3):
            o = f3 + (c - f3 + step) % 3
            v = faces[o]
            if v == s:
                continue
            e0 = float(positions[v, 0] - coarse[0])
            e1 = float(positions[v, 1] - coarse[1])
            e2 = float(positions[v, 2] - coarse[2])
            w = wedges[o]
            m00 += e0 * e0
            m01 += e0 * e1
            m02 += e0 * e2
            m11 += e1 * e1
            m12 += e1 * e2
            m22 += e2 * e2
            for j in range(k):
                dd = float(values[w, j] - values[p, j])
                sums[0, j] += e0 * dd
                sums[1, j] += e1 * dd
                sums[2, j] += e2 * dd
            edges += 1
    if edges < 2:
        return False
    damping = (m00 + m11 + m22) * _GRADIENT_DAMPING + 1e-9
    c00, c01, c02, c11, c12, c22, det = symmetric_cofactors(m00 + damping, m01, m02,
                                                            m11 + damping, m12, m22 + damping)
    if not det > 0:
        return False
    i00, i01, i02 = c00 / det, c01 / det, c02 / det
    i11, i12, i22 = c11 / det, c12 / det, c22 / det
    for j in range(k):
        out[0, j] = i00 * sums[0, j] + i01 * sums[1, j] + i02 * sums[2, j]
        out[1, j] = i01 * sums[0, j] + i11 * sums[1, j] + i12 * sums[2, j]
        out[2, j] = i02 * sums[0, j] + i12 * sums[1, j] + i22 * sums[2, j]
    return True


@njit(cache=True, nogil=True)
def _extrapolated_kernel(gradient, j, value, d0, d1, d2, limit):
    """:func:`_extrapolated`, the same float operations in the same order."""
    x = (float(value) + (float(d0) * gradient[0, j] + float(d1) * gradient[1, j]
                         + float(d2) * gradient[2, j])) + 0.5
    if not x >= 0:
        return np.int64(0)
    if x > limit:
        return np.int64(limit)
    return np.int64(np.floor(x))


@njit(cache=True, nogil=True)
def _distinct_wedges(wedges, corners, n, below, out):
    """``out[:k]``: the distinct wedges of ``corners[:n]`` that are below ``below``,
    ascending; returns ``(out, k)`` (``out`` grown if needed)."""
    if n > out.shape[0]:
        out = np.empty(2 * n, dtype=np.int64)
    k = 0
    for i in range(n):
        w = wedges[corners[i]]
        if w < below:
            out[k] = w
            k += 1
    _sort(out, k)
    distinct = 0
    for i in range(k):
        if distinct == 0 or out[i] != out[distinct - 1]:
            out[distinct] = out[i]
            distinct += 1
    return out, distinct


@njit(cache=True, nogil=True)
def _wedge_code(held, k, bottom, top, w):
    """``w``'s code relative to the candidate list of ``held[:k]`` (ascending)
    followed by the new wedges ``bottom .. top-1`` not among them (:func:`_corner_candidates`)."""
    i = _search(held, k, w)
    if i < k and held[i] == w:
        return i
    rank = k
    for x in range(bottom, top):
        j = _search(held, k, x)
        if j < k and held[j] == x:
            continue
        if x == w:
            return rank
        rank += 1
    return rank + w


@njit(cache=True, nogil=True)
def _split_wedges_kernel(faces, positions, blocks, pool, s, t, scratch, d, first_face,
                         face_count, first, coarse, fine, new, limits, gradient, sums, wedges,
                         values, bottom, top, wedge_parent, wedge_fine, wedge_new, wedge_from,
                         birth_corners, full_corners, offsets, streams, used, value_streams,
                         value_used, candidates):
    """The wedge part of split ``t`` (:func:`_split_wedges`); ``scratch`` holds
    ``held(s)`` (``d`` corners), the new faces are ``first_face .. face_count-1``
    in the state and from row ``first`` in ``birth_corners``. Returns the
    candidate buffer (grown if needed)."""
    wedge_count, wedge_parents, wedge_corner = streams[0], streams[1], streams[2]
    held = scratch[_HELD]
    used[0] = _put(wedge_count, used[0], top - bottom)
    candidates, k = _distinct_wedges(wedges, held, d, top, candidates)
    for x in range(bottom, top):
        p = wedge_parent[x]
        i = _search(candidates, k, p)
        used[1] = _put(wedge_parents, used[1], i if i < k and candidates[i] == p else k + p)
        row = x - wedge_from
        fitted = _gradient_kernel(faces, positions, wedges, values, held, d, s, p, coarse,
                                  gradient, sums)
        if not fitted:
            ratio = _split_ratio_kernel(coarse, fine, new)
        for a in range(offsets.shape[0] - 1):
            for col in range(offsets[a], offsets[a + 1]):
                c = values[p, col]
                guess = c
                if fitted:
                    guess = _extrapolated_kernel(gradient, col, c, fine[0] - coarse[0],
                                                 fine[1] - coarse[1], fine[2] - coarse[2],
                                                 limits[col])
                value_used[a] = _put(value_streams[a], value_used[a],
                                     _zz(wedge_fine[row, col] - guess))
            for col in range(offsets[a], offsets[a + 1]):
                c = values[p, col]
                if fitted:
                    guess = _extrapolated_kernel(gradient, col, c, new[0] - coarse[0],
                                                 new[1] - coarse[1], new[2] - coarse[2],
                                                 limits[col])
                else:
                    guess = c + _scaled_kernel(ratio, c - wedge_fine[row, col])
                value_used[a] = _put(value_streams[a], value_used[a],
                                     _zz(wedge_new[row, col] - guess))
        for col in range(offsets[-1]):
            values[p, col] = wedge_fine[row, col]
            values[x, col] = wedge_new[row, col]
    m = top - bottom
    for i in range(d):            # moved corners, ascending
        c = held[i]
        if faces[c] != t:
            continue
        y = wedges[c]
        w = _ancestor_below(wedge_parent, full_corners[c // 3, c % 3], top)
        guess = y
        for x in range(bottom, top):
            if wedge_parent[x] == y:
                guess = x
                break
        if w == guess:
            code = 0
        elif bottom <= w < top:
            code = 1 + w - bottom
        elif w == y:
            code = m + 1
        else:
            code = m + 2 + w
        used[2] = _put(wedge_corner, used[2], code)
        wedges[c] = w
    # the corners of the new faces, each relative to its vertex's wedges
    limit = 3 * first_face
    for f in range(first_face, face_count):
        for k in range(3):
            c = 3 * f + k
            v = faces[c]
            begin, n = blocks[v, 0], blocks[v, 1]
            if n > candidates.shape[0]:
                candidates = np.empty(2 * n, dtype=np.int64)
            size = 0
            for i in range(n):
                other = pool[begin + i]
                if other < limit:
                    candidates[size] = wedges[other]
                    size += 1
            _sort(candidates, size)
            distinct = 0
            for i in range(size):
                if distinct == 0 or candidates[i] != candidates[distinct - 1]:
                    candidates[distinct] = candidates[i]
                    distinct += 1
            w = birth_corners[first + f - first_face, k]
            used[2] = _put(wedge_corner, used[2], _wedge_code(candidates, distinct, bottom, top, w))
            wedges[c] = w
    return candidates


@njit(cache=True, nogil=True)
def _mark(marks, i, vertex, count, pattern, other, fan, mask, position, used, value_used,
          attributes, has_materials):
    """Column ``i`` of ``marks``: every stream's length, in body order."""
    marks[0, i], marks[1, i], marks[2, i], marks[3, i] = vertex, count, pattern, other
    marks[4, i], marks[5, i], marks[6, i] = fan, mask, position
    row = 7
    if attributes:
        marks[7, i], marks[8, i], marks[9, i] = used[0], used[1], used[2]
        for a in range(attributes):
            marks[10 + a, i] = value_used[a]
        row = 10 + attributes
    if has_materials:
        marks[row, i] = used[3]


@njit(cache=True, nogil=True)
def _encode_collapses(positions, faces, face_count, start, stop, base, parent, face_counts,
                      coarse, wedges, values, wedge_counts, wedge_parent, wedge_coarse,
                      wedge_from, offsets, marks):
    """The streams of collapse records ``start-1`` down to ``stop``, as
    :func:`_encode_splits` (``coarse``: quantized positions of records ``stop ..``;
    ``wedge_coarse``: quantized merged values of wedges ``wedge_from ..``)."""
    blocks, pool, end, slot = _corner_blocks(faces, face_count, positions.shape[0])
    records = start - stop
    vertex = np.empty(_VARINT_MAX * records, dtype=np.uint8)
    count = np.empty(_VARINT_MAX * records, dtype=np.uint8)
    position = np.empty(3 * _VARINT_MAX * records, dtype=np.uint8)
    n_vertex = n_count = n_position = 0
    scratch = np.empty((_SCRATCH_ROWS, 64), dtype=np.int64)

    attributes = offsets.shape[0] - 1
    removed_wedges = wedge_coarse.shape[0]
    wedge_count = np.empty(_VARINT_MAX * records if attributes else 0, dtype=np.uint8)
    wedge_parents = np.empty(_VARINT_MAX * removed_wedges, dtype=np.uint8)
    n_wedge_count = n_wedge_parents = 0
    widest = 0
    for a in range(attributes):
        widest = max(widest, offsets[a + 1] - offsets[a])
    value_streams = np.empty((attributes, widest * _VARINT_MAX * removed_wedges), dtype=np.uint8)
    value_used = np.zeros(attributes, dtype=np.int64)
    candidates = np.empty(64, dtype=np.int64)
    fine = np.empty(3, dtype=np.int64)
    used = np.zeros(4, dtype=np.int64)              # as _encode_splits' wedge streams

    for t in range(start - 1, stop - 2, -1):
        if marks.shape[0]:
            used[0], used[1] = n_wedge_count, n_wedge_parents
            _mark(marks, start - 1 - t, n_vertex, n_count, 0, 0, 0, 0, n_position, used,
                  value_used, attributes, False)
        if t == stop - 1:
            break
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
        if not attributes:
            for a in range(3):
                positions[s, a] = coarse[i, a]
            continue
        for a in range(3):
            fine[a] = positions[s, a]
            positions[s, a] = coarse[i, a]

        # wedges: how many go, then each (last first) with its parent and merged value
        ratio = _collapse_ratio_kernel(fine, positions[t], positions[s])
        bottom, top = wedge_counts[j], wedge_counts[j + 1]
        n_wedge_count = _put(wedge_count, n_wedge_count, top - bottom)
        first, d = blocks[s, 0], blocks[s, 1]
        candidates, k = _distinct_wedges(wedges, pool[first:first + d], d, bottom, candidates)
        for x in range(top - 1, bottom - 1, -1):
            p = wedge_parent[x]
            r = _search(candidates, k, p)
            n_wedge_parents = _put(wedge_parents, n_wedge_parents,
                                   r if r < k and candidates[r] == p else k + p)
            row = x - wedge_from
            for a in range(attributes):
                for col in range(offsets[a], offsets[a + 1]):
                    predicted = values[p, col] + _scaled_kernel(ratio,
                                                                values[x, col] - values[p, col])
                    value_used[a] = _put(value_streams[a], value_used[a],
                                         _zz(wedge_coarse[row, col] - predicted))
            for col in range(offsets[-1]):
                values[p, col] = wedge_coarse[row, col]
        for q in range(d):
            c = pool[first + q]
            wedges[c] = _ancestor_below(wedge_parent, wedges[c], bottom)
    empty = np.empty(0, dtype=np.uint8)
    return ((vertex[:n_vertex], count[:n_count], empty, empty, empty, empty,
             position[:n_position]),
            (wedge_count[:n_wedge_count], wedge_parents[:n_wedge_parents], empty, empty),
            (value_streams, value_used))


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
    attribute_grids: tuple = ()
    has_materials: bool = False

    @property
    def records(self) -> int:
        return abs(self.stop - self.start)


def stream_names(attribute_grids: tuple, has_materials: bool) -> tuple[str, ...]:
    """The names of a packet's streams, in body order."""
    names = _STREAM_NAMES
    if attribute_grids:
        names += _WEDGE_STREAM_NAMES + tuple(f"value:{g.name}" for g in attribute_grids)
    if has_materials:
        names += ("material",)
    return names


def pack_header(grid: Grid, attribute_grids: tuple, has_materials: bool, start: int, stop: int,
                start_faces: int, stop_faces: int, body_length: int) -> bytes:
    """The header of a packet (docs/packets.md), attribute records included."""
    out = bytearray(_HEADER.pack(MAGIC, PACKET_VERSION, grid.bits, len(attribute_grids),
                                 _HAS_MATERIALS if has_materials else 0, start, stop,
                                 start_faces, stop_faces, *grid.origin, grid.step, body_length))
    for g in attribute_grids:
        out += _ATTRIBUTE.pack(ATTRIBUTE_IDS[g.name], _ENCODING_IDS[g.encoding], g.bits, 0, g.step)
        out += struct.pack(f"<{g.components}d", *g.origin)
    return bytes(out)


def decode_packet(data: bytes) -> Packet:
    """Parse a packet's header and inflate its streams.

    Raises
    ------
    PacketError
        On a bad magic, version, length, attribute record, deflate stream or stream table.
    """
    data = bytes(data)
    if len(data) < _HEADER.size:
        raise PacketError(f"the packet is truncated: {len(data)} bytes is shorter than the header")
    (magic, version, bits, attributes, flags, start, stop, start_faces, stop_faces,
     ox, oy, oz, step, body_length) = _HEADER.unpack_from(data)
    if magic != MAGIC:
        raise PacketError("this is not a lodserver vsplit packet (bad magic bytes)")
    if version not in READABLE_VERSIONS:
        raise PacketError(f"the packet has version {version}; this decoder reads "
                          f"{' and '.join(map(str, READABLE_VERSIONS))}")
    if version == 1 and (attributes or flags):
        raise PacketError("the packet has version 1 but sets reserved header bytes")
    if flags & ~_HAS_MATERIALS:
        raise PacketError(f"the packet sets unknown header flags {flags:#x}")
    at = _HEADER.size
    grids = []
    encodings = {v: k for k, v in _ENCODING_IDS.items()}
    for _ in range(attributes):
        if len(data) < at + _ATTRIBUTE.size:
            raise PacketError("the packet is truncated in its attribute records")
        kind, encoding, attribute_bits, _reserved, attribute_step = _ATTRIBUTE.unpack_from(data, at)
        at += _ATTRIBUTE.size
        if kind not in _ATTRIBUTE_NAMES or encoding not in encodings:
            raise PacketError(f"the packet names an unknown attribute ({kind}) or encoding "
                              f"({encoding})")
        name, encoding = _ATTRIBUTE_NAMES[kind], encodings[encoding]
        if encoding == OCTAHEDRAL and name != "NORMAL":
            raise PacketError(f"the packet encodes {name} as octahedral: only NORMAL can be")
        components = 2 if encoding == OCTAHEDRAL else ATTRIBUTE_WIDTHS[name]
        if len(data) < at + 8 * components:
            raise PacketError("the packet is truncated in its attribute records")
        origin = struct.unpack_from(f"<{components}d", data, at)
        at += 8 * components
        grids.append(AttributeGrid(name, encoding, origin, attribute_step, attribute_bits))
    try:
        body = zlib.decompress(data[at:])
    except zlib.error as exc:
        raise PacketError(f"the packet's body does not inflate ({exc})") from exc
    if len(body) != body_length:
        raise PacketError(f"the packet's body is {len(body)} bytes, the header says {body_length}")
    table = _Reader(body, "stream table")
    has_materials = bool(flags & _HAS_MATERIALS)
    streams = []
    for _ in stream_names(tuple(grids), has_materials):
        streams.append(table.take(table.varint()))
    if not table.done():
        raise PacketError("the packet's body has bytes after its last stream")
    return Packet(start, stop, start_faces, stop_faces, Grid((ox, oy, oz), step, bits),
                  tuple(streams), tuple(grids), has_materials)


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
    work = _Working(state.positions, state.faces, max(packet.start, packet.stop),
                    max(packet.start_faces, packet.stop_faces))
    work.attach_wedges(state.wedges, state.corners, state.face_material)
    names = stream_names(packet.attribute_grids, packet.has_materials)
    readers = [_Reader(s, name) for s, name in zip(packet.streams, names)]
    try:
        if packet.stop > packet.start:
            _apply_splits(work, packet.start, packet.stop, readers, packet.attribute_grids)
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
        if corners.min(initial=0) < 0 or corners.max(initial=-1) >= len(wedges):
            raise PacketError("the packet leaves a corner on a wedge that does not exist")
    if packet.has_materials:
        material = work.face_material[:work.face_count].copy()
    return LodState(positions, work.faces[:work.face_count].copy(), state.grid, wedges, corners,
                    state.attribute_grids, material)


def _apply_splits(work: _Working, start, stop, readers, grids):
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
        first = work.face_count
        for c in moved:
            work.set_corner(c, t)
        for corners in added:
            work.append_face(corners)

        coarse = work.positions[s].copy()
        fine = coarse + [position.signed() for _ in range(3)]
        work.positions[s] = fine
        work.positions[t] = 2 * coarse - fine + [position.signed() for _ in range(3)]
        if grids:
            geometry = (coarse.tolist(), fine.tolist(), work.positions[t].tolist())
            _split_wedges(work, s, t, held, set(moved), first, geometry, readers, grids)
        if work.face_material is not None:
            material = readers[-1]
            for f in range(first, work.face_count):
                work.face_material[f] = material.varint() - 1


def _split_wedges(work: _Working, s, t, held, moved, first, geometry, readers, grids):
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
        guess_fine, guess_new = _split_guesses(work, s, held, p, geometry, grids)
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
            w = _moved_prediction(parents, bottom, y)
        elif u <= m:
            w = bottom + u - 1
        elif u == m + 1:
            w = y
        else:
            w = u - m - 2
        work.set_wedge(c, w)
    for f in range(first, work.face_count):
        for k in range(3):
            candidates = _corner_candidates(work, int(work.faces[f, k]), 3 * first, bottom, top)
            u = wedge_corner.varint()
            work.set_wedge(3 * f + k, candidates[u] if u < len(candidates) else u - len(candidates))


def _apply_collapses(work: _Working, start, stop, readers, grids):
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
            ratio = _collapse_ratio(fine, work.positions[t].tolist(), work.positions[s].tolist())
            _collapse_wedges(work, t, s, ratio, readers, grids)


def _collapse_wedges(work: _Working, t, s, ratio, readers, grids):
    """The wedge part of collapse ``t`` into ``s``, after its geometry part
    (``ratio``: the :func:`_collapse_ratio` of the positions)."""
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
                merged.append(a + _scaled(ratio, b - a) + stream.signed())
            at += grid.components
        work.wedge_values[p] = merged
    for c in work.corners.of(s):
        w = work.wedge_of(c)
        while w >= bottom:
            w = parents[w]
        work.set_wedge(c, w)
    del work.wedge_values[bottom:]
