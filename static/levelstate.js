// The level a client holds (LodState): its arrays, the dirty ranges a renderer
// re-uploads, and apply(), which checks a packet fits and runs its records.
// Mirrors docs/packets.md, "Exactness" (the quantized form of a level) and
// "The client's state"; the reference is lodserver/packets/ (grids.py:
// state_from_json; reference.py: apply_packet).
//
// The state is one level in its quantized form: integer grid positions and
// faces in their prefix-layout slots. The arrays are allocated once at
// full-detail size, so three.js can render them in place: a level is a prefix
// of both (draw range), and a packet changes only a few ranges of them
// (reported by takeDirty()).
//
// Unlike the reference, apply() works in place for speed: a packet that fails
// half-way leaves the state unusable, and the caller must reopen the mesh.
//
// A mesh with attributes (any of lodserver/mesh.py's ATTRIBUTE_RULES: normals, UVs,
// colours, tangents, skin, morph deltas, custom ones) also has wedges (version 2 and 3
// packets): integer grid values per wedge, the wedge of every corner, and the
// material of every face. The state keeps each wedge's vertex (the vertex of
// the corners holding it) so a renderer can draw one vertex per wedge, and
// lists the vertices and wedges a packet touched (takeDirty()).
//
// The records themselves are in splits.js and collapses.js, the corner lists
// in fans.js, the wedge predictions in wedges.js: methods of this class, each
// module's mixed in at the end of this one.

import { grow } from './arrays.js';
import { collapseMethods } from './collapses.js';
import { fanMethods, homeRings, NONE } from './fans.js';
import {
  attributeGrid, fieldReader, PacketError, readPacket, sameGrid, streamNames,
} from './packet.js';
import { splitMethods } from './splits.js';
import { wedgeMethods } from './wedges.js';

// Puts x at list[count], growing the list first when it is full; the list
// (the grown one if it grew).
function append(list, count, x) {
  if (count === list.length) list = grow(list, count);
  list[count] = x;
  return list;
}

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
      ([name, width]) => attributeGrid(name, document.attribute_grid[name], width));
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

  // Parse a packet's header and decode its fields (packet.js); apply() checks it fits.
  static readPacket(buffer) {
    return readPacket(buffer);
  }

  // Every field is set here, scratch included, so all states share one shape
  // and the record loops stay monomorphic.
  constructor(grid, vertexCapacity, faceCapacity,
              { attributes = [], wedgeCapacity = 0, hasMaterials = false } = {}) {
    this.grid = { origin: [...grid.origin], step: grid.step, bits: grid.bits };
    this.gridSize = 2 ** grid.bits;                        // grid coordinates are below this
    this.positions = new Int32Array(3 * vertexCapacity);   // grid coordinates, xyz per vertex
    this.faces = new Uint32Array(3 * faceCapacity);        // vertex per corner
    this.vertexCount = 0;
    this.faceCount = 0;
    // corners(v) (fans.js): ring[at .. at + size), room for `room`, where
    // ringInfo[4v ..] = at, size, room (the fourth column unused)
    const rings = homeRings(vertexCapacity);
    this.ringInfo = rings.ringInfo;
    this.ring = rings.ring;
    this.ringEnd = rings.ringEnd;                          // the pool's used length
    this.sources = new Int32Array(1024);                   // s of each record of a packet
    this.sink = 0;                                         // where reads ahead go (splits.js)
    // The vertex each vertex t was split from (its parent s, the same in both
    // directions), once a split or a collapse of t named it: what geomorphs
    // glide a new vertex out of, and a vanishing one into.
    this.parent = new Int32Array(vertexCapacity).fill(NONE);
    // Scratch for one record (fans.js): corners of a vertex with their next and prev vertices.
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
    // Scratch for the wedge records (wedges.js, and the wedge parts of splits.js, collapses.js).
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
    return this.ringInfo.length / 4;
  }

  get faceCapacity() {
    return this.faces.length / 3;
  }

  // ---- what changed ------------------------------------------------------------

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
    this.touchedVertices = append(this.touchedVertices, this.touchedVertexCount++, v);
  }

  touchWedge(w) {
    if (this.wedgeTouched[w]) return;
    this.wedgeTouched[w] = 1;
    this.touchedWedges = append(this.touchedWedges, this.touchedWedgeCount++, w);
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

  // ---- packets -------------------------------------------------------------------

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
    const readers = packet.fields.map((values, i) => fieldReader(values, names[i]));
    // a version 4 packet whose positions need the state as it goes (packet_v4.js,
    // RING_POSITIONS) gives the reader of its position field itself
    if (packet.positionReader) readers[names.indexOf('position')] = packet.positionReader(this);
    if (packet.stop > packet.start) this.applySplits(packet.start, packet.stop, readers);
    else this.applyCollapses(packet.start, packet.stop, readers);
    if (!readers.every((reader) => reader.done())) {
      throw new PacketError("the packet's streams hold more than its records");
    }
    if (this.faceCount !== packet.stopFaces) {
      throw new PacketError(`the packet left ${this.faceCount} faces, its header says ` +
                            `${packet.stopFaces}`);
    }
    this.checkHandedness();
    return Math.abs(packet.stop - packet.start);
  }

  // A tangent's handedness is 0 or 1 (w = -1 or +1) on its grid, not any value below
  // 2^bits: checked on the wedges touched since takeDirty() (those a packet changed).
  checkHandedness() {
    const { wedges, components, touchedWedges } = this;
    for (const a of this.attributes) {
      if (a.encoding !== 'tangent') continue;
      for (let i = 0; i < this.touchedWedgeCount; i++) {
        if (wedges[components * touchedWedges[i] + a.offset + 2] > 1) {
          throw new PacketError('the packet gives a TANGENT a handedness other than -1 or +1');
        }
      }
    }
  }
}

// Once, at load: the parts' methods become the class's own (see fans.js for why).
Object.assign(LodState.prototype, fanMethods, wedgeMethods, splitMethods, collapseMethods);
