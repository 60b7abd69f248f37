// Edge collapses: a packet from level A down to level B < A, applied record by
// record to a LodState. Mirrors docs/packets.md, "Collapse records"; the
// reference is lodserver/packets/reference.py (_apply_collapses, _collapse_wedges).
//
// Collapse t merges the last vertex t into s: the last faces go (the prefix
// layout puts a split's new faces last), t's corners become s's, s moves to
// the midpoint plus a residual; with attributes, the last wedges merge into
// their parents.
//
// These are methods of LodState, mixed into its prototype by levelstate.js
// (`this` is the state), not functions taking it: the record loops call them
// as the class's own methods, which cost less in those hot loops than calls
// to another module's functions.

import { READ_AHEAD_VERTICES } from './fans.js';
import { offGrid, PacketError } from './packet.js';

// Collapses start-1 down to stop from the packet's stream readers (streamNames() order).
function applyCollapses(start, stop, readers) {
  const [vertex, count, , , , , position] = readers;
  const { positions, faces, gridSize } = this;
  const hasWedges = this.attributes.length > 0;
  let sink = 0;
  const ahead = this.vertexCapacity >= READ_AHEAD_VERTICES;
  for (let t = start - 1; t >= stop; t--) {
    this.gatherCorners(t);
    this.gatherNeighbours(t);
    const s = this.decodeVertex(vertex.next());
    if (!(s >= 0 && s < t)) {
      throw new PacketError(`collapse of ${t} names vertex ${s}, which is not below it`);
    }
    this.parent[t] = s;
    const removed = count.next();
    if (removed > this.faceCount) {
      throw new PacketError(`collapse of ${t} removes more faces than the state holds`);
    }
    this.faceCount -= removed;
    for (let c = 3 * this.faceCount; c < 3 * (this.faceCount + removed); c++) {
      this.unlink(c, faces[c]);
    }
    // Reads whose values are not used (summed into a field, so they are kept):
    // the vertices of the faces just below, which the next record removes (its
    // s and the other vertices of its split's faces), their rows and positions.
    if (ahead) {
      const info = this.ringInfo;
      for (let c = Math.max(3 * this.faceCount - 6, 0); c < 3 * this.faceCount; c++) {
        const u = faces[c];
        sink = (sink + info[4 * u] + positions[3 * u]) | 0;
      }
    }
    this.moveAll(t, s);
    // floor((q_s + q_t) / 2) + r; both are non-negative, so >> 1 is the floor.
    const ps = 3 * s, pt = 3 * t;
    const f0 = positions[ps], f1 = positions[ps + 1], f2 = positions[ps + 2];
    for (let j = 0; j < 3; j++) {
      const q = ((positions[ps + j] + positions[pt + j]) >> 1) + position.signed();
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
  this.sink = sink;
}

// The wedge part of collapse t into s, after its geometry part (t's corners
// are s's now): the last wedges go, each merged into its parent.
function collapseWedges(t, s, ratio, readers) {
  const wedgeCount = readers[7], wedgeParent = readers[8];
  const { wedges, corners, components, ring } = this;
  const from = this.ringInfo[4 * s], to = from + this.ringInfo[4 * s + 1];   // corners(s)
  const { attributeOffset, attributeComponents, attributeLimit } = this;
  const top = this.wedgeCount;
  const m = wedgeCount.next();
  const bottom = top - m;
  if (bottom < 0) throw new PacketError(`collapse of ${t} removes more wedges than there are`);
  if (m > this.parents.length) this.parents = new Int32Array(2 * m);
  // code 0's parent and wedges(corners(s)) are each found once per record, and
  // only if a code needs them (-2, -1: not yet)
  let smallest = -2, known = -1;
  for (let x = top - 1; x >= bottom; x--) {
    const u = wedgeParent.next();
    let p;
    if (u === 0) {
      if (smallest === -2) {
        smallest = -1;
        for (let i = from; i < to; i++) {
          const w = corners[ring[i]];
          if (w < bottom && (smallest < 0 || w < smallest)) smallest = w;
        }
      }
      p = smallest >= 0 ? smallest : 0;
    } else {
      if (known < 0) {
        known = this.heldWedges(ring, from, to, bottom);
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
        const q = a + Math.floor(ratio * (wedges[xc + k] - a) + 0.5) + stream.signed();
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
  for (let i = from; i < to; i++) {
    const c = ring[i];
    let w = corners[c];
    if (w < bottom) {
      this.wedgeVertex[w] = s;
      continue;
    }
    while (w >= bottom) w = this.parents[w - bottom];
    this.setWedge(c, w);
  }
}

// The methods of LodState this module defines.
export const collapseMethods = { applyCollapses, collapseWedges };
