// Geomorphs (Hoppe 1996, section 4.2): a level change shown as a short glide
// instead of a pop. When the level rises, each new vertex starts at the place
// its ancestor held at the old level and glides to its own position, and the
// vertices the splits moved glide from where they were; when it falls, the
// vanishing vertices glide into the position their ancestor takes at the new
// level, and only then are their faces dropped. The same for every change of
// the level: by hand or in auto mode.
//
// What is glided are the GPU's position floats (mesh units relative to the
// grid origin: q * step, as levelmesh.js writes them); the decoder's state is
// always the exact level. A glide takes settings.geomorphMs (0: off) with a
// smoothstep ease; a change moving more than settings.geomorphMaxVertices
// vertices is shown at once (the first stream to full detail is never
// morphed: stream.js does not ask for it). Normals glide too, from the ones
// shown to the new level's (a new vertex's from its ancestor's; a vanishing
// one's into its ancestor's new normal): without that the shading pops when
// the level lands, the most visible pop left once positions glide.
//
// Ancestors come from the decoder's parent array (LodState.parent: the vertex
// each vertex was split from, the same s in both directions). For a mesh
// drawn per wedge, each GPU vertex w takes the glide of its vertex
// wedgeVertex[w].
//
// Signals in: 'mesh', 'level' (after the LevelMesh drawing the level, in
// progressivemesh.js: it writes the exact positions, then this overwrites the
// gliding ones before the frame is drawn).
// Used by stream.js: coarsen(state) before reporting a collapse batch.

import { NormalGlide } from './normalglide.js';

const DEFAULTS = { geomorphMs: 250, geomorphMaxVertices: 200000 };

// Smoothstep: zero speed at both ends, so neither end shows a jolt.
export function ease(x) {
  const t = Math.min(1, Math.max(0, x));
  return t * t * (3 - 2 * t);
}

// Where each new vertex of a refinement from level `from` starts: into
// start[3v ..] for v in [from, to), the shown position of its ancestor at
// level `from` (parent[] chains always descend, so one ascending pass does
// it). shown: (3 * n) float, the positions shown at level `from`.
export function splitStarts(parent, shown, from, to, start) {
  for (let v = from; v < to; v++) {
    const p = parent[v];
    const source = p < from ? shown : start;     // an older vertex, or a new one placed above
    start[3 * v] = source[3 * p];
    start[3 * v + 1] = source[3 * p + 1];
    start[3 * v + 2] = source[3 * p + 2];
  }
}

// The ancestor of each vanishing vertex v in [to, from) at level `to`, into
// ancestor[v] (descending parent chains, one ascending pass).
export function collapseTargets(parent, from, to, ancestor) {
  for (let v = to; v < from; v++) {
    const p = parent[v];
    ancestor[v] = p < to ? p : ancestor[p];
  }
}

// The glide of one streamed mesh. bus: its stream's (settings: geomorphMs,
// geomorphMaxVertices; signals 'mesh' and 'level', registered after the
// LevelMesh's own listeners); view: { mesh() -> the THREE.Mesh drawing the
// level (or null), rendered() -> a frame is due }.
export class Geomorph {
  constructor(bus, view) {
    this.settings = bus.settings;
    this.view = view;
    this.state = null;
    this.level = 0;             // the level whose positions `shown` holds
    this.wedgesDrawn = 0;       // GPU vertices of that level (wedges, or vertices)
    this.shown = null;          // (3 * capacity) float: the positions on screen, per vertex
    this.start = this.end = null;   // per vertex: the glide's ends
    this.ancestor = null;       // per vertex: scratch for collapseTargets
    this.gliding = null;        // the vertices gliding, glidingCount of them
    this.glidingCount = 0;
    this.mark = null;           // per vertex: 1 while gliding
    this.began = this.duration = this.frame = 0;
    this.finished = this.resolveFinished = null;   // the running glide's promise
    this.counts = { glides: 0, largest: 0 };
    this.normals = null;        // the normals' glide (normalglide.js)
    this.scratch = null;        // per vertex: a level's normals, for coarsening
    this.tick = this.tick.bind(this);
    bus.on('mesh', (detail) => this.onMesh(detail));
    bus.on('level', (detail) => this.onLevel(detail));
  }

  option(key) {
    return this.settings[key] ?? DEFAULTS[key];
  }

  enabled() {
    return this.option('geomorphMs') > 0;
  }

  // Resolves when no glide is running.
  idle() {
    return this.finished ?? Promise.resolve();
  }

  // For tests and benchmarks: glides started, and the most vertices in one.
  get measure() { return { ...this.counts }; }

  exact(v, out, at) {
    const { positions, grid: { step } } = this.state;
    out[at] = positions[3 * v] * step;
    out[at + 1] = positions[3 * v + 1] * step;
    out[at + 2] = positions[3 * v + 2] * step;
  }

  onMesh({ state }) {
    this.stopGlide();
    this.state = state;
    const n = state.vertexCapacity;
    this.shown = new Float32Array(3 * n);
    this.start = new Float32Array(3 * n);
    this.end = new Float32Array(3 * n);
    this.ancestor = new Int32Array(n);
    this.gliding = new Int32Array(1024);
    this.mark = new Uint8Array(n);
    this.normals = new NormalGlide(state.attributes.length ? state.wedgeCapacity : n);
    this.scratch = new Float32Array(3 * n);
    this.level = 0;
  }

  normalBuffer() {
    return this.view.mesh()?.geometry.getAttribute('normal') ?? null;
  }

  // Adds v to the glide (its start is set by the caller).
  addGliding(v) {
    if (this.mark[v]) return;
    this.mark[v] = 1;
    if (this.glidingCount === this.gliding.length) {
      const grown = new Int32Array(2 * this.gliding.length);
      grown.set(this.gliding);
      this.gliding = grown;
    }
    this.gliding[this.glidingCount++] = v;
  }

  // Starts v's glide from where it is shown, unless it glides already.
  startFromShown(v) {
    if (this.mark[v]) return;
    const k = 3 * v;
    this.start[k] = this.shown[k];
    this.start[k + 1] = this.shown[k + 1];
    this.start[k + 2] = this.shown[k + 2];
  }

  // Writes the positions of the gliding vertices at ease `t` into `shown` and
  // the GPU buffer.
  writeGlide(t) {
    const normal = this.normalBuffer();
    if (normal) this.normals.write(normal, t);
    const { gliding, glidingCount, shown, start, end, mark, state } = this;
    const mesh = this.view.mesh();
    for (let i = 0; i < glidingCount; i++) {
      const k = 3 * gliding[i];
      shown[k] = start[k] + (end[k] - start[k]) * t;
      shown[k + 1] = start[k + 1] + (end[k + 1] - start[k + 1]) * t;
      shown[k + 2] = start[k + 2] + (end[k + 2] - start[k + 2]) * t;
    }
    if (!mesh) return;
    const position = mesh.geometry.getAttribute('position');
    const p = position.array;
    let low = Infinity, high = -1;
    if (state.attributes.length) {
      const { wedgeVertex } = state;
      for (let w = 0; w < this.wedgesDrawn; w++) {
        const v = wedgeVertex[w];
        if (!mark[v]) continue;
        p[3 * w] = shown[3 * v];
        p[3 * w + 1] = shown[3 * v + 1];
        p[3 * w + 2] = shown[3 * v + 2];
        if (w < low) low = w;
        if (w > high) high = w;
      }
    } else {
      for (let i = 0; i < glidingCount; i++) {
        const v = gliding[i], k = 3 * v;
        p[k] = shown[k];
        p[k + 1] = shown[k + 1];
        p[k + 2] = shown[k + 2];
        if (v < low) low = v;
        if (v > high) high = v;
      }
    }
    if (high >= low) {
      position.addUpdateRange(3 * low, 3 * (high - low + 1));
      position.needsUpdate = true;
    }
  }

  tick() {
    this.frame = 0;
    const x = this.duration > 0 ? (performance.now() - this.began) / this.duration : 1;
    this.writeGlide(ease(x));
    this.view.rendered();
    if (x < 1) this.frame = requestAnimationFrame(this.tick);
    else this.endGlide();
  }

  endGlide() {
    for (let i = 0; i < this.glidingCount; i++) this.mark[this.gliding[i]] = 0;
    this.glidingCount = 0;
    if (this.normals) this.normals.count = 0;
    if (this.frame) cancelAnimationFrame(this.frame);
    this.frame = 0;
    const resolve = this.resolveFinished;
    this.finished = this.resolveFinished = null;
    resolve?.();
  }

  // Ends a running glide at its end positions.
  stopGlide() {
    if (this.glidingCount) this.writeGlide(1);
    this.endGlide();
  }

  // Starts (or restarts, from where everything is now) the glide of the
  // marked vertices; a promise of its end.
  beginGlide() {
    this.counts.glides++;
    this.counts.largest = Math.max(this.counts.largest, this.glidingCount);
    this.began = performance.now();
    this.duration = this.option('geomorphMs');
    this.writeGlide(0);
    if (!this.finished) this.finished = new Promise((resolve) => { this.resolveFinished = resolve; });
    if (!this.frame) this.frame = requestAnimationFrame(this.tick);
    return this.finished;
  }

  // The vertices gliding keep going from where they are now toward their end.
  restartFromShown() {
    const { gliding, start, shown } = this;
    for (let i = 0; i < this.glidingCount; i++) {
      const k = 3 * gliding[i];
      start[k] = shown[k];
      start[k + 1] = shown[k + 1];
      start[k + 2] = shown[k + 2];
    }
  }

  // After the LevelMesh (levelmesh.js) showed a level: glide the new vertices
  // out of their ancestors (refinement asked for by the stream), else take the
  // level as shown.
  onLevel({ dirty, morph }) {
    const { state } = this;
    if (!state) return;
    const to = state.level, from = this.level;
    const { vertexStart, vertexEnd } = dirty;
    const moved = Math.max(0, vertexEnd - vertexStart);
    const glide = morph && to > from && from > 0 && this.option('geomorphMs') > 0 &&
                  moved <= this.option('geomorphMaxVertices');
    if (glide) {
      this.glideSplits(from, to, vertexStart, vertexEnd);
      return;
    }
    // shown as it is: the exact positions (a glide still running keeps going
    // toward its ends, now exact)
    for (let v = vertexStart; v < vertexEnd; v++) {
      this.exact(v, this.shown, 3 * v);
      if (this.mark[v]) this.exact(v, this.end, 3 * v);
    }
    if (from === 0) for (let v = 0; v < to; v++) this.exact(v, this.shown, 3 * v);   // a new mesh
    this.level = to;
    this.wedgesDrawn = state.attributes.length ? state.wedgeCount : to;
    if (this.glidingCount) {
      this.writeGlide(ease((performance.now() - this.began) / Math.max(this.duration, 1)));
    } else {
      const normal = this.normalBuffer();
      if (normal) this.normals.take(normal, this.wedgesDrawn);
    }
  }

  // A refinement from level `from` to `to` glides: the new vertices out of
  // their ancestors, the ones the splits moved (vertexStart..vertexEnd) from
  // where they were.
  glideSplits(from, to, vertexStart, vertexEnd) {
    const { state } = this;
    this.restartFromShown();
    splitStarts(state.parent, this.shown, from, to, this.start);
    for (let v = vertexStart; v < vertexEnd; v++) {
      if (v < from) this.startFromShown(v);
      this.exact(v, this.end, 3 * v);
      this.addGliding(v);
    }
    // the mesh wrote the new level's normals: glide to them from those shown
    const normal = this.normalBuffer();
    const wedged = state.attributes.length > 0;
    if (normal) this.normals.planSplits(state, normal, from, to, this.wedgesDrawn);
    this.level = to;
    this.wedgesDrawn = wedged ? state.wedgeCount : to;
    this.beginGlide();
  }

  // Called by stream.js once a collapse batch is applied to `opened` but not
  // yet shown (the GPU still draws level `level`): the vanishing vertices glide
  // into their ancestors' new positions and the moved ones to theirs.
  // Resolves when the glide ends (at once when off or too big).
  coarsen(opened) {
    if (opened !== this.state || this.level === 0) return Promise.resolve();
    const to = opened.level, from = this.level;
    const first = Math.min(opened.vertexStart, to), last = Math.min(opened.vertexEnd, to);
    if (!(to < from) || this.option('geomorphMs') <= 0 ||
        from - to + Math.max(0, last - first) > this.option('geomorphMaxVertices')) {
      return Promise.resolve();
    }
    this.restartFromShown();
    collapseTargets(this.state.parent, from, to, this.ancestor);
    for (let v = first; v < last; v++) {      // the survivors the collapses moved
      this.startFromShown(v);
      this.exact(v, this.end, 3 * v);
      this.addGliding(v);
    }
    for (let v = to; v < from; v++) {        // the vanishing ones, into their ancestors
      this.startFromShown(v);
      this.exact(this.ancestor[v], this.end, 3 * v);
      this.addGliding(v);
    }
    // the GPU keeps drawing the old level's faces and wedges until the report;
    // their normals glide to the new level's
    if (this.normalBuffer()) {
      this.normals.planCollapses(this.state, this.wedgesDrawn, to, opened.wedgeCount,
                                 this.ancestor, this.scratch);
    }
    return this.beginGlide();
  }

  // Ends the glide and forgets the mesh (its object is disposed).
  dispose() {
    this.stopGlide();
    this.state = null;
  }
}
