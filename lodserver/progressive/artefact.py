"""The stored artefact of a progressive mesh: one versioned ``.pm`` file.

A codec of named arrays: ``encode_artefact`` writes a mapping of the stored
fields (``STORED_FIELDS``: a few header values and named arrays) and
``decode_artefact`` reads them back, checked, as the keywords
``ProgressiveMesh`` is made from. It knows the format, not the class:
``progressive.mesh`` calls it (``encode_progressive``, ``ProgressiveMesh.save``
and ``load``), never the other way round.

Byte layout (all integers little-endian)::

    offset  size  field
    0       8     magic  b"LODSRVPM"
    8       4     uint32 format version (FORMAT_VERSION)
    12      4     uint32 CRC-32 of the payload (zlib.crc32)
    16      8     uint64 payload length in bytes
    24      ...   payload: a sequence of named blocks

    block:
      2     uint16 name length L, then L bytes of UTF-8 name
      1     uint8  dtype code: b"f" float64, b"i" int64, b"j" int32, b"u" uint8 (raw bytes)
      1     uint8  number of dimensions d
      8*d   uint64 shape
      ...   the array, C order, little-endian

The ``meta`` block holds UTF-8 JSON (base_vertices, the metadata dict and,
with attributes, their layout). Version 2 adds optional blocks for
appearance: the wedge arrays (``WEDGE_ARRAYS``), ``face_material``,
``materials`` (UTF-8 JSON of the glTF material records) and ``image.<i>`` (the
image files' bytes); and ``split_batch`` for a mesh whose splits come in
batches (``progressive.batches``). A reader skips blocks it does not know.
Version 1 files (geometry only) are still read.
Only the arrays ``ProgressiveMesh`` is made from are written; everything derived
(vertex hierarchy, split positions, birth faces) is rebuilt on load. Integer
arrays whose values fit in int32 are stored as int32 (half the bytes).

Any mismatch (magic, version, length, checksum, missing block, bad shape)
raises ``ArtefactError`` with a sentence saying what is wrong.
"""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import numpy as np

from collections.abc import Mapping

from ..io.files import write_atomic
from ..mesh import Materials, MeshError

__all__ = ["ArtefactError", "encode_artefact", "decode_artefact", "write_artefact",
           "read_artefact", "ARRAYS", "WEDGE_ARRAYS", "STORED_FIELDS", "MAGIC", "FORMAT_VERSION",
           "READABLE_VERSIONS"]

MAGIC = b"LODSRVPM"
FORMAT_VERSION = 2
READABLE_VERSIONS = (1, 2)
_HEADER = struct.Struct("<8sIIQ")
_DTYPES = {b"f": np.dtype("<f8"), b"i": np.dtype("<i8"), b"j": np.dtype("<i4"), b"u": np.dtype("u1")}
# The arrays every artefact holds, in their order in the file.
ARRAYS = ("positions", "faces", "parent", "coarse_position", "error", "face_counts",
          "moved_offsets", "moved_corners")
# The arrays of the wedges, present when the mesh has appearance attributes.
WEDGE_ARRAYS = ("wedge_values", "corner_wedges", "wedge_parent", "wedge_coarse_value",
                "wedge_counts")
# Every field ``encode_artefact`` reads: base_vertices (int) and metadata
# (JSON-able dict), the arrays, and the optional attribute_layout (tuple of
# (name, width)), face_material (m,) int, materials (``mesh.Materials``) and
# split_batch (k,) int, each None when absent.
STORED_FIELDS = (("base_vertices", "metadata") + ARRAYS + WEDGE_ARRAYS
                 + ("attribute_layout", "face_material", "materials", "split_batch"))
# Arrays read back as float64; every other array is read back as int64.
_FLOATS = ("positions", "coarse_position", "error", "wedge_values", "wedge_coarse_value")


class ArtefactError(MeshError):
    """A ``.pm`` file is unreadable, truncated, corrupted or of another version."""


def _encode_block(name: str, array: np.ndarray) -> bytes:
    array = np.asarray(array)
    if array.dtype.kind == "f":
        code, array = b"f", array.astype("<f8")
    elif array.dtype.kind in "iu" and array.dtype != np.uint8:
        small = array.size == 0 or (array.min() >= -2**31 and array.max() < 2**31)
        code, array = (b"j", array.astype("<i4")) if small else (b"i", array.astype("<i8"))
    else:
        code, array = b"u", array.astype("u1")
    encoded = name.encode()
    head = struct.pack("<H", len(encoded)) + encoded + code + struct.pack("<B", array.ndim)
    head += struct.pack(f"<{array.ndim}Q", *array.shape)
    return head + np.ascontiguousarray(array).tobytes()


def encode_artefact(fields: Mapping) -> bytes:
    """The whole ``.pm`` file as bytes.

    Parameters
    ----------
    fields : mapping
        At least ``STORED_FIELDS`` by name (a progressive mesh's own fields);
        the wedge arrays and ``attribute_layout`` are written when
        ``wedge_values`` is not None, ``face_material``, ``materials`` and
        ``split_batch`` when not None.
    """
    meta = {"base_vertices": fields["base_vertices"], "metadata": fields["metadata"]}
    attributes = fields["wedge_values"] is not None
    if attributes:
        meta["attribute_layout"] = [list(item) for item in fields["attribute_layout"]]
    blocks = [_encode_block("meta", _json_bytes(meta))]
    blocks += [_encode_block(name, fields[name]) for name in ARRAYS]
    if attributes:
        blocks += [_encode_block(name, fields[name]) for name in WEDGE_ARRAYS]
    if fields["face_material"] is not None:
        blocks.append(_encode_block("face_material", fields["face_material"]))
    materials = fields["materials"]
    if materials is not None:
        blocks.append(_encode_block("materials", _json_bytes(materials.gltf)))
        blocks += [_encode_block(f"image.{i}", np.frombuffer(image, dtype=np.uint8))
                   for i, image in enumerate(materials.images)]
    if fields.get("split_batch") is not None:
        blocks.append(_encode_block("split_batch", fields["split_batch"]))
    payload = b"".join(blocks)
    return _HEADER.pack(MAGIC, FORMAT_VERSION, zlib.crc32(payload), len(payload)) + payload


def _json_bytes(value) -> np.ndarray:
    return np.frombuffer(json.dumps(value).encode(), dtype=np.uint8)


def decode_artefact(data: bytes, *, source: str = "the artefact") -> dict:
    """Parse bytes written by ``encode_artefact``.

    Returns
    -------
    dict
        The stored fields present, by name, arrays as float64 or int64 (int32
        for ``face_material`` and ``split_batch``) of their own: the keywords
        of ``ProgressiveMesh``.

    Raises
    ------
    ArtefactError
        A sentence naming ``source`` and what is wrong (magic, version,
        length, checksum, a missing or malformed block).
    """
    if len(data) < _HEADER.size:
        raise ArtefactError(f"{source} is truncated: {len(data)} bytes is shorter than the header")
    magic, version, crc, length = _HEADER.unpack_from(data)
    if magic != MAGIC:
        raise ArtefactError(f"{source} is not a lodserver progressive mesh (bad magic bytes)")
    if version not in READABLE_VERSIONS:
        raise ArtefactError(f"{source} has format version {version}; this lodserver reads "
                            f"versions {', '.join(map(str, READABLE_VERSIONS))}")
    payload = memoryview(data)[_HEADER.size:]
    if len(payload) != length:
        raise ArtefactError(f"{source} is truncated or padded: payload is {len(payload)} bytes, "
                            f"header says {length}")
    if zlib.crc32(payload) != crc:
        raise ArtefactError(f"{source} is corrupted: checksum mismatch")
    blocks = {}
    at = 0
    try:
        while at < length:
            (name_len,) = struct.unpack_from("<H", payload, at)
            at += 2
            name = bytes(payload[at:at + name_len]).decode()
            at += name_len
            code = bytes(payload[at:at + 1])
            (ndim,) = struct.unpack_from("<B", payload, at + 1)
            at += 2
            shape = struct.unpack_from(f"<{ndim}Q", payload, at)
            at += 8 * ndim
            dtype = _DTYPES[code]
            size = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
            if at + size > length:
                raise ArtefactError(f"{source}: block {name!r} runs past the end of the payload")
            blocks[name] = np.frombuffer(payload, dtype=dtype, count=size // dtype.itemsize,
                                         offset=at).reshape(shape)
            at += size
    except (struct.error, KeyError, UnicodeDecodeError) as exc:
        raise ArtefactError(f"{source} has a malformed block table ({exc})") from exc
    missing = [name for name in ("meta",) + ARRAYS if name not in blocks]
    if missing:
        raise ArtefactError(f"{source} lacks the blocks {', '.join(missing)}")
    try:
        meta = json.loads(blocks["meta"].tobytes())
        fields = {"base_vertices": int(meta["base_vertices"]),
                  "metadata": meta.get("metadata", {})}
        fields.update({name: _array(blocks[name], name) for name in ARRAYS})
        if "attribute_layout" in meta:
            missing = [name for name in WEDGE_ARRAYS if name not in blocks]
            if missing:
                raise ArtefactError(f"{source} lacks the blocks {', '.join(missing)}")
            fields.update({name: _array(blocks[name], name) for name in WEDGE_ARRAYS})
            fields["attribute_layout"] = tuple(tuple(item) for item in meta["attribute_layout"])
        if "face_material" in blocks:
            fields["face_material"] = np.array(blocks["face_material"], dtype=np.int32)
        if "materials" in blocks:
            images = []
            while f"image.{len(images)}" in blocks:
                images.append(blocks[f"image.{len(images)}"].tobytes())
            fields["materials"] = Materials(json.loads(blocks["materials"].tobytes()),
                                            tuple(images))
        if "split_batch" in blocks:
            fields["split_batch"] = np.array(blocks["split_batch"], dtype=np.int32)
        return fields
    except (ValueError, KeyError, IndexError, TypeError) as exc:
        raise ArtefactError(f"{source} holds inconsistent arrays ({exc})") from exc


def _array(block: np.ndarray, name: str) -> np.ndarray:
    """A block read back as the array the mesh holds: a copy, float64 or int64."""
    return np.array(block, dtype=np.float64 if name in _FLOATS else np.int64)


def write_artefact(path, fields: Mapping) -> None:
    """Write ``encode_artefact(fields)`` to ``path`` atomically
    (:func:`lodserver.io.files.write_atomic`): a temporary file in the same
    directory, flushed to disk, then renamed over the target."""
    write_atomic(path, encode_artefact(fields))


def read_artefact(path) -> bytes:
    """The bytes of the ``.pm`` file ``path`` (``decode_artefact`` parses them).

    Raises
    ------
    ArtefactError
        The file cannot be read.
    """
    path = Path(path)
    try:
        return path.read_bytes()
    except OSError as exc:
        raise ArtefactError(f"cannot read {path}: {exc.strerror or exc}") from exc
