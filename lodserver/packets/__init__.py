"""Vertex-split packets: the bytes that take a client from one level to another.

A client holds one level of a progressive mesh in its *quantized form*
(:func:`quantized_level`, served by the LOD endpoint as ``format=json``). A
packet from level ``A`` to level ``B`` carries the ``|B - A|`` vertex splits
(``B > A``) or edge collapses (``B < A``) between them; applying it
(:func:`apply_packet`) yields exactly the quantized form of level ``B``: the
same grid positions, the same faces in the same slots, and the same wedge
values, corner wedges and face materials. The byte layout is specified in
``docs/packets.md`` for clients in any language.

The package, in the order data flows through it:

- ``format.py``     the wire format: constants, header, stream names, varints
- ``grids.py``      quantization grids (positions, every attribute of
                    ``mesh.ATTRIBUTE_RULES``) and a level's quantized form
- ``encode.py``     the compiled encoder (numba), with ``corners.py`` (connectivity)
                    and ``encode_wedges.py`` (the wedge part of each record); its
                    kernels take the small records of ``kernel_types.py``
- ``records.py``    every record encoded once per mesh; the server's packets are slices
- ``reference.py``  the readable decoder, the reference for clients
- ``rans.py``, ``streams_v4.py``, ``encode_v4.py``, ``decode_v4.py``  version 4:
                    the same records, each field coded by kind with adaptive rANS
                    (served on request: ``served.py``; docs/packets.md, "Version 4")

The compiled encoder is checked byte for byte against the readable encoder in
``tests/naive_packets.py``, which predicts with ``reference.py``'s functions.
"""

from .decode_v4 import decode_any, decode_packet_v4
from .encode import encode_packet
from .encode_v4 import encode_packet_v4
from .format import (
    ATTRIBUTE_IDS,
    COUNT,
    FAN,
    LINEAR,
    MAGIC,
    MASK,
    MAX_ATTRIBUTES,
    MAX_BITS,
    MAX_NAME,
    MIN_BITS,
    OCTAHEDRAL,
    OTHER,
    PACKET_VERSION,
    PATTERN,
    POSITION,
    READABLE_VERSIONS,
    TANGENT,
    VERTEX,
    WEDGE_CORNER,
    WEDGE_COUNT,
    WEDGE_PARENT,
    PacketError,
    deflate_body,
    pack_header,
    stream_names,
)
from .grids import (
    DEFAULT_ATTRIBUTE_BITS,
    EDGE_BITS,
    MORPH_EDGE_BITS,
    AttributeGrid,
    Grid,
    LodState,
    attribute_grids_of,
    check_bits,
    default_attribute_bits,
    default_bits,
    fold_octahedral,
    grid_of,
    mean_edge,
    quantize_wedges,
    quantized_level,
    state_from_json,
    unfold_octahedral,
)
from .records import (
    CHUNK_RECORDS,
    RecordStreams,
    cached_records,
    encode_records,
    packet_between,
    prepare_records,
    record_cache,
    record_streams,
    records_ready,
    shutdown_background,
)
from .reference import Packet, apply_packet, decode_packet

__all__ = [
    "ATTRIBUTE_IDS", "CHUNK_RECORDS", "COUNT", "DEFAULT_ATTRIBUTE_BITS", "EDGE_BITS", "FAN",
    "LINEAR", "MAGIC", "MASK", "MAX_ATTRIBUTES", "MAX_BITS", "MAX_NAME", "MIN_BITS",
    "MORPH_EDGE_BITS", "OCTAHEDRAL", "OTHER", "PACKET_VERSION", "PATTERN", "POSITION",
    "READABLE_VERSIONS", "TANGENT", "VERTEX", "WEDGE_CORNER", "WEDGE_COUNT",
    "WEDGE_PARENT", "AttributeGrid", "Grid", "LodState", "Packet", "PacketError",
    "RecordStreams", "apply_packet", "attribute_grids_of", "cached_records", "check_bits",
    "decode_any", "decode_packet", "decode_packet_v4", "default_attribute_bits",
    "default_bits", "deflate_body", "encode_packet", "encode_packet_v4", "encode_records",
    "fold_octahedral", "grid_of", "mean_edge",
    "pack_header", "packet_between", "prepare_records", "quantize_wedges", "quantized_level",
    "record_cache", "record_streams", "records_ready", "shutdown_background",
    "state_from_json", "stream_names", "unfold_octahedral",
]
