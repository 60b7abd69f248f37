"""The packet wire format: constants, the header, stream names, varints.

This module mirrors ``docs/packets.md`` section by section and holds no
geometry: what every encoder and decoder of a packet must agree on, byte for
byte. The prediction rules of the records themselves (the fan walk, the split
and collapse ratios, the attribute gradient) are written out, readably, in
:mod:`lodserver.packets.reference`; the numbers they share are here.
"""

from __future__ import annotations

import struct
import zlib

from ..mesh import MeshError, attribute_width

# ---- "Byte layout" -------------------------------------------------------------
MAGIC = b"LODV"
PACKET_VERSION = 3
# Versions a decoder reads: version 3 differs from version 2 only in its attribute
# records (which name the attribute instead of giving one of four kind codes), and a
# version 1 packet is a geometry-only one of either ("A geometry-only mesh's version 3
# packet is byte for byte a version 1 (and 2) packet but for the version byte").
READABLE_VERSIONS = (1, 2, 3)
# Version 4 ("Version 4" in docs/packets.md): the same records, their fields coded by
# kind with rANS (packets/rans.py) instead of varints and deflate. Read by
# packets/decode_v4.py; the server writes it on request (packets/served.py).
VERSION_4 = 4
# The server's range for the header's ``bits`` (positions and attributes alike).
MIN_BITS, MAX_BITS = 8, 24

# magic, version, bits, attribute count, flags, from, to, faces at from, faces at to,
# origin (3 f64), step, body length; then one attribute record (+ origin) per attribute.
HEADER = struct.Struct("<4sBBBBIIII3ddI")
# Version 3 attribute record: u8 name length, the ASCII name, then ATTRIBUTE (width,
# encoding, bits, step), then the origin. Version 2's: ATTRIBUTE_V2 (kind code,
# encoding, bits, reserved, step), then the origin.
ATTRIBUTE = struct.Struct("<BBBd")
ATTRIBUTE_V2 = struct.Struct("<BBBBd")
# Bounds on the attribute records, so that a damaged header cannot ask for much.
# 255: the header counts records in a byte; a mesh with 80 morph targets (position and
# normal deltas) needs 160 records plus its own (mesh.MAX_ATTRIBUTES holds meshes to it)
MAX_ATTRIBUTES, MAX_NAME = 255, 64
# header flags
HAS_MATERIALS = 1
# version 4 only: positions coded as the split edge and the place of vs along it
# (EDGE_POSITIONS); position and value symbols coded in contexts of the magnitudes
# before them (MAGNITUDE_CONTEXTS); the split edge coded less its prediction from the
# rings of the split's two vertices (RING_POSITIONS, only with EDGE_POSITIONS)
EDGE_POSITIONS, MAGNITUDE_CONTEXTS, RING_POSITIONS = 2, 4, 8
# RING_POSITIONS predicts the split edge as this fraction of the difference of the two
# rings' centroids: each ring, without the other vertex, leans away from it, so the
# difference overshoots the edge, by a little less than twice (bench/README.md, "Positions
# from the ring"). A dyadic fraction (5/8), exact in float64.
RING_SCALE = 0.625

# Version 2's attribute kind codes (read only); version 3 names every attribute.
ATTRIBUTE_IDS = {"NORMAL": 0, "TEXCOORD_0": 1, "TEXCOORD_1": 2, "COLOR_0": 3}
ATTRIBUTE_NAMES = {v: k for k, v in ATTRIBUTE_IDS.items()}
# Grid encodings: ``linear`` for any attribute; ``octahedral`` for NORMAL (2 components);
# ``tangent`` for TANGENT: its xyz octahedral, then the handedness as a third component
# (q = 0: w = -1, q = 1: w = +1).
LINEAR, OCTAHEDRAL, TANGENT = "linear", "octahedral", "tangent"
ENCODING_IDS = {LINEAR: 0, OCTAHEDRAL: 1, TANGENT: 2}
ENCODING_NAMES = {v: k for k, v in ENCODING_IDS.items()}
V2_ENCODING_NAMES = {0: LINEAR, 1: OCTAHEDRAL}
# The only attribute each non-linear encoding applies to.
ENCODING_ATTRIBUTE = {OCTAHEDRAL: "NORMAL", TANGENT: "TANGENT"}


def encoding_components(encoding: str, width: int) -> int:
    """Integers per quantized value of an attribute of ``width`` floats in ``encoding``."""
    return {OCTAHEDRAL: 2, TANGENT: 3}.get(encoding, width)

# ---- "How the server cuts packets": the body's streams, in body order ----------
# A collapse packet leaves PATTERN, OTHER, FAN and MASK empty.
VERTEX, COUNT, PATTERN, OTHER, FAN, MASK, POSITION = range(7)
STREAM_NAMES = ("vertex", "count", "pattern", "other", "fan", "mask", "position")
# With attributes these follow, then one value stream per attribute, then MATERIAL
# when the mesh has face materials (MATERIAL alone when it has materials only).
WEDGE_COUNT, WEDGE_PARENT, WEDGE_CORNER = range(7, 10)
WEDGE_STREAM_NAMES = ("wedge_count", "wedge_parent", "wedge_corner")

# ---- "Split records" -------------------------------------------------------------
# A corner of a split's new face is vs, the new vertex, or another vertex (pattern byte).
IS_VS, IS_NEW, IS_OTHER = 0, 1, 2
# FAN: whether a split's moved corners are the predicted fan (0) or listed in MASK (1).
FAN_PREDICTED, FAN_LISTED = 0, 1

# ---- "The wedge part of split t" and of collapses -------------------------------
# The split ratio is clamped to [0, MAX_SPLIT_RATIO]; the gradient fit is damped
# by GRADIENT_DAMPING times the trace (plus 1e-9).
MAX_SPLIT_RATIO = 4.0
GRADIENT_DAMPING = 1e-3


class PacketError(MeshError):
    """A packet cannot be decoded or does not fit the state it is applied to."""


def stream_names(attribute_grids: tuple, has_materials: bool) -> tuple[str, ...]:
    """The names of a packet's streams, in body order."""
    names = STREAM_NAMES
    if attribute_grids:
        names += WEDGE_STREAM_NAMES + tuple(f"value:{g.name}" for g in attribute_grids)
    if has_materials:
        names += ("material",)
    return names


def pack_header(grid, attribute_grids: tuple, has_materials: bool, start: int, stop: int,
                start_faces: int, stop_faces: int, body_length: int, *,
                version: int = PACKET_VERSION, flags: int = 0) -> bytes:
    """The header of a packet, attribute records included ("Byte layout").

    ``grid`` is a :class:`~lodserver.packets.grids.Grid` (``bits``, ``origin``,
    ``step``), ``attribute_grids`` its :class:`~lodserver.packets.grids.AttributeGrid`
    per attribute in layout order.
    """
    flags |= HAS_MATERIALS if has_materials else 0
    out = bytearray(HEADER.pack(MAGIC, version, grid.bits, len(attribute_grids), flags, start,
                                stop, start_faces, stop_faces, *grid.origin, grid.step,
                                body_length))
    if len(attribute_grids) > MAX_ATTRIBUTES:
        raise ValueError(f"a packet carries at most {MAX_ATTRIBUTES} attributes, "
                         f"got {len(attribute_grids)}")
    for g in attribute_grids:
        name = g.name.encode("ascii")
        if not 0 < len(name) <= MAX_NAME:
            raise ValueError(f"attribute names must be 1 to {MAX_NAME} bytes, got {g.name!r}")
        out.append(len(name))
        out += name
        out += ATTRIBUTE.pack(g.width, ENCODING_IDS[g.encoding], g.bits, g.step)
        out += struct.pack(f"<{g.components}d", *g.origin)
    return bytes(out)


def unpack_header(data: bytes, versions: tuple = READABLE_VERSIONS,
                  known_flags: int = HAS_MATERIALS) -> tuple[dict, list, int]:
    """The fields of a packet's header ("Byte layout"), checked: its version one of
    ``versions``, no flag outside ``known_flags``.

    Returns
    -------
    fields : dict
        ``bits, flags, start, stop, start_faces, stop_faces, origin`` (3 floats),
        ``step``, ``body_length``.
    attributes : list of (name, width, encoding, origin, step, bits)
        One per attribute record, in layout order.
    at : int
        Where the deflated body starts.

    Raises
    ------
    PacketError
        On a short header, bad magic, unreadable version, reserved or unknown
        flags, or a bad attribute record.
    """
    if len(data) < HEADER.size:
        raise PacketError(f"the packet is truncated: {len(data)} bytes is shorter than the header")
    (magic, version, bits, attributes, flags, start, stop, start_faces, stop_faces,
     ox, oy, oz, step, body_length) = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise PacketError("this is not a lodserver vsplit packet (bad magic bytes)")
    if version not in versions:
        raise PacketError(f"the packet has version {version}; this decoder reads "
                          f"{' and '.join(map(str, versions))}")
    if version == 1 and (attributes or flags):
        raise PacketError("the packet has version 1 but sets reserved header bytes")
    if flags & ~known_flags:
        raise PacketError(f"the packet sets unknown header flags {flags:#x}")
    if attributes > MAX_ATTRIBUTES:
        raise PacketError(f"the packet has {attributes} attribute records; at most "
                          f"{MAX_ATTRIBUTES} are allowed")
    at = HEADER.size
    records = []
    for _ in range(attributes):
        record, at = (_attribute_v2 if version == 2 else _attribute_v3)(data, at)
        records.append(record)
    if len({record[0] for record in records}) != len(records):
        raise PacketError("the packet names an attribute twice")
    fields = dict(version=version, bits=bits, flags=flags, start=start, stop=stop,
                  start_faces=start_faces, stop_faces=stop_faces, origin=(ox, oy, oz), step=step,
                  body_length=body_length)
    return fields, records, at


def _truncated() -> PacketError:
    return PacketError("the packet is truncated in its attribute records")


def _attribute_v3(data: bytes, at: int) -> tuple[tuple, int]:
    """One version 3 attribute record at ``at``: ``((name, width, encoding, origin, step,
    bits), where it ends)``; a bad record is a PacketError."""
    if len(data) < at + 1:
        raise _truncated()
    size = data[at]
    if not 0 < size <= MAX_NAME:
        raise PacketError(f"the packet has an attribute name of {size} bytes; names have "
                          f"1 to {MAX_NAME}")
    if len(data) < at + 1 + size + ATTRIBUTE.size:
        raise _truncated()
    raw = data[at + 1:at + 1 + size]
    name = raw.decode("ascii", errors="replace")
    if not raw.isascii() or not name.isprintable():
        raise PacketError("the packet has an attribute name that is not printable ASCII")
    width, encoding, bits, step = ATTRIBUTE.unpack_from(data, at + 1 + size)
    try:
        width = attribute_width(name, width)
    except MeshError as exc:
        raise PacketError(f"the packet has a bad attribute record: {exc}") from None
    return _attribute_grid(data, at + 1 + size + ATTRIBUTE.size, name, width, encoding, bits,
                           step)


def _attribute_v2(data: bytes, at: int) -> tuple[tuple, int]:
    """One version 2 attribute record (a kind code for four names), as ``_attribute_v3``."""
    if len(data) < at + ATTRIBUTE_V2.size:
        raise _truncated()
    kind, encoding, bits, _reserved, step = ATTRIBUTE_V2.unpack_from(data, at)
    if kind not in ATTRIBUTE_NAMES:
        raise PacketError(f"the packet names an unknown attribute ({kind})")
    name = ATTRIBUTE_NAMES[kind]
    return _attribute_grid(data, at + ATTRIBUTE_V2.size, name, attribute_width(name),
                           encoding, bits, step, V2_ENCODING_NAMES)


def _attribute_grid(data, at, name, width, encoding, bits, step,
                    encodings=ENCODING_NAMES) -> tuple[tuple, int]:
    """The rest of an attribute record: the encoding (one of ``encodings``, by id)
    checked against the name, then the origin."""
    if encoding not in encodings:
        raise PacketError(f"the packet gives {name} an unknown encoding ({encoding})")
    encoding = encodings[encoding]
    if ENCODING_ATTRIBUTE.get(encoding, name) != name:
        raise PacketError(f"the packet encodes {name} as {encoding}: only "
                          f"{ENCODING_ATTRIBUTE[encoding]} can be")
    if not 1 <= bits <= MAX_BITS:
        raise PacketError(f"the packet gives {name} a grid of {bits} bits; 1 to {MAX_BITS} "
                          "are allowed")
    components = encoding_components(encoding, width)
    if len(data) < at + 8 * components:
        raise _truncated()
    origin = struct.unpack_from(f"<{components}d", data, at)
    return (name, width, encoding, origin, step, bits), at + 8 * components


def deflate_body(body: bytes) -> bytes:
    """The zlib stream of a packet body. The level is not part of the format:
    on a large body, level 9 packs barely tighter than 6 and takes much longer,
    so bodies of 1 MiB or more are packed at 6."""
    return zlib.compress(body, 9 if len(body) < 2**20 else 6)


# ---- varints and zigzag (the bullets after "How the server cuts packets") -------
def put_varint(out: bytearray, value: int) -> None:
    """Unsigned LEB128: 7 bits per byte, low bits first, high bit = more follows."""
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)


def zigzag(value: int) -> int:
    """Signed -> unsigned, small magnitudes first: 0, -1, 1, -2, ... -> 0, 1, 2, 3, ..."""
    return 2 * value if value >= 0 else -2 * value - 1


class Reader:
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
        """A zigzag varint: ``n = (u >> 1) ^ -(u & 1)``."""
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
