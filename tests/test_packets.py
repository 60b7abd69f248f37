"""Vsplit packets: exact round trips between levels, compactness, and clear errors."""

import struct
import zlib
from itertools import pairwise

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lodserver.packets import (
    FAN,
    MAGIC,
    PacketError,
    _put_varint,
    _Reader,
    _zigzag,
    apply_packet,
    decode_packet,
    default_bits,
    encode_packet,
    grid_of,
    quantized_level,
)

from .meshes import progressive


def _same(a, b):
    assert a.level == b.level
    assert np.array_equal(a.positions, b.positions)
    assert np.array_equal(a.faces, b.faces)


def test_varints_and_zigzag_by_hand():
    out = bytearray()
    for value in (0, 1, 127, 128, 300, 2**35):
        _put_varint(out, value)
    assert bytes(out[:5]) == b"\x00\x01\x7f\x80\x01"
    assert bytes(out[5:7]) == b"\xac\x02"  # 300 = 0b10_0101100
    reader = _Reader(bytes(out), "test")
    assert [reader.varint() for _ in range(6)] == [0, 1, 127, 128, 300, 2**35]
    assert [_zigzag(v) for v in (0, -1, 1, -2, 2)] == [0, 1, 2, 3, 4]
    out = bytearray()
    for v in (0, -1, 1, -2, 2, -1000, 1000):
        _put_varint(out, _zigzag(v))
    reader = _Reader(bytes(out), "test")
    assert [reader.signed() for _ in range(7)] == [0, -1, 1, -2, 2, -1000, 1000]


def test_grid_rounds_to_within_half_a_step():
    pm = progressive("torus")
    grid = grid_of(pm, bits=12)
    q = grid.quantize(pm.positions)
    assert q.min() >= 0 and q.max() <= 2**12 - 1
    assert np.abs(grid.dequantize(q) - pm.positions).max() <= grid.step / 2 + 1e-12
    assert default_bits(pm) == grid_of(pm).bits


@pytest.mark.parametrize("name", ["spot", "torus", "grid", "two_boxes", "icosphere"])
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
    pm = progressive("spot")
    n0, n = pm.base_vertices, pm.vertex_count
    data = encode_packet(pm, n0, n)
    packet = decode_packet(data)
    assert packet.records == n - n0 and set(packet.streams[FAN]) == {0}
    # 9.3 bytes per split at the default 12 bits (docs/packets.md); OpenMesh's record is 24
    assert len(data) / (n - n0) < 10
    assert len(encode_packet(pm, n, n0)) / (n - n0) < 4


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
