"""The browser's version 4 decoder (static/packet_v4.js, static/rans.js) in headless
Chromium: a Python-encoded version 4 packet, read by ``readPacket`` and applied by
``LodState.apply`` to the json level state, lands byte for byte (positions, faces,
wedges, corner wedges, face materials) on the state the Python reference decoder
gives (``decode_v4``, ``reference.apply_packet``) and on the state the browser's
version 3 path gives; a damaged or truncated packet is a ``PacketError``.

The page is served from the repository's ``static/`` through Playwright's request
routing (no server process); results come back as SHA-256 digests of each array's
bytes, compared with the digests of the reference's arrays in the same dtypes.
"""

from __future__ import annotations

import base64
import hashlib
import struct
import zlib
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from lodserver import build
from lodserver.packets import (
    PacketError,
    apply_packet,
    encode_packet,
    grid_of,
    quantized_level,
)
from lodserver.packets.decode_v4 import decode_packet_v4
from lodserver.packets.encode_v4 import encode_packet_v4
from lodserver.packets.format import (
    EDGE_POSITIONS, MAGNITUDE_CONTEXTS, RING_POSITIONS, Reader, stream_names,
)

from ..meshes import mesh as input_mesh
from ..packets.test_attributes import _built as every_attribute_pm
from ..packets.test_v4 import _ascending_runs

STATIC = Path(__file__).resolve().parents[2] / "static"
ORIGIN = "http://localhost:8765"   # localhost: a secure context, for crypto.subtle
TYPES = {".js": "text/javascript", ".html": "text/html", ".css": "text/css"}
E, M, R = EDGE_POSITIONS, MAGNITUDE_CONTEXTS, RING_POSITIONS
SHARED = Path(__file__).resolve().parents[3] / "shared" / "meshes"

# The state's arrays as the browser keeps them (levelstate.js), by the Python
# LodState's field: the dtype its bytes are compared in.
ARRAYS = {"positions": "<i4", "faces": "<u4", "wedges": "<i4", "corners": "<u4",
          "face_material": "<i4"}

APPLY_JS = """async ({ document, capacity, chains }) => {
  const { LodState } = await import('/vsplit.js');
  const bytesOf = (b64) => Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
  const digest = async (array, count) => {
    const bytes = new Uint8Array(array.buffer, array.byteOffset, 4 * count);
    const hash = new Uint8Array(await crypto.subtle.digest('SHA-256', bytes));
    return Array.from(hash, (b) => b.toString(16).padStart(2, '0')).join('');
  };
  const snapshot = async (state) => {
    const k = state.components || 0;
    const out = {
      level: state.vertexCount,
      positions: await digest(state.positions, 3 * state.vertexCount),
      faces: await digest(state.faces, 3 * state.faceCount),
    };
    if (state.attributes.length) {
      out.wedges = await digest(state.wedges, k * state.wedgeCount);
      out.corners = await digest(state.corners, 3 * state.faceCount);
    }
    if (state.faceMaterial) out.face_material = await digest(state.faceMaterial, state.faceCount);
    return out;
  };
  const results = [];
  for (const packets of chains) {
    const state = LodState.fromJson(document, capacity);
    const reached = [];
    for (const packet of packets) {
      try {
        state.apply(await LodState.readPacket(bytesOf(packet)));
        reached.push(await snapshot(state));
      } catch (error) {
        reached.push({ error: error.name, message: error.message });
        break;
      }
    }
    results.push(reached);
  }
  return results;
}"""

# Each damaged packet read, then applied to a fresh state: what readPacket gave (a
# PacketError, or the digest of each field: the values of a version 3 stream, as
# float64) and what apply gave (a PacketError, or the digest of the positions reached).
DAMAGED_JS = """async ({ document, capacity, packets }) => {
  const { LodState } = await import('/vsplit.js');
  const bytesOf = (b64) => Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
  const hex = async (bytes) => Array.from(
    new Uint8Array(await crypto.subtle.digest('SHA-256', bytes)),
    (b) => b.toString(16).padStart(2, '0')).join('');
  const out = [];
  for (const packet of packets) {
    let read;
    try {
      read = await LodState.readPacket(bytesOf(packet));
    } catch (error) {
      out.push({ read: error.name, message: error.message });
      continue;
    }
    const streams = [];
    for (const field of read.fields) {
      streams.push(await hex(new Uint8Array(field.buffer, field.byteOffset, field.byteLength)));
    }
    const state = LodState.fromJson(document, capacity);
    try {
      state.apply(read);
      out.push({ streams, applied: await hex(new Uint8Array(state.positions.buffer, 0,
                                                            12 * state.vertexCount)) });
    } catch (error) {
      out.push({ streams, applied: error.name, message: error.message });
    }
  }
  return out;
}"""


@pytest.fixture(scope="module")
def page(chromium):
    """A page of the fake origin whose every request is answered from ``static/``."""
    page = chromium.new_page()

    def answer(route):
        path = route.request.url[len(ORIGIN):].split("?")[0].lstrip("/") or "index.html"
        file = (STATIC / path).resolve()
        if STATIC not in file.parents or not file.is_file():
            route.fulfill(status=404, body="not found")
            return
        route.fulfill(status=200, body=file.read_bytes(),
                      headers={"Content-Type": TYPES.get(file.suffix, "application/octet-stream")})

    page.route(f"{ORIGIN}/**", answer)
    page.goto(f"{ORIGIN}/packet.js")
    yield page
    page.close()


# ---- meshes -----------------------------------------------------------------------

def _shared(name):
    if not (SHARED / name).exists():
        pytest.skip(f"shared mesh {name} not found under {SHARED}")
    return SHARED / name


def _scene_pm(name, index=None):
    from lodserver.io.scene import load_scene
    from lodserver.simplify.poses import scene_poses
    loaded = load_scene(_shared(f"scenes/{name}"))
    index = index if index is not None else next(iter(loaded.meshes))
    mesh = loaded.meshes[index]
    return build(mesh, poses=scene_poses(loaded, index, mesh))


@cache
def _pm(name):
    if name.endswith("+batched"):         # built with its splits in batches: coded as runs
        from lodserver.progressive.batches import schedule
        return schedule(_pm(name.removesuffix("+batched"))).pm
    if name == "every_attribute":
        return every_attribute_pm()
    if name in ("Fox.glb", "AnimatedMorphCube.glb"):
        return _scene_pm(name)
    if name != "spot":
        _shared(name)
    return build(input_mesh(name))


def _document(pm, level):
    """The json level document as the server serves it (``/lod?format=json``)."""
    import orjson

    from lodserver.service.levels import encode_level
    return orjson.loads(bytes(encode_level(pm, level, file_type="json")))


def _digests(state):
    out = {"level": int(state.level)}
    for name, dtype in ARRAYS.items():
        array = getattr(state, name)
        if array is not None:
            out[name] = hashlib.sha256(np.ascontiguousarray(array, dtype=dtype).tobytes()).hexdigest()
    return out


def _b64(data):
    return base64.b64encode(bytes(data)).decode()


def _run(page, pm, steps):
    """Apply the chain ``steps`` ((a, b, flags, batch), each starting where the last
    ended) as v4 packets and as v3 packets in the browser; both land, step by step,
    on the states the Python reference decoder reaches."""
    grid = grid_of(pm)
    start = quantized_level(pm, steps[0][0], grid)
    capacity = {"vertexCapacity": pm.vertex_count, "faceCapacity": int(pm.face_counts[-1])}
    v4, v3, expected = [], [], []
    state = start
    for a, b, flags, batch in steps:
        assert state.level == a
        data = encode_packet_v4(pm, a, b, flags=flags, batch=batch)
        state = apply_packet(state, decode_packet_v4(data))
        expected.append(_digests(state))
        v4.append(_b64(data))
        v3.append(_b64(encode_packet(pm, a, b)))
    by_v4, by_v3 = page.evaluate(APPLY_JS, {"document": _document(pm, steps[0][0]),
                                            "capacity": capacity, "chains": [v4, v3]})
    for i, (step, want) in enumerate(zip(steps, expected)):
        assert by_v4[i] == want, f"v4 step {i} {step[:3]}: {by_v4[i]}"
        assert by_v3[i] == want, f"v3 step {i} {step[:3]}: {by_v3[i]}"
        # the reference itself lands on the level's quantized form
        assert want == _digests(quantized_level(pm, step[1], grid))


def _chain(pm, flag_cycle=(E | R, E, 0, E | M | R, E | M, M)):
    """Base -> full -> base, then mid levels both ways, the flags cycling."""
    n0, n = pm.base_vertices, pm.vertex_count
    levels = [n0, n, n0, (n0 + n) // 2, n0 + 1, n - 1, (n0 + 2 * n) // 3, n0]
    return [(a, b, flag_cycle[i % len(flag_cycle)], None)
            for i, (a, b) in enumerate(zip(levels, levels[1:]))]


@pytest.mark.parametrize("name", ["spot", "stanford-bunny.obj", "Duck.glb", "Fox.glb",
                                  "AnimatedMorphCube.glb", "every_attribute",
                                  "every_attribute+batched"])
def test_v4_packets_land_where_the_reference_and_v3_do(page, name):
    pm = _pm(name)
    _run(page, pm, _chain(pm))


def test_every_flag_combination_both_ways(page):
    pm = _pm("spot")
    n0, n = pm.base_vertices, pm.vertex_count
    steps = []
    for flags in (0, E, M, E | M, E | R, E | M | R):
        steps += [(n0, n, flags, None), (n, n0, flags, None)]
    _run(page, pm, steps)


@pytest.mark.parametrize("longest", [1, 3, 1000])
def test_batch_runs(page, longest):
    pm = _pm("spot")
    n0, n = pm.base_vertices, pm.vertex_count
    batch = _ascending_runs(pm, longest)
    steps = [(n0, n, E, batch), (n, n0 + 5, E, batch), (n0 + 5, n - 9, E | M, batch),
             (n - 9, n0, 0, batch), (n0, n, E | R, batch)]
    _run(page, pm, steps)


def test_segments_of_a_long_packet(page):
    """Packets past 8192 records come in several segments (bunny: 34819 splits)."""
    pm = _pm("stanford-bunny.obj")
    n0, n = pm.base_vertices, pm.vertex_count
    assert n - n0 > 2 * 8192
    _run(page, pm, [(n0, n0 + 8191, E, None), (n0 + 8191, n, M | E, None),
                    (n, n0 + 8193, E, None), (n0 + 8193, n, E | R, None)])


# ---- damage ---------------------------------------------------------------------------

@cache
def _damage_subject(flags=None):
    pm = _pm("every_attribute")
    a, b = pm.base_vertices + 3, pm.vertex_count - 20
    grid = grid_of(pm)
    state = quantized_level(pm, a, grid)
    capacity = {"vertexCapacity": pm.vertex_count, "faceCapacity": int(pm.face_counts[-1])}
    return pm, state, _document(pm, a), capacity, encode_packet_v4(pm, a, b, flags=flags)


def _field(stream, name):
    """A version 3 stream's values as the browser's packet holds them (a field,
    packet.js): its bytes, or its varints, as float64."""
    if name in ("pattern", "fan", "mask"):
        values = list(stream)
    else:
        reader, values = Reader(stream, name), []
        while not reader.done():
            values.append(reader.varint())
    return np.array(values, dtype="<f8").tobytes()


def _python_outcome(state, data):
    """What the reference gives: ("PacketError", None) when decode_packet_v4 refuses,
    else (its fields' digests, "PacketError" or the positions' digest after apply)."""
    try:
        packet = decode_packet_v4(data)
    except PacketError:
        return "PacketError", None
    names = stream_names(packet.attribute_grids, packet.has_materials)
    streams = [hashlib.sha256(_field(s, name)).hexdigest()
               for s, name in zip(packet.streams, names)]
    try:
        reached = apply_packet(state, packet)
    except PacketError:
        return streams, "PacketError"
    return streams, hashlib.sha256(np.ascontiguousarray(reached.positions, "<i4").tobytes()
                                   ).hexdigest()


@pytest.mark.parametrize("flags", [None, E | R])
def test_damaged_or_truncated_packets_are_packet_errors(page, flags):
    """Random truncations and byte flips (seeded): the checksum refuses every one, as a
    PacketError and nothing else."""
    pm, state, document, capacity, packet = _damage_subject(flags)
    rng = np.random.default_rng(4)
    damaged = []
    for _ in range(300):
        data = bytearray(packet)
        if rng.random() < 0.5:
            data = data[:rng.integers(0, len(packet))]
        else:
            data[rng.integers(0, len(packet))] ^= int(rng.integers(1, 256))
        assert _python_outcome(state, bytes(data)) == ("PacketError", None)
        damaged.append(_b64(data))
    outcomes = page.evaluate(DAMAGED_JS, {"document": document, "capacity": capacity,
                                          "packets": damaged})
    assert [o.get("read") for o in outcomes] == ["PacketError"] * len(damaged), \
        [o for o in outcomes if o.get("read") != "PacketError"][:3]


@pytest.mark.parametrize("flags", [None, E | R])
def test_damage_behind_a_valid_checksum_decodes_as_the_reference_does(page, flags):
    """Byte flips with the checksum made to match reach the symbol decoder: each ends
    (no hang) in a PacketError exactly when the reference decoder refuses it, and
    otherwise in the reference's version 3 streams' values, stream for stream. Applied, those
    give a PacketError whenever the reference's apply does, or else the reference's
    state or a PacketError (LodState checks every record's values against their grids
    as it goes; the reference checks the state it ends on). With the ring (``E | R``)
    the positions resolve as the records apply, in both."""
    pm, state, document, capacity, packet = _damage_subject(flags)
    rng = np.random.default_rng(44)
    damaged, expected = [], []
    for _ in range(200):
        data = bytearray(packet[:-4])
        data[rng.integers(0, len(data))] ^= int(rng.integers(1, 256))
        data += struct.pack("<I", zlib.crc32(bytes(data)))
        damaged.append(_b64(data))
        expected.append(_python_outcome(state, bytes(data)))
    outcomes = page.evaluate(DAMAGED_JS, {"document": document, "capacity": capacity,
                                          "packets": damaged})
    read = [o.get("read") or o["streams"] for o in outcomes]
    wrong = [(i, outcomes[i]) for i in range(len(read)) if read[i] != expected[i][0]]
    assert not wrong, wrong[:3]
    for i, outcome in enumerate(outcomes):
        if "applied" in outcome:
            allowed = {"PacketError", expected[i][1]}
            assert outcome["applied"] in allowed, (i, outcome, expected[i][1])
    refused = sum(o.get("read") == "PacketError" for o in outcomes)
    assert 0 < refused < len(outcomes)      # both kinds of outcome were exercised


def _varint(n):
    out = bytearray()
    while n >= 128:
        out.append(n & 127 | 128)
        n >>= 7
    out.append(n)
    return bytes(out)


def test_a_symbol_count_past_what_its_bytes_code_is_a_packet_error(page):
    """A checksum-valid packet declaring 2^32 - 1 - A records and a batch stream of
    more symbols than its bytes can code (2^36 or 5000 in 8 bytes) is refused before
    anything is allocated for them; one of 10^6 in 4 KiB, within that bound, ends
    inside a symbol. Each is a PacketError, as the reference's outcome is."""
    pm, state, document, capacity, packet = _damage_subject()
    header = bytearray(packet[:60])
    start = struct.unpack_from("<I", header, 8)[0]
    struct.pack_into("<I", header, 12, 2**32 - 1)
    crafted = []
    for count, size in ((2**36, 8), (10**6, 2**12), (5000, 8)):
        body = (_varint(1) + _varint(2**32 - 1 - start) + _varint(count) + _varint(size)
                + struct.pack("<I", 2**30) + bytes(size - 4))
        struct.pack_into("<I", header, 56, len(body))
        data = bytes(header) + packet[60:60 + (len(packet) - 64 - struct.unpack_from(
            "<I", packet, 56)[0])] + body
        data += struct.pack("<I", zlib.crc32(data))
        assert _python_outcome(state, data) == ("PacketError", None)
        crafted.append(_b64(data))
    outcomes = page.evaluate(DAMAGED_JS, {"document": document, "capacity": capacity,
                                          "packets": crafted})
    assert [o.get("read") for o in outcomes] == ["PacketError"] * len(crafted), outcomes


def test_one_batch_run_over_a_huge_declared_segment_is_a_packet_error(page):
    """A checksum-valid packet declaring 2^32 - 1 - A records in one segment, its batch
    stream one run over all of them (a valid coded symbol), then a short vertex
    stream: a PacketError, with nothing allocated per declared split, in the
    browser as in the reference."""
    from lodserver.packets.rans import encode_symbols

    pm, state, document, capacity, packet = _damage_subject()
    header = bytearray(packet[:60])
    start = struct.unpack_from("<I", header, 8)[0]
    size = 2**32 - 1 - start
    struct.pack_into("<I", header, 12, 2**32 - 1)
    body = bytearray(_varint(1) + _varint(size))
    encode_symbols(body, np.array([size - 1]), np.zeros(1, dtype=np.int64), 1)
    body += _varint(5) + _varint(8) + struct.pack("<I", 2**30) + bytes(4)
    struct.pack_into("<I", header, 56, len(body))
    records = packet[60:len(packet) - 4 - struct.unpack_from("<I", packet, 56)[0]]
    data = bytes(header) + records + bytes(body)
    data += struct.pack("<I", zlib.crc32(data))
    assert _python_outcome(state, data) == ("PacketError", None)
    outcome, = page.evaluate(DAMAGED_JS, {"document": document, "capacity": capacity,
                                          "packets": [_b64(data)]})
    assert outcome.get("read") == "PacketError", outcome
    assert "vertex stream" in outcome["message"], outcome
