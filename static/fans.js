// Corner bookkeeping: corners(v), held(v), neighbours(v) and vertex codes, and
// the fan of corners a split moves, predicted or listed. Mirrors docs/packets.md,
// "The client's state", and steps 1-2 and the fan steps of "Split records"
// (Hoppe 1996's vl/vr rule); the reference is lodserver/packets/reference.py
// (predict_fan).
//
// corners(v), the corners c = 3 * face + slot holding v, are kept per vertex in
// a block of one shared pool (ring): the block of v starts at ringInfo[4v],
// holds ringInfo[4v + 1] corners, in no particular order (every use sorts them
// or takes a minimum), and has room for ringInfo[4v + 2] (one 16-byte row per
// vertex, so a vertex's three numbers are one memory read). A vertex's corners
// are read from one run of memory, not chased through a list threaded across
// the face array (a cache miss per corner on a large mesh). Every vertex starts with a home block
// of FIRST_ROOM corners at FIRST_ROOM * v (vertices made one after another have
// their blocks side by side); a vertex whose block fills moves to a block twice
// as big at the pool's end, and a vertex a collapse empties keeps its block
// for when a split makes it again.
//
// The per-record scratch: aroundCorners/Nexts/Prevs (the corners gathered
// around one vertex, each with its next and prev vertex in its face),
// neighbours, moved.
//
// These are methods of LodState, mixed into its prototype by levelstate.js
// (`this` is the state), not functions taking it: the record loops call them
// as the class's own methods, which cost less in those hot loops than calls
// to another module's functions.

export const NONE = -1;            // no corner, no vertex

const FIRST_ROOM = 8;               // corners a vertex's home block holds (valence 6 is typical)
// From this many vertices the state's arrays outgrow a core's cache, and the
// record loops (splits.js, collapses.js) read the memory of the next records
// ahead; below it, those reads would only cost.
export const READ_AHEAD_VERTICES = 1 << 16;
// Splits read ahead in groups of this many records (readAhead).
export const AHEAD_GROUP = 32;

// The rows and pool of vertexCapacity vertices, each with its empty home block:
// { ringInfo, ring, ringEnd } for LodState's fields.
export function homeRings(vertexCapacity) {
  const ringInfo = new Int32Array(4 * vertexCapacity);
  for (let v = 0; v < vertexCapacity; v++) {
    ringInfo[4 * v] = FIRST_ROOM * v;
    ringInfo[4 * v + 2] = FIRST_ROOM;
  }
  const ringEnd = FIRST_ROOM * vertexCapacity;
  return { ringInfo, ring: new Int32Array(Math.max(ringEnd, FIRST_ROOM)), ringEnd };
}

// Corner c holds v now: appended to v's block (moved to a bigger one when full).
function link(c, v) {
  const info = this.ringInfo, row = 4 * v;
  const n = info[row + 1];
  if (n === info[row + 2]) this.growRing(v, n);
  this.ring[info[row] + n] = c;
  info[row + 1] = n + 1;
}

// v's block moved to the pool's end with twice its room; its n corners copied.
// The pool grows by a quarter when it has no room left: it starts full of home
// blocks and only the few vertices of high valence move, so doubling it would
// mostly add room no vertex takes.
function growRing(v, n) {
  const info = this.ringInfo, row = 4 * v;
  const room = 2 * info[row + 2];
  const at = this.ringEnd;
  if (at + room > this.ring.length) {
    const bigger = new Int32Array(this.ring.length + Math.max(room, this.ring.length >> 2));
    bigger.set(this.ring.subarray(0, at));
    this.ring = bigger;
  }
  this.ring.copyWithin(at, info[row], info[row] + n);
  info[row] = at;
  info[row + 2] = room;
  this.ringEnd = at + room;
}

// Corner c no longer holds v: the block's last corner takes its place.
function unlink(c, v) {
  const { ring } = this;
  const info = this.ringInfo, row = 4 * v;
  const last = info[row] + info[row + 1] - 1;
  let i = last;
  while (ring[i] !== c) i--;
  ring[i] = ring[last];
  info[row + 1]--;
}

// Corner c now holds vertex v.
function moveCorner(c, v) {
  this.unlink(c, this.faces[c]);
  this.faces[c] = v;
  this.link(c, v);
  this.markCorners(c, c + 1);
}

// Every corner of t holds s now (a collapse of t into s); t keeps its empty block.
function moveAll(t, s) {
  const { faces } = this;
  const at = this.ringInfo[4 * t], n = this.ringInfo[4 * t + 1];
  for (let i = at; i < at + n; i++) {
    const c = this.ring[i];      // read afresh: linking to s may move the pool
    faces[c] = s;
    this.link(c, s);
    this.markCorners(c, c + 1);
  }
  this.ringInfo[4 * t + 1] = 0;
}

// corners(v) into the scratch, each with its next and prev vertex in the face.
function gatherCorners(v) {
  const { faces, ring } = this;
  const at = this.ringInfo[4 * v], n = this.ringInfo[4 * v + 1];
  while (n > this.aroundCorners.length) this.growScratch();
  const { aroundCorners, aroundNexts, aroundPrevs } = this;
  for (let i = 0; i < n; i++) {
    const c = ring[at + i];
    const slot = c % 3;
    aroundCorners[i] = c;
    aroundNexts[i] = faces[slot === 2 ? c - 2 : c + 1];
    aroundPrevs[i] = faces[slot === 0 ? c + 2 : c - 1];
  }
  this.aroundCount = n;
}

// Doubles the scratch sized by a vertex's corners (a vertex of unusual valence).
function growScratch() {
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
// Reads the scratch this.gatherCorners(v) filled.
function gatherNeighbours(v) {
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
function decodeVertex(code) {
  return code < this.neighbourCount ? this.neighbours[code] : code - this.neighbourCount;
}

// The corners of held(s) that the mask stream flags, into this.moved; their count.
function listedCorners(mask) {
  const count = this.aroundCount;
  const held = Array.from(this.aroundCorners.subarray(0, count)).sort((a, b) => a - b);
  const bits = mask.take((count + 7) >> 3);
  let moves = 0;
  for (let i = 0; i < count; i++) {
    if ((bits[i >> 3] >> (i & 7)) & 1) this.moved[moves++] = held[i];
  }
  return moves;
}

// The predicted fan of split t of s (docs/packets.md, Hoppe 1996's vl/vr rule),
// from its k new faces in this.added, into this.moved; returns its size, or
// -1 when there is no prediction.
function predictFan(s, t, k) {
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
  const stamp = ++this.fanStamp;  // marks this walk's corners without clearing old marks
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

// The memory the splits of groups ahead will read, touched (the values summed
// into this.sink, so the reads are kept): sources[g .. g + AHEAD_GROUP) is the
// group about to run. A split's reads form a chain (its row, then its block,
// then its corners' faces), each step's address in the last step's value: one
// split at a time, each miss waits for the one before. Here every step is
// taken for a whole group at once, a group further ahead for each earlier step,
// so a step's misses are independent loads the core has in flight together, and
// its addresses were fetched by the step before, one group earlier. What a
// split reads may change before it runs (an earlier split moves a block): such
// a touch is only wasted.
function readAhead(sources, g, count) {
  const info = this.ringInfo, ring = this.ring, faces = this.faces;
  const positions = this.positions;
  const G = AHEAD_GROUP;
  let sink = this.sink;
  // three groups ahead: the rows and positions
  for (let i = Math.max(g + 3 * G, 0), end = Math.min(g + 4 * G, count); i < end; i++) {
    const s = sources[i];
    sink = (sink + info[4 * s] + positions[3 * s]) | 0;
  }
  // two groups ahead: the blocks (their first and last corner)
  for (let i = Math.max(g + 2 * G, 0), end = Math.min(g + 3 * G, count); i < end; i++) {
    const row = 4 * sources[i], n = info[row + 1];
    if (n > 0) sink = (sink + ring[info[row]] + ring[info[row] + n - 1]) | 0;
  }
  // one group ahead: the faces of the corners
  for (let i = Math.max(g + G, 0), end = Math.min(g + 2 * G, count); i < end; i++) {
    const row = 4 * sources[i];
    for (let j = info[row], stop = j + info[row + 1]; j < stop; j++) {
      sink = (sink + faces[ring[j]]) | 0;
    }
  }
  this.sink = sink;
}

// The methods of LodState this module defines.
export const fanMethods = {
  readAhead, link, growRing, unlink, moveCorner, moveAll, gatherCorners, growScratch,
  gatherNeighbours, decodeVertex, listedCorners, predictFan,
};
