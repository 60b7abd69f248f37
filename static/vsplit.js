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

const MAGIC = 0x56444f4c;          // "LODV" read as a little-endian u32
const PACKET_VERSION = 1;
const HEADER_BYTES = 60;
const STREAM_NAMES = ['vertex', 'count', 'pattern', 'other', 'fan', 'mask', 'position'];
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
    const state = new LodState(document.grid, vertexCapacity, faceCapacity);
    const { positions, faces } = state;
    document.positions.forEach((q, v) => positions.set(q, 3 * v));
    document.faces.forEach((corners, f) => faces.set(corners, 3 * f));
    state.vertexCount = vertexCount;
    state.faceCount = faceCount;
    for (let c = 0; c < 3 * faceCount; c++) state.link(c, faces[c]);
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
    if (version !== PACKET_VERSION) {
      throw new PacketError(`the packet has version ${version}; this decoder reads ` +
                            `${PACKET_VERSION}`);
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
      streams: [],
    };
    const bodyLength = view.getUint32(56, true);
    let body;
    try {
      body = await inflate(bytes.subarray(HEADER_BYTES));
    } catch (error) {
      throw new PacketError(`the packet's body does not inflate (${error.message})`);
    }
    if (body.length !== bodyLength) {
      throw new PacketError(`the packet's body is ${body.length} bytes, the header says ` +
                            `${bodyLength}`);
    }
    const table = makeReader(body, 'stream table');
    for (const name of STREAM_NAMES) packet.streams.push(readBytes(table, readVarint(table)));
    if (table.at !== body.length) {
      throw new PacketError("the packet's body has bytes after its last stream");
    }
    return packet;
  }

  constructor(grid, vertexCapacity, faceCapacity) {
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
    this.clean();
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
  takeDirty() {
    const dirty = { vertexStart: this.vertexStart, vertexEnd: this.vertexEnd,
                    cornerStart: this.cornerStart, cornerEnd: this.cornerEnd };
    this.clean();
    return dirty;
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
    const readers = packet.streams.map((data, i) => makeReader(data, STREAM_NAMES[i]));
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

  applySplits(start, stop, [vertex, count, pattern, other, fan, mask, position]) {
    const { positions, faces, gridSize } = this;
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
    }
  }

  applyCollapses(start, stop, [vertex, count, , , , , position]) {
    const { positions, faces, gridSize } = this;
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
      for (let j = 0; j < 3; j++) {
        const q = ((positions[3 * s + j] + positions[3 * t + j]) >> 1) + readSigned(position);
        if (!(q >= 0 && q < gridSize)) throw offGrid();
        positions[3 * s + j] = q;
      }
      this.vertexCount = t;
      this.markVertices(s, s + 1);
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
