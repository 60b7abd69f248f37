// Reading a vertex-split packet: the header, the inflated body cut into its
// streams, their varints decoded into the fields the records read (FieldReader).
// Mirrors docs/packets.md,
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

import { readBodyV4, withoutChecksum } from './packet_v4.js';

const MAGIC = 0x56444f4c;          // "LODV" read as a little-endian u32
// Version 1: a geometry-only packet of version 2; version 2: attribute records with
// one of four kind codes; version 3: attribute records that name the attribute;
// version 4: version 3's header and records, the body rANS-coded (packet_v4.js).
const READABLE_VERSIONS = [1, 2, 3, 4];
const VERSION_4 = 4;
const HEADER_BYTES = 60;
const STREAM_NAMES = ['vertex', 'count', 'pattern', 'other', 'fan', 'mask', 'position'];
// The streams of bytes (by index in STREAM_NAMES); the others are varints.
export const BYTE_STREAMS = [2, 4, 5];
const HAS_MATERIALS = 1;           // header flag
const V2_ATTRIBUTE_NAMES = ['NORMAL', 'TEXCOORD_0', 'TEXCOORD_1', 'COLOR_0'];   // by kind code
const ENCODINGS = ['linear', 'octahedral', 'tangent'];
const V2_ENCODINGS = ['linear', 'octahedral'];       // version 2 had these two only
// The attribute each non-linear encoding is for, and its components.
const ENCODING_ATTRIBUTE = { octahedral: 'NORMAL', tangent: 'TANGENT' };
const ENCODING_COMPONENTS = { octahedral: 2, tangent: 3 };
const MAX_ATTRIBUTES = 255, MAX_NAME = 64, MAX_BITS = 24;
// Floats per value by glTF name, as lodserver/mesh.py's ATTRIBUTE_RULES (first match
// wins); null: a custom attribute, 1 to 4 as its layout or record says.
const ATTRIBUTE_RULES = [
  [/^NORMAL$/, 3], [/^TEXCOORD_\d+$/, 2], [/^COLOR_\d+$/, 4], [/^TANGENT$/, 4],
  [/^JOINTS_\d+$/, 4], [/^WEIGHTS_\d+$/, 4], [/^TARGET\d+_(POSITION|NORMAL|TANGENT)$/, 3],
  [/^_[A-Za-z0-9_]+$/, null],
];
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
// call them for every value, and method calls on one class are the cheaper call.
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

// A cursor over one field of the records: the values of one stream as readPacket()
// decoded them, in a Float64Array (a value can pass 2^32). Whatever the version, the
// record loops read the same arrays through this one class: no varints are parsed
// while a packet is applied, and the loops' calls stay monomorphic.
class FieldReader {
  constructor(values, name) {
    this.values = values;
    this.at = 0;
    this.name = name;
  }

  next() {
    if (this.at >= this.values.length) throw endOfStream(this);
    return this.values[this.at++];
  }

  // Zigzag: even u is u / 2, odd u is -(u + 1) / 2 (float operations, exact for
  // integers: values pass 2^31, and % on a float is a slow library call).
  signed() {
    const u = this.next();
    const half = u / 2, floor = Math.floor(half);
    return floor === half ? half : -(floor + 1);
  }

  // The next `count` values, as a view (no copy).
  take(count) {
    const end = this.at + count;
    if (end > this.values.length) throw endOfStream(this);
    const values = this.values.subarray(this.at, end);
    this.at = end;
    return values;
  }

  done() {
    return this.at === this.values.length;
  }
}

export function fieldReader(values, name) {
  return new FieldReader(values, name);
}

// The varints of a version 3 stream, as the values of its field: a loop on locals
// for the values of up to four bytes (below 2^28), the reader's varint() for the rest.
function varintValues(data, name) {
  // one value per byte below 128 (a varint's last), and one for a varint cut short
  let count = 0;
  for (let i = 0; i < data.length; i++) count += data[i] < 0x80 ? 1 : 0;
  if (data.length && data[data.length - 1] >= 0x80) count++;
  const values = new Float64Array(count);
  const reader = new StreamReader(data, name);
  const length = data.length;
  let n = 0, at = 0;
  while (at < length) {
    let byte = data[at];
    let value = byte & 0x7f;
    let end = at + 1;
    for (let shift = 7; byte >= 0x80 && shift < 28 && end < length; shift += 7) {
      byte = data[end++];
      value |= (byte & 0x7f) << shift;
    }
    if (byte >= 0x80) {
      reader.at = at;
      values[n++] = reader.varint();
      at = reader.at;
    } else {
      values[n++] = value;
      at = end;
    }
  }
  return values;
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

// The floats per value of attribute `name` (`width`, 1 to 4, for a custom `_NAME`
// one; checked against the name for the others); a PacketError for an unknown name.
export function attributeWidth(name, width) {
  for (const [pattern, fixed] of ATTRIBUTE_RULES) {
    if (!pattern.test(name)) continue;
    if (fixed === null) {
      if (Number.isInteger(width) && width >= 1 && width <= 4) return width;
      throw new PacketError(`custom attribute ${name} must have 1 to 4 components, got ${width}`);
    }
    if (width !== undefined && width !== fixed) {
      throw new PacketError(`attribute ${name} has ${fixed} components, got ${width}`);
    }
    return fixed;
  }
  throw new PacketError(`unknown attribute ${name}`);
}

// An attribute grid as the json form gives it ({encoding, origin, step, bits}), with
// the attribute's width from the json layout (needed for a custom attribute).
// `components` are the stored values per wedge (2 for an octahedral normal, 3 for a
// tangent), `width` the floats drawn (3 for any normal, 4 for a tangent).
export function attributeGrid(name, grid, width) {
  width = attributeWidth(name, width);
  const components = ENCODING_COMPONENTS[grid.encoding] || width;
  return { name, encoding: grid.encoding, origin: [...grid.origin], step: grid.step,
           bits: grid.bits, components, width };
}

// Exact comparison: a packet is only valid on the very grid it was made for.
export function sameGrid(a, b) {
  return a.name === b.name && a.encoding === b.encoding && a.bits === b.bits &&
         a.width === b.width && a.step === b.step && a.origin.length === b.origin.length &&
         a.origin.every((x, k) => x === b.origin[k]);
}

// The float value of wedge grid coordinates q[at .. at + components) into out[o ..):
// origin + q * step, for octahedral normals the unfolded unit vector, and for a
// tangent that vector then its handedness -1 + 2 q.
export function dequantize(grid, q, at, out, o) {
  const { origin, step } = grid;
  if (grid.encoding === 'linear') {
    for (let k = 0; k < grid.components; k++) out[o + k] = origin[k] + q[at + k] * step;
    return;
  }
  if (grid.encoding === 'tangent') out[o + 3] = origin[2] + 2 * q[at + 2];
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

function truncatedAttributes() {
  return new PacketError('the packet is truncated in its attribute records');
}

// A version 3 attribute record at `at`: u8 name length, the ASCII name, u8 width,
// u8 encoding, u8 bits, f64 step, f64 origin per component; { grid, at (its end) }.
function readAttributeV3(bytes, view, at) {
  if (bytes.length < at + 1) throw truncatedAttributes();
  const size = bytes[at];
  if (size < 1 || size > MAX_NAME) {
    throw new PacketError(`the packet has an attribute name of ${size} bytes; names have ` +
                          `1 to ${MAX_NAME}`);
  }
  if (bytes.length < at + 1 + size + 11) throw truncatedAttributes();
  let name = '';
  for (let k = 0; k < size; k++) {
    const code = bytes[at + 1 + k];
    if (code < 0x20 || code > 0x7e) {
      throw new PacketError('the packet has an attribute name that is not printable ASCII');
    }
    name += String.fromCharCode(code);
  }
  at += 1 + size;
  const width = attributeWidthOf(name, view.getUint8(at));
  return readAttributeGrid(bytes, view, at + 3, name, width, view.getUint8(at + 1),
                           view.getUint8(at + 2), view.getFloat64(at + 3, true));
}

// A version 2 attribute record: u8 kind code, u8 encoding, u8 bits, u8 reserved, f64 step, origin.
function readAttributeV2(bytes, view, at) {
  if (bytes.length < at + 12) throw truncatedAttributes();
  const name = V2_ATTRIBUTE_NAMES[view.getUint8(at)];
  if (!name) throw new PacketError(`the packet names an unknown attribute (${view.getUint8(at)})`);
  const encoding = view.getUint8(at + 1);
  return readAttributeGrid(bytes, view, at + 4, name, attributeWidth(name), encoding,
                           view.getUint8(at + 2), view.getFloat64(at + 4, true),
                           V2_ENCODINGS);
}

function attributeWidthOf(name, width) {
  try {
    return attributeWidth(name, width);
  } catch (error) {
    throw new PacketError(`the packet has a bad attribute record: ${error.message}`);
  }
}

// The end of an attribute record: `at` is where its step is, the origin follows.
function readAttributeGrid(bytes, view, at, name, width, code, bits, step,
                           encodings = ENCODINGS) {
  const encoding = encodings[code];
  if (!encoding) throw new PacketError(`the packet gives ${name} an unknown encoding (${code})`);
  if ((ENCODING_ATTRIBUTE[encoding] || name) !== name) {
    throw new PacketError(`the packet encodes ${name} as ${encoding}: only ` +
                          `${ENCODING_ATTRIBUTE[encoding]} can be`);
  }
  if (bits < 1 || bits > MAX_BITS) {
    throw new PacketError(`the packet gives ${name} a grid of ${bits} bits; 1 to ${MAX_BITS} ` +
                          'are allowed');
  }
  const components = ENCODING_COMPONENTS[encoding] || width;
  at += 8;
  if (bytes.length < at + 8 * components) throw truncatedAttributes();
  const origin = [];
  for (let k = 0; k < components; k++, at += 8) origin.push(view.getFloat64(at, true));
  return { grid: attributeGrid(name, { encoding, origin, step, bits }, width), at };
}

// Parse a packet's header and decode its body: { grid, start, stop, startFaces,
// stopFaces, attributes, hasMaterials, fields (Float64Array, one per stream in
// streamNames() order: the values the records read; a byte stream's bytes, a varint
// stream's varints) }.
export async function readPacket(buffer) {
  let bytes = new Uint8Array(buffer);
  // version 4 ends in a CRC-32, checked before anything else is read
  if (bytes.length > 4 && bytes[4] === VERSION_4) bytes = withoutChecksum(bytes);
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
  if (attributeCount > MAX_ATTRIBUTES) {
    throw new PacketError(`the packet has ${attributeCount} attribute records; at most ` +
                          `${MAX_ATTRIBUTES} are allowed`);
  }
  const attributes = [];
  let at = HEADER_BYTES;
  for (let i = 0; i < attributeCount; i++) {
    const record = (version === 2 ? readAttributeV2 : readAttributeV3)(bytes, view, at);
    at = record.at;
    if (attributes.some((a) => a.name === record.grid.name)) {
      throw new PacketError('the packet names an attribute twice');
    }
    attributes.push(record.grid);
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
    fields: [],
  };
  const bodyLength = view.getUint32(56, true);
  if (version === VERSION_4) {
    packet.fields = readBodyV4(bytes.subarray(at), bodyLength, packet, flags);
    return packet;
  }
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
  for (const [i, name] of streamNames(attributes, packet.hasMaterials).entries()) {
    const data = table.bytes(table.varint());
    packet.fields.push(BYTE_STREAMS.includes(i) ? Float64Array.from(data)
      : varintValues(data, name));
  }
  if (table.at !== body.length) {
    throw new PacketError("the packet's body has bytes after its last stream");
  }
  return packet;
}
