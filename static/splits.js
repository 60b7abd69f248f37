// Vertex splits: a packet from level A up to level B > A, applied record by
// record to a LodState. Mirrors docs/packets.md, "Split records" and "The
// wedge part of split t"; the reference is lodserver/packets/reference.py
// (_apply_splits, _split_wedges).
//
// Split t creates vertex t from vertex s: new faces (their corners coded by a
// base-3 pattern and neighbour ranks), a fan of s's corners moved to t
// (predicted, else listed), then the two new positions; with attributes, new
// wedges and the wedge of every corner the split changed.
//
// These are methods of LodState, mixed into its prototype by levelstate.js
// (`this` is the state), not functions taking it: the record loops call them
// as the class's own methods, which cost less in those hot loops than calls
// to another module's functions.

import { grow } from './arrays.js';
import { AHEAD_GROUP, READ_AHEAD_VERTICES } from './fans.js';
import { offGrid, PacketError } from './packet.js';

const FAN_PREDICTED = 0;
const IS_VS = 0, IS_NEW = 1;       // corner kinds in a new face's pattern; 2 = another vertex
// The kinds of the three corners of each pattern code 0..26 (its base-3 digits,
// first corner first), looked up rather than divided out per corner.
const PATTERN_KINDS = Uint8Array.from({ length: 81 },
                                      (_, i) => Math.floor((i / 3 | 0) / 3 ** (2 - i % 3)) % 3);

// Splits start .. stop-1 from the packet's stream readers (streamNames() order).
function applySplits(start, stop, readers) {
  const [vertex, count, pattern, other, fan, mask, position] = readers;
  const { positions, faces, gridSize } = this;
  const hasWedges = this.attributes.length > 0;
  const material = this.faceMaterial ? readers[readers.length - 1] : null;
  // Every record's s first (the vertex stream is read on its own), so each
  // record can touch the memory of the next ones' s before it needs it.
  if (stop - start > this.sources.length) this.sources = new Int32Array(2 * (stop - start));
  const sources = this.sources;
  for (let t = start; t < stop; t++) {
    const s = t - 1 - vertex.next();
    if (s < 0) throw new PacketError(`split ${t} names a vertex below 0`);
    sources[t - start] = s;
  }
  const ahead = this.vertexCapacity >= READ_AHEAD_VERTICES;
  if (ahead) {
    // the pipeline's first groups: the steps readAhead() takes for them before they run
    this.readAhead(sources, -3 * AHEAD_GROUP, stop - start);
    this.readAhead(sources, -2 * AHEAD_GROUP, stop - start);
    this.readAhead(sources, -AHEAD_GROUP, stop - start);
  }
  for (let t = start; t < stop; t++) {
    const s = sources[t - start];
    if (ahead && (t - start) % AHEAD_GROUP === 0) this.readAhead(sources, t - start, stop - start);
    this.parent[t] = s;
    // held(s) and neighbours(s) are taken before the record changes anything.
    this.gatherCorners(s);
    const k = count.next();
    if (3 * k > this.added.length) this.added = new Int32Array(6 * k);
    const added = this.added;
    let neighboursKnown = false;
    for (let i = 0; i < 3 * k; i += 3) {
      const code = pattern.next();
      if (code > 26) throw new PacketError(`split ${t} has a face pattern out of range`);
      // the base-3 digits of code, first corner first
      for (let j = 0; j < 3; j++) {
        const kind = PATTERN_KINDS[3 * code + j];
        let v;
        if (kind === IS_VS) v = s;
        else if (kind === IS_NEW) v = t;
        else {
          // neighbours(s) is gathered lazily: a record whose faces name only
          // s and t never needs it
          if (!neighboursKnown) {
            this.gatherNeighbours(s);
            neighboursKnown = true;
          }
          v = this.decodeVertex(other.next());
        }
        if (v > t) {
          throw new PacketError(`split ${t} adds a face on a vertex that does not exist yet`);
        }
        added[i + j] = v;
      }
    }

    const moves = fan.next() === FAN_PREDICTED
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
      const fine = coarse + position.signed();
      if (!(fine >= 0 && fine < gridSize)) throw offGrid();
      positions[pt + j] = 2 * coarse - fine;
      positions[ps + j] = fine;
    }
    for (let j = 0; j < 3; j++) {
      const q = positions[pt + j] + position.signed();
      if (!(q >= 0 && q < gridSize)) throw offGrid();
      positions[pt + j] = q;
    }
    this.vertexCount = t + 1;
    this.markVertices(s, t + 1);
    if (material) {
      for (let f = firstFace; f < this.faceCount; f++) {
        this.faceMaterial[f] = material.next() - 1;
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

// The wedge part of split t (docs/packets.md), after its geometry part: the
// scratch still holds held(s) as gathered before the split, this.moved its
// `moves` moved corners, and its new faces start at face firstFace.
// Codes are nearly always 0, the smallest candidate: found by one walk,
// without building the sorted list.
function splitWedges(s, t, moves, firstFace, readers) {
  const wedgeCount = readers[7], wedgeParent = readers[8], wedgeCorner = readers[9];
  const { wedges, corners, components, faces, fine, ring, ringInfo } = this;
  const { attributeOffset, attributeComponents, attributeLimit } = this;
  const bottom = this.wedgeCount;
  const m = wedgeCount.next();
  const top = bottom + m;
  if (top > this.wedgeCapacity) {
    throw new PacketError(`split ${t} adds wedges beyond the mesh this state was made for`);
  }
  if (m > this.parents.length) this.parents = new Int32Array(2 * m);
  // held(s) ascending, for the gradient's sums
  const held = m > 0 ? this.sortedHeld() : null;
  // parents, by rank among the wedges of held(s)
  let known = -1, ratio = -1;
  for (let x = bottom; x < top; x++) {
    const u = wedgeParent.next();
    let p;
    if (u === 0) p = this.smallestWedge(this.aroundCorners, this.aroundCount, bottom, 0);
    else {
      if (known < 0) known = this.heldWedges(this.aroundCorners, 0, this.aroundCount, bottom);
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
        fine[k] = guess + stream.signed();
      }
      for (let k = first; k < end; k++) {
        const c = wedges[pc + k];
        const guess = fitted ? this.extrapolate(k, c, t, limit)
          : c + Math.floor(ratio * (c - fine[k]) + 0.5);
        const q = guess + stream.signed();
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
    const u = wedgeCorner.next();
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
    const u = wedgeCorner.next();
    let w;
    if (u === 0) {
      w = -1;
      for (let i = ringInfo[4 * v], end = i + ringInfo[4 * v + 1]; i < end; i++) {
        const d = ring[i];
        if (d < limit && (w < 0 || corners[d] < w)) w = corners[d];
      }
      if (w < 0) w = this.candidate(0, 0, bottom, top);
    } else {
      let n = 0;
      for (let i = ringInfo[4 * v], end = i + ringInfo[4 * v + 1]; i < end; i++) {
        const d = ring[i];
        if (d >= limit) continue;
        if (n === this.cornerList.length) this.cornerList = grow(this.cornerList, n);
        this.cornerList[n++] = d;
      }
      w = this.candidate(u, this.heldWedges(this.cornerList, 0, n, top), bottom, top);
    }
    this.setWedge(c, w);
  }
}

// The methods of LodState this module defines.
export const splitMethods = { applySplits, splitWedges };
