"""Packets and json levels carry every vertex attribute of ``mesh.ATTRIBUTE_RULES``.

The meshes here carry TANGENT, JOINTS_0/WEIGHTS_0, two morph targets (positions, and
normals for one), TEXCOORD_2 and custom ``_ID`` values, built through ``lodserver.build``
(the carried columns interpolated along every collapse). The property: decoding the
packets from level A to level B, forward and backward, gives exactly the quantized
form of level B (integers), for every attribute; the compiled encoder writes the
readable encoder's bytes; the grids follow their rules (docs/packets.md,
"Attribute grids").
"""

import struct
import threading
import zlib
from dataclasses import replace
from functools import cache
from itertools import pairwise

import numpy as np
import orjson
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lodserver import build, packets
from lodserver.mesh import Attributes, Mesh
from lodserver.packets import (
    MIN_BITS,
    PacketError,
    apply_packet,
    attribute_grids_of,
    decode_packet,
    encode_packet,
    grid_of,
    packet_between,
    quantized_level,
    state_from_json,
)
from lodserver.packets.format import HEADER
from lodserver.service.levels import encode_level

from .. import naive_packets
from ..meshes import skinned_sphere
from .test_packets import _same

LAYOUT_NAMES = ["NORMAL", "TEXCOORD_0", "TANGENT", "JOINTS_0", "WEIGHTS_0", "TARGET0_POSITION",
                "TARGET1_POSITION", "_BAND", "TEXCOORD_2", "TARGET1_NORMAL", "_ID"]


def every_attribute_mesh(nu=32, nv=16) -> Mesh:
    """``tests.meshes.skinned_sphere`` (tangent, skin, two morph targets, ``_BAND``) plus
    TEXCOORD_2 (the UVs scaled and turned), TARGET1_NORMAL (the lift target's normal
    delta) and a custom ``_ID`` of width 2 (an integer band and a smooth value); the
    joints are renumbered to 37, 300 and 1000 so their grid needs 10 bits."""
    base = skinned_sphere(nu, nv)
    a = base.attributes
    p = base.positions[base.wedge_vertices()]
    uv = a.values[:, a.columns("TEXCOORD_0")]
    values = a.values.copy()
    joints = values[:, a.columns("JOINTS_0")]
    values[:, a.columns("JOINTS_0")] = np.choose(joints.astype(int), [37.0, 300.0, 1000.0])
    uv2 = np.stack([2 * uv[:, 1], 3 * uv[:, 0] - 1], axis=1)
    normal_delta = np.stack([np.zeros(len(p)), 0.2 * p[:, 0] * (p[:, 2] > 0),
                             -0.1 * np.clip(p[:, 2], 0, 1)], axis=1)
    ident = np.stack([np.floor((p[:, 2] + 1) * 3), p[:, 0] * p[:, 1]], axis=1)
    layout = a.layout + (("TEXCOORD_2", 2), ("TARGET1_NORMAL", 3), ("_ID", 2))
    return Mesh(base.positions, base.faces,
                Attributes(layout, np.concatenate([values, uv2, normal_delta, ident], 1),
                           a.corners))


@cache
def _built(nu=32, nv=16):
    return build(every_attribute_mesh(nu, nv))


def _levels(pm):
    n0, n = pm.base_vertices, pm.vertex_count
    return sorted({n0, n0 + 1, (n0 + n) // 3, (n0 + n) // 2, n - 1, n})


def test_the_mesh_carries_every_kind_of_attribute():
    pm = _built()
    assert [name for name, _ in pm.attribute_layout] == LAYOUT_NAMES
    grids = attribute_grids_of(pm)
    assert [g.name for g in grids] == LAYOUT_NAMES
    assert [g.components for g in grids] == [2, 2, 3, 4, 4, 3, 3, 1, 2, 3, 2]
    assert [g.width for g in grids] == [3, 2, 4, 4, 4, 3, 3, 1, 2, 3, 2]


def test_forward_and_back_reproduce_every_attribute_exactly():
    pm = _built()
    grid = grid_of(pm)
    levels = _levels(pm)
    for a, b in zip(levels, levels[::-1]):
        start = quantized_level(pm, a, grid)
        data = encode_packet(pm, a, b)
        assert data[4] == 3
        there = apply_packet(start, data)
        _same(there, quantized_level(pm, b, grid))
        _same(apply_packet(there, encode_packet(pm, b, a)), start)


@settings(max_examples=20, deadline=None)
@given(st.data())
def test_any_chain_of_packets_lands_on_the_level_with_every_attribute(data):
    pm = _built()
    grid = grid_of(pm)
    level = st.integers(pm.base_vertices, pm.vertex_count)
    path = data.draw(st.lists(level, min_size=2, max_size=4))
    state = quantized_level(pm, path[0], grid)
    for a, b in pairwise(path):
        state = apply_packet(state, packet_between(pm, a, b))
        _same(state, quantized_level(pm, b, grid))


@settings(max_examples=15, deadline=None)
@given(st.data())
def test_compiled_encoder_writes_the_reference_bytes_for_every_attribute(data):
    pm = _built(16, 8)
    level = st.integers(pm.base_vertices, pm.vertex_count)
    a, b = data.draw(level), data.draw(level)
    bits = data.draw(st.sampled_from([None, 10]))
    attribute_bits = data.draw(st.sampled_from([None, {"TANGENT": 8, "TARGET0_POSITION": 12,
                                                       "_ID": 9, "JOINTS_0": 11}]))
    assert encode_packet(pm, a, b, bits=bits, attribute_bits=attribute_bits) == \
        naive_packets.encode_packet(pm, a, b, bits=bits, attribute_bits=attribute_bits)


def test_json_levels_carry_every_attribute_and_packets_apply_to_them():
    """The LOD endpoint's json form, read back as a client does (state_from_json),
    is the quantized level, and a packet takes it to the next json level exactly."""
    pm = _built()
    levels = _levels(pm)
    for a, b in zip(levels, levels[::-1]):
        document = orjson.loads(bytes(encode_level(pm, a, file_type="json")))
        assert [name for name, _ in document["layout"]] == LAYOUT_NAMES
        assert document["attribute_grid"]["TANGENT"]["encoding"] == "tangent"
        assert document["layout"][-1] == ["_ID", 2]
        state = state_from_json(document)
        _same(state, quantized_level(pm, a, grid_of(pm)))
        there = apply_packet(state, packet_between(pm, a, b))
        _same(there, state_from_json(orjson.loads(bytes(encode_level(pm, b, file_type="json")))))


def test_grids_follow_their_rules():
    pm = _built()
    grids = {g.name: g for g in attribute_grids_of(pm)}
    layout = dict(pm.attribute_layout)
    columns, start = {}, 0
    for name, width in pm.attribute_layout:
        columns[name] = slice(start, start + width)
        start += width
    values = np.concatenate([pm.wedge_values, pm.wedge_coarse_value])

    def round_trip(name):
        g = grids[name]
        q = g.quantize(values[:, columns[name]])
        assert q.shape == (len(values), g.components)
        assert q.min() >= 0 and q.max() <= 2**g.bits - 1
        return q, g.dequantize(q)

    # joints: exact integers, origin 0, step 1, enough bits for joint 1000
    joints = grids["JOINTS_0"]
    assert (joints.encoding, joints.origin, joints.step, joints.bits) == \
        ("linear", (0.0,) * 4, 1.0, 10)
    q, back = round_trip("JOINTS_0")
    np.testing.assert_array_equal(back, values[:, columns["JOINTS_0"]])
    assert set(np.unique(q)) <= {0, 37, 300, 1000}
    # weights: [0, 1] at 12 bits, within half a step, sums stay near 1
    weights = grids["WEIGHTS_0"]
    assert (weights.origin, weights.bits) == ((0.0,) * 4, 12)
    assert weights.step == 1 / 4095
    _, back = round_trip("WEIGHTS_0")
    assert np.abs(back - values[:, columns["WEIGHTS_0"]]).max() <= weights.step / 2 + 1e-12
    # tangent: xyz octahedral as a normal, the handedness exact
    tangent = grids["TANGENT"]
    assert (tangent.encoding, tangent.bits, tangent.origin) == ("tangent", 10, (-1.0,) * 3)
    q, back = round_trip("TANGENT")
    exact = values[:, columns["TANGENT"]]
    assert set(np.unique(q[:, 2])) == {0, 1}
    np.testing.assert_array_equal(back[:, 3], exact[:, 3])
    xyz = exact[:, :3] / np.linalg.norm(exact[:, :3], axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip((back[:, :3] * xyz).sum(axis=1), -1, 1)))
    assert angle.max() < 0.25
    # morph position deltas: the mean full-detail edge spans at least 2**7 steps
    edge = packets.mean_edge(pm)
    for name in ("TARGET0_POSITION", "TARGET1_POSITION"):
        g = grids[name]
        assert g.encoding == "linear" and MIN_BITS <= g.bits <= packets.MAX_BITS
        assert g.step <= edge / 2**packets.MORPH_EDGE_BITS
        if g.bits > MIN_BITS:   # and no more bits than that needs
            extent = g.step * (2**g.bits - 1)
            assert extent / (2**(g.bits - 1) - 1) > edge / 2**packets.MORPH_EDGE_BITS
        _, back = round_trip(name)
        assert np.abs(back - values[:, columns[name]]).max() <= g.step / 2 + 1e-12
    # linear over their range: UVs 12 bits, morph normal deltas 10, customs 16
    for name, bits in (("TEXCOORD_0", 12), ("TEXCOORD_2", 12), ("TARGET1_NORMAL", 10),
                       ("_ID", 16), ("_BAND", 16)):
        g = grids[name]
        assert (g.encoding, g.bits, g.width) == ("linear", bits, layout[name])
        _, back = round_trip(name)
        assert np.abs(back - values[:, columns[name]]).max() <= g.step / 2 + 1e-12
    # defaults are by rule, overridable per name; joints refuse too few bits
    assert packets.default_attribute_bits("TEXCOORD_7") == 12
    assert packets.default_attribute_bits("COLOR_3") == 10
    assert packets.default_attribute_bits("_ANYTHING") == 16
    assert packets.default_attribute_bits("JOINTS_1") is None
    assert {g.name: g.bits for g in attribute_grids_of(pm, attribute_bits={
        "TANGENT": 12, "TARGET1_POSITION": 14})}["TARGET1_POSITION"] == 14
    with pytest.raises(ValueError, match="JOINTS_0 needs 10 bits"):
        attribute_grids_of(pm, attribute_bits={"JOINTS_0": 9})


def _header_records(data):
    """The attribute records of a version 3 packet: [(name, width, encoding, bits, step,
    origin)], and where the body starts."""
    fields = HEADER.unpack_from(data)
    at, records = HEADER.size, []
    for _ in range(fields[3]):
        size = data[at]
        name = data[at + 1:at + 1 + size].decode()
        width, encoding, bits, step = struct.unpack_from("<BBBd", data, at + 1 + size)
        at += 1 + size + 11
        components = {1: 2, 2: 3}.get(encoding, width)
        origin = struct.unpack_from(f"<{components}d", data, at)
        at += 8 * components
        records.append((name, width, encoding, bits, step, origin))
    return records, at


def test_the_header_names_every_attribute():
    """docs/packets.md, "Byte layout": each record is the name's length, the ASCII name,
    width, encoding, bits, step and the origin, read here independently of format.py."""
    pm = _built(16, 8)
    data = encode_packet(pm, pm.base_vertices, pm.vertex_count)
    records, at = _header_records(data)
    assert [r[0] for r in records] == LAYOUT_NAMES
    grids = attribute_grids_of(pm)
    assert [(r[1], r[3], r[4], r[5]) for r in records] == \
        [(g.width, g.bits, g.step, g.origin) for g in grids]
    assert [r[2] for r in records] == [1, 0, 2, 0, 0, 0, 0, 0, 0, 0, 0]
    assert len(zlib.decompress(data[at:])) == HEADER.unpack_from(data)[-1]


def _v2(data):
    """A version 3 packet of NORMAL/TEXCOORD_0/TEXCOORD_1/COLOR_0 rewritten as the
    version 2 packet of the same body (kind codes in place of names)."""
    records, at = _header_records(data)
    kinds = {"NORMAL": 0, "TEXCOORD_0": 1, "TEXCOORD_1": 2, "COLOR_0": 3}
    out = bytearray(data[:HEADER.size])
    out[4] = 2
    for name, _, encoding, bits, step, origin in records:
        out += struct.pack("<BBBBd", kinds[name], encoding, bits, 0, step)
        out += struct.pack(f"<{len(origin)}d", *origin)
    return bytes(out) + data[at:]


def test_version_2_packets_with_attributes_still_decode():
    from ..meshes import progressive
    pm = progressive("textured_sphere")
    grid = grid_of(pm)
    n0, n = pm.base_vertices, pm.vertex_count
    start = quantized_level(pm, n0, grid)
    data = encode_packet(pm, n0, n)
    old = _v2(data)
    assert old[4] == 2 and len(old) == len(data) - len("NORMAL") - len("TEXCOORD_0")
    _same(apply_packet(start, old), quantized_level(pm, n, grid))


def _with_record(data, mutate):
    """``data`` with its first attribute record's (name bytes, width, encoding, bits)
    replaced by ``mutate`` of them."""
    size = data[HEADER.size]
    name = data[HEADER.size + 1:HEADER.size + 1 + size]
    at = HEADER.size + 1 + size
    new_name, width, encoding, bits = mutate(name, data[at], data[at + 1], data[at + 2])
    return (data[:HEADER.size] + bytes([len(new_name)]) + new_name
            + bytes([width, encoding, bits]) + data[at + 3:])


@pytest.mark.parametrize("mutate, message", [
    (lambda n, w, e, b: (b"", w, e, b), "name of 0 bytes"),
    (lambda n, w, e, b: (b"N" * 65, w, e, b), "name of 65 bytes"),
    (lambda n, w, e, b: (b"NORM\x01L", w, e, b), "not printable ASCII"),
    (lambda n, w, e, b: (b"NORMALS", w, e, b), "unknown attribute 'NORMALS'"),
    (lambda n, w, e, b: (n, 4, e, b), "NORMAL' has 3 components, got 4"),
    (lambda n, w, e, b: (n, w, 7, b), "unknown encoding"),
    (lambda n, w, e, b: (n, w, 2, b), "only TANGENT can be"),
    (lambda n, w, e, b: (n, w, e, 0), "0 bits"),
    (lambda n, w, e, b: (b"TEXCOORD_0", 2, 0, b), "names an attribute twice"),
    (lambda n, w, e, b: (b"_ID", 9, e, b), "custom attribute '_ID' must have 1 to 4"),
])
def test_bad_attribute_records_are_a_packet_error(mutate, message):
    from ..meshes import progressive
    pm = progressive("textured_sphere")
    data = encode_packet(pm, pm.base_vertices, pm.base_vertices + 20)
    with pytest.raises(PacketError, match=message):
        decode_packet(_with_record(data, mutate))
    with pytest.raises(PacketError, match="truncated in its attribute records"):
        decode_packet(data[:HEADER.size + 5])


def test_more_attribute_records_than_the_packet_holds_is_a_packet_error():
    """The record count is a byte (at most 255, format.MAX_ATTRIBUTES): a count past the
    records present runs into the body and is refused, not misread."""
    pm = _built(16, 8)
    data = bytearray(encode_packet(pm, pm.base_vertices, pm.base_vertices + 5))
    data[6] = 255
    with pytest.raises(PacketError):
        decode_packet(bytes(data))


def test_a_handedness_off_plus_or_minus_one_is_a_packet_error():
    """A packet that leaves a tangent's handedness at 2 (on the 10-bit grid, but not
    -1 or +1) is refused: applied to a state whose handedness was moved by one."""
    pm = _built(16, 8)
    grid = grid_of(pm)
    n0, n = pm.base_vertices, pm.vertex_count
    state = quantized_level(pm, n, grid)
    column = sum(g.components for g in state.attribute_grids[:2]) + 2
    wedges = state.wedges.copy()
    wedges[:, column] += 1        # 0 -> 1, 1 -> 2
    with pytest.raises(PacketError, match="handedness"):
        apply_packet(replace(state, wedges=wedges), encode_packet(pm, n, n0))


def test_attribute_packets_stay_compact():
    """The carried attributes add bytes per split in proportion to what they hold:
    measured here so a regression in their prediction shows."""
    pm = _built()
    n0, n = pm.base_vertices, pm.vertex_count
    forward = len(encode_packet(pm, n0, n)) / (n - n0)
    backward = len(encode_packet(pm, n, n0)) / (n - n0)
    assert forward < 60 and backward < 40, (forward, backward)


@cache
def _chunked():
    """The every-attribute mesh of its own, its records pre-deflated in chunks of 16."""
    pm = build(every_attribute_mesh(16, 8))
    for forward in (True, False):
        packets.record_cache.setdefault(pm, {})[forward] = [
            threading.Lock(), packets.record_streams(pm, forward=forward, chunk=16)]
    return pm


@settings(max_examples=20, deadline=None)
@given(st.data())
def test_packets_cut_from_chunked_records_carry_every_attribute(data):
    """The server's packets (slices of the records encoded once, chained from
    pre-deflated chunks) are the encoded packets' streams and land on the level."""
    pm = _chunked()
    level = st.integers(pm.base_vertices, pm.vertex_count)
    a, b = data.draw(level), data.draw(level)
    ours, direct = packet_between(pm, a, b), encode_packet(pm, a, b)
    assert decode_packet(ours).streams == decode_packet(direct).streams
    grid = grid_of(pm)
    _same(apply_packet(quantized_level(pm, a, grid), ours), quantized_level(pm, b, grid))
