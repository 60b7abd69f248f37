// Reading a version 4 packet (docs/packets.md, "Version 4"): the checksum, then
// the body's segments of rANS-coded symbols (rans.js), each symbol in the
// context its stream's rule gives, turned back into version 3's streams of
// varints and bytes. packet.js's readPacket() hands a version 4 packet here,
// and its result is the structure it gives for version 3, so LodState.apply()
// runs the records unchanged: they are version 3's. The reference is
// lodserver/packets/decode_v4.py (and streams_v4.py for the contexts). With
// RING_POSITIONS a split's positions need the state after its faces: the
// packet's position stream is then empty and its `positionReader(state)` gives
// the reader LodState.apply() reads them through (ringpositions.js).

import { makeReader, PacketError, streamNames } from './packet.js';
import { SymbolReader } from './rans.js';
import { edgeSymbols, ringPositions } from './ringpositions.js';

const HAS_MATERIALS = 1, EDGE_POSITIONS = 2, MAGNITUDE_CONTEXTS = 4, RING_POSITIONS = 8;
const FLAGS = HAS_MATERIALS | EDGE_POSITIONS | MAGNITUDE_CONTEXTS | RING_POSITIONS;
const HEADER_BYTES = 60, CRC_BYTES = 4;
// Stream indices in version 3's order (the v4 body puts `batch` before them).
const VERTEX = 0, COUNT = 1, PATTERN = 2, FAN = 4, MASK = 5, POSITION = 6;
const BYTE_STREAMS = [PATTERN, FAN, MASK];
const CLASSES = 8;                  // magnitude classes of a classed context
const PLACES = 16;                  // the split edge's places, in 16ths
const PLACE_COLUMN = 3;             // the place is not zigzagged
const PATTERNS = 27;                // 3 codes per corner, 3 corners
const RUN_CONTEXTS = 2, FACE_CONTEXTS = PATTERNS + 1;
// A damaged packet's work is bounded by its records: at most this many symbols per
// record and this many more in any stream but the position's.
const SYMBOLS_PER_RECORD = 64, SYMBOLS_SLACK = 2 ** 16;
// Varint bytes of a symbol (below 2^44), and of any value the split edge can give
// from symbols (below 2^90).
const SYMBOL_VARINT_BYTES = 7, VARINT_BYTES = 13;

// ---- the checksum ----------------------------------------------------------------

const CRC_TABLE = new Int32Array(256);
for (let n = 0; n < 256; n++) {
  let c = n;
  for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1;
  CRC_TABLE[n] = c;
}

// CRC-32 (IEEE 802.3, zlib's crc32) of `bytes`, unsigned.
function crc32(bytes) {
  let c = -1;
  for (let i = 0; i < bytes.length; i++) c = CRC_TABLE[(c ^ bytes[i]) & 255] ^ (c >>> 8);
  return (c ^ -1) >>> 0;
}

// The packet without its trailing CRC-32, once it matches: a truncated or damaged
// packet is refused before anything is decoded.
export function withoutChecksum(bytes) {
  if (bytes.length < HEADER_BYTES + CRC_BYTES) {
    throw new PacketError(`the packet is truncated: ${bytes.length} bytes is shorter than ` +
                          'the header');
  }
  const end = bytes.length - CRC_BYTES;
  const stored = (bytes[end] | (bytes[end + 1] << 8) | (bytes[end + 2] << 16) |
                  (bytes[end + 3] << 24)) >>> 0;
  if (stored !== crc32(bytes.subarray(0, end))) {
    throw new PacketError("the packet's checksum does not match: it is damaged or truncated");
  }
  return bytes.subarray(0, end);
}

// ---- version 3 streams -------------------------------------------------------------

// A growing byte buffer: one version 3 stream being rewritten.
class StreamWriter {
  constructor() {
    this.data = new Uint8Array(1024);
    this.length = 0;
  }

  reserve(extra) {
    if (this.length + extra <= this.data.length) return;
    const bigger = new Uint8Array(Math.max(2 * this.data.length, this.length + extra));
    bigger.set(this.data.subarray(0, this.length));
    this.data = bigger;
  }

  // Every value of `values`, as varints: one reservation, the loop on locals.
  varints(values) {
    this.reserve(SYMBOL_VARINT_BYTES * values.length);
    const { data } = this;
    let n = this.length;
    for (let i = 0; i < values.length; i++) {
      const v = values[i];
      if (v < 128) data[n++] = v;
      else n = putVarint(data, n, v);
    }
    this.length = n;
  }

  view() {
    return this.data.subarray(0, this.length);
  }
}

// `v` as a varint into data[n ..]; returns its end.
function putVarint(data, n, v) {
  while (v >= 0x80000000) {
    data[n++] = (v % 128) | 128;
    v = Math.floor(v / 128);
  }
  while (v >= 128) {
    data[n++] = (v & 127) | 128;
    v >>>= 7;
  }
  data[n++] = v;
  return n;
}

// `d` zigzagged, as version 3's signed varints.
function putSigned(data, n, d) {
  return putVarint(data, n, d >= 0 ? 2 * d : -2 * d - 1);
}

function unzigzag(u) {
  return u % 2 === 0 ? u / 2 : -(u + 1) / 2;
}

// The class of a symbol: 0 below 8, then one per power of two, the last 512 and more.
function magnitudeClass(v) {
  if (v < 8) return 0;
  if (v >= 512) return CLASSES - 1;
  return 31 - Math.clz32(v) - 2;
}

// ---- the body ----------------------------------------------------------------------

// How each stream's symbols get their contexts (streams_v4.py's Shape): `period`
// symbols to a group, `classed` by magnitude, `runs` the vertex stream of splits,
// `faces` the pattern stream of splits.
function shapes(packet, forward, flags) {
  const classed = (flags & MAGNITUDE_CONTEXTS) !== 0;
  const shape = (period = 1, withClasses = false, runs = false, faces = false) => ({
    period, classed: withClasses, runs, faces,
    contexts: runs ? RUN_CONTEXTS : faces ? FACE_CONTEXTS
      : period * (withClasses ? CLASSES : 1),
  });
  const out = [shape(), shape(1, false, forward), shape(), shape(1, false, false, forward),
               shape(), shape(), shape(),
               shape(forward ? (flags & EDGE_POSITIONS ? 7 : 6) : 3, classed)];
  if (packet.attributes.length) {
    out.push(shape(), shape(), shape());
    for (const a of packet.attributes) out.push(shape((forward ? 2 : 1) * a.components, classed));
  }
  if (packet.hasMaterials) out.push(shape());
  return out;
}

// The version 3 streams (Uint8Array, in streamNames() order) of a version 4 body,
// for the packet whose header readPacket() parsed; `bodyLength` is the header's.
// A split packet with RING_POSITIONS also gets packet.positionReader.
export function readBodyV4(body, bodyLength, packet, flags) {
  if (flags & ~FLAGS) throw new PacketError(`the packet sets unknown flags (${flags})`);
  if (flags & RING_POSITIONS && !(flags & EDGE_POSITIONS)) {
    throw new PacketError('the packet predicts the split edge from the ring (flag 8) without ' +
                          'coding the edge (flag 2)');
  }
  if (body.length !== bodyLength) {
    throw new PacketError(`the packet's body is ${body.length} bytes, the header says ` +
                          `${bodyLength}`);
  }
  const forward = packet.stop > packet.start;
  const records = Math.abs(packet.stop - packet.start);
  const names = ['batch', ...streamNames(packet.attributes, packet.hasMaterials)];
  const layout = shapes(packet, forward, flags);
  const out = names.slice(1).map(() => new StreamWriter());
  // with the ring: every split's symbols E - P, l, r, resolved as it is applied
  const edges = forward && flags & RING_POSITIONS ? [] : null;
  const table = makeReader(body, 'segment table');
  const segments = table.varint();
  let done = 0;
  for (let i = 0; i < segments; i++) {
    const size = table.varint();
    if (!(size > 0 && size <= records - done)) {
      throw new PacketError("the packet's segments do not add up to its records");
    }
    const decoded = readSegment(table, names, layout, size, forward);
    if (edges) {
      edges.push(edgeSymbols(decoded[1 + POSITION]));
      decoded[1 + POSITION] = [];
    }
    writeFields(decoded, out, forward ? packet.start + done : -1, flags);
    done += size;
  }
  if (done !== records || table.at !== body.length) {
    throw new PacketError("the packet's segments do not add up to its records");
  }
  if (edges) packet.positionReader = ringPositions(edges, packet.start);
  return out.map((writer) => writer.view());
}

// Every stream of one segment of `size` records, as arrays of symbols.
function readSegment(table, names, layout, size, forward) {
  const decoded = [];
  for (let k = 0; k < names.length; k++) {
    const shape = layout[k], name = names[k];
    const stream = new SymbolReader(table, shape.contexts, name);
    const count = stream.count;
    if (k === 1 + POSITION) {
      if (count !== size * shape.period) {
        throw new PacketError(`the packet's ${name} stream holds ${count} symbols for ` +
                              `${size} records`);
      }
    } else if (count > SYMBOLS_PER_RECORD * size + SYMBOLS_SLACK) {
      throw new PacketError(`the packet's ${name} stream holds more symbols than its ` +
                            'records can read');
    }
    const values = symbolArray(count, name);
    if (shape.runs) {
      if (count !== size) {
        throw new PacketError("the packet's vertex stream does not hold one gap per split");
      }
      readGaps(stream, decoded[0], values);
    } else if (shape.faces) {
      readPatterns(stream, decoded[1 + COUNT], values);
    } else if (shape.classed) {
      readClassed(stream, shape.period, values);
    } else {
      const { period } = shape;
      for (let i = 0, j = 0; i < count; i++) {
        values[i] = stream.read(j);
        if (++j === period) j = 0;
      }
    }
    stream.done();
    if (k === 0) {
      if (!forward && count) {
        throw new PacketError("the packet's batch stream holds runs, but it collapses");
      }
      if (forward) checkRuns(values, size);
    }
    decoded.push(values);
  }
  return decoded;
}

// Room for a stream's symbols: a damaged count can ask for more than a browser
// will allocate (rans.js bounds it by the stream's bytes, not below that).
function symbolArray(count, name) {
  try {
    return new Float64Array(count);
  } catch {
    throw new PacketError(`the packet's ${name} stream holds more symbols (${count}) than ` +
                          'can be decoded here');
  }
}

// The batch runs (lengths less one) must cover the segment's splits exactly.
function checkRuns(runs, size) {
  let covered = 0;
  for (const length of runs) {
    covered += 1 + length;
    if (covered > size) {
      throw new PacketError("the packet's batch runs hold more splits than its segment");
    }
  }
  if (covered !== size) throw new PacketError("the packet's batch runs do not cover its segment");
}

// One gap per split, in context 0 for the first of its run and 1 for the others
// (the runs walked as they go: a damaged segment size allocates nothing here).
function readGaps(stream, runs, values) {
  for (let i = 0, run = 0, left = 0; i < values.length; i++) {
    let context = 1;
    if (left === 0) {
      left = runs[run++] + 1;
      context = 0;
    }
    values[i] = stream.read(context);
    left--;
  }
}

// Patterns, each in the context of its place: 0 for a record's first new face,
// 1 + p after a face of pattern p.
function readPatterns(stream, counts, values) {
  let total = 0;
  for (const faces of counts) total += faces;
  if (stream.count !== total) {
    throw new PacketError("the packet's pattern stream does not hold one pattern per new face");
  }
  let i = 0;
  for (const faces of counts) {
    for (let f = 0; f < faces; f++, i++) {
      const p = stream.read(f === 0 ? 0 : 1 + values[i - 1]);
      if (p >= PATTERNS) throw new PacketError(`the packet holds a pattern above ${PATTERNS - 1}`);
      values[i] = p;
    }
  }
}

// A classed stream: symbol j of a group in context 8 j + the class of the largest
// symbol before it in its group, or for the first, of the whole previous group.
function readClassed(stream, period, values) {
  let group = 0, previous = 0;
  for (let i = 0, j = 0; i < values.length; i++) {
    let v;
    if (j === 0) {
      previous = i ? group : 0;
      group = 0;
      v = stream.read(magnitudeClass(previous));
    } else {
      v = stream.read(j * CLASSES + magnitudeClass(group));
    }
    values[i] = v;
    if (v > group) group = v;
    if (++j === period) j = 0;
  }
}

// Append one segment's fields to the version 3 streams: the batch runs' gaps back
// to vertex codes (`t0`, its first new vertex; -1 for collapses), the split edge
// back to d1, d2.
function writeFields(decoded, out, t0, flags) {
  for (let k = 0; k < out.length; k++) {
    const values = decoded[k + 1], writer = out[k];
    if (k === VERTEX && t0 >= 0) {
      writeVertexCodes(decoded[0], values, t0, writer);
    } else if (k === POSITION && t0 >= 0 && flags & EDGE_POSITIONS) {
      writeEdgePositions(values, writer);
    } else if (BYTE_STREAMS.includes(k)) {
      writer.reserve(values.length);
      const { data } = writer;
      let n = writer.length;
      for (let i = 0; i < values.length; i++) {
        if (values[i] > 255) {
          throw new PacketError('the packet holds a pattern, fan or mask symbol above 255');
        }
        data[n++] = values[i];
      }
      writer.length = n;
    } else {
      writer.varints(values);
    }
  }
}

// Version 3's vertex codes t - 1 - vs from the runs: a run's first gap is its vs,
// each next one vs - previous vs - 1.
function writeVertexCodes(runs, gaps, t0, writer) {
  writer.reserve(SYMBOL_VARINT_BYTES * gaps.length);
  const { data } = writer;
  let n = writer.length, i = 0;
  for (const length of runs) {
    let s = -1;
    for (let k = 0; k <= length; k++, i++) {
      s = k === 0 ? gaps[i] : s + 1 + gaps[i];
      const t = t0 + i;
      if (s >= t) throw new PacketError(`split ${t} names vertex ${s}, which does not exist yet`);
      n = putVarint(data, n, t - 1 - s);
    }
  }
  writer.length = n;
}

// Per split: the edge E (3, zigzagged), the place l, the rest r (3, zigzagged);
// d1 = r - floor((l E + 8) / 16), d2 = E + 2 d1, written zigzagged.
function writeEdgePositions(symbols, writer) {
  writer.reserve(VARINT_BYTES * 6 * (symbols.length / 7));
  const { data } = writer;
  let n = writer.length;
  for (let at = 0; at < symbols.length; at += 7) {
    const place = symbols[at + PLACE_COLUMN];
    const ex = unzigzag(symbols[at]), ey = unzigzag(symbols[at + 1]),
          ez = unzigzag(symbols[at + 2]);
    const x = moved(symbols[at + 4], place, ex), y = moved(symbols[at + 5], place, ey),
          z = moved(symbols[at + 6], place, ez);
    n = putSigned(data, n, x);
    n = putSigned(data, n, y);
    n = putSigned(data, n, z);
    n = putSigned(data, n, ex + 2 * x);
    n = putSigned(data, n, ey + 2 * y);
    n = putSigned(data, n, ez + 2 * z);
  }
  writer.length = n;
}

// d1 on one axis from its rest symbol, the place and the edge.
function moved(rest, place, edge) {
  return unzigzag(rest) - Math.floor((place * edge + PLACES / 2) / PLACES);
}
