"""Vsplit packets: exact round trips between levels, compactness, and clear errors."""

import struct
import threading
import time
import zlib
from dataclasses import replace
from functools import cache
from itertools import pairwise

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lodserver import build, packets
from lodserver.io import clean_mesh
from lodserver.mesh import Materials, Mesh
from lodserver.packets import (
    FAN,
    MAGIC,
    MASK,
    MAX_BITS,
    MIN_BITS,
    WEDGE_CORNER,
    PacketError,
    apply_packet,
    attribute_grids_of,
    decode_packet,
    default_bits,
    encode_packet,
    grid_of,
    packet_between,
    quantized_level,
)
from lodserver.packets import corners, encode
from lodserver.packets.corners import zz as _zigzag  # the compiled zigzag the encoder uses
from lodserver.packets.format import Reader, put_varint
from lodserver.progressive.mesh import ProgressiveMesh

from .. import naive_packets
from ..meshes import mesh as input_mesh
from ..meshes import progressive


def _same(a, b):
    assert a.level == b.level
    assert np.array_equal(a.positions, b.positions)
    assert np.array_equal(a.faces, b.faces)
    assert a.attribute_grids == b.attribute_grids
    for name in ("wedges", "corners", "face_material"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert np.array_equal(x, y), name


@cache
def _geometry_only(name):
    """``name`` built from its positions and faces alone."""
    m = input_mesh(name)
    return build(Mesh(m.positions, m.faces))


def _with_materials():
    """The textured sphere with two materials and some faces without: packets carry
    the material of every new face."""
    m = input_mesh("textured_sphere")
    material = (np.arange(m.face_count) % 3 - 1).astype(np.int32)   # -1, 0, 1, ...
    materials = Materials({"materials": [{"name": "a"}, {"name": "b"}], "textures": [],
                           "samplers": [], "images": []})
    return Mesh(m.positions, m.faces, m.attributes, material, materials)


def test_varints_and_zigzag_by_hand():
    out = bytearray()
    for value in (0, 1, 127, 128, 300, 2**35):
        put_varint(out, value)
    assert bytes(out[:5]) == b"\x00\x01\x7f\x80\x01"
    assert bytes(out[5:7]) == b"\xac\x02"  # 300 = 0b10_0101100
    reader = Reader(bytes(out), "test")
    assert [reader.varint() for _ in range(6)] == [0, 1, 127, 128, 300, 2**35]
    assert [_zigzag(v) for v in (0, -1, 1, -2, 2)] == [0, 1, 2, 3, 4]
    out = bytearray()
    for v in (0, -1, 1, -2, 2, -1000, 1000):
        put_varint(out, _zigzag(v))
    reader = Reader(bytes(out), "test")
    assert [reader.signed() for _ in range(7)] == [0, -1, 1, -2, 2, -1000, 1000]


def test_grid_rounds_to_within_half_a_step():
    pm = progressive("torus")
    grid = grid_of(pm, bits=12)
    q = grid.quantize(pm.positions)
    assert q.min() >= 0 and q.max() <= 2**12 - 1
    assert np.abs(grid.dequantize(q) - pm.positions).max() <= grid.step / 2 + 1e-12
    assert default_bits(pm) == grid_of(pm).bits


@pytest.mark.parametrize("name", ["spot", "torus", "grid", "two_boxes", "icosphere",
                                  "textured_sphere", "hard_sphere"])
def test_forward_and_back_reproduce_the_levels_exactly(name):
    pm = progressive(name)
    grid = grid_of(pm)
    n0, n = pm.base_vertices, pm.vertex_count
    levels = sorted({n0, n0 + 1, (n0 + n) // 3, (n0 + n) // 2, n - 1, n})
    for a, b in zip(levels, levels[::-1]):
        start = quantized_level(pm, a, grid)
        there = apply_packet(start, encode_packet(pm, a, b))
        _same(there, quantized_level(pm, b, grid))
        _same(apply_packet(there, encode_packet(pm, b, a)), start)


@settings(max_examples=25, deadline=None)
@given(st.data())
def test_any_chain_of_packets_lands_on_the_level(data):
    pm = progressive("torus")
    grid = grid_of(pm, bits=10)
    level = st.integers(pm.base_vertices, pm.vertex_count)
    path = data.draw(st.lists(level, min_size=2, max_size=4))
    state = quantized_level(pm, path[0], grid)
    for a, b in pairwise(path):
        state = apply_packet(state, encode_packet(pm, a, b, bits=10))
    _same(state, quantized_level(pm, path[-1], grid))


def test_packets_are_compact_and_predict_every_fan_on_spot():
    pm = _geometry_only("spot")
    n0, n = pm.base_vertices, pm.vertex_count
    data = encode_packet(pm, n0, n)
    packet = decode_packet(data)
    assert packet.records == n - n0 and set(packet.streams[FAN]) == {0}
    assert packet.attribute_grids == () and len(packet.streams) == 7
    # 9.2 bytes per split at the default 12 bits (docs/packets.md); OpenMesh's record is 24
    assert len(data) / (n - n0) < 10
    assert len(encode_packet(pm, n, n0)) / (n - n0) < 4


def test_packets_with_uvs_stay_compact_on_spot():
    """spot with its UVs: about 12.9 bytes per split forward, 4.6 backward (docs/packets.md)."""
    pm = progressive("spot")
    assert pm.attribute_layout == (("TEXCOORD_0", 2),)
    n0, n = pm.base_vertices, pm.vertex_count
    packet = decode_packet(encode_packet(pm, n0, n))
    assert [g.name for g in packet.attribute_grids] == ["TEXCOORD_0"]
    assert len(encode_packet(pm, n0, n)) / (n - n0) < 13.5
    assert len(encode_packet(pm, n, n0)) / (n - n0) < 5.5
    # nearly every changed corner's wedge is the first candidate (code 0); few fall
    # back to a wedge id (a wedge no corner of its vertex holds at that level)
    reader, codes = Reader(packet.streams[WEDGE_CORNER], "wedge_corner"), []
    while not reader.done():
        codes.append(reader.varint())
    codes = np.array(codes)
    assert np.mean(codes == 0) > 0.9 and np.mean(codes > 8) < 0.02


def test_version_1_packets_still_decode():
    """A geometry-only version 3 packet is a version 1 (and 2) packet but for its version byte."""
    pm = progressive("grid")
    data = encode_packet(pm, 40, 80)
    assert data[4] == packets.PACKET_VERSION == 3
    start = quantized_level(pm, 40, grid_of(pm))
    for version in (1, 2):
        old = data[:4] + bytes([version]) + data[5:]
        _same(apply_packet(start, old), apply_packet(start, data))
    old = data[:4] + bytes([1]) + data[5:]
    with pytest.raises(PacketError, match="reserved"):
        decode_packet(old[:6] + bytes([1]) + old[7:])


def test_attribute_grids_round_values_to_within_half_a_step():
    pm = progressive("textured_sphere")
    normal, uv = attribute_grids_of(pm)
    assert (normal.encoding, normal.bits, uv.encoding, uv.bits) == ("octahedral", 10, "linear", 12)
    values = pm.wedge_values
    q = uv.quantize(values[:, 3:])
    assert q.min() >= 0 and q.max() <= 2**12 - 1
    assert np.abs(uv.dequantize(q) - values[:, 3:]).max() <= uv.step / 2 + 1e-12
    n = normal.dequantize(normal.quantize(values[:, :3]))
    angle = np.degrees(np.arccos(np.clip((n * values[:, :3]).sum(axis=1), -1, 1)))
    assert angle.max() < 0.25 and angle.mean() < 0.1   # degrees
    # the axes are exact: the octahedral grid has a row and a column at 0
    axes = np.eye(3)[[0, 1, 2, 0, 1, 2]] * [[1], [1], [1], [-1], [-1], [-1]]
    np.testing.assert_array_equal(normal.dequantize(normal.quantize(axes)), axes)
    assert [g.bits for g in attribute_grids_of(pm, attribute_bits={"NORMAL": 12})] == [12, 12]
    with pytest.raises(ValueError, match="no attribute named COLOR_0"):
        attribute_grids_of(pm, attribute_bits={"COLOR_0": 8})


def test_packets_carry_face_materials():
    pm = build(_with_materials())
    grid = grid_of(pm)
    n0, n = pm.base_vertices, pm.vertex_count
    levels = [n0, (n0 + n) // 2, n, n0 + 7, n]
    state = quantized_level(pm, levels[0], grid)
    assert state.face_material is not None
    for a, b in pairwise(levels):
        data = encode_packet(pm, a, b)
        assert data == naive_packets.encode_packet(pm, a, b)
        state = apply_packet(state, data)
        _same(state, quantized_level(pm, b, grid))
    assert set(state.face_material.tolist()) == {-1, 0, 1}
    with pytest.raises(PacketError, match="materials"):
        apply_packet(replace(state, face_material=None), encode_packet(pm, n, n0))
    with pytest.raises(PacketError, match="attribute"):
        apply_packet(replace(state, attribute_grids=attribute_grids_of(
            pm, attribute_bits={"TEXCOORD_0": 11})), encode_packet(pm, n, n0))


def test_empty_packet_is_the_identity():
    pm = progressive("grid")
    state = quantized_level(pm, 50, grid_of(pm))
    _same(apply_packet(state, encode_packet(pm, 50, 50)), state)


@pytest.mark.parametrize("damage, message", [
    (lambda b: b[:20], "truncated"),
    (lambda b: b"NOPE" + b[4:], "magic"),
    (lambda b: b[:4] + bytes([9]) + b[5:], "version"),
    (lambda b: b[:-3], "inflate"),
    (lambda b: b[:60] + zlib.compress(zlib.decompress(b[60:]) + b"x"), "says"),
])
def test_damaged_packets_are_refused_with_a_reason(damage, message):
    pm = progressive("grid")
    data = encode_packet(pm, 40, 80)
    assert data[:4] == MAGIC
    with pytest.raises(PacketError, match=message):
        apply_packet(quantized_level(pm, 40, grid_of(pm)), damage(data))


def test_packet_for_another_level_or_grid_is_refused():
    pm = progressive("grid")
    data = encode_packet(pm, 40, 80)
    with pytest.raises(PacketError, match="starts at level 40"):
        apply_packet(quantized_level(pm, 41, grid_of(pm)), data)
    with pytest.raises(PacketError, match="grid"):
        apply_packet(quantized_level(pm, 40, grid_of(pm, bits=9)), data)


def test_corrupt_records_are_a_packet_error_not_a_crash():
    pm = progressive("grid")
    data = encode_packet(pm, 40, 120)
    header, body = data[:60], bytearray(zlib.decompress(data[60:]))
    length = struct.unpack("<I", header[56:60])[0]
    assert length == len(body)
    rng = np.random.default_rng(1)
    start = quantized_level(pm, 40, grid_of(pm))
    for _ in range(30):
        broken = bytearray(body)
        broken[int(rng.integers(len(broken)))] ^= int(rng.integers(1, 256))
        try:
            apply_packet(start, header + zlib.compress(bytes(broken)))
        except PacketError:
            pass


# ---- the compiled encoder against the pure-Python reference ------------------
# tests/naive_packets.py is the encoder as first written (corner sets, dicts,
# bytearrays); the numba kernels must write exactly its bytes, fans listed or
# predicted, forward and backward, at any grid.


def _book(pages=4, nx=12, ny=6):
    """Pages of a book sharing their spine: a chain of non-manifold edges, where
    some fans cannot be predicted and are listed in the mask stream."""
    positions, faces = [(x, 0.0, 0.0) for x in np.linspace(0, 1, nx)], []
    for p in range(pages):
        theta = 2 * np.pi * p / pages + 0.3
        rows = [list(range(nx))]
        for r in range(1, ny):
            rows.append(list(range(len(positions), len(positions) + nx)))
            rr = r / (ny - 1)
            positions += [(x, rr * np.cos(theta), rr * np.sin(theta) + 0.05 * np.sin(5 * x))
                          for x in np.linspace(0, 1, nx)]
        for r in range(ny - 1):
            for i in range(nx - 1):
                a, b, c, d = rows[r][i], rows[r][i + 1], rows[r + 1][i + 1], rows[r + 1][i]
                faces += [(a, b, c), (a, c, d)]
    return clean_mesh(np.array(positions, float), np.array(faces, np.int64))[0]


def _flipped_torus():
    """A torus with every third face wound the other way: fans predicted from the
    wrong side, or not at all."""
    mesh = input_mesh("torus")
    faces = mesh.faces.copy()
    faces[::3] = faces[::3, ::-1]
    return Mesh(mesh.positions, faces)


@cache
def _built(name):
    return build({"book": _book, "flipped_torus": _flipped_torus}[name]())


def _some_levels(pm):
    n0, n = pm.base_vertices, pm.vertex_count
    return sorted({n0, n0 + 1, (2 * n0 + n) // 3, (n0 + n) // 2, n - 1, n})


def _assert_same_bytes(pm, pairs, bits_options=(None, 10), attribute_bits=None):
    for a, b in pairs:
        for bits in bits_options:
            ours = encode_packet(pm, a, b, bits=bits, attribute_bits=attribute_bits)
            reference = naive_packets.encode_packet(pm, a, b, bits=bits,
                                                    attribute_bits=attribute_bits)
            assert ours == reference, f"levels {a} -> {b}, bits {bits}: the bytes differ"


@pytest.mark.parametrize("name", ["spot", "torus", "grid", "two_boxes", "icosphere",
                                  "textured_sphere", "hard_sphere"])
def test_compiled_encoder_writes_the_reference_bytes(name):
    pm = progressive(name)
    levels = _some_levels(pm)
    _assert_same_bytes(pm, [(a, b) for a in levels for b in levels])


@pytest.mark.parametrize("name", ["book", "flipped_torus"])
def test_compiled_encoder_writes_the_reference_bytes_with_listed_fans(name):
    pm = _built(name)
    n0, n = pm.base_vertices, pm.vertex_count
    packet = decode_packet(encode_packet(pm, n0, n))
    assert 0 < sum(packet.streams[FAN]) and len(packet.streams[MASK]) > 0
    levels = _some_levels(pm)
    _assert_same_bytes(pm, [(a, b) for a in levels for b in levels])
    # and the listed fans decode to the level, both ways
    grid = grid_of(pm)
    there = apply_packet(quantized_level(pm, n0, grid), encode_packet(pm, n0, n))
    _same(there, quantized_level(pm, n, grid))
    _same(apply_packet(there, encode_packet(pm, n, n0)), quantized_level(pm, n0, grid))


@settings(max_examples=30, deadline=None)
@given(st.data())
def test_compiled_encoder_matches_the_reference_between_any_levels(data):
    name = data.draw(st.sampled_from(["torus", "grid", "icosphere", "textured_sphere",
                                      "hard_sphere", "materials"]))
    pm = build(_with_materials()) if name == "materials" else progressive(name)
    level = st.integers(pm.base_vertices, pm.vertex_count)
    a, b = data.draw(level), data.draw(level)
    bits = data.draw(st.sampled_from([None, MIN_BITS, 10, 16, MAX_BITS]))
    attribute_bits = None
    if pm.has_attributes:
        attribute_bits = {"NORMAL": data.draw(st.sampled_from([MIN_BITS, 10, 16])),
                          "TEXCOORD_0": data.draw(st.sampled_from([MIN_BITS, 12, MAX_BITS]))}
    _assert_same_bytes(pm, [(a, b)], bits_options=(bits,), attribute_bits=attribute_bits)
    # and the packet lands on the level
    grid, grids = grid_of(pm, bits=bits), attribute_grids_of(pm, attribute_bits=attribute_bits)
    there = apply_packet(quantized_level(pm, a, grid, grids),
                         encode_packet(pm, a, b, bits=bits, attribute_bits=attribute_bits))
    _same(there, quantized_level(pm, b, grid, grids))


@settings(max_examples=40, deadline=None)
@given(st.data())
def test_packets_cut_from_the_encoded_records_are_the_encoded_packets(data):
    """The server's packets are slices of every record encoded once: the same bytes
    as encoding the packet on its own, between any two levels, both ways."""
    name = data.draw(st.sampled_from(["spot", "torus", "textured_sphere", "hard_sphere",
                                      "materials", "book"]))
    pm = {"materials": _materials_built, "book": lambda: _built("book")}.get(
        name, lambda: progressive(name))()
    level = st.integers(pm.base_vertices, pm.vertex_count)
    a, b = data.draw(level), data.draw(level)
    bits = data.draw(st.sampled_from([None, default_bits(pm), 10]))
    assert packet_between(pm, a, b, bits=bits) == encode_packet(pm, a, b, bits=bits)


@cache
def _materials_built():
    return build(_with_materials())


def test_encoded_records_cover_the_full_packet_and_its_reverse():
    pm = progressive("textured_sphere")
    n0, n = pm.base_vertices, pm.vertex_count
    for forward in (True, False):
        records = packets.record_streams(pm, forward=forward)
        assert len(records.marks) == len(decode_packet(encode_packet(pm, n0, n)).streams)
        for row in records.marks:
            assert row.shape == (n - n0 + 1,) and row[0] == 0
            assert np.all(np.diff(row.astype(np.int64)) >= 0)
        # collapses add no faces: those streams keep no per-record lengths
        assert forward or records.marks[packets.PATTERN].strides == (0,)
        whole = decode_packet(encode_packet(pm, *((n0, n) if forward else (n, n0))))
        assert tuple(bytes(s) for s in records.slices(0, n - n0)) == whole.streams


@settings(max_examples=30, deadline=None)
@given(st.data())
def test_long_packets_chain_pre_deflated_chunks_into_the_same_body(data):
    """Past one chunk of records a packet copies deflated chunks between two freshly
    deflated ends: a valid zlib stream of the same body, landing on the level."""
    name = data.draw(st.sampled_from(["torus", "textured_sphere", "materials"]))
    pm = _chunked(name)
    level = st.integers(pm.base_vertices, pm.vertex_count)
    a, b = data.draw(level), data.draw(level)
    ours, direct = packet_between(pm, a, b), encode_packet(pm, a, b)
    assert decode_packet(ours).streams == decode_packet(direct).streams
    grid = grid_of(pm)
    _same(apply_packet(quantized_level(pm, a, grid), ours), quantized_level(pm, b, grid))


@cache
def _chunked(name):
    """A progressive mesh of its own (not shared with other tests' record caches)
    whose records are pre-deflated in chunks of 16."""
    pm = build(_with_materials()) if name == "materials" else build(input_mesh(name))
    for forward in (True, False):
        packets.record_cache.setdefault(pm, {})[forward] = [
            threading.Lock(), packets.record_streams(pm, forward=forward, chunk=16)]
    return pm


def test_compiled_encoder_with_64_bit_ids_writes_the_same_bytes(monkeypatch):
    """Meshes past 2**31 corners run the kernels on int64 ids: same bytes."""
    pm = _built("book")
    levels = _some_levels(pm)
    pairs = [(levels[0], levels[-1]), (levels[-1], levels[0]), (levels[2], levels[4])]
    small = [encode_packet(pm, a, b) for a, b in pairs]
    monkeypatch.setattr(encode, "index_dtype", lambda corners, vertices: np.int64)
    assert [encode_packet(pm, a, b) for a, b in pairs] == small
    _assert_same_bytes(pm, pairs, bits_options=(None,))


def test_a_moved_corner_off_its_vertex_is_the_reference_error():
    """A corrupt artefact whose split moves a corner that does not hold vs is
    refused by both encoders with the same message (and no crash)."""
    pm = progressive("torus")
    n0 = pm.base_vertices
    j = pm.split_count // 2
    moved = pm.moved_corners.copy()
    first = int(pm.moved_offsets[j])
    # a corner of a face that exists at level n0 + j but does not hold vs
    s = int(pm.parent[n0 + j])
    faces_then = pm.arrays_at(n0 + j)[1].ravel()
    moved[first] = int(np.nonzero(faces_then != s)[0][0])
    broken = ProgressiveMesh(pm.positions, pm.faces, pm.parent, n0, pm.coarse_position,
                             pm.error, pm.face_counts, pm.moved_offsets, moved)
    with pytest.raises(PacketError) as reference:
        naive_packets.encode_packet(broken, n0, broken.vertex_count)
    with pytest.raises(PacketError) as ours:
        encode_packet(broken, n0, broken.vertex_count)
    assert str(ours.value) == str(reference.value)
    assert "does not hold vertex" in str(ours.value)


@pytest.mark.parametrize("size", [0, 1, 2, 5, 16, 17, 40, 300])
def test_kernel_sorts_and_searches(size):
    rng = np.random.default_rng(size)
    keys = rng.integers(0, max(size // 2, 1), size).astype(np.int64)
    a = keys.copy()
    corners.sort_prefix(a, size)
    assert np.array_equal(a, np.sort(keys))
    order = np.full(size, -1, dtype=np.int64)
    corners.argsort_prefix(keys, size, order)
    assert np.array_equal(np.sort(order), np.arange(size))
    assert np.all(np.diff(keys[order]) >= 0)
    for x in range(-1, max(size // 2, 1) + 1):
        assert corners.search(a, size, x) == np.searchsorted(a, x)
        found = np.nonzero(keys == x)[0]
        expected = -1 if len(found) == 0 else -2 if len(found) > 1 else found[0]
        assert corners.lookup(keys, order, size, x) == expected


@pytest.mark.parametrize("name", ["conrod.stl", "office_chair.obj", "non_manif_hole.ply",
                                  "soup.stl", "joined_tetrahedra.obj", "brain.ply", "Duck.glb",
                                  "bunny10k_textured/bunny10k_textured.obj"])
def test_compiled_encoder_writes_the_reference_bytes_on_shared_meshes(shared_meshes, name):
    pm = progressive(name)
    n0, n = pm.base_vertices, pm.vertex_count
    middle = (n0 + n) // 2
    _assert_same_bytes(pm, [(n0, n), (n, n0), (middle, n), (n, middle), (middle, min(n0 + 1, n))],
                       bits_options=(None,))
    near = min(n0 + 1, n)
    for a, b in [(n0, n), (n, n0), (middle, n), (n, middle), (middle, near), (near, middle)]:
        ours, direct = packet_between(pm, a, b), encode_packet(pm, a, b)
        if abs(b - a) < packets.CHUNK_RECORDS:
            assert ours == direct, (a, b)
        assert decode_packet(ours).streams == decode_packet(direct).streams, (a, b)


def test_compiled_encoder_writes_the_reference_bytes_on_the_stanford_bunny(shared_meshes):
    """The measured case (docs/packets.md): the full packet each way, 34,819 records."""
    pm = progressive("stanford-bunny.obj")
    n0, n = pm.base_vertices, pm.vertex_count
    _assert_same_bytes(pm, [(n0, n), (n, n0), (n // 3, 2 * n // 3)], bits_options=(None,))
    # the server's cut of the same packets: the same body, pre-deflated chunks cost < 1%
    for a, b in [(n0, n), (n, n0), (n // 3, 2 * n // 3), (n - 1, n0 + 2)]:
        ours, direct = packet_between(pm, a, b), encode_packet(pm, a, b)
        assert decode_packet(ours).streams == decode_packet(direct).streams
        assert len(ours) < 1.01 * len(direct)


def test_background_encoder_starts_on_first_use_and_shuts_down():
    """Importing the package starts no thread; prepare_records starts one worker,
    shutdown_background stops it, and a later preparation starts another."""
    import subprocess
    import sys

    code = ("import threading, lodserver.packets; "
            "print(sorted(t.name for t in threading.enumerate()))")
    names = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           check=True).stdout
    assert "packet-records" not in names
    pm = build(input_mesh("torus"))

    def workers():
        return [t for t in threading.enumerate() if t.name.startswith("packet-records")]

    packets.shutdown_background()
    assert not workers()
    packets.prepare_records(pm)
    assert len(workers()) == 1
    deadline = time.monotonic() + 120
    while not packets.records_ready(pm):
        assert time.monotonic() < deadline, "the packet records were not prepared"
        time.sleep(0.05)
    packets.shutdown_background()
    assert not workers()
    packets.prepare_records(pm)         # scheduled again: a new worker, records already there
    assert len(workers()) == 1
    packets.shutdown_background()
    assert not workers()
