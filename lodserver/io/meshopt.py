"""EXT_meshopt_compression: bufferViews decoded on reading, encoded on writing.

The extension (KhronosGroup/glTF, extensions/2.0/Vendor/EXT_meshopt_compression)
compresses a bufferView as a whole: its extension object names a byte range of
another buffer holding ``count`` elements of ``byteStride`` bytes in one of three
bitstreams (``mode``), and for attributes a ``filter`` applied after decoding.
The bitstreams are decoded and encoded by meshoptimizer's C library (PyPI
``meshoptimizer``); the filters are the few lines of arithmetic of the spec's
Appendix B, written here over numpy arrays (the PyPI wrapper declares no ctypes
signature for its filter functions, so their ``size_t`` arguments would be passed
as 32-bit ints).

Reading (:func:`decode_view`): every declared size is checked before the decoder
allocates: the element layout as the spec requires it, ``count * byteStride``
equal to the parent bufferView's length, inside its (possibly uri-less fallback)
buffer, and at most what the compressed bytes can expand to (:data:`MAX_EXPANSION`):
a few bytes declaring a gigabyte are refused, not decoded. A decoder's failure is
one sentence.

Writing (:func:`encode_view`): ``(count, stride)`` bytes in, the compressed bytes
and the extension object out; octahedral normals and tangents by
:func:`encode_octahedral`.
"""

from __future__ import annotations

import numpy as np

from ..mesh import MeshError
from .gltf_document import natural
from .limits import LimitError

EXTENSION = "EXT_meshopt_compression"

# The most bytes one compressed byte can decode to, by mode (Appendix A). Attributes:
# a group of 16 equal bytes costs 2 header bits, so 64 bytes a byte at best (plus a
# header byte and the 32-byte tail). Triangles: every triangle has a code byte,
# 3 indices a byte at best. Indices: every index is a varint of at least one byte.
# The bound is on elements of the decoded stream per compressed byte for the index
# modes, on decoded bytes for attributes.
MAX_EXPANSION = {"ATTRIBUTES": 64, "TRIANGLES": 3, "INDICES": 1}

FILTERS = ("NONE", "OCTAHEDRAL", "QUATERNION", "EXPONENTIAL")


def _decoder():
    """meshoptimizer's decoders, imported when a file needs them: a MeshError naming
    the package when it is not installed (a dependency of lodserver's)."""
    try:
        import meshoptimizer
    except ImportError:
        raise MeshError("it is compressed with EXT_meshopt_compression and the meshoptimizer "
                        "package is not installed (pip install meshoptimizer)") from None
    return meshoptimizer


def check_view(extension, view_length: int, label: str) -> tuple[str, str, int, int]:
    """(mode, filter, count, stride) of a bufferView's extension object, checked as
    the spec requires (before anything is decoded); MeshError naming ``label``."""
    if not isinstance(extension, dict):
        raise MeshError(f"its {label} has an {EXTENSION} that is not an object")
    mode, kind = extension.get("mode"), extension.get("filter", "NONE")
    count = natural(extension.get("count"), f"{label} {EXTENSION} count")
    stride = natural(extension.get("byteStride"), f"{label} {EXTENSION} byteStride")
    if mode not in MAX_EXPANSION:
        raise MeshError(f"its {label} has {EXTENSION} mode {str(mode)[:40]!r}, not ATTRIBUTES, "
                        "TRIANGLES or INDICES")
    if kind not in FILTERS:
        raise MeshError(f"its {label} has {EXTENSION} filter {str(kind)[:40]!r}, not "
                        f"{', '.join(FILTERS)}")
    valid = {"ATTRIBUTES": stride % 4 == 0 and 0 < stride <= 256,
             "TRIANGLES": stride in (2, 4) and count % 3 == 0 and kind == "NONE",
             "INDICES": stride in (2, 4) and kind == "NONE"}[mode]
    valid = valid and {"NONE": True, "OCTAHEDRAL": stride in (4, 8), "QUATERNION": stride == 8,
                       "EXPONENTIAL": stride % 4 == 0}[kind]
    if not valid:
        raise MeshError(f"its {label} has {EXTENSION} mode {mode} with filter {kind}, "
                        f"byteStride {stride} and count {count}, which the extension forbids")
    if count * stride != view_length:
        raise MeshError(f"its {label} declares {count} elements of {stride} bytes compressed, "
                        f"but a byteLength of {view_length}")
    return mode, kind, count, stride


def decode_view(extension: dict, source: memoryview, view_length: int, label: str) -> bytes:
    """The bytes of a compressed bufferView, decoded and filtered.

    Parameters
    ----------
    extension : dict
        The bufferView's ``EXT_meshopt_compression`` object.
    source : memoryview
        Its compressed bytes (``extension``'s buffer range, already cut and checked).
    view_length : int
        The parent bufferView's ``byteLength``: what the decoded bytes must fill.
    label : str
        What the messages call the view (``"bufferView 3"``).

    Returns
    -------
    bytes
        ``view_length`` bytes: ``count`` elements of ``byteStride`` bytes.

    Raises
    ------
    MeshError
        For a layout the spec forbids or a stream the decoder rejects.
    LimitError
        When the declared size is more than the compressed bytes can hold
        (:data:`MAX_EXPANSION`), before anything is allocated.
    """
    mode, kind, count, stride = check_view(extension, view_length, label)
    bound = MAX_EXPANSION[mode] * len(source)
    declared = count * stride if mode == "ATTRIBUTES" else count
    if declared > bound:
        unit = "bytes" if mode == "ATTRIBUTES" else "indices"
        raise LimitError(f"its {label} declares {declared} {unit} compressed in {len(source)} "
                         f"bytes, more than {EXTENSION} can hold in them ({bound})")
    if count == 0:
        return b""
    meshopt = _decoder()
    data = np.frombuffer(source, np.uint8)
    try:
        if mode == "ATTRIBUTES":
            decoded = meshopt.decode_vertex_buffer(count, stride, data).view(np.uint8)
        elif mode == "TRIANGLES":
            decoded = meshopt.decode_index_buffer(count, 4, data)
        else:
            decoded = meshopt.decode_index_sequence(count, 4, data)
    except (RuntimeError, ValueError) as exc:
        raise MeshError(f"its {label} could not be decoded from {EXTENSION} "
                        f"({str(exc)[:80]})") from None
    if mode != "ATTRIBUTES":
        # decoded as 32-bit indices; a 16-bit view holds them as 16 bits
        if stride == 2:
            if count and int(decoded.max()) > 0xFFFF:
                raise MeshError(f"its {label} decodes to indices past the 16 bits of its "
                                "byteStride 2")
            decoded = decoded.astype("<u2")
        return decoded.astype(decoded.dtype.newbyteorder("<"), copy=False).tobytes()
    elements = decoded.reshape(count, stride)
    if kind == "OCTAHEDRAL":
        elements = _octahedral(elements, stride)
    elif kind == "QUATERNION":
        elements = _quaternion(elements)
    elif kind == "EXPONENTIAL":
        elements = _exponential(elements)
    return np.ascontiguousarray(elements).tobytes()


def _octahedral(elements: np.ndarray, stride: int) -> np.ndarray:
    """Appendix B filter 1: (count, 4 or 8) bytes of four 8- or 16-bit octahedral
    components -> three unit components normalized to the same width, the fourth as is."""
    dtype, top = (np.int8, 127.0) if stride == 4 else (np.dtype("<i2"), 32767.0)
    values = np.ascontiguousarray(elements).view(dtype).reshape(-1, 4)
    one = values[:, 2].astype(np.float32)
    one[one == 0] = 1.0         # an invalid K: unspecified, but never a division by zero
    x = values[:, 0] / one
    y = values[:, 1] / one
    z = 1.0 - np.abs(x) - np.abs(y)
    t = np.minimum(z, 0.0)
    x = x - np.copysign(t, x)
    y = y - np.copysign(t, y)
    length = np.sqrt(x * x + y * y + z * z)
    length[length == 0] = 1.0
    out = values.copy()
    for k, component in enumerate((x, y, z)):
        out[:, k] = np.rint(component / length * top)
    return out.view(np.uint8).reshape(len(values), stride)


def _quaternion(elements: np.ndarray) -> np.ndarray:
    """Appendix B filter 2: (count, 8) bytes of three 16-bit components and the index of
    the omitted largest one -> the unit quaternion's four components, 16-bit normalized."""
    values = np.ascontiguousarray(elements).view("<i2").reshape(-1, 4)
    one = (values[:, 3] | 3).astype(np.float32)
    scale = np.float32(1.0 / np.sqrt(2.0))
    x, y, z = (values[:, k] / one * scale for k in range(3))
    w = np.sqrt(np.maximum(0.0, 1.0 - x * x - y * y - z * z))
    largest = (values[:, 3] & 3).astype(np.int64)
    rows = np.arange(len(values))
    out = np.empty_like(values)
    for shift, component in ((1, x), (2, y), (3, z), (0, w)):
        out[rows, (largest + shift) % 4] = np.rint(component * 32767.0)
    return out.view(np.uint8).reshape(len(values), 8)


def _exponential(elements: np.ndarray) -> np.ndarray:
    """Appendix B filter 3: 32-bit words of an 8-bit exponent and a 24-bit mantissa
    -> float32 ``2**e * m``."""
    words = np.ascontiguousarray(elements).view("<i4")
    exponent = words >> 24
    mantissa = (words << 8) >> 8
    values = np.ldexp(mantissa.astype(np.float64), exponent).astype("<f4")
    return values.view(np.uint8).reshape(elements.shape)


def encode_octahedral(vectors: np.ndarray, bits: int = 8) -> np.ndarray:
    """(count, 3) unit vectors (or (count, 4) with a fourth component in [-1, 1] kept, a
    tangent's sign) as (count, 4) int8 octahedral components of ``bits`` precision, for
    the OCTAHEDRAL filter of byteStride 4 (``bits`` at most 8).

    The inverse of :func:`_octahedral`: x and y projected on the octahedron, folded
    for the lower hemisphere, as ``bits``-bit signed normalized integers; the third
    component is ``bits``-bit 1.0, which tells the decoder the precision.
    """
    vectors = np.asarray(vectors, dtype=np.float64)
    top = (1 << (bits - 1)) - 1
    x, y, z = vectors[:, 0], vectors[:, 1], vectors[:, 2]
    scale = np.abs(x) + np.abs(y) + np.abs(z)
    scale[scale == 0] = 1.0
    u, v = x / scale, y / scale
    lower = z < 0
    fold_u = (1.0 - np.abs(v)) * np.where(u >= 0, 1.0, -1.0)
    fold_v = (1.0 - np.abs(u)) * np.where(v >= 0, 1.0, -1.0)
    u, v = np.where(lower, fold_u, u), np.where(lower, fold_v, v)
    out = np.zeros((len(vectors), 4), np.int8)
    out[:, 0] = np.rint(u * top)
    out[:, 1] = np.rint(v * top)
    out[:, 2] = top
    if vectors.shape[1] > 3:
        out[:, 3] = np.where(vectors[:, 3] < 0, -127, 127)
    return out


def encode_view(elements: np.ndarray, mode: str, kind: str = "NONE") -> tuple[bytes, dict]:
    """Compressed bytes of a bufferView's elements, and its extension object without
    ``buffer`` and ``byteOffset`` (the writer places the bytes).

    ``elements`` is (count, stride) uint8 for ATTRIBUTES (already filtered, e.g. by
    :func:`encode_octahedral`; stride a multiple of 4), a flat uint16 or uint32 index
    array for TRIANGLES (count a multiple of 3) and INDICES.
    """
    meshopt = _decoder()
    if mode == "ATTRIBUTES":
        count, stride = elements.shape
        data = meshopt.encode_vertex_buffer(np.ascontiguousarray(elements), count, stride)
    else:
        count, stride = len(elements), elements.dtype.itemsize
        indices = np.ascontiguousarray(elements, dtype=np.uint32)
        encode = meshopt.encode_index_buffer if mode == "TRIANGLES" else \
            meshopt.encode_index_sequence
        data = encode(indices, count, int(indices.max()) + 1 if count else 0)
    extension = {"byteLength": len(data), "byteStride": stride, "mode": mode, "count": count}
    if kind != "NONE":
        extension["filter"] = kind
    return data, extension
