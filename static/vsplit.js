// Vertex-split packets (docs/packets.md), decoded and applied on typed arrays.
//
// A port of the reference decoder, lodserver/packets.py (decode_packet,
// apply_packet, state_from_json). The state is one level in its quantized
// form: integer grid positions and faces in their prefix-layout slots. The
// arrays are allocated once at full-detail size, so three.js can render them
// in place: a level is a prefix of both (draw range), and a packet changes
// only a few ranges of them (reported by takeDirty()).
//
// Unlike the reference, apply() works in place for speed: a packet that fails
// half-way leaves the state unusable, and the caller must reopen the mesh.
//
// Per vertex the decoder needs corners(v), the corners c = 3 * face + slot
// holding v. They are kept as linked lists threaded through the corners (head
// per vertex, next per corner): a vertex's corners are found without a search,
// and moving a corner costs a walk over one vertex's few corners.
//
// A mesh with attributes (normals, UVs, colours) also has wedges (version 2
// packets): integer grid values per wedge, the wedge of every corner, and the
// material of every face. The state keeps each wedge's vertex (the vertex of
// the corners holding it) so a renderer can draw one vertex per wedge, and
// lists the vertices and wedges a packet touched (takeDirty()).

const MAGIC = 0x56444f4c;          // "LODV" read as a little-endian u32
const READABLE_VERSIONS = [1, 2];  // version 1: a geometry-only packet of version 2
const HEADER_BYTES = 60;
const STREAM_NAMES = ['vertex', 'count', 'pattern', 'other', 'fan', 'mask', 'position'];
const HAS_MATERIALS = 1;           // header flag
const ATTRIBUTE_NAMES = ['NORMAL', 'TEXCOORD_0', 'TEXCOORD_1', 'COLOR_0'];   // by header id
const ATTRIBUTE_WIDTHS = { NORMAL: 3, TEXCOORD_0: 2, TEXCOORD_1: 2, COLOR_0: 4 };
const ENCODINGS = ['linear', 'octahedral'];
const MAX_SPLIT_RATIO = 4;
const GRADIENT_DAMPING = 1e-3;
const FAN_PREDICTED = 0;
const IS_VS = 0, IS_NEW = 1;       // corner kinds in a new face's pattern; 2 = another vertex
const NONE = -1;                   // no corner, no vertex
// A malformed varint could run on forever; 2^63 bounds any value the format uses.
const MAX_VARINT_SCALE = 2 ** 63;

class PacketError extends Error {
  constructor(message) {
    super(message);
    this.name = 'PacketError';
  }
}

// ---- streams -----------------------------------------------------------------

function makeReader(data, name) {
  return { data, at: 0, name };
}

// A typed array twice as long holding the first `used` items of `array`.
function grow(array, used) {
  const bigger = new array.constructor(2 * Math.max(array.length, 8));
  bigger.set(array.subarray(0, used));
  return bigger;
}

// Unsigned LEB128. Values may exceed 2^31, so the high groups are scaled by
// multiplication: JavaScript's bit operators truncate to 32 bits.
function readVarint(reader) {
  const data = reader.data;
  let at = reader.at;
  if (at >= data.length) throw endOfStream(reader);
  let byte = data[at++];
  let value = byte & 0x7f;
  let scale = 128;
  while (byte >= 0x80) {
    if (at >= data.length) throw endOfStream(reader);
    if (scale > MAX_VARINT_SCALE) {
      throw new PacketError(`the packet's ${reader.name} stream holds an overlong varint`);
    }
    byte = data[at++];
    value += (byte & 0x7f) * scale;
    scale *= 128;
  }
  reader.at = at;
  return value;
}

// Zigzag: even u is u / 2, odd u is -(u + 1) / 2 (arithmetic, not >>, for the same reason).
function readSigned(reader) {
  const u = readVarint(reader);
  return u % 2 === 0 ? u / 2 : -(u + 1) / 2;
}

function readByte(reader) {
  if (reader.at >= reader.data.length) throw endOfStream(reader);
  return reader.data[reader.at++];
}

function readBytes(reader, count) {
  const end = reader.at + count;
  if (end > reader.data.length) throw endOfStream(reader);
  const bytes = reader.data.subarray(reader.at, end);
  reader.at = end;
  return bytes;
}

function offGrid() {
  return new PacketError('the packet moves a vertex off the grid');
}

function endOfStream(reader) {
  return new PacketError(`the packet's ${reader.name} stream ends in the middle of a record`);
}

async function inflate(bytes) {
  const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream('deflate'));
  return new Uint8Array(await new Response(stream).arrayBuffer());
}

// The streams of a packet, in body order.
function streamNames(attributes, hasMaterials) {
  const names = [...STREAM_NAMES];
  if (attributes.length) {
    names.push('wedge_count', 'wedge_parent', 'wedge_corner',
               ...attributes.map((a) => `value:${a.name}`));
  }
  if (hasMaterials) names.push('material');
  return names;
}

// An attribute grid as the json form gives it ({encoding, origin, step, bits}).
function attributeGrid(name, grid) {
  const components = grid.encoding === 'octahedral' ? 2 : ATTRIBUTE_WIDTHS[name];
  return { name, encoding: grid.encoding, origin: [...grid.origin], step: grid.step,
           bits: grid.bits, components, width: ATTRIBUTE_WIDTHS[name] };
}

function sameGrid(a, b) {
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

// ---- the state -----------------------------------------------------------------

export class LodState {
  // The quantized level of a /lod?format=json document, with room to grow to
  // vertexCapacity vertices and faceCapacity faces (the mesh's full detail).
  static fromJson(document, { vertexCapacity, faceCapacity }) {
    const vertexCount = document.positions.length;
    const faceCount = document.faces.length;
    if (vertexCount > vertexCapacity || faceCount > faceCapacity) {
      throw new PacketError(`the level (${vertexCount} vertices, ${faceCount} faces) exceeds ` +
                            `the capacity (${vertexCapacity}, ${faceCapacity})`);
    }
    const attributes = (document.layout || []).map(
      ([name]) => attributeGrid(name, document.attribute_grid[name]));
    const wedgeCapacity = attributes.length ? document.wedge_capacity : 0;
    const hasMaterials = Array.isArray(document.face_material);
    const state = new LodState(document.grid, vertexCapacity, faceCapacity,
                               { attributes, wedgeCapacity, hasMaterials });
    const { positions, faces } = state;
    document.positions.forEach((q, v) => positions.set(q, 3 * v));
    document.faces.forEach((corners, f) => faces.set(corners, 3 * f));
    state.vertexCount = vertexCount;
    state.faceCount = faceCount;
    for (let c = 0; c < 3 * faceCount; c++) state.link(c, faces[c]);
    if (attributes.length) {
      const { wedges, corners, components, wedgeVertex } = state;
      if (document.wedges.length > wedgeCapacity) {
        throw new PacketError(`the level has ${document.wedges.length} wedges, more than its ` +
                              `capacity ${wedgeCapacity}`);
      }
      document.wedges.forEach((q, w) => wedges.set(q, components * w));
      document.corners.forEach((row, f) => corners.set(row, 3 * f));
      state.wedgeCount = document.wedges.length;
      for (let c = 0; c < 3 * faceCount; c++) wedgeVertex[corners[c]] = faces[c];
      for (let w = 0; w < state.wedgeCount; w++) state.touchWedge(w);
      for (let v = 0; v < vertexCount; v++) state.touchVertex(v);
    }
    if (hasMaterials) state.faceMaterial.set(document.face_material);
    state.markVertices(0, vertexCount);
    state.markCorners(0, 3 * faceCount);
    return state;
  }

  // Parse a packet's header and inflate its streams; apply() checks it fits.
  static async readPacket(buffer) {
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
      packet.streams.push(readBytes(table, readVarint(table)));
    }
    if (table.at !== body.length) {
      throw new PacketError("the packet's body has bytes after its last stream");
    }
    return packet;
  }

  constructor(grid, vertexCapacity, faceCapacity,
              { attributes = [], wedgeCapacity = 0, hasMaterials = false } = {}) {
    this.grid = { origin: [...grid.origin], step: grid.step, bits: grid.bits };
    this.gridSize = 2 ** grid.bits;                        // grid coordinates are below this
    this.positions = new Int32Array(3 * vertexCapacity);   // grid coordinates, xyz per vertex
    this.faces = new Uint32Array(3 * faceCapacity);        // vertex per corner
    this.vertexCount = 0;
    this.faceCount = 0;
    this.head = new Int32Array(vertexCapacity).fill(NONE); // a corner of each vertex
    this.next = new Int32Array(3 * faceCapacity);          // next corner of the same vertex
    // Scratch for one record: corners of a vertex with their next and prev vertices.
    this.aroundCorners = new Int32Array(64);
    this.aroundNexts = new Int32Array(64);
    this.aroundPrevs = new Int32Array(64);
    this.aroundCount = 0;
    this.neighbours = new Int32Array(128);
    this.neighbourCount = 0;
    this.added = new Int32Array(24);                       // new faces of one split
    this.moved = new Int32Array(64);                       // corners one split moves
    this.fanMark = new Float64Array(64);                   // = fanStamp: in the current fan
    this.fanStamp = 0;                                     // counts fan predictions
    // Wedges: attribute grids (with each one's first column), values, corners.
    this.attributes = attributes;
    this.components = 0;
    for (const a of attributes) {
      a.offset = this.components;
      this.components += a.components;
    }
    this.wedges = new Int32Array(this.components * wedgeCapacity);  // grid values per wedge
    this.corners = new Uint32Array(attributes.length ? 3 * faceCapacity : 0);  // wedge per corner
    this.wedgeVertex = new Int32Array(wedgeCapacity);      // the vertex of each wedge
    this.wedgeCount = 0;
    this.faceMaterial = hasMaterials ? new Int32Array(faceCapacity) : null;
    // Scratch for the wedge records.
    this.attributeOffset = Int32Array.from(attributes, (a) => a.offset);
    this.attributeComponents = Int32Array.from(attributes, (a) => a.components);
    this.attributeLimit = Float64Array.from(attributes, (a) => 2 ** a.bits);
    this.wedgeList = new Int32Array(64);                   // candidate wedges
    this.parents = new Int32Array(16);                     // parents of one record's wedges
    this.fine = new Float64Array(this.components);
    this.coarse = new Float64Array(3);                     // vs before a split
    this.gradient = new Float64Array(3 * this.components); // rows x, y, z
    this.sums = new Float64Array(3 * this.components);
    this.heldSorted = new Int32Array(64);
    this.cornerList = new Int32Array(64);                  // moved corners, sorted
    // What the packets since takeDirty() touched: vertices (position or corners
    // changed) and wedges (value changed), each listed once.
    this.touchedVertices = new Int32Array(1024);
    this.touchedVertexCount = 0;
    this.vertexTouched = new Uint8Array(attributes.length ? vertexCapacity : 0);
    this.touchedWedges = new Int32Array(1024);
    this.touchedWedgeCount = 0;
    this.wedgeTouched = new Uint8Array(wedgeCapacity);
    this.clean();
  }

  get wedgeCapacity() {
    return this.wedgeVertex.length;
  }

  get level() {
    return this.vertexCount;
  }

  get vertexCapacity() {
    return this.head.length;
  }

  get faceCapacity() {
    return this.faces.length / 3;
  }

  // The vertex range [vertexStart, vertexEnd) and corner range whose values
  // changed since the last call, for partial uploads to the GPU.
  // With attributes, also the vertices and wedges touched (lists, valid until
  // the next packet is applied).
  takeDirty() {
    const dirty = { vertexStart: this.vertexStart, vertexEnd: this.vertexEnd,
                    cornerStart: this.cornerStart, cornerEnd: this.cornerEnd };
    if (this.attributes.length) {
      dirty.vertices = this.touchedVertices.subarray(0, this.touchedVertexCount);
      dirty.wedges = this.touchedWedges.subarray(0, this.touchedWedgeCount);
      for (const v of dirty.vertices) this.vertexTouched[v] = 0;
      for (const w of dirty.wedges) this.wedgeTouched[w] = 0;
      this.touchedVertexCount = this.touchedWedgeCount = 0;
    }
    this.clean();
    return dirty;
  }

  touchVertex(v) {
    if (this.vertexTouched[v]) return;
    this.vertexTouched[v] = 1;
    if (this.touchedVertexCount === this.touchedVertices.length) {
      this.touchedVertices = grow(this.touchedVertices, this.touchedVertexCount);
    }
    this.touchedVertices[this.touchedVertexCount++] = v;
  }

  touchWedge(w) {
    if (this.wedgeTouched[w]) return;
    this.wedgeTouched[w] = 1;
    if (this.touchedWedgeCount === this.touchedWedges.length) {
      this.touchedWedges = grow(this.touchedWedges, this.touchedWedgeCount);
    }
    this.touchedWedges[this.touchedWedgeCount++] = w;
  }

  clean() {
    this.vertexStart = this.cornerStart = Infinity;
    this.vertexEnd = this.cornerEnd = 0;
  }

  markVertices(start, end) {
    if (start < this.vertexStart) this.vertexStart = start;
    if (end > this.vertexEnd) this.vertexEnd = end;
  }

  markCorners(start, end) {
    if (start < this.cornerStart) this.cornerStart = start;
    if (end > this.cornerEnd) this.cornerEnd = end;
  }

  // Apply a packet from readPacket(); returns the number of records applied.
  apply(packet) {
    const { grid } = this;
    if (this.vertexCount !== packet.start || this.faceCount !== packet.startFaces) {
      throw new PacketError(`the packet starts at level ${packet.start} with ` +
                            `${packet.startFaces} faces; the state is at level ` +
                            `${this.vertexCount} with ${this.faceCount}`);
    }
    if (packet.grid.bits !== grid.bits || packet.grid.step !== grid.step ||
        packet.grid.origin.some((x, k) => x !== grid.origin[k])) {
      throw new PacketError("the packet was made for another quantization grid than the state's");
    }
    if (packet.stop > this.vertexCapacity || packet.stopFaces > this.faceCapacity) {
      throw new PacketError(`the packet goes to level ${packet.stop} with ${packet.stopFaces} ` +
                            'faces, beyond the mesh this state was made for');
    }
    if (packet.attributes.length !== this.attributes.length ||
        !packet.attributes.every((a, i) => sameGrid(a, this.attributes[i]))) {
      throw new PacketError('the packet was made for other attributes or attribute grids than ' +
                            "the state's");
    }
    if (packet.hasMaterials !== (this.faceMaterial !== null)) {
      throw new PacketError('the packet and the state disagree on face materials');
    }
    const names = streamNames(packet.attributes, packet.hasMaterials);
    const readers = packet.streams.map((data, i) => makeReader(data, names[i]));
    if (packet.stop > packet.start) this.applySplits(packet.start, packet.stop, readers);
    else this.applyCollapses(packet.start, packet.stop, readers);
    if (!readers.every((reader) => reader.at === reader.data.length)) {
      throw new PacketError("the packet's streams hold more than its records");
    }
    if (this.faceCount !== packet.stopFaces) {
      throw new PacketError(`the packet left ${this.faceCount} faces, its header says ` +
                            `${packet.stopFaces}`);
    }
    return Math.abs(packet.stop - packet.start);
  }

  applySplits(start, stop, readers) {
    const [vertex, count, pattern, other, fan, mask, position] = readers;
    const { positions, faces, gridSize } = this;
    const hasWedges = this.attributes.length > 0;
    const material = this.faceMaterial ? readers[readers.length - 1] : null;
    for (let t = start; t < stop; t++) {
      const s = t - 1 - readVarint(vertex);
      if (s < 0) throw new PacketError(`split ${t} names a vertex below 0`);
      // held(s) and neighbours(s) are taken before the record changes anything.
      this.gatherCorners(s);
      const k = readVarint(count);
      if (3 * k > this.added.length) this.added = new Int32Array(6 * k);
      const added = this.added;
      let neighboursKnown = false;
      for (let i = 0; i < 3 * k; i += 3) {
        const code = readByte(pattern);
        if (code > 26) throw new PacketError(`split ${t} has a face pattern out of range`);
        // the base-3 digits of code, first corner first
        for (let j = 0, digits = code; j < 3; j++) {
          const kind = j === 0 ? (digits / 9) | 0 : j === 1 ? ((digits / 3) | 0) % 3 : digits % 3;
          let v;
          if (kind === IS_VS) v = s;
          else if (kind === IS_NEW) v = t;
          else {
            if (!neighboursKnown) {
              this.gatherNeighbours(s);
              neighboursKnown = true;
            }
            v = this.decodeVertex(readVarint(other));
          }
          if (v > t) {
            throw new PacketError(`split ${t} adds a face on a vertex that does not exist yet`);
          }
          added[i + j] = v;
        }
      }

      const moves = readByte(fan) === FAN_PREDICTED
        ? this.predictFan(s, t, k) : this.listedCorners(mask);
      if (moves < 0) {
        throw new PacketError(`split ${t} relies on a fan prediction that does not exist`);
      }
      const moved = this.moved;
      for (let i = 0; i < moves; i++) this.moveCorner(moved[i], t);
      const firstFace = this.faceCount;
      const first = 3 * this.faceCount;
      for (let i = 0; i < 3 * k; i++) {
        faces[first + i] = added[i];
        this.link(first + i, added[i]);
      }
      this.faceCount += k;
      this.markCorners(first, first + 3 * k);

      // s moves to f = c + d1; t lands on the other side of c: 2c - f + d2.
      // The stream holds d1 (x, y, z), then d2 (x, y, z).
      const ps = 3 * s, pt = 3 * t;
      const c0 = positions[ps], c1 = positions[ps + 1], c2 = positions[ps + 2];
      for (let j = 0; j < 3; j++) {
        const coarse = positions[ps + j];
        const fine = coarse + readSigned(position);
        if (!(fine >= 0 && fine < gridSize)) throw offGrid();
        positions[pt + j] = 2 * coarse - fine;
        positions[ps + j] = fine;
      }
      for (let j = 0; j < 3; j++) {
        const q = positions[pt + j] + readSigned(position);
        if (!(q >= 0 && q < gridSize)) throw offGrid();
        positions[pt + j] = q;
      }
      this.vertexCount = t + 1;
      this.markVertices(s, t + 1);
      if (material) {
        for (let f = firstFace; f < this.faceCount; f++) {
          this.faceMaterial[f] = readVarint(material) - 1;
        }
      }
      if (hasWedges) {
        const coarse = this.coarse;
        coarse[0] = c0;
        coarse[1] = c1;
        coarse[2] = c2;
        this.splitWedges(s, t, moves, firstFace, readers);
        this.touchVertex(s);
        this.touchVertex(t);
      }
    }
  }

  applyCollapses(start, stop, readers) {
    const [vertex, count, , , , , position] = readers;
    const { positions, faces, gridSize } = this;
    const hasWedges = this.attributes.length > 0;
    for (let t = start - 1; t >= stop; t--) {
      this.gatherCorners(t);
      this.gatherNeighbours(t);
      const s = this.decodeVertex(readVarint(vertex));
      if (!(s >= 0 && s < t)) {
        throw new PacketError(`collapse of ${t} names vertex ${s}, which is not below it`);
      }
      const removed = readVarint(count);
      if (removed > this.faceCount) {
        throw new PacketError(`collapse of ${t} removes more faces than the state holds`);
      }
      this.faceCount -= removed;
      for (let c = 3 * this.faceCount; c < 3 * (this.faceCount + removed); c++) {
        this.unlink(c, faces[c]);
      }
      for (let c = this.head[t]; c !== NONE; c = this.head[t]) this.moveCorner(c, s);
      // floor((q_s + q_t) / 2) + r; both are non-negative, so >> 1 is the floor.
      const ps = 3 * s, pt = 3 * t;
      const f0 = positions[ps], f1 = positions[ps + 1], f2 = positions[ps + 2];
      for (let j = 0; j < 3; j++) {
        const q = ((positions[ps + j] + positions[pt + j]) >> 1) + readSigned(position);
        if (!(q >= 0 && q < gridSize)) throw offGrid();
        positions[ps + j] = q;
      }
      this.vertexCount = t;
      this.markVertices(s, s + 1);
      if (hasWedges) {
        // where the merged position lies between s's and t's
        const n0 = positions[pt] - f0, n1 = positions[pt + 1] - f1, n2 = positions[pt + 2] - f2;
        let a = 0, b = 0;
        a += n0 * n0; a += n1 * n1; a += n2 * n2;
        b += (positions[ps] - f0) * n0;
        b += (positions[ps + 1] - f1) * n1;
        b += (positions[ps + 2] - f2) * n2;
        const ratio = a > 0 ? Math.min(Math.max(b / a, 0), 1) : 0.5;
        this.collapseWedges(t, s, ratio, readers);
        this.touchVertex(s);
      }
    }
  }

  // ---- wedges ------------------------------------------------------------------

  // How far t lies beyond vs's coarse position, in units of coarse - fine: the
  // split ratio of docs/packets.md (this.coarse: vs before the split).
  splitRatio(s, t) {
    const { positions, coarse } = this;
    const a0 = coarse[0] - positions[3 * s], a1 = coarse[1] - positions[3 * s + 1];
    const a2 = coarse[2] - positions[3 * s + 2];
    let a = 0, b = 0;
    a += a0 * a0;
    a += a1 * a1;
    a += a2 * a2;
    b += (positions[3 * t] - coarse[0]) * a0;
    b += (positions[3 * t + 1] - coarse[1]) * a1;
    b += (positions[3 * t + 2] - coarse[2]) * a2;
    return a > 0 ? Math.min(Math.max(b / a, 0), MAX_SPLIT_RATIO) : 1;
  }

  // The gradient of wedge p's values against position around s (docs/packets.md;
  // lodserver/packets.py _gradient, the same float operations in the same order)
  // into this.gradient (3 rows of `components`); false when there is none.
  // held[0 .. n): held(s), ascending.
  fitGradient(s, p, held, n) {
    const { faces, positions, corners, wedges, components, coarse, gradient, sums } = this;
    let m00 = 0, m01 = 0, m02 = 0, m11 = 0, m12 = 0, m22 = 0;
    sums.fill(0);
    let edges = 0;
    const pc = components * p;
    for (let i = 0; i < n; i++) {
      const c = held[i];
      if (corners[c] !== p) continue;
      const f3 = c - (c % 3);
      for (let step = 1; step < 3; step++) {
        const o = f3 + ((c - f3 + step) % 3);
        const v = faces[o];
        if (v === s) continue;
        const e0 = positions[3 * v] - coarse[0], e1 = positions[3 * v + 1] - coarse[1];
        const e2 = positions[3 * v + 2] - coarse[2];
        const oc = components * corners[o];
        m00 += e0 * e0;
        m01 += e0 * e1;
        m02 += e0 * e2;
        m11 += e1 * e1;
        m12 += e1 * e2;
        m22 += e2 * e2;
        for (let j = 0; j < components; j++) {
          const d = wedges[oc + j] - wedges[pc + j];
          sums[j] += e0 * d;
          sums[components + j] += e1 * d;
          sums[2 * components + j] += e2 * d;
        }
        edges++;
      }
    }
    if (edges < 2) return false;
    const damping = (m00 + m11 + m22) * GRADIENT_DAMPING + 1e-9;
    m00 += damping;
    m11 += damping;
    m22 += damping;
    const c00 = m11 * m22 - m12 * m12, c01 = m02 * m12 - m01 * m22;
    const c02 = m01 * m12 - m02 * m11, c11 = m00 * m22 - m02 * m02;
    const c12 = m01 * m02 - m00 * m12, c22 = m00 * m11 - m01 * m01;
    const det = m00 * c00 + m01 * c01 + m02 * c02;
    if (!(det > 0)) return false;
    const i00 = c00 / det, i01 = c01 / det, i02 = c02 / det;
    const i11 = c11 / det, i12 = c12 / det, i22 = c22 / det;
    for (let j = 0; j < components; j++) {
      const b0 = sums[j], b1 = sums[components + j], b2 = sums[2 * components + j];
      gradient[j] = i00 * b0 + i01 * b1 + i02 * b2;
      gradient[components + j] = i01 * b0 + i11 * b1 + i12 * b2;
      gradient[2 * components + j] = i02 * b0 + i12 * b1 + i22 * b2;
    }
    return true;
  }

  // floor(value + J . (position of v - coarse) + 0.5) within [0, limit).
  extrapolate(j, value, v, limit) {
    const { gradient, positions, coarse, components } = this;
    const x = (value + ((positions[3 * v] - coarse[0]) * gradient[j] +
                        (positions[3 * v + 1] - coarse[1]) * gradient[components + j] +
                        (positions[3 * v + 2] - coarse[2]) * gradient[2 * components + j])) + 0.5;
    if (!(x >= 0)) return 0;
    if (x > limit - 1) return limit - 1;
    return Math.floor(x);
  }

  // The wedge part of split t (docs/packets.md), after its geometry part: the
  // scratch still holds held(s) as gathered before the split, this.moved its
  // `moves` moved corners, and its new faces start at face firstFace.
  // Codes are nearly always 0, the smallest candidate: found by one walk,
  // without building the sorted list.
  splitWedges(s, t, moves, firstFace, readers) {
    const wedgeCount = readers[7], wedgeParent = readers[8], wedgeCorner = readers[9];
    const { wedges, corners, components, faces, fine, head, next, parents } = this;
    const { attributeOffset, attributeComponents, attributeLimit } = this;
    const bottom = this.wedgeCount;
    const m = readVarint(wedgeCount);
    const top = bottom + m;
    if (top > this.wedgeCapacity) {
      throw new PacketError(`split ${t} adds wedges beyond the mesh this state was made for`);
    }
    if (m > parents.length) this.parents = new Int32Array(2 * m);
    // held(s) ascending, for the gradient's sums
    const held = m > 0 ? this.sortedHeld() : null;
    // parents, by rank among the wedges of held(s)
    let known = -1, ratio = -1;
    for (let x = bottom; x < top; x++) {
      const u = readVarint(wedgeParent);
      let p;
      if (u === 0) p = this.smallestWedge(this.aroundCorners, this.aroundCount, bottom, 0);
      else {
        if (known < 0) known = this.heldWedges(this.aroundCorners, this.aroundCount, bottom);
        p = u < known ? this.wedgeList[u] : u - known;
      }
      if (!(p >= 0 && p < x)) {
        throw new PacketError(`split ${t} gives wedge ${x} the parent ${p}, which is not below it`);
      }
      this.parents[x - bottom] = p;
      // per attribute: the parent's finer value and the new wedge's, each as a
      // residual from its prediction: extrapolated along the gradient around s,
      // or without one, the parent's value and beyond it as t lies beyond s
      const pc = components * p, xc = components * x;
      const fitted = this.fitGradient(s, p, held, this.aroundCount);
      if (!fitted && ratio < 0) ratio = this.splitRatio(s, t);
      for (let i = 0; i < attributeOffset.length; i++) {
        const stream = readers[10 + i], limit = attributeLimit[i];
        const first = attributeOffset[i], end = first + attributeComponents[i];
        for (let k = first; k < end; k++) {
          const guess = fitted ? this.extrapolate(k, wedges[pc + k], s, limit) : wedges[pc + k];
          fine[k] = guess + readSigned(stream);
        }
        for (let k = first; k < end; k++) {
          const c = wedges[pc + k];
          const guess = fitted ? this.extrapolate(k, c, t, limit)
            : c + Math.floor(ratio * (c - fine[k]) + 0.5);
          const q = guess + readSigned(stream);
          if (!(q >= 0 && q < limit && fine[k] >= 0 && fine[k] < limit)) {
            throw new PacketError(`split ${t} moves a ${this.attributes[i].name} value off ` +
                                  'its grid');
          }
          wedges[xc + k] = q;
        }
      }
      for (let k = 0; k < components; k++) wedges[pc + k] = fine[k];
      this.touchWedge(p);
      this.touchWedge(x);
    }
    this.wedgeCount = top;
    // moved corners, ascending: code 0 is the predicted wedge (the new wedge whose
    // parent the corner holds, else the same), 1..m a new wedge, m+1 the same, then ids
    const sorted = moves > 1 ? this.sortedMoved(moves) : this.moved;
    for (let i = 0; i < moves; i++) {
      const c = sorted[i];
      const y = corners[c];
      const u = readVarint(wedgeCorner);
      let w;
      if (u === 0) {
        w = y;
        for (let x = bottom; x < top; x++) {
          if (this.parents[x - bottom] === y) {
            w = x;
            break;
          }
        }
      } else if (u <= m) w = bottom + u - 1;
      else if (u === m + 1) w = y;
      else w = u - m - 2;
      this.setWedge(c, w);
    }
    // the new faces' corners, each by rank among its vertex's wedges (on the
    // faces before this split), then the new ones
    const limit = 3 * firstFace;
    for (let c = limit; c < 3 * this.faceCount; c++) {
      const v = faces[c];
      const u = readVarint(wedgeCorner);
      let w;
      if (u === 0) {
        w = -1;
        for (let d = head[v]; d !== NONE; d = next[d]) {
          if (d < limit && (w < 0 || corners[d] < w)) w = corners[d];
        }
        if (w < 0) w = this.candidate(0, 0, bottom, top);
      } else {
        let n = 0;
        for (let d = head[v]; d !== NONE; d = next[d]) {
          if (d >= limit) continue;
          if (n === this.cornerList.length) this.cornerList = grow(this.cornerList, n);
          this.cornerList[n++] = d;
        }
        w = this.candidate(u, this.heldWedges(this.cornerList, n, top), bottom, top);
      }
      this.setWedge(c, w);
    }
  }

  // held(s) (the scratch's corners) ascending, in this.heldSorted.
  sortedHeld() {
    const n = this.aroundCount;
    if (n > this.heldSorted.length) this.heldSorted = new Int32Array(2 * n);
    const out = this.heldSorted, from = this.aroundCorners;
    for (let i = 0; i < n; i++) {
      const c = from[i];
      let j = i - 1;
      while (j >= 0 && out[j] > c) {
        out[j + 1] = out[j];
        j--;
      }
      out[j + 1] = c;
    }
    return out;
  }

  // The smallest wedge below `below` of corners[0 .. n), or `none` if there is none.
  smallestWedge(cornerIds, n, below, none) {
    let w = -1;
    const corners = this.corners;
    for (let i = 0; i < n; i++) {
      const x = corners[cornerIds[i]];
      if (x < below && (w < 0 || x < w)) w = x;
    }
    return w < 0 ? none : w;
  }

  // The distinct wedges of corners[0 .. n) below `below`, ascending, into
  // this.wedgeList; their number.
  heldWedges(cornerIds, n, below) {
    if (n > this.wedgeList.length) this.wedgeList = new Int32Array(2 * n);
    const list = this.wedgeList, corners = this.corners;
    let size = 0;
    for (let i = 0; i < n; i++) {
      const w = corners[cornerIds[i]];
      if (w >= below) continue;
      let j = size - 1;
      while (j >= 0 && list[j] > w) j--;
      if (j >= 0 && list[j] === w) continue;
      for (let k = size; k > j + 1; k--) list[k] = list[k - 1];
      list[j + 1] = w;
      size++;
    }
    return size;
  }

  // The wedge of code u relative to this.wedgeList[0 .. size) followed by the new
  // wedges bottom .. top-1 not among them; past those, a wedge id.
  candidate(u, size, bottom, top) {
    if (u < size) return this.wedgeList[u];
    let rank = size;
    const list = this.wedgeList;
    for (let x = bottom; x < top; x++) {
      let found = false;
      for (let i = 0; i < size; i++) {
        if (list[i] === x) {
          found = true;
          break;
        }
      }
      if (found) continue;
      if (rank === u) return x;
      rank++;
    }
    return u - rank;
  }

  // this.moved[0 .. moves) ascending, in this.cornerList.
  sortedMoved(moves) {
    if (moves > this.cornerList.length) this.cornerList = new Int32Array(2 * moves);
    const out = this.cornerList, moved = this.moved;
    for (let i = 0; i < moves; i++) {
      const c = moved[i];
      let j = i - 1;
      while (j >= 0 && out[j] > c) {
        out[j + 1] = out[j];
        j--;
      }
      out[j + 1] = c;
    }
    return out;
  }

  setWedge(c, w) {
    if (!(w >= 0 && w < this.wedgeCount)) {
      throw new PacketError(`a corner is given wedge ${w}, which does not exist`);
    }
    this.corners[c] = w;
    this.wedgeVertex[w] = this.faces[c];
    this.markCorners(c, c + 1);
  }

  // The wedge part of collapse t into s, after its geometry part (t's corners
  // are s's now): the last wedges go, each merged into its parent.
  collapseWedges(t, s, ratio, readers) {
    const wedgeCount = readers[7], wedgeParent = readers[8];
    const { wedges, corners, components, head, next } = this;
    const { attributeOffset, attributeComponents, attributeLimit } = this;
    const top = this.wedgeCount;
    const m = readVarint(wedgeCount);
    const bottom = top - m;
    if (bottom < 0) throw new PacketError(`collapse of ${t} removes more wedges than there are`);
    if (m > this.parents.length) this.parents = new Int32Array(2 * m);
    let smallest = -2, known = -1;
    for (let x = top - 1; x >= bottom; x--) {
      const u = readVarint(wedgeParent);
      let p;
      if (u === 0) {
        if (smallest === -2) {
          smallest = -1;
          for (let c = head[s]; c !== NONE; c = next[c]) {
            const w = corners[c];
            if (w < bottom && (smallest < 0 || w < smallest)) smallest = w;
          }
        }
        p = smallest >= 0 ? smallest : 0;
      } else {
        if (known < 0) {
          let n = 0;
          for (let c = head[s]; c !== NONE; c = next[c]) {
            if (n === this.cornerList.length) this.cornerList = grow(this.cornerList, n);
            this.cornerList[n++] = c;
          }
          known = this.heldWedges(this.cornerList, n, bottom);
        }
        p = u < known ? this.wedgeList[u] : u - known;
      }
      if (!(p >= 0 && p < x)) {
        throw new PacketError(`collapse of ${t} merges wedge ${x} into ${p}, which is not below it`);
      }
      this.parents[x - bottom] = p;
      // the merged value: between the two as the positions are, plus a residual
      const pc = components * p, xc = components * x;
      for (let i = 0; i < attributeOffset.length; i++) {
        const stream = readers[10 + i], limit = attributeLimit[i];
        const first = attributeOffset[i], end = first + attributeComponents[i];
        for (let k = first; k < end; k++) {
          const a = wedges[pc + k];
          const q = a + Math.floor(ratio * (wedges[xc + k] - a) + 0.5) + readSigned(stream);
          if (!(q >= 0 && q < limit)) {
            throw new PacketError(`collapse of ${t} moves a ${this.attributes[i].name} value ` +
                                  'off its grid');
          }
          wedges[pc + k] = q;
        }
      }
      this.touchWedge(p);
    }
    this.wedgeCount = bottom;
    // corners holding a removed wedge take its parent (repeatedly)
    for (let c = head[s]; c !== NONE; c = next[c]) {
      let w = corners[c];
      if (w < bottom) {
        this.wedgeVertex[w] = s;
        continue;
      }
      while (w >= bottom) w = this.parents[w - bottom];
      this.setWedge(c, w);
    }
  }

  // ---- connectivity ----------------------------------------------------------

  link(c, v) {
    this.next[c] = this.head[v];
    this.head[v] = c;
  }

  // Singly linked: the walk to c's predecessor is short (a vertex's valence)
  // and usually over a list just gathered, so cheaper than keeping back links.
  unlink(c, v) {
    const { head, next } = this;
    if (head[v] === c) {
      head[v] = next[c];
      return;
    }
    let p = head[v];
    while (next[p] !== c) p = next[p];
    next[p] = next[c];
  }

  moveCorner(c, v) {
    this.unlink(c, this.faces[c]);
    this.faces[c] = v;
    this.link(c, v);
    this.markCorners(c, c + 1);
  }

  // corners(v) into the scratch, each with its next and prev vertex in the face.
  gatherCorners(v) {
    const { faces, next } = this;
    let n = 0;
    for (let c = this.head[v]; c !== NONE; c = next[c]) {
      if (n === this.aroundCorners.length) this.growScratch();
      const slot = c % 3;
      this.aroundCorners[n] = c;
      this.aroundNexts[n] = faces[slot === 2 ? c - 2 : c + 1];
      this.aroundPrevs[n] = faces[slot === 0 ? c + 2 : c - 1];
      n++;
    }
    this.aroundCount = n;
  }

  growScratch() {
    const size = 2 * this.aroundCorners.length;
    for (const name of ['aroundCorners', 'aroundNexts', 'aroundPrevs', 'moved']) {
      const grown = new Int32Array(size);
      grown.set(this[name]);
      this[name] = grown;
    }
    this.neighbours = new Int32Array(2 * size);
    this.fanMark = new Float64Array(size);
  }

  // neighbours(v): the distinct other vertices of v's faces, ascending
  // (insertion sort: a handful of values; a library sort costs more here).
  gatherNeighbours(v) {
    const { aroundNexts: nexts, aroundPrevs: prevs, aroundCount: count } = this;
    const out = this.neighbours;
    let n = 0;
    for (let i = 0; i < 2 * count; i++) {
      const u = i < count ? nexts[i] : prevs[i - count];
      if (u === v) continue;
      let j = n - 1;
      while (j >= 0 && out[j] > u) j--;
      if (j >= 0 && out[j] === u) continue;
      for (let m = n; m > j + 1; m--) out[m] = out[m - 1];
      out[j + 1] = u;
      n++;
    }
    this.neighbourCount = n;
  }

  // A vertex code relative to the sorted neighbours: a rank, else an id past them.
  decodeVertex(code) {
    return code < this.neighbourCount ? this.neighbours[code] : code - this.neighbourCount;
  }

  // The corners held(s) flags in the mask stream, into this.moved; their count.
  listedCorners(mask) {
    const count = this.aroundCount;
    const held = Array.from(this.aroundCorners.subarray(0, count)).sort((a, b) => a - b);
    const bits = readBytes(mask, (count + 7) >> 3);
    let moves = 0;
    for (let i = 0; i < count; i++) {
      if ((bits[i >> 3] >> (i & 7)) & 1) this.moved[moves++] = held[i];
    }
    return moves;
  }

  // The predicted fan of a split (docs/packets.md, Hoppe 1996's vl/vr rule)
  // into this.moved; returns its size, or -1 when there is no prediction.
  predictFan(s, t, k) {
    const added = this.added;
    let vl = NONE, vr = NONE;
    for (let i = 0; i < 3 * k; i += 3) {
      let at = -1, tAt = -1;
      for (let j = 2; j >= 0; j--) {
        // the first occurrence, as index() in the reference
        if (added[i + j] === s) at = j;
        if (added[i + j] === t) tAt = j;
      }
      if (at < 0 || tAt < 0) return -1;
      if ((at + 1) % 3 === tAt) vl = added[i + (tAt + 1) % 3];
      else vr = added[i + (at + 1) % 3];
    }
    // From vl: look corners up by their prev vertex and step to their next,
    // until vr. From vr alone (a border): look up by next, step to prev.
    const { aroundCorners: corners, aroundCount: count, fanMark } = this;
    const stamp = ++this.fanStamp;   // marks this walk's corners without clearing old marks
    let keys = this.aroundPrevs, steps = this.aroundNexts, y = vl, end = vr;
    if (vl === NONE) {
      if (vr === NONE) return -1;
      keys = this.aroundNexts;
      steps = this.aroundPrevs;
      y = vr;
      end = NONE;
    }
    let moves = 0;
    for (;;) {
      // the corner keyed by y; two of them means a non-manifold edge: no prediction
      let found = NONE;
      for (let i = 0; i < count; i++) {
        if (keys[i] !== y) continue;
        if (found !== NONE) return -1;
        found = i;
      }
      if (found === NONE || fanMark[found] === stamp) break;
      fanMark[found] = stamp;
      this.moved[moves++] = corners[found];
      y = steps[found];
      if (y === end) break;
    }
    return moves;
  }
}
