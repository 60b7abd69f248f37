// The wedge tools both directions share: the split ratio, the gradient of a
// wedge's values against position and the extrapolation along it, wedges(L)
// and the wedge codes relative to it, and giving a corner its wedge. Mirrors
// docs/packets.md, "The client's state" (wedges(L)) and the predictions of
// "The wedge part of split t"; the reference is lodserver/packets/reference.py
// (split_ratio, fit_gradient, extrapolated, corner_candidates).
//
// The predictions must be bit for bit the reference's: the same float
// operations in the same order, so a residual decodes to the value the server
// encoded. The wedge scratch: coarse (vs's position before the split),
// gradient, sums, wedgeList, heldSorted, cornerList.
//
// These are methods of LodState, mixed into its prototype by levelstate.js
// (`this` is the state), not functions taking it: the record loops call them
// as the class's own methods, which cost less in those hot loops than calls
// to another module's functions.

import { PacketError } from './packet.js';

const MAX_SPLIT_RATIO = 4;
const GRADIENT_DAMPING = 1e-3;

// How far t lies beyond vs's coarse position, in units of coarse - fine: the
// split ratio of docs/packets.md (this.coarse: vs before the split).
function splitRatio(s, t) {
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
// reference.py fit_gradient, the same float operations in the same order)
// into this.gradient (3 rows of `components`); false when there is none.
// held[0 .. n): held(s), ascending.
function fitGradient(s, p, held, n) {
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
  // Damped (a fraction of the trace, as docs/packets.md fixes it) so a flat fan,
  // all its edges in one plane, still gives a solvable system.
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

// floor(value + J . (position of v - coarse) + 0.5) within [0, limit), for
// component j of the gradient fitGradient() left in the this.
function extrapolate(j, value, v, limit) {
  const { gradient, positions, coarse, components } = this;
  const x = (value + ((positions[3 * v] - coarse[0]) * gradient[j] +
                      (positions[3 * v + 1] - coarse[1]) * gradient[components + j] +
                      (positions[3 * v + 2] - coarse[2]) * gradient[2 * components + j])) + 0.5;
  if (!(x >= 0)) return 0;
  if (x > limit - 1) return limit - 1;
  return Math.floor(x);
}

// from[0 .. n) ascending, into out (an insertion sort: a vertex's corners, a
// handful); out.
function sortInto(from, n, out) {
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

// held(s) (the scratch's corners) ascending, in this.heldSorted.
function sortedHeld() {
  const n = this.aroundCount;
  if (n > this.heldSorted.length) this.heldSorted = new Int32Array(2 * n);
  return sortInto(this.aroundCorners, n, this.heldSorted);
}

// this.moved[0 .. moves) ascending, in this.cornerList.
function sortedMoved(moves) {
  if (moves > this.cornerList.length) this.cornerList = new Int32Array(2 * moves);
  return sortInto(this.moved, moves, this.cornerList);
}

// The smallest wedge below `below` of the corners cornerIds[0 .. n), or `none`
// if there is none: code 0, the common case, without building wedges(L).
function smallestWedge(cornerIds, n, below, none) {
  let w = -1;
  const corners = this.corners;
  for (let i = 0; i < n; i++) {
    const x = corners[cornerIds[i]];
    if (x < below && (w < 0 || x < w)) w = x;
  }
  return w < 0 ? none : w;
}

// wedges(L) of the corners cornerIds[start .. end), those below `below`,
// ascending, into this.wedgeList; their number.
function heldWedges(cornerIds, start, end, below) {
  if (end - start > this.wedgeList.length) this.wedgeList = new Int32Array(2 * (end - start));
  const list = this.wedgeList, corners = this.corners;
  let size = 0;
  for (let i = start; i < end; i++) {
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
function candidate(u, size, bottom, top) {
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

// Corner c holds wedge w now (and w's vertex is c's).
function setWedge(c, w) {
  if (!(w >= 0 && w < this.wedgeCount)) {
    throw new PacketError(`a corner is given wedge ${w}, which does not exist`);
  }
  this.corners[c] = w;
  this.wedgeVertex[w] = this.faces[c];
  this.markCorners(c, c + 1);
}

// The methods of LodState this module defines.
export const wedgeMethods = {
  splitRatio, fitGradient, extrapolate, sortedHeld, sortedMoved, smallestWedge, heldWedges,
  candidate, setWedge,
};
