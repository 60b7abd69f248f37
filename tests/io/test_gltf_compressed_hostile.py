"""Compressed glTF from someone else: bombs refused before allocation, broken streams
refused in a sentence, and the meshopt filters and modes against hand-made values.

The files are built here (lodserver's own meshopt encoder, DracoPy's encoder), so
these tests need no npm tool.
"""

import json
import struct
import tracemalloc

import numpy as np
import pytest

from lodserver.io import LimitError, LoadLimits, load_mesh
from lodserver.io.draco import draco_header
from lodserver.io.meshopt import decode_view, encode_octahedral, encode_view
from lodserver.io.scene import load_scene
from lodserver.mesh import MeshError

from ..hostile_files import grid

# what a refusal may allocate at most: far below the sizes the bombs declare
REFUSAL_BYTES = 16 << 20


def pack(document: dict, binary: bytes) -> bytes:
    """A GLB of ``document`` and its BIN chunk."""
    binary += b"\0" * (-len(binary) % 4)
    header = json.dumps(document).encode()
    header += b" " * (-len(header) % 4)
    return b"".join([struct.pack("<4sII", b"glTF", 2, 28 + len(header) + len(binary)),
                     struct.pack("<I4s", len(header), b"JSON"), header,
                     struct.pack("<I4s", len(binary), b"BIN\x00"), binary])


def meshopt_glb(size: int = 4, edit=None) -> bytes:
    """A grid whose positions (float32, ATTRIBUTES) and indices (TRIANGLES) are
    EXT_meshopt_compression views over a uri-less fallback buffer; ``edit(document,
    binary)`` may change both before packing (it returns the binary)."""
    positions, faces = grid(size)
    streams = [encode_view(np.ascontiguousarray(positions, "<f4").view(np.uint8)
                           .reshape(len(positions), 12), "ATTRIBUTES"),
               encode_view(np.ascontiguousarray(faces, "<u4").ravel(), "TRIANGLES")]
    binary, views, fallback = bytearray(), [], 0
    for data, extension in streams:
        binary.extend(b"\0" * (-len(binary) % 4))
        extension.update(buffer=0, byteOffset=len(binary))
        binary.extend(data)
        length = extension["count"] * extension["byteStride"]
        views.append({"buffer": 1, "byteOffset": fallback, "byteLength": length,
                      "extensions": {"EXT_meshopt_compression": extension}})
        fallback += length + (-length % 4)
    document = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": len(positions),
                       "type": "VEC3", "min": positions.min(0).tolist(),
                       "max": positions.max(0).tolist()},
                      {"bufferView": 1, "componentType": 5125, "count": faces.size,
                       "type": "SCALAR"}],
        "bufferViews": views,
        "buffers": [{"byteLength": len(binary)},
                    {"byteLength": fallback,
                     "extensions": {"EXT_meshopt_compression": {"fallback": True}}}],
        "extensionsUsed": ["EXT_meshopt_compression"],
        "extensionsRequired": ["EXT_meshopt_compression"],
    }
    if edit is not None:
        binary = edit(document, binary)
    return pack(document, bytes(binary))


def draco_glb(size: int = 4, edit=None) -> bytes:
    """A grid in one KHR_draco_mesh_compression primitive (DracoPy's encoder);
    ``edit(document, stream)`` may change the document and return another stream."""
    DracoPy = pytest.importorskip("DracoPy")
    positions, faces = grid(size)
    stream = DracoPy.encode(positions.astype(np.float32), faces.astype(np.uint32))
    decoded = DracoPy.decode(stream)
    document = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{
            "attributes": {"POSITION": 0}, "indices": 1,
            "extensions": {"KHR_draco_mesh_compression": {
                "bufferView": 0, "attributes": {"POSITION": 0}}}}]}],
        "accessors": [{"componentType": 5126, "count": len(decoded.points), "type": "VEC3",
                       "min": [0, 0, 0], "max": [1, 1, 0]},
                      {"componentType": 5125, "count": 3 * len(decoded.faces),
                       "type": "SCALAR"}],
        "extensionsUsed": ["KHR_draco_mesh_compression"],
        "extensionsRequired": ["KHR_draco_mesh_compression"],
    }
    if edit is not None:
        stream = edit(document, stream)
    document["bufferViews"] = [{"buffer": 0, "byteOffset": 0, "byteLength": len(stream)}]
    document["buffers"] = [{"byteLength": len(stream) + (-len(stream) % 4)}]
    return pack(document, stream)


def refused(path, error=MeshError, **kwargs) -> str:
    """The message loading ``path`` refuses it with (load_mesh and load_scene alike),
    checked to be one sentence naming the file by its name only, and the refusal to
    allocate under :data:`REFUSAL_BYTES`."""
    messages = []
    for load in (load_mesh, load_scene):
        tracemalloc.start()
        try:
            with pytest.raises(error) as caught:
                load(path, **kwargs)
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        message = str(caught.value)
        assert message.startswith(f"cannot load {path.name}: ")
        assert str(path.parent) not in message and "\n" not in message
        assert peak < REFUSAL_BYTES, f"refusing {path.name} took {peak} bytes"
        messages.append(message)
    return messages[0]


def test_meshopt_grid_reads_back(tmp_path):
    path = tmp_path / "grid.glb"
    path.write_bytes(meshopt_glb())
    positions, faces = grid(4)
    mesh, _ = load_mesh(path)
    assert mesh.face_count == len(faces)
    np.testing.assert_allclose(np.sort(mesh.positions, axis=0),
                               np.sort(positions.astype(np.float32), axis=0))


def test_meshopt_bomb_is_refused_before_allocation(tmp_path):
    # a few dozen compressed bytes declaring half a gigabyte of positions, within
    # every declared-size limit (the fallback buffer is within max_file_bytes)
    def bomb(document, binary):
        count = 1 << 25
        view = document["bufferViews"][0]
        view["extensions"]["EXT_meshopt_compression"].update(count=count, byteStride=16)
        view["byteLength"] = 16 * count
        document["bufferViews"][1]["byteOffset"] = 16 * count
        document["buffers"][1]["byteLength"] = 16 * count + 1024
        document["accessors"][0]["byteStride"] = 16
        return binary

    path = tmp_path / "bomb.glb"
    path.write_bytes(meshopt_glb(edit=bomb))
    for limits in (LoadLimits(), LoadLimits.unbounded()):
        message = refused(path, LimitError, limits=limits)
        assert "bufferView 0 declares 536870912 bytes compressed in" in message
        assert "more than EXT_meshopt_compression can hold" in message


def test_meshopt_index_bomb_is_refused(tmp_path):
    def bomb(document, binary):
        extension = document["bufferViews"][1]["extensions"]["EXT_meshopt_compression"]
        extension["count"] = 3 * (1 << 24)
        document["bufferViews"][1]["byteLength"] = 4 * extension["count"]
        document["buffers"][1]["byteLength"] = 1 << 29
        return binary

    path = tmp_path / "indices.glb"
    path.write_bytes(meshopt_glb(edit=bomb))
    assert "indices compressed in" in refused(path, LimitError)


@pytest.mark.parametrize("change, words", [
    (lambda e, v, b: e.update(byteStride=6), "which the extension forbids"),
    (lambda e, v, b: e.update(mode="ZIP"), "not ATTRIBUTES, TRIANGLES or INDICES"),
    (lambda e, v, b: e.update(filter="OCTAHEDRAL"), "which the extension forbids"),
    (lambda e, v, b: e.update(count=e["count"] - 1), "but a byteLength of"),
    (lambda e, v, b: e.update(byteLength=10 ** 6), "past the end of their buffer"),
    (lambda e, v, b: v.update(byteOffset=1 << 20), "runs past the end of buffer 1"),
])
def test_meshopt_layout_the_spec_forbids_is_refused(tmp_path, change, words):
    def edit(document, binary):
        view = document["bufferViews"][0]
        change(view["extensions"]["EXT_meshopt_compression"], view, binary)
        return binary

    path = tmp_path / "layout.glb"
    path.write_bytes(meshopt_glb(edit=edit))
    assert words in refused(path)


def test_meshopt_corrupt_stream_is_one_sentence(tmp_path):
    def corrupt(document, binary):
        extension = document["bufferViews"][0]["extensions"]["EXT_meshopt_compression"]
        binary[extension["byteOffset"]] = 0x55       # not the attribute header 0xa0
        return binary

    path = tmp_path / "corrupt.glb"
    path.write_bytes(meshopt_glb(edit=corrupt))
    assert "could not be decoded from EXT_meshopt_compression" in refused(path)


def test_draco_grid_reads_back(tmp_path):
    path = tmp_path / "grid.glb"
    path.write_bytes(draco_glb())
    mesh, _ = load_mesh(path)
    assert mesh.face_count == len(grid(4)[1])
    assert np.ptp(mesh.positions, axis=0)[:2] == pytest.approx([1, 1], abs=1e-3)


def _varint(value: int) -> bytes:
    out = bytearray()
    while True:
        out.append(value & 0x7F | (0x80 if value > 0x7F else 0))
        value >>= 7
        if not value:
            return bytes(out)


def test_draco_bomb_is_refused_before_decoding(tmp_path):
    # a header declaring a billion triangles, the accessors within the limits
    def bomb(document, stream):
        return (b"DRACO\x02\x02\x01\x00\x00\x00" + _varint(10 ** 9) + _varint(3 * 10 ** 9)
                + bytes(32))

    path = tmp_path / "bomb.glb"
    path.write_bytes(draco_glb(edit=bomb))
    message = refused(path)
    assert "but its Draco bitstream 1000000000 triangles and 3000000000 vertices" in message

    # and accessors that declare as much are refused by the limits, before any read
    def declared(document, stream):
        document["accessors"][1]["count"] = 3 * 10 ** 9
        return bomb(document, stream)

    path.write_bytes(draco_glb(edit=declared))
    assert "triangles in mesh 0" in refused(path, LimitError, limits=LoadLimits())


@pytest.mark.parametrize("change, words", [
    (lambda s: s[:-40] + bytes(40), "could not be decoded from KHR_draco_mesh_compression"),
    (lambda s: b"DRACO\x01\x03" + s[7:], "Draco bitstream is version 1.3"),
    (lambda s: b"NOTDRACO" + s, "is not a Draco bitstream"),
    (lambda s: s[:8] + b"\x07" + s[9:], "neither sequential nor edgebreaker"),
    (lambda s: s[:13], "ends inside its header"),
])
def test_draco_broken_stream_is_one_sentence(tmp_path, change, words):
    path = tmp_path / "broken.glb"
    path.write_bytes(draco_glb(edit=lambda document, stream: change(stream)))
    assert words in refused(path)


def test_draco_header_reads_both_methods():
    DracoPy = pytest.importorskip("DracoPy")
    positions, faces = grid(6)
    for method, options in ((1, {}), (0, {"create_metadata": True})):
        stream = DracoPy.encode(positions.astype(np.float32), faces.astype(np.uint32),
                                preserve_order=method == 0, **options)
        found, count, vertices = draco_header(stream)
        assert (found, count) == (method, len(faces))
        assert vertices <= len(positions)


# --- the filters and modes, by hand -------------------------------------------------------


def _extension(count, stride, mode="ATTRIBUTES", kind="NONE"):
    return {"buffer": 0, "count": count, "byteStride": stride, "mode": mode, "filter": kind}


def test_octahedral_filter_round_trips_unit_vectors():
    rng = np.random.default_rng(3)
    vectors = rng.normal(size=(500, 3))
    vectors /= np.linalg.norm(vectors, axis=1, keepdims=True)
    encoded = encode_octahedral(vectors)
    data, extension = encode_view(encoded.view(np.uint8).reshape(-1, 4), "ATTRIBUTES",
                                  "OCTAHEDRAL")
    decoded = np.frombuffer(decode_view(extension, memoryview(data), 4 * len(vectors), "v"),
                            np.int8).reshape(-1, 4)
    unit = decoded[:, :3] / 127.0
    cosine = (unit * vectors).sum(1) / np.linalg.norm(unit, axis=1)
    assert np.degrees(np.arccos(np.clip(cosine, -1, 1))).max() < 1.5


def test_exponential_and_quaternion_filters_by_hand():
    # exponential: 2**e * m with e in the top byte: (-2, 3) -> 0.75, (1, -5) -> -10
    words = np.array([(-2 << 24) | 3, (1 << 24) | (-5 & 0xFFFFFF)], "<i4")
    data, extension = encode_view(words.view(np.uint8).reshape(1, 8), "ATTRIBUTES")
    extension["filter"] = "EXPONENTIAL"
    values = np.frombuffer(decode_view(extension, memoryview(data), 8, "v"), "<f4")
    np.testing.assert_array_equal(values, [0.75, -10.0])
    # quaternion: the identity stored as three zeros and "w is largest" (index 3)
    stored = np.array([[0, 0, 0, 0x7FFC | 3]], "<i2")
    data, extension = encode_view(stored.view(np.uint8).reshape(1, 8), "ATTRIBUTES")
    extension["filter"] = "QUATERNION"
    values = np.frombuffer(decode_view(extension, memoryview(data), 8, "v"), "<i2")
    np.testing.assert_array_equal(values, [0, 0, 0, 32767])


def test_index_modes_round_trip_16_and_32_bits():
    rng = np.random.default_rng(5)
    triangles = rng.integers(0, 300, size=3 * 200).astype(np.uint32)
    for mode in ("TRIANGLES", "INDICES"):
        for dtype in ("<u2", "<u4"):
            data, extension = encode_view(triangles.astype(dtype), mode)
            decoded = decode_view(extension, memoryview(data), triangles.size * extension[
                "byteStride"], "v")
            found = np.frombuffer(decoded, dtype)
            if mode == "TRIANGLES":     # the codec may rotate a triangle's corners
                found, expected = _rotated_first(found), _rotated_first(triangles)
            else:
                expected = triangles
            np.testing.assert_array_equal(found, expected)


def _rotated_first(indices: np.ndarray) -> np.ndarray:
    """Triangles (flat) each rotated to start at its smallest index (winding kept)."""
    triangles = indices.reshape(-1, 3).astype(np.int64)
    first = np.argmin(triangles, axis=1)[:, None]
    return np.take_along_axis(triangles, (first + np.arange(3)) % 3, axis=1)
