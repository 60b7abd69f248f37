// Reading a vertex-split packet: the header, the inflated body cut into its
// streams, and the varints records are made of. Mirrors docs/packets.md,
// "Byte layout" and the stream order and varint rules of "How the server cuts
// packets"; the reference is lodserver/packets/format.py (unpack_header,
// stream_names) and reference.py (decode_packet).
//
// Nothing here knows a level: readPacket() only checks that the bytes are a
// well-formed packet; LodState.apply() checks that it fits the state.
//
// Also here, because packets and json levels share them: attribute grids and
// dequantize(), the float value of a wedge's grid values (docs/packets.md,
// "Exactness").

const MAGIC = 0x56444f4c;          // "LODV" read as a little-endian u32
const READABLE_VERSIONS = [1, 2];  // version 1: a geometry-only packet of version 2
const HEADER_BYTES = 60;
const STREAM_NAMES = ['vertex', 'count', 'pattern', 'other', 'fan', 'mask', 'position'];
const HAS_MATERIALS = 1;           // header flag
const ATTRIBUTE_NAMES = ['NORMAL', 'TEXCOORD_0', 'TEXCOORD_1', 'COLOR_0'];   // by header id
const ATTRIBUTE_WIDTHS = { NORMAL: 3, TEXCOORD_0: 2, TEXCOORD_1: 2, COLOR_0: 4 };
const ENCODINGS = ['linear', 'octahedral'];
// A malformed varint could run on forever; 2^63 bounds any value the format uses.
const MAX_VARINT_SCALE = 2 ** 63;

export class PacketError extends Error {
  constructor(message) {
    super(message);
    this.name = 'PacketError';
  }
}

// ---- streams -----------------------------------------------------------------

// A cursor over one stream; `name` is only for error messages. The readers are
// methods, not functions of another module taking the cursor: the record loops
// call them for every value, and method calls on one class measured faster.
class StreamReader {
  constructor(data, name) {
    this.data = data;
    this.at = 0;
    this.name = name;
  }

  // Unsigned LEB128. Values may exceed 2^31, so the high groups are scaled by
  // multiplication: JavaScript's bit operators truncate to 32 bits.
  varint() {
    const data = this.data;
    let at = this.at;
    if (at >= data.length) throw endOfStream(this);
    let byte = data[at++];
    let value = byte & 0x7f;
    let scale = 128;
    while (byte >= 0x80) {
      if (at >= data.length) throw endOfStream(this);
      if (scale > MAX_VARINT_SCALE) {
        throw new PacketError(`the packet's ${this.name} stream holds an overlong varint`);
      }
      byte = data[at++];
      value += (byte & 0x7f) * scale;
      scale *= 128;
    }
    this.at = at;
    return value;
  }

  // Zigzag: even u is u / 2, odd u is -(u + 1) / 2 (arithmetic, not >>, for the same reason).
  signed() {
    const u = this.varint();
    return u % 2 === 0 ? u / 2 : -(u + 1) / 2;
  }

  byte() {
    if (this.at >= this.data.length) throw endOfStream(this);
    return this.data[this.at++];
  }

  // The next `count` bytes, as a view (no copy).
  bytes(count) {
    const end = this.at + count;
    if (end > this.data.length) throw endOfStream(this);
    const bytes = this.data.subarray(this.at, end);
    this.at = end;
    return bytes;
  }
}

export function makeReader(data, name) {
  return new StreamReader(data, name);
}

export function offGrid() {
  return new PacketError('the packet moves a vertex off the grid');
}

function endOfStream(reader) {
  return new PacketError(`the packet's ${reader.name} stream ends in the middle of a record`);
}

// The body is one zlib stream (RFC 1950), possibly chained from pre-deflated
// segments; the browser's own inflater reads both.
async function inflate(bytes) {
  const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream('deflate'));
  return new Uint8Array(await new Response(stream).arrayBuffer());
}

// The streams of a packet, in body order.
export function streamNames(attributes, hasMaterials) {
  const names = [...STREAM_NAMES];
  if (attributes.length) {
    names.push('wedge_count', 'wedge_parent', 'wedge_corner',
               ...attributes.map((a) => `value:${a.name}`));
  }
  if (hasMaterials) names.push('material');
  return names;
}

// ---- attribute grids -------------------------------------------------------------

// An attribute grid as the json form gives it ({encoding, origin, step, bits}).
// `components` are the stored values per wedge (2 for an octahedral normal),
// `width` the floats drawn (3 for any normal).
export function attributeGrid(name, grid) {
  const components = grid.encoding === 'octahedral' ? 2 : ATTRIBUTE_WIDTHS[name];
  return { name, encoding: grid.encoding, origin: [...grid.origin], step: grid.step,
           bits: grid.bits, components, width: ATTRIBUTE_WIDTHS[name] };
}

// Exact comparison: a packet is only valid on the very grid it was made for.
export function sameGrid(a, b) {
  return a.name === b.name && a.encoding === b.encoding && a.bits === b.bits &&
         a.step === b.step && a.origin.every((x, k) => x === b.origin[k]);
}

// The float value of wedge grid coordinates q[at .. at + components) into out[o ..):
// origin + q * step, and for octahedral normals the unfolded unit vector.
export function dequantize(grid, q, at, out, o) {
  const { origin, step } = grid;
  if (grid.encoding !== 'octahedral') {
    for (let k = 0; k < grid.components; k++) out[o + k] = origin[k] + q[at + k] * step;
    return;
  }
  let x = origin[0] + q[at] * step, y = origin[1] + q[at + 1] * step;
  const z = 1 - Math.abs(x) - Math.abs(y);
  if (z < 0) {
    const fx = (1 - Math.abs(y)) * (x >= 0 ? 1 : -1);
    y = (1 - Math.abs(x)) * (y >= 0 ? 1 : -1);
    x = fx;
  }
  const length = Math.hypot(x, y, z) || 1;
  out[o] = x / length;
  out[o + 1] = y / length;
  out[o + 2] = z / length;
}

// ---- the header and body -----------------------------------------------------------

// Parse a packet's header and inflate its streams: { grid, start, stop,
// startFaces, stopFaces, attributes, hasMaterials, streams (Uint8Array views
// into the body, in streamNames() order) }.
export async function readPacket(buffer) {
  const bytes = new Uint8Array(buffer);
  if (bytes.length < HEADER_BYTES) {
    throw new PacketError(`the packet is truncated: ${bytes.length} bytes is shorter than ` +
                          'the header');
  }
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.length);
  if (view.getUint32(0, true) !== MAGIC) {
    throw new PacketError('this is not a lodserver vsplit packet (bad magic bytes)');
  }
  const version = view.getUint8(4);
  if (!READABLE_VERSIONS.includes(version)) {
    throw new PacketError(`the packet has version ${version}; this decoder reads ` +
                          `${READABLE_VERSIONS.join(' and ')}`);
  }
  const attributeCount = view.getUint8(6), flags = view.getUint8(7);
  if (version === 1 && (attributeCount || flags)) {
    throw new PacketError('the packet has version 1 but sets reserved header bytes');
  }
  const attributes = [];
  let at = HEADER_BYTES;
  for (let i = 0; i < attributeCount; i++) {
    if (bytes.length < at + 12) throw new PacketError('the packet is truncated in its attributes');
    const name = ATTRIBUTE_NAMES[view.getUint8(at)], encoding = ENCODINGS[view.getUint8(at + 1)];
    if (!name || !encoding || (encoding === 'octahedral' && name !== 'NORMAL')) {
      throw new PacketError('the packet names an unknown attribute or encoding');
    }
    const grid = { bits: view.getUint8(at + 2), step: view.getFloat64(at + 4, true),
                   encoding, origin: [] };
    const components = encoding === 'octahedral' ? 2 : ATTRIBUTE_WIDTHS[name];
    at += 12;
    if (bytes.length < at + 8 * components) {
      throw new PacketError('the packet is truncated in its attributes');
    }
    for (let k = 0; k < components; k++, at += 8) grid.origin.push(view.getFloat64(at, true));
    attributes.push(attributeGrid(name, grid));
  }
  const packet = {
    grid: {
      bits: view.getUint8(5),
      origin: [view.getFloat64(24, true), view.getFloat64(32, true), view.getFloat64(40, true)],
      step: view.getFloat64(48, true),
    },
    start: view.getUint32(8, true),
    stop: view.getUint32(12, true),
    startFaces: view.getUint32(16, true),
    stopFaces: view.getUint32(20, true),
    attributes,
    hasMaterials: (flags & HAS_MATERIALS) !== 0,
    streams: [],
  };
  const bodyLength = view.getUint32(56, true);
  let body;
  try {
    body = await inflate(bytes.subarray(at));
  } catch (error) {
    throw new PacketError(`the packet's body does not inflate (${error.message})`);
  }
  if (body.length !== bodyLength) {
    throw new PacketError(`the packet's body is ${body.length} bytes, the header says ` +
                          `${bodyLength}`);
  }
  const table = makeReader(body, 'stream table');
  for (const name of streamNames(attributes, packet.hasMaterials)) {
    packet.streams.push(table.bytes(table.varint()));
  }
  if (table.at !== body.length) {
    throw new PacketError("the packet's body has bytes after its last stream");
  }
  return packet;
}
