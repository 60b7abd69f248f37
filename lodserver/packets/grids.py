"""Quantization: the grids positions and attributes live on, and a level's quantized form.

A client holds one level of a progressive mesh in its *quantized form*
(:func:`quantized_level`, served by the LOD endpoint as ``format=json``):
integer grid positions, faces in the slots of the prefix layout
(``progressive/mesh.py``) and, with attributes, integer wedge values and the wedge of
every corner (docs/packets.md, "Exactness").

- Positions live on a uniform grid over the bounding box of every position any
  level uses: ``x = origin + q * step`` with ``q`` in ``[0, 2**bits - 1]``.
- Attributes have a grid each (:class:`AttributeGrid`): linear, octahedral for
  normals (Meyer et al. 2010), or for tangents octahedral plus the handedness;
  every name of ``mesh.ATTRIBUTE_RULES`` has one (:func:`attribute_grids_of`).
"""

from __future__ import annotations

import re
import threading
import weakref
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..mesh import attribute_width, unit_box
from .format import LINEAR, MAX_BITS, MIN_BITS, OCTAHEDRAL, TANGENT, encoding_components

if TYPE_CHECKING:
    from ..progressive.mesh import ProgressiveMesh

# Grid steps per mean edge at full detail, as a power of two: see default_bits.
EDGE_BITS = 6
# Default grid bits per attribute, by rule (a pattern refining mesh.ATTRIBUTE_RULES',
# first match wins; see attribute_grids_of). Normals and tangents: octahedral, 10 bits
# per component (at most 0.25 degrees off); UVs: 12 bits over their range (a quarter
# texel on a 1024-texel texture spanning it); colours: 10 bits; skin weights: 12 bits
# over [0, 1]; morph normal and tangent deltas: 10 bits over their range; custom
# attributes: 16 bits over their range. None: chosen from the mesh (joints: enough for
# the largest joint index; morph position deltas: from the mesh's mean edge).
DEFAULT_ATTRIBUTE_BITS = {
    r"NORMAL": 10,
    r"TEXCOORD_\d+": 12,
    r"COLOR_\d+": 10,
    r"TANGENT": 10,
    r"JOINTS_\d+": None,
    r"WEIGHTS_\d+": 12,
    r"TARGET\d+_POSITION": None,
    r"TARGET\d+_(NORMAL|TANGENT)": 10,
    r"_[A-Za-z0-9_]+": 16,
}
# Morph position deltas: grid steps per mean full-detail edge, as a power of two. 2**7 =
# 128 steps is about what the position grid gives (114 on spot, 155 on the bunny), so a
# morphed position is as precise as the position it moves.
MORPH_EDGE_BITS = 7


def default_attribute_bits(name: str) -> int | None:
    """The default grid bits of attribute ``name`` (:data:`DEFAULT_ATTRIBUTE_BITS`),
    None where the mesh decides them."""
    for pattern, bits in DEFAULT_ATTRIBUTE_BITS.items():
        if re.fullmatch(pattern, name):
            return bits
    raise ValueError(f"unknown attribute {name!r}")


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

    name : str          a glTF vertex attribute name (``mesh.ATTRIBUTE_RULES``)
    encoding : str      ``linear``: ``value = origin + q * step`` per component;
                        ``octahedral`` (normals): two coordinates ``origin + q * step``
                        on the octahedron, unfolded to a unit vector (:func:`unfold_octahedral`);
                        ``tangent``: the xyz of a tangent as ``octahedral``, then its
                        handedness as a third component, ``w = 2 q - 1`` (q is 0 or 1)
    origin : tuple      per component of the encoding (the handedness' is -1)
    step : float        the same for all components (but the handedness')
    bits : int          grid coordinates lie in ``[0, 2**bits - 1]``
    width : int         floats per value, the attribute's width; required for a custom
                        ``_NAME`` attribute (1..4), else fixed by the name
    """

    name: str
    encoding: str
    origin: tuple
    step: float
    bits: int
    width: int | None = None

    def __post_init__(self):
        object.__setattr__(self, "width", attribute_width(self.name, self.width))

    @property
    def components(self) -> int:
        """Integers per quantized value."""
        return encoding_components(self.encoding, self.width)

    def quantize(self, values: np.ndarray) -> np.ndarray:
        """(k, width) float values -> (k, components) int64 grid coordinates (nearest)."""
        values = np.asarray(values, dtype=np.float64).reshape(-1, self.width)
        if self.encoding == TANGENT:
            folded = fold_octahedral(values[:, :3])
            q = np.clip(np.rint((folded - np.array(self.origin[:2])) / self.step),
                        0, 2**self.bits - 1)
            # the handedness exactly: +1 (and 0, which glTF does not allow) -> 1, -1 -> 0
            return np.concatenate([q, (values[:, 3:] >= 0)], axis=1).astype(np.int64)
        if self.encoding == OCTAHEDRAL:
            values = fold_octahedral(values)
        q = np.rint((values - np.array(self.origin)) / self.step)
        return np.clip(q, 0, 2**self.bits - 1).astype(np.int64)

    def dequantize(self, q: np.ndarray) -> np.ndarray:
        """(k, components) grid coordinates -> (k, width) float64 values, as a client computes them."""
        q = np.asarray(q, dtype=np.float64).reshape(-1, self.components)
        if self.encoding == TANGENT:
            xyz = unfold_octahedral(np.array(self.origin[:2]) + q[:, :2] * self.step)
            return np.concatenate([xyz, self.origin[2] + 2 * q[:, 2:]], axis=1)
        x = np.array(self.origin) + q * self.step
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


def check_bits(bits) -> int:
    """``bits`` as an int in ``[MIN_BITS, MAX_BITS]``, else ValueError."""
    bits = int(bits)
    if not MIN_BITS <= bits <= MAX_BITS:
        raise ValueError(f"bits must be in [{MIN_BITS}, {MAX_BITS}], got {bits}")
    return bits


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
    return Grid(lo, extent / (2**bits - 1), bits)


# The boxes of each progressive mesh in use, so that a request on a big mesh does not
# scan every position again (a ProgressiveMesh is immutable, and dropped with them).
_boxes: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_attribute_boxes: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_boxes_lock = threading.Lock()


def _box_of(pm: ProgressiveMesh) -> tuple[tuple[float, float, float], float]:
    """The smallest coordinate of any position at any level, per axis, and the
    largest extent over the axes (``mesh.unit_box``: 1.0 if they all coincide,
    which no mesh with a face does)."""
    with _boxes_lock:
        box = _boxes.get(pm)
    if box is None:
        lo, extent = unit_box(np.concatenate([pm.positions, pm.coarse_position]))
        box = tuple(float(x) for x in lo), extent
        with _boxes_lock:
            _boxes[pm] = box
    return box


def _attribute_box_of(pm: ProgressiveMesh) -> list:
    """Per attribute: the smallest value of any wedge at any level per component, the
    largest extent over the components, and the largest value."""
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
            boxes.append((tuple(float(x) for x in lo), float((hi - lo).max()), float(hi.max())))
        with _boxes_lock:
            _attribute_boxes[pm] = boxes
    return boxes


def mean_edge(pm: ProgressiveMesh) -> float:
    """The mean length of the full-detail faces' sides, in mesh units (each interior
    edge counted twice, once per face: a mean over sides, as a renderer sees them)."""
    faces = pm.faces
    if not len(faces):
        return 0.0
    corners = pm.positions[faces]
    sides = corners - np.roll(corners, 1, axis=1)
    return float(np.linalg.norm(sides, axis=2).mean())


def _linear(name, lo, extent, bits, width) -> AttributeGrid:
    """A linear grid over ``lo .. lo + extent`` per component (one step for all)."""
    return AttributeGrid(name, LINEAR, lo, extent / (2**bits - 1) if extent > 0 else 1.0, bits,
                         width)


def _morph_bits(pm: ProgressiveMesh, extent: float) -> int:
    """Bits for a morph position delta spanning ``extent``: enough that the grid step is
    at most the mean full-detail edge over ``2**MORPH_EDGE_BITS``, in [MIN_BITS, MAX_BITS]."""
    edge = mean_edge(pm)
    if not extent > 0 or not edge > 0:
        return MIN_BITS
    steps = extent / (edge / 2**MORPH_EDGE_BITS)
    return int(np.clip(np.ceil(np.log2(steps + 1)), MIN_BITS, MAX_BITS))


def attribute_grids_of(pm: ProgressiveMesh, *, attribute_bits: dict | None = None) -> tuple:
    """The grids of ``pm``'s attributes, in layout order (empty without attributes).

    By rule (docs/packets.md, "Attribute grids"):

    - ``NORMAL``: octahedral, ``origin = (-1, -1)``, ``step = 2 / (2**bits - 2)``, so
      that ``q = 2**(bits-1) - 1`` is exactly 0 (axis-aligned normals stay exact).
    - ``TANGENT``: its xyz as a normal, then the handedness exactly (0: -1, 1: +1).
    - ``JOINTS_n``: exact integers: linear, origin 0, step 1, ``bits`` enough for the
      largest joint index (at least ``MIN_BITS``).
    - ``WEIGHTS_n``: linear over [0, 1].
    - ``TARGET{t}_POSITION``: linear over its range, ``bits`` from the mean edge
      (:data:`MORPH_EDGE_BITS`).
    - the others (``TEXCOORD_n``, ``COLOR_n``, ``TARGET{t}_NORMAL``/``_TANGENT``, custom
      ``_NAME``): linear over every value any level uses, one step for all components.

    ``attribute_bits`` maps attribute names to bits (default
    :data:`DEFAULT_ATTRIBUTE_BITS`); joints cannot have fewer bits than their largest
    index needs (ValueError).
    """
    if not pm.has_attributes:
        return ()
    attribute_bits = dict(attribute_bits or {})
    unknown = set(attribute_bits) - {name for name, _ in pm.attribute_layout}
    if unknown:
        raise ValueError(f"the mesh has no attribute named {', '.join(sorted(unknown))}")
    grids = []
    for i, (name, width) in enumerate(pm.attribute_layout):
        lo, extent, top = _attribute_box_of(pm)[i]
        bits = attribute_bits.get(name, default_attribute_bits(name))
        if name.startswith("JOINTS_"):
            needed = max(MIN_BITS, int(max(top, 0)).bit_length())
            if needed > MAX_BITS:
                raise ValueError(f"{name} holds joint {int(top)}, beyond a {MAX_BITS}-bit grid")
            bits = needed if bits is None else check_bits(bits)
            if bits < needed:
                raise ValueError(f"{name} needs {needed} bits for joint {int(top)}, got {bits}")
            grids.append(AttributeGrid(name, LINEAR, (0.0,) * width, 1.0, bits, width))
            continue
        if bits is None:                        # TARGET{t}_POSITION
            bits = _morph_bits(pm, extent)
        bits = check_bits(bits)
        if name == "NORMAL":
            grids.append(AttributeGrid(name, OCTAHEDRAL, (-1.0, -1.0), 2 / (2**bits - 2), bits))
        elif name == "TANGENT":
            grids.append(AttributeGrid(name, TANGENT, (-1.0, -1.0, -1.0), 2 / (2**bits - 2),
                                       bits))
        elif name.startswith("WEIGHTS_"):
            grids.append(AttributeGrid(name, LINEAR, (0.0,) * width, 1 / (2**bits - 1), bits))
        else:
            grids.append(_linear(name, lo, extent, bits, width))
    return tuple(grids)


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


def state_from_json(document: dict) -> LodState:
    """The state held by a client that fetched ``/lod?format=json`` (``export.encode_level``)."""
    grid = document["grid"]
    faces = np.array(document["faces"], dtype=np.int64).reshape(-1, 3)
    grids, wedges, corners = (), None, None
    if document.get("layout"):
        grids = tuple(AttributeGrid(name, document["attribute_grid"][name]["encoding"],
                                    tuple(float(x) for x in document["attribute_grid"][name]["origin"]),
                                    float(document["attribute_grid"][name]["step"]),
                                    int(document["attribute_grid"][name]["bits"]), int(width))
                      for name, width in document["layout"])
        k = sum(g.components for g in grids)
        wedges = np.array(document["wedges"], dtype=np.int64).reshape(-1, k)
        corners = np.array(document["corners"], dtype=np.int64).reshape(-1, 3)
    material = document.get("face_material")
    return LodState(np.array(document["positions"], dtype=np.int64).reshape(-1, 3), faces,
                    Grid(tuple(float(x) for x in grid["origin"]), float(grid["step"]),
                         int(grid["bits"])),
                    wedges, corners, grids,
                    None if material is None else np.array(material, dtype=np.int64).reshape(-1))
