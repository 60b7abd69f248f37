"""KHR_mesh_quantization on writing: each vertex attribute in the narrowest type that
keeps it within its use's precision, as the rows a bufferView holds.

:func:`attribute_stream` turns one attribute's float values into a :class:`Stream`:
its rows as bytes (each row padded to 4 bytes, as glTF requires of vertex
attributes) and the accessor fields that read them back. The rule per attribute is
:data:`RULES`; for ``EXT_meshopt_compression`` NORMAL and TANGENT are stored for
the OCTAHEDRAL filter instead (:func:`.meshopt.encode_octahedral`), which decodes
to the same int8 accessor.

Positions are integers on one grid for the whole file (:func:`position_grid`):
``stored = round((p - offset) / step)`` in 14 bits (gltfpack's default, so that
bytes compare on equal footing), uniform on all axes so that the node transform
that undoes it (translation ``offset``, scale ``step``) is a uniform scale and
normals need no change. The step is 1/16383 of the largest side of the box.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .meshopt import encode_octahedral

EXTENSION = "KHR_mesh_quantization"

POSITION_BITS = 14

BYTE, UNSIGNED_BYTE, SHORT, UNSIGNED_SHORT, FLOAT = 5120, 5121, 5122, 5123, 5126

# Attribute (name prefix) -> (componentType, normalized) when quantized, and why:
# unit vectors need a degree or so (int8: 0.5 degree steps, the spec's allowed type);
# UVs a sixteenth of a texel of a 4k texture (uint16 in [0, 1]; int16 in [-1, 1], a
# little past the unit square as atlases often are; beyond that they stay float, since
# a texture transform on the materials would be needed to rescale them); linear
# colours 16 bits (8 bits band in the darks); skin, morph and custom columns stay as
# the writer has them (weights must sum to 1, which rounding would break).
RULES = {
    "NORMAL": (BYTE, True),
    "TANGENT": (BYTE, True),
    "TEXCOORD_": (UNSIGNED_SHORT, True),
    "COLOR_": (UNSIGNED_SHORT, True),
}

_DTYPES = {BYTE: "<i1", UNSIGNED_BYTE: "<u1", SHORT: "<i2", UNSIGNED_SHORT: "<u2",
           FLOAT: "<f4", 5125: "<u4"}
_SCALE = {BYTE: 127.0, UNSIGNED_BYTE: 255.0, SHORT: 32767.0, UNSIGNED_SHORT: 65535.0}
_COMPONENTS = {np.dtype("<f4"): FLOAT, np.dtype("u1"): UNSIGNED_BYTE,
               np.dtype("<u2"): UNSIGNED_SHORT, np.dtype("<u4"): 5125}


@dataclass
class Stream:
    """One attribute's stored rows and how to read them.

    rows : (count, stride) uint8
        The bytes of each vertex's value, padded to a multiple of 4.
    component : int
        The accessor's componentType.
    width : int
        Components per vertex (the accessor's type: SCALAR, VEC2, ...).
    normalized : bool
        The accessor's ``normalized``.
    filter : str
        The EXT_meshopt_compression filter the rows are stored for (``"NONE"`` or
        ``"OCTAHEDRAL"``).
    """

    rows: np.ndarray
    component: int
    width: int
    normalized: bool = False
    filter: str = "NONE"

    def take(self, rows: np.ndarray) -> Stream:
        """The stream of ``rows`` (an index array) of this one."""
        return Stream(self.rows[rows], self.component, self.width, self.normalized,
                      self.filter)

    @property
    def values(self) -> np.ndarray:
        """(count, width) values as the accessor reads them (after any filter is undone
        by the reader; for min and max, which only POSITION needs)."""
        dtype = np.dtype(_DTYPES[self.component])
        return np.ascontiguousarray(self.rows).view(dtype)[:, :self.width]


def _rows(values: np.ndarray) -> np.ndarray:
    """(count, k) values of a fixed dtype as (count, stride) bytes, padded to 4."""
    raw = np.ascontiguousarray(values).view(np.uint8).reshape(len(values), -1)
    pad = -raw.shape[1] % 4
    if pad:
        raw = np.concatenate([raw, np.zeros((len(raw), pad), np.uint8)], axis=1)
    return raw


def plain_stream(values: np.ndarray) -> Stream:
    """``values`` (count, k) float32, uint8, uint16 or uint32 stored as they are."""
    component = _COMPONENTS[values.dtype.newbyteorder("<")
                            if values.dtype.byteorder == ">" else values.dtype]
    return Stream(_rows(values), component, values.shape[1])


def attribute_stream(name: str, values: np.ndarray, *, octahedral: bool = False) -> Stream:
    """The stored form of attribute ``name``'s values (count, k), valid as written
    (unit normals, colours in [0, 1]: ``glb.render_attributes``), by :data:`RULES`;
    ``octahedral`` stores NORMAL and TANGENT for the meshopt OCTAHEDRAL filter."""
    rule = next((r for prefix, r in RULES.items() if name.startswith(prefix)), None)
    if rule is None or values.dtype != np.float32:
        return plain_stream(values)
    component, normalized = rule
    if name.startswith("TEXCOORD_") and not (values.min(initial=0) >= 0
                                             and values.max(initial=0) <= 1):
        if not (values.min(initial=0) >= -1 and values.max(initial=0) <= 1):
            return plain_stream(values)
        component = SHORT
    width = values.shape[1]
    if octahedral and name in ("NORMAL", "TANGENT"):
        return Stream(_rows(encode_octahedral(values)), BYTE, width, True, "OCTAHEDRAL")
    scale = _SCALE[component]
    stored = np.rint(np.asarray(values, np.float64) * scale).astype(_DTYPES[component])
    return Stream(_rows(stored), component, width, normalized)


def merge_vertices(streams: dict, triangles: np.ndarray) -> tuple[dict, np.ndarray]:
    """Vertices whose stored rows are equal in every stream merged into one, and the
    triangles this leaves without area (two corners one vertex) dropped.

    Wedges apart before quantization may round to the same bytes (normals a hair
    apart, a UV seam of a thousandth of a texel): stored twice they cost twice, and
    the index codec sees a seam that is not there.

    Parameters
    ----------
    streams : dict of str to Stream
        One primitive's streams, (r, stride) rows each.
    triangles : (f, 3) integer array
        Its triangles over the r vertices.

    Returns
    -------
    streams : dict of str to Stream
        The distinct vertices' rows, in order of first occurrence.
    triangles : (g, 3) uint32
        Over them, g <= f.
    """
    table = np.ascontiguousarray(np.concatenate([s.rows for s in streams.values()], axis=1))
    keys = table.view(np.dtype((np.void, table.shape[1]))).ravel()
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    mapped = rank[inverse.ravel()][np.asarray(triangles, dtype=np.int64)]
    kept = (mapped[:, 0] != mapped[:, 1]) & (mapped[:, 1] != mapped[:, 2]) \
        & (mapped[:, 2] != mapped[:, 0])
    rows = first[order]
    return ({name: stream.take(rows) for name, stream in streams.items()},
            mapped[kept].astype(np.uint32))


def position_grid(boxes) -> tuple[np.ndarray, float]:
    """(offset (3,), step) of the one position grid of a file whose meshes span the
    boxes ``[(lo (3,), hi (3,)), ...]``: offset the lowest corner, step the largest
    side over ``2**POSITION_BITS - 1`` (1.0 for a flat point)."""
    lo = np.min([b[0] for b in boxes], axis=0)
    hi = np.max([b[1] for b in boxes], axis=0)
    side = float(np.max(hi - lo))
    step = side / (2 ** POSITION_BITS - 1) if side > 0 else 1.0
    return lo, step


def position_stream(positions: np.ndarray, grid) -> Stream:
    """(r, 3) positions on ``grid`` (:func:`position_grid`): uint16, not normalized
    (the node's scale gives them their size)."""
    offset, step = grid
    stored = np.rint((np.asarray(positions, np.float64) - offset) / step)
    stored = np.clip(stored, 0, 2 ** POSITION_BITS - 1).astype("<u2")
    return Stream(_rows(stored), UNSIGNED_SHORT, 3)


def grid_transform(grid) -> dict:
    """The node fields that place grid positions back where they were."""
    offset, step = grid
    return {"translation": [float(v) for v in offset], "scale": [float(step)] * 3}
