// Reading a version 4 packet (docs/packets.md, "Version 4"): the checksum, then
// the body's segments of rANS-coded symbols (rans.js), each symbol in the
// context its stream's rule gives, turned back into the values of version 3's
// streams (its fields: the varints and bytes a version 3 packet holds, as
// numbers). packet.js's readPacket() hands a version 4 packet here, and its
// result is the structure it gives for version 3, so LodState.apply() runs the
// records unchanged: they are version 3's. The reference is
// lodserver/packets/decode_v4.py (and streams_v4.py for the contexts). With
// RING_POSITIONS a split's positions need the state after its faces: the
// packet's position field is then empty and its `positionReader(state)` gives
// the reader LodState.apply() reads them through (ringpositions.js).

import { BYTE_STREAMS, makeReader, PacketError, streamNames } from './packet.js';
import {
  CLASSED, CLASSES, FACES, MAX_SYMBOLS_PER_BYTE, PATTERNS, PLAIN, RUNS, SymbolReader,
} from './rans.js';
import { edgeSymbols, ringPositions } from './ringpositions.js';

const HAS_MATERIALS = 1, EDGE_POSITIONS = 2, MAGNITUDE_CONTEXTS = 4, RING_POSITIONS = 8;
const FLAGS = HAS_MATERIALS | EDGE_POSITIONS | MAGNITUDE_CONTEXTS | RING_POSITIONS;
const HEADER_BYTES = 60, CRC_BYTES = 4;
// Stream indices in version 3's order (the v4 body puts `batch` before them).
const VERTEX = 0, COUNT = 1, POSITION = 6;
const PLACES = 16;                  // the split edge's places, in 16ths
const PLACE_COLUMN = 3;             // the place is not zigzagged
const RUN_CONTEXTS = 2, FACE_CONTEXTS = PATTERNS + 1;
// A damaged packet's work is bounded by its records: at most this many symbols per
// record and this many more in any stream but the position's.
const SYMBOLS_PER_RECORD = 64, SYMBOLS_SLACK = 2 ** 16;

const NO_AUX = new Float64Array(0);    // decode()'s aux for the rules without one

// ---- the checksum ----------------------------------------------------------------

// Four tables (slicing by 4): CRC_TABLE[256 k + n] is byte n's CRC followed by k
// zero bytes, so four bytes are folded in with four independent lookups.
const CRC_TABLE = new Int32Array(4 * 256);
for (let n = 0; n < 256; n++) {
  let c = n;
  for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1;
  CRC_TABLE[n] = c;
}
for (let n = 0; n < 256; n++) {
  for (let k = 1; k < 4; k++) {
    const c = CRC_TABLE[256 * (k - 1) + n];
    CRC_TABLE[256 * k + n] = CRC_TABLE[c & 255] ^ (c >>> 8);
  }
}

// CRC-32 (IEEE 802.3, zlib's crc32) of `bytes`, unsigned.
function crc32(bytes) {
  const t = CRC_TABLE;
  let c = -1, i = 0;
  for (const end = bytes.length - 3; i < end; i += 4) {
    c ^= bytes[i] | (bytes[i + 1] << 8) | (bytes[i + 2] << 16) | (bytes[i + 3] << 24);
    c = t[768 + (c & 255)] ^ t[512 + ((c >>> 8) & 255)] ^ t[256 + ((c >>> 16) & 255)] ^
        t[c >>> 24];
  }
  for (; i < bytes.length; i++) c = t[(c ^ bytes[i]) & 255] ^ (c >>> 8);
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

// ---- the fields ---------------------------------------------------------------------

// One field, filled segment by segment: allocated once at its size (symbolCounts).
class Field {
  constructor(size, name) {
    this.values = allocate(size, name);
    this.length = 0;
  }

  // The next `count` values' room (a view), counted as filled.
  append(count) {
    const end = this.length + count;
    const room = this.values.subarray(this.length, end);
    this.length = end;
    return room;
  }
}

// The symbols each stream holds over all segments, and the most in one segment: a
// pass over the segment table that skips the coded bytes, so that every field and
// scratch array is allocated once. It stops, without an error, at the first stream
// whose table entry is malformed (cut short, or a count its bytes cannot code):
// decoding reaches the same entry after the ones counted here and refuses it, with
// its own message and nothing allocated for it.
function symbolCounts(body, streams) {
  const table = makeReader(body, 'segment table');
  const totals = new Float64Array(streams), largest = new Float64Array(streams);
  try {
    const segments = table.varint();
    for (let i = 0; i < segments; i++) {
      table.varint();
      for (let k = 0; k < streams; k++) {
        const count = table.varint();
        if (count > 0) {
          const bytes = table.varint();
          if (count > MAX_SYMBOLS_PER_BYTE * bytes) return { totals, largest };
          table.bytes(bytes);
        }
        totals[k] += count;
        if (count > largest[k]) largest[k] = count;
      }
    }
  } catch (error) {
    if (!(error instanceof PacketError)) throw error;
  }
  return { totals, largest };
}

// Room for a stream's values: a damaged count can ask for more than a browser will
// allocate (rans.js bounds it by the stream's bytes, not below that).
function allocate(count, name) {
  try {
    return new Float64Array(count);
  } catch {
    throw new PacketError(`the packet's ${name} stream holds more symbols (${count}) than ` +
                          'can be decoded here');
  }
}

// Even u is u / 2, odd u is -(u + 1) / 2, in float operations that are exact for
// integers (% on a float is a slow library call).
function unzigzag(u) {
  const half = u / 2, floor = Math.floor(half);
  return floor === half ? half : -(floor + 1);
}

function zigzag(d) {
  return d >= 0 ? 2 * d : -2 * d - 1;
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

// The fields (Float64Array, in streamNames() order: version 3's values) of a
// version 4 body, for the packet whose header readPacket() parsed; `bodyLength` is
// the header's. A split packet with RING_POSITIONS also gets packet.positionReader.
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
  const { totals, largest } = symbolCounts(body, names.length);
  const edges = forward && flags & EDGE_POSITIONS;
  // with the ring, every split's seven signed symbols (E - P, l, r), resolved as
  // it is applied; the position field stays empty
  const ring = edges && flags & RING_POSITIONS
    ? { values: allocate(totals[1 + POSITION], names[1 + POSITION]), at: 0 } : null;
  const out = names.slice(1).map((name, k) => new Field(
    k === POSITION && edges ? (ring ? 0 : 6 * (totals[k + 1] / 7)) : totals[k + 1], name));
  // scratch for one segment: its runs, gaps, and positions before they are turned back
  const scratch = { runs: allocate(largest[0], names[0]),
                    gaps: allocate(forward ? largest[1 + VERTEX] : 0, names[1 + VERTEX]),
                    edges: allocate(edges ? largest[1 + POSITION] : 0, names[1 + POSITION]),
                    ring };
  const table = makeReader(body, 'segment table');
  const segments = table.varint();
  let done = 0;
  for (let i = 0; i < segments; i++) {
    const size = table.varint();
    if (!(size > 0 && size <= records - done)) {
      throw new PacketError("the packet's segments do not add up to its records");
    }
    readSegment(table, names, layout, size, forward ? packet.start + done : -1, flags, out,
                scratch);
    done += size;
  }
  if (done !== records || table.at !== body.length) {
    throw new PacketError("the packet's segments do not add up to its records");
  }
  if (ring) packet.positionReader = ringPositions(ring.values, packet.start);
  return out.map((field) => field.values);
}

// Every stream of one segment of `size` records, appended to the fields `out`: the
// symbols straight into their field, but for the batch runs, their gaps turned back
// into vertex codes (`t0`, the segment's first new vertex; -1 for collapses), and the
// split edge back to d1, d2.
function readSegment(table, names, layout, size, t0, flags, out, scratch) {
  const forward = t0 >= 0;
  let runs = null, counts = null;
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
    if (k === 0) {
      if (!forward && count) {
        throw new PacketError("the packet's batch stream holds runs, but it collapses");
      }
      runs = scratch.runs.subarray(0, count);
      stream.decode(runs, PLAIN, 1, NO_AUX);
      if (forward) checkRuns(runs, size);
    } else if (shape.runs) {
      if (count !== size) {
        throw new PacketError("the packet's vertex stream does not hold one gap per split");
      }
      const gaps = scratch.gaps.subarray(0, count);
      stream.decode(gaps, RUNS, 1, runs);
      vertexCodes(runs, gaps, t0, out[VERTEX].append(count));
    } else if (k === 1 + POSITION && forward && flags & EDGE_POSITIONS) {
      const symbols = scratch.edges.subarray(0, count);
      stream.decode(symbols, shape.classed ? CLASSED : PLAIN, shape.period, NO_AUX);
      const { ring } = scratch;
      if (ring) {
        edgeSymbols(symbols, ring.values.subarray(ring.at, ring.at + count));
        ring.at += count;
      } else {
        edgePositions(symbols, out[POSITION].append(6 * size));
      }
    } else {
      const values = out[k - 1].append(count);
      if (shape.faces) {
        let total = 0;
        for (let i = 0; i < counts.length; i++) total += counts[i];
        if (count !== total) {
          throw new PacketError("the packet's pattern stream does not hold one pattern per " +
                                'new face');
        }
        stream.decode(values, FACES, 1, counts);
      } else {
        stream.decode(values, shape.classed ? CLASSED : PLAIN, shape.period, NO_AUX);
      }
      if (k - 1 === COUNT) counts = values;
      if (BYTE_STREAMS.includes(k - 1)) {
        for (let i = 0; i < count; i++) {
          if (values[i] > 255) {
            throw new PacketError('the packet holds a pattern, fan or mask symbol above 255');
          }
        }
      }
    }
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

// Version 3's vertex codes t - 1 - vs from the runs, into `codes`: a run's first gap
// is its vs, each next one vs - previous vs - 1.
function vertexCodes(runs, gaps, t0, codes) {
  let i = 0;
  for (const length of runs) {
    let s = -1;
    for (let k = 0; k <= length; k++, i++) {
      s = k === 0 ? gaps[i] : s + 1 + gaps[i];
      const t = t0 + i;
      if (s >= t) throw new PacketError(`split ${t} names vertex ${s}, which does not exist yet`);
      codes[i] = t - 1 - s;
    }
  }
}

// Per split: the edge E (3, zigzagged), the place l, the rest r (3, zigzagged);
// d1 = r - floor((l E + 8) / 16), d2 = E + 2 d1, into `out` zigzagged, six a split.
function edgePositions(symbols, out) {
  for (let at = 0, n = 0; at < symbols.length; at += 7, n += 6) {
    const place = symbols[at + PLACE_COLUMN];
    const ex = unzigzag(symbols[at]), ey = unzigzag(symbols[at + 1]),
          ez = unzigzag(symbols[at + 2]);
    const x = moved(symbols[at + 4], place, ex), y = moved(symbols[at + 5], place, ey),
          z = moved(symbols[at + 6], place, ez);
    out[n] = zigzag(x);
    out[n + 1] = zigzag(y);
    out[n + 2] = zigzag(z);
    out[n + 3] = zigzag(ex + 2 * x);
    out[n + 4] = zigzag(ey + 2 * y);
    out[n + 5] = zigzag(ez + 2 * z);
  }
}

// d1 on one axis from its rest symbol, the place and the edge.
function moved(rest, place, edge) {
  return unzigzag(rest) - Math.floor((place * edge + PLACES / 2) / PLACES);
}
