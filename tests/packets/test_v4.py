"""Version 4 packets (docs/packets.md, "Version 4"): exact between any two levels both
ways, for every attribute, with every combination of codings and with batch runs;
compositions land where the direct packet does; a damaged packet is a PacketError.

The property everywhere: applying the decoded packet A -> B (``decode_v4``, then
``reference.apply_packet``) to the quantized form of level A gives, bit for bit, the
quantized form of level B: positions, faces, wedge values, corner wedges, materials.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lodserver import build
from lodserver.packets import (
    PacketError,
    apply_packet,
    encode_packet,
    grid_of,
    quantized_level,
)
from lodserver.packets import rans
from lodserver.packets.decode_v4 import decode_any, decode_packet_v4
from lodserver.packets.encode_v4 import DEFAULT_FLAGS, encode_packet_v4
from lodserver.packets.format import EDGE_POSITIONS, MAGNITUDE_CONTEXTS, RING_POSITIONS, Reader
from lodserver.packets.streams_v4 import from_edge, to_edge

from ..meshes import mesh as input_mesh
from .test_attributes import _built as every_attribute_pm
from .test_packets import _book, _flipped_torus, _same, _with_materials

ALL_FLAGS = (0, EDGE_POSITIONS, MAGNITUDE_CONTEXTS, EDGE_POSITIONS | MAGNITUDE_CONTEXTS,
             EDGE_POSITIONS | RING_POSITIONS, EDGE_POSITIONS | MAGNITUDE_CONTEXTS | RING_POSITIONS)
# The position codings the exactness properties run with: the default, and the
# split edge alone and predicted from the ring (whichever of them the default is).
POSITION_FLAGS = tuple(dict.fromkeys((DEFAULT_FLAGS, EDGE_POSITIONS,
                                      EDGE_POSITIONS | RING_POSITIONS)))


@cache
def _pm(name):
    if name.endswith("+batched"):         # the same mesh built with its splits in batches
        from lodserver.progressive.batches import schedule
        return schedule(_pm(name.removesuffix("+batched"))).pm
    if name == "every_attribute":
        return every_attribute_pm()
    if name == "book":
        return build(_book())
    if name == "flipped_torus":
        return build(_flipped_torus())
    if name == "materials":
        return build(_with_materials())
    return build(input_mesh(name))


def _state(pm, level, bits=None):
    return quantized_level(pm, level, grid_of(pm, bits=bits))


def _check(pm, a, b, bits=None, **kw):
    """The v4 packet a -> b decodes onto level b exactly; returns its bytes."""
    data = encode_packet_v4(pm, a, b, bits=bits, **kw)
    _same(apply_packet(_state(pm, a, bits), decode_packet_v4(data)), _state(pm, b, bits))
    return data


GENERATED = ["spot", "torus", "grid", "two_boxes", "icosphere", "textured_sphere", "book",
             "flipped_torus", "materials", "every_attribute"]


@pytest.mark.parametrize("flags", POSITION_FLAGS)
@pytest.mark.parametrize("name", GENERATED)
def test_base_to_full_and_back_are_exact(name, flags):
    pm = _pm(name)
    n0, n = pm.base_vertices, pm.vertex_count
    for a, b in ((n0, n), (n, n0), ((n0 + n) // 2, n0 + 1), (n0 + 1, n - 1)):
        _check(pm, a, b, flags=flags)


@pytest.mark.parametrize("name", ["spot", "every_attribute", "materials"])
def test_every_level_is_exact_both_ways_with_the_ring(name):
    # every split and every collapse of the mesh, in about 150 chained packets each
    # way, each landing checked: each ring prediction reads the state the packets
    # before it left
    pm = _pm(name)
    n0, n = pm.base_vertices, pm.vertex_count
    flags = EDGE_POSITIONS | RING_POSITIONS
    step = max(1, (n - n0) // 150)
    state = _state(pm, n0)
    for a in range(n0, n, step):
        b = min(n, a + step)
        state = apply_packet(state, decode_packet_v4(encode_packet_v4(pm, a, b, flags=flags)))
        _same(state, _state(pm, b))
    for a in range(n, n0, -step):
        b = max(n0, a - step)
        state = apply_packet(state, decode_packet_v4(encode_packet_v4(pm, a, b, flags=flags)))
        _same(state, _state(pm, b))


def test_the_ring_needs_the_edge():
    pm = _pm("spot")
    n0 = pm.base_vertices
    with pytest.raises(ValueError, match="EDGE_POSITIONS"):
        encode_packet_v4(pm, n0, n0 + 10, flags=RING_POSITIONS)
    data = bytearray(encode_packet_v4(pm, n0, n0 + 10, flags=EDGE_POSITIONS | RING_POSITIONS))
    data[7] &= ~EDGE_POSITIONS                      # the header's flags byte
    import struct
    import zlib
    data[-4:] = struct.pack("<I", zlib.crc32(bytes(data[:-4])))
    with pytest.raises(PacketError, match="ring"):
        decode_packet_v4(bytes(data))


def test_the_ring_saves_bytes_on_a_real_mesh():
    pm = _pm("spot")
    n0, n = pm.base_vertices, pm.vertex_count
    edge = encode_packet_v4(pm, n0, n, flags=EDGE_POSITIONS)
    ring = encode_packet_v4(pm, n0, n, flags=EDGE_POSITIONS | RING_POSITIONS)
    assert len(ring) < len(edge)
    # collapses carry no split edge: the flag changes only the header's flags byte
    back = encode_packet_v4(pm, n, n0, flags=EDGE_POSITIONS)
    back_ring = encode_packet_v4(pm, n, n0, flags=EDGE_POSITIONS | RING_POSITIONS)
    assert len(back) == len(back_ring) and back[8:-4] == back_ring[8:-4]


@pytest.mark.parametrize("flags", ALL_FLAGS)
def test_every_coding_is_exact(flags):
    for name in ("spot", "every_attribute"):
        pm = _pm(name)
        n0, n = pm.base_vertices, pm.vertex_count
        _check(pm, n0, n, flags=flags)
        _check(pm, n, n0, flags=flags)


@settings(max_examples=30, deadline=None)
@given(st.data())
def test_any_levels_and_compositions_land_on_the_level(data):
    pm = _pm(data.draw(st.sampled_from(["spot", "every_attribute", "materials", "book"])))
    levels = st.integers(pm.base_vertices, pm.vertex_count)
    a, b, c = data.draw(levels), data.draw(levels), data.draw(levels)
    bits = data.draw(st.sampled_from([None, 10, 14]))
    flags = data.draw(st.sampled_from(POSITION_FLAGS))
    _check(pm, a, c, bits=bits, flags=flags)
    # a -> b -> c lands on the state of the direct packet a -> c
    state = apply_packet(_state(pm, a, bits), decode_packet_v4(
        encode_packet_v4(pm, a, b, bits=bits, flags=flags)))
    state = apply_packet(state, decode_packet_v4(encode_packet_v4(pm, b, c, bits=bits,
                                                                  flags=flags)))
    _same(state, _state(pm, c, bits))


def test_segments_start_at_fixed_records(monkeypatch):
    from lodserver.packets import encode_v4
    monkeypatch.setattr(encode_v4, "SEGMENT_RECORDS", 64)
    pm = _pm("every_attribute")
    n0, n = pm.base_vertices, pm.vertex_count
    for a, b in ((n0, n), (n, n0), (n0 + 30, n - 7), (n - 3, n0 + 65)):
        _check(pm, a, b)


def _ascending_runs(pm, longest):
    """A batch id per split: consecutive splits share one while their vs ascend (at
    most ``longest`` per batch). It exercises the coding; independence is the
    schedule's business, not the coder's."""
    s = pm.parent[pm.base_vertices:]
    ids = np.zeros(len(s), dtype=np.int64)
    size = 1
    for i in range(1, len(s)):
        same = s[i] > s[i - 1] and size < longest
        ids[i] = ids[i - 1] + (0 if same else 1)
        size = size + 1 if same else 1
    return ids


@pytest.mark.parametrize("longest", [1, 3, 1000])
def test_batch_runs_decode_to_the_same_splits(longest):
    pm = _pm("spot")
    n0, n = pm.base_vertices, pm.vertex_count
    batch = _ascending_runs(pm, longest)
    for a, b in ((n0, n), (n0 + 5, n - 9), (n, n0)):
        _check(pm, a, b, batch=batch)


@pytest.mark.parametrize("name", ["spot+batched", "every_attribute+batched", "materials+batched"])
def test_a_batched_build_codes_its_own_schedule(name):
    # encode_packet_v4 and packet_between_v4 take the mesh's schedule by default:
    # runs of gaps, exact both ways, and fewer bytes than one batch per split
    from lodserver.packets.records_v4 import packet_between_v4
    pm = _pm(name)
    n0, n = pm.base_vertices, pm.vertex_count
    assert pm.split_batch is not None and pm.split_batch[-1] + 1 < n - n0
    for a, b in ((n0, n), (n, n0), (n0 + 5, n - 9), ((n0 + n) // 2, n0 + 1)):
        data = _check(pm, a, b)
        assert packet_between_v4(pm, a, b) == data
    one_each = encode_packet_v4(pm, n0, n, batch=np.arange(n - n0))
    assert len(_check(pm, n0, n)) < len(one_each)


def test_a_batch_with_descending_vertices_is_refused():
    pm = _pm("spot")
    with pytest.raises(ValueError, match="ascending"):
        encode_packet_v4(pm, pm.base_vertices, pm.vertex_count,
                         batch=np.zeros(pm.vertex_count - pm.base_vertices, dtype=np.int64))
    with pytest.raises(ValueError, match="non-decreasing"):
        encode_packet_v4(pm, pm.base_vertices, pm.vertex_count, batch=np.zeros(3))


@pytest.mark.parametrize("flags", POSITION_FLAGS)
@pytest.mark.parametrize("name", ["stanford-bunny.obj", "Duck.glb"])
def test_shared_meshes_are_exact(shared_meshes, name, flags):
    pm = _pm(name)
    n0, n = pm.base_vertices, pm.vertex_count
    for a, b in ((n0, min(n, n0 + 3000)), (n, max(n0, n - 3000)), (n - 500, n0 + 200)):
        for bits in (None, 14):
            _check(pm, a, b, bits=bits, flags=flags)


@pytest.mark.parametrize("scene", ["Fox.glb", "AnimatedMorphCube.glb"])
def test_skinned_and_morphed_scene_meshes_are_exact(shared_meshes, scene):
    from lodserver.io.scene import load_scene
    from lodserver.simplify.poses import scene_poses
    loaded = load_scene(shared_meshes / "scenes" / scene)
    for index, mesh in loaded.meshes.items():
        pm = build(mesh, poses=scene_poses(loaded, index, mesh))
        n0, n = pm.base_vertices, pm.vertex_count
        for a, b in ((n0, n), (n, n0), ((n0 + n) // 2, n0 + 1)):
            for flags in POSITION_FLAGS:
                _check(pm, a, b, flags=flags)


def test_decode_any_reads_every_version():
    pm = _pm("spot")
    n0 = pm.base_vertices
    for data in (encode_packet(pm, n0, n0 + 40), encode_packet_v4(pm, n0, n0 + 40)):
        _same(apply_packet(_state(pm, n0), decode_any(data)), _state(pm, n0 + 40))


def test_empty_packet_is_the_identity():
    pm = _pm("spot")
    _check(pm, 100, 100)


@cache
def _some_packet(flags=DEFAULT_FLAGS):
    pm = _pm("every_attribute")
    return pm, encode_packet_v4(pm, pm.base_vertices + 3, pm.vertex_count - 20, flags=flags)


def _apply(pm, data):
    return apply_packet(_state(pm, pm.base_vertices + 3), decode_packet_v4(data))


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_a_truncated_or_damaged_packet_is_a_packet_error(data):
    pm, packet = _some_packet(data.draw(st.sampled_from(POSITION_FLAGS)))
    damaged = bytearray(packet)
    if data.draw(st.booleans()):
        damaged = damaged[:data.draw(st.integers(0, len(packet) - 1))]
    else:
        at = data.draw(st.integers(0, len(packet) - 1))
        damaged[at] ^= data.draw(st.integers(1, 255))
    with pytest.raises(PacketError):
        _apply(pm, bytes(damaged))


@settings(max_examples=100, deadline=None)
@given(st.data())
def test_damage_behind_a_valid_checksum_is_still_a_packet_error_or_exact(data):
    """A packet damaged on purpose, with its checksum made to match: the decoder
    ends (no hang) with a PacketError, or applies it to a state (a damaged value can
    still be a valid record); it never raises anything else."""
    import struct
    import zlib
    pm, packet = _some_packet(data.draw(st.sampled_from(POSITION_FLAGS)))
    damaged = bytearray(packet[:-4])
    at = data.draw(st.integers(0, len(damaged) - 1))
    damaged[at] ^= data.draw(st.integers(1, 255))
    damaged += struct.pack("<I", zlib.crc32(bytes(damaged)))
    try:
        _apply(pm, bytes(damaged))
    except PacketError:
        pass


# ---- the coder -----------------------------------------------------------------------
@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 2**44 - 1) | st.integers(0, 40), st.integers(0, 3)),
                max_size=300))
def test_rans_round_trips_any_integers(items):
    values = np.array([v for v, _ in items], dtype=np.int64)
    ctx = np.array([c for _, c in items], dtype=np.int64)
    out = bytearray()
    rans.encode_symbols(out, values, ctx, 4)
    reader = Reader(bytes(out), "test")
    assert rans.decode_symbols(reader, 4, lambda i, _: int(ctx[i])) == values.tolist()
    assert reader.done()
    if len(items):
        with pytest.raises(PacketError):
            rans.decode_symbols(Reader(bytes(out[:-1]), "test"), 4, lambda i, _: int(ctx[i]))


def test_rans_codes_near_the_entropy():
    rng = np.random.default_rng(1)
    p = np.array([0.6, 0.25, 0.1, 0.05])
    values = rng.choice(4, size=50_000, p=p)
    out = bytearray()
    rans.encode_symbols(out, values, np.zeros(len(values), dtype=np.int64), 1)
    entropy = -(p * np.log2(p)).sum() * len(values) / 8
    # within 3%: the model reserves 1/4096 for each of the 96 buckets (2.3% of the range)
    assert len(out) < 1.03 * entropy + 64


def test_rans_refuses_values_it_cannot_code():
    with pytest.raises(ValueError):
        rans.encode_symbols(bytearray(), np.array([2**44]), np.zeros(1, dtype=np.int64), 1)
    with pytest.raises(ValueError):
        rans.encode_symbols(bytearray(), np.array([-1]), np.zeros(1, dtype=np.int64), 1)


@given(st.lists(st.lists(st.integers(-5000, 5000), min_size=6, max_size=6), max_size=50))
def test_the_split_edge_is_an_exact_rewrite(rows):
    d = np.array(rows, dtype=np.int64).reshape(-1, 6)
    e = to_edge(d)
    assert np.all((e[:, 3] >= 0) & (e[:, 3] <= 16))
    assert np.array_equal(from_edge(e), d)


@settings(max_examples=30, deadline=None)
@given(st.data())
def test_packets_cut_from_kept_segments_are_the_encoded_packets(data):
    from lodserver.packets import encode_v4
    from lodserver.packets.records_v4 import packet_between_v4
    pm = _pm(data.draw(st.sampled_from(["every_attribute", "materials", "spot+batched"])))
    size = data.draw(st.sampled_from([64, 8192]))
    flags = data.draw(st.sampled_from(POSITION_FLAGS))
    levels = st.integers(pm.base_vertices, pm.vertex_count)
    a, b = data.draw(levels), data.draw(levels)
    original = encode_v4.SEGMENT_RECORDS, encode_v4.DEFAULT_FLAGS
    encode_v4.SEGMENT_RECORDS, encode_v4.DEFAULT_FLAGS = size, flags
    try:
        # twice: the second cuts from the segments the first kept
        for _ in range(2):
            assert packet_between_v4(pm, a, b) == encode_packet_v4(pm, a, b, flags=flags)
    finally:
        encode_v4.SEGMENT_RECORDS, encode_v4.DEFAULT_FLAGS = original
