// The normals' part of a geomorph (geomorph.js): the normals shown per GPU
// vertex (a wedge, or a vertex), glided from those shown to a new level's so
// that the shading does not pop when the level lands (the most visible pop
// left once positions glide).

import { levelNormals } from './levelmesh.js';
import { dequantize } from './packet.js';

// A normal that moved less than this (per component) is not glided.
const NORMAL_EPSILON = 1e-3;

export class NormalGlide {
  // drawn: the GPU vertices a full-detail level has (wedges, or vertices).
  constructor(drawn) {
    this.shown = new Float32Array(3 * drawn);   // the normals on screen
    this.start = new Float32Array(3 * drawn);   // a glide's ends
    this.end = new Float32Array(3 * drawn);
    this.list = new Int32Array(1024);           // the GPU vertices gliding, count of them
    this.count = 0;
  }

  // The GPU's normals [0, count) as shown now (normal: the mesh's attribute).
  take(normal, count) {
    this.shown.set(normal.array.subarray(0, 3 * count));
  }

  // Glides the GPU normals i in [0, count) whose end (endOf(i, out, at)) differs
  // from the one shown; the others are set to their end at once.
  plan(count, endOf) {
    const { end, start, shown } = this;
    this.count = 0;
    for (let i = 0; i < count; i++) {
      const k = 3 * i;
      endOf(i, end, k);
      if (Math.abs(end[k] - shown[k]) < NORMAL_EPSILON &&
          Math.abs(end[k + 1] - shown[k + 1]) < NORMAL_EPSILON &&
          Math.abs(end[k + 2] - shown[k + 2]) < NORMAL_EPSILON) continue;
      start[k] = shown[k];
      start[k + 1] = shown[k + 1];
      start[k + 2] = shown[k + 2];
      if (this.count === this.list.length) {
        const grown = new Int32Array(2 * this.list.length);
        grown.set(this.list);
        this.list = grown;
      }
      this.list[this.count++] = i;
    }
  }

  // Writes the gliding normals at ease `t` into the mesh's attribute `normal`.
  write(normal, t) {
    if (!this.count) return;
    const { list, start, end, shown } = this;
    const out = normal.array;
    let low = Infinity, high = -1;
    for (let j = 0; j < this.count; j++) {
      const i = list[j], k = 3 * i;
      for (let c = 0; c < 3; c++) {
        const x = start[k + c] + (end[k + c] - start[k + c]) * t;
        out[k + c] = x;
        shown[k + c] = x;
      }
      if (i < low) low = i;
      if (i > high) high = i;
    }
    normal.addUpdateRange(3 * low, 3 * (high - low + 1));
    normal.needsUpdate = true;
  }

  // A refinement from level `from` to `to` of `state` was written into the
  // mesh's `normal`: glide to it from the normals shown, a new vertex from its
  // ancestor's, a new wedge (from oldDrawn on) from its own.
  planSplits(state, normal, from, to, oldDrawn) {
    const { shown } = this;
    const wedged = state.attributes.length > 0;
    if (!wedged) {
      for (let v = from; v < to; v++) {
        const p = 3 * state.parent[v], k = 3 * v;
        shown[k] = shown[p];
        shown[k + 1] = shown[p + 1];
        shown[k + 2] = shown[p + 2];
      }
    } else {
      shown.set(normal.array.subarray(3 * oldDrawn, 3 * state.wedgeCount), 3 * oldDrawn);
    }
    this.plan(wedged ? state.wedgeCount : to, (i, out, at) => {
      out[at] = normal.array[at];
      out[at + 1] = normal.array[at + 1];
      out[at + 2] = normal.array[at + 2];
    });
  }

  // A coarsening of `state` to level `to` (wedgesTo wedges), the GPU still
  // drawing `drawn` vertices: each glides to the new level's normal, per
  // vertex from levelNormals (into scratch, (3 * capacity) float; a vanishing
  // vertex takes its ancestor's, ancestor[v]), per wedge its streamed NORMAL
  // (a vanishing wedge keeps its own) or its vertex's.
  planCollapses(state, drawn, to, wedgesTo, ancestor, scratch) {
    const normals = state.attributes.find((a) => a.name === 'NORMAL');
    if (!normals) levelNormals(state, scratch);
    const vertexOf = (v) => (v < to ? v : ancestor[v]);
    const fromVertex = (v, out, at) => {
      const k = 3 * vertexOf(v);
      out[at] = scratch[k];
      out[at + 1] = scratch[k + 1];
      out[at + 2] = scratch[k + 2];
    };
    if (!state.attributes.length) {
      this.plan(drawn, fromVertex);
      return;
    }
    const { wedges, components, wedgeVertex } = state;
    this.plan(drawn, (i, out, at) => {
      if (!normals) fromVertex(wedgeVertex[i], out, at);
      else if (i < wedgesTo) dequantize(normals, wedges, components * i + normals.offset, out, at);
      else out.set(this.shown.subarray(at, at + 3), at);
    });
  }
}
