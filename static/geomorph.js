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
// scene.js or progressivemesh.js: it writes the exact positions, then this
// overwrites the gliding ones before the frame is drawn).
// Used by stream.js: coarsen(state) before reporting a collapse batch.

import { levelNormals } from './levelmesh.js';
import { dequantize } from './packet.js';

const DEFAULTS = { geomorphMs: 250, geomorphMaxVertices: 200000 };
// A normal that moved less than this (per component) is not glided.
const NORMAL_EPSILON = 1e-3;

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

export function createGeomorph(viewer, scene) {
  const { settings } = viewer;
  const option = (key) => settings[key] ?? DEFAULTS[key];
  let state = null;
  let level = 0;              // the level whose positions `shown` holds
  let wedgesDrawn = 0;        // GPU vertices of that level (wedges, or vertices)
  let shown = null;           // (3 * capacity) float: the positions on screen, per vertex
  let start = null, end = null;   // per vertex: the glide's ends
  let ancestor = null;        // per vertex: scratch for collapseTargets
  let gliding = null, glidingCount = 0;   // the vertices gliding
  let mark = null;            // per vertex: 1 while gliding
  let began = 0, duration = 0, frame = 0;
  let finished = null, resolveFinished = null;   // the running glide's promise
  let measure = { glides: 0, largest: 0 };
  // Normals per GPU vertex: shown, and a glide's ends; the GPU vertices gliding.
  let shownNormal = null, normalStart = null, normalEnd = null, scratch = null;
  let normalList = new Int32Array(1024), normalCount = 0;

  function exact(v, out, at) {
    const { positions, grid: { step } } = state;
    out[at] = positions[3 * v] * step;
    out[at + 1] = positions[3 * v + 1] * step;
    out[at + 2] = positions[3 * v + 2] * step;
  }

  function onMesh({ state: opened }) {
    stopGlide();
    state = opened;
    const n = state.vertexCapacity;
    shown = new Float32Array(3 * n);
    start = new Float32Array(3 * n);
    end = new Float32Array(3 * n);
    ancestor = new Int32Array(n);
    gliding = new Int32Array(1024);
    mark = new Uint8Array(n);
    const drawn = state.attributes.length ? state.wedgeCapacity : n;
    shownNormal = new Float32Array(3 * drawn);
    normalStart = new Float32Array(3 * drawn);
    normalEnd = new Float32Array(3 * drawn);
    scratch = new Float32Array(3 * n);
    normalCount = 0;
    level = 0;
  }

  function normalBuffer() {
    return scene.three.mesh?.geometry.getAttribute('normal') ?? null;
  }

  // The GPU's normals [0, count) as shown now.
  function takeNormals(count) {
    const normal = normalBuffer();
    if (normal) shownNormal.set(normal.array.subarray(0, 3 * count));
  }

  // Glides the GPU normals i in [0, count) whose end (endOf(i, out, at)) differs
  // from the one shown; the others are set to their end at once.
  function planNormals(count, endOf) {
    normalCount = 0;
    for (let i = 0; i < count; i++) {
      const k = 3 * i;
      endOf(i, normalEnd, k);
      if (Math.abs(normalEnd[k] - shownNormal[k]) < NORMAL_EPSILON &&
          Math.abs(normalEnd[k + 1] - shownNormal[k + 1]) < NORMAL_EPSILON &&
          Math.abs(normalEnd[k + 2] - shownNormal[k + 2]) < NORMAL_EPSILON) continue;
      normalStart[k] = shownNormal[k];
      normalStart[k + 1] = shownNormal[k + 1];
      normalStart[k + 2] = shownNormal[k + 2];
      if (normalCount === normalList.length) {
        const grown = new Int32Array(2 * normalList.length);
        grown.set(normalList);
        normalList = grown;
      }
      normalList[normalCount++] = i;
    }
  }

  function writeNormals(t) {
    const normal = normalBuffer();
    if (!normal || !normalCount) return;
    const out = normal.array;
    let low = Infinity, high = -1;
    for (let j = 0; j < normalCount; j++) {
      const i = normalList[j], k = 3 * i;
      for (let c = 0; c < 3; c++) {
        const x = normalStart[k + c] + (normalEnd[k + c] - normalStart[k + c]) * t;
        out[k + c] = x;
        shownNormal[k + c] = x;
      }
      if (i < low) low = i;
      if (i > high) high = i;
    }
    normal.addUpdateRange(3 * low, 3 * (high - low + 1));
    normal.needsUpdate = true;
  }

  // The new level's normal of GPU vertex i, for a coarsening: per vertex from
  // levelNormals (in scratch; a vanishing vertex takes its ancestor's), per
  // wedge its streamed NORMAL (a vanishing wedge keeps its own) or its vertex's.
  function coarseNormal(to, wedgesTo) {
    const normals = state.attributes.find((a) => a.name === 'NORMAL');
    if (!normals) levelNormals(state, scratch);
    const vertexOf = (v) => (v < to ? v : ancestor[v]);
    if (!state.attributes.length) {
      return (i, out, at) => {
        const k = 3 * vertexOf(i);
        out[at] = scratch[k];
        out[at + 1] = scratch[k + 1];
        out[at + 2] = scratch[k + 2];
      };
    }
    const { wedges, components, wedgeVertex } = state;
    return (i, out, at) => {
      if (normals) {
        if (i < wedgesTo) dequantize(normals, wedges, components * i + normals.offset, out, at);
        else out.set(shownNormal.subarray(at, at + 3), at);
        return;
      }
      const k = 3 * vertexOf(wedgeVertex[i]);
      out[at] = scratch[k];
      out[at + 1] = scratch[k + 1];
      out[at + 2] = scratch[k + 2];
    };
  }

  // Adds v to the glide (its start is set by the caller).
  function addGliding(v) {
    if (mark[v]) return;
    mark[v] = 1;
    if (glidingCount === gliding.length) {
      const grown = new Int32Array(2 * gliding.length);
      grown.set(gliding);
      gliding = grown;
    }
    gliding[glidingCount++] = v;
  }

  // Writes the positions of the gliding vertices at ease `t` into `shown` and
  // the GPU buffer.
  function writeGlide(t) {
    writeNormals(t);
    const mesh = scene.three.mesh;
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
      for (let w = 0; w < wedgesDrawn; w++) {
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

  function tick() {
    frame = 0;
    const x = duration > 0 ? (performance.now() - began) / duration : 1;
    writeGlide(ease(x));
    scene.rendered();
    if (x < 1) frame = requestAnimationFrame(tick);
    else endGlide();
  }

  function endGlide() {
    for (let i = 0; i < glidingCount; i++) mark[gliding[i]] = 0;
    glidingCount = 0;
    normalCount = 0;
    if (frame) cancelAnimationFrame(frame);
    frame = 0;
    const resolve = resolveFinished;
    finished = resolveFinished = null;
    resolve?.();
  }

  // Ends a running glide at its end positions.
  function stopGlide() {
    if (!glidingCount) return endGlide();
    writeGlide(1);
    return endGlide();
  }

  // Starts (or restarts, from where everything is now) the glide of the
  // marked vertices; a promise of its end.
  function beginGlide() {
    measure.glides++;
    measure.largest = Math.max(measure.largest, glidingCount);
    began = performance.now();
    duration = option('geomorphMs');
    writeGlide(0);
    if (!finished) finished = new Promise((resolve) => { resolveFinished = resolve; });
    if (!frame) frame = requestAnimationFrame(tick);
    return finished;
  }

  // The vertices gliding keep going from where they are now toward their end.
  function restartFromShown() {
    for (let i = 0; i < glidingCount; i++) {
      const k = 3 * gliding[i];
      start[k] = shown[k];
      start[k + 1] = shown[k + 1];
      start[k + 2] = shown[k + 2];
    }
  }

  // After the LevelMesh (levelmesh.js) showed a level: glide the new vertices
  // out of their ancestors (refinement asked for by the stream), else take the
  // level as shown.
  function onLevel({ dirty, morph }) {
    if (!state) return;
    const to = state.level, from = level;
    const { vertexStart, vertexEnd } = dirty;
    const moved = Math.max(0, vertexEnd - vertexStart);
    const glide = morph && to > from && from > 0 && option('geomorphMs') > 0 &&
                  moved <= option('geomorphMaxVertices');
    if (glide) {
      restartFromShown();
      splitStarts(state.parent, shown, from, to, start);
      for (let v = vertexStart; v < vertexEnd; v++) {
        if (v < from && !mark[v]) {
          const k = 3 * v;
          start[k] = shown[k];
          start[k + 1] = shown[k + 1];
          start[k + 2] = shown[k + 2];
        }
        exact(v, end, 3 * v);
        addGliding(v);
      }
      // the scene wrote the new level's normals: glide to them from those shown
      // (a new vertex from its ancestor's; a new wedge starts at its own)
      const normal = normalBuffer();
      const wedged = state.attributes.length > 0, oldDrawn = wedgesDrawn;
      if (normal) {
        if (!wedged) {
          for (let v = from; v < to; v++) {      // a new vertex shows its ancestor's normal
            const p = 3 * state.parent[v], k = 3 * v;
            shownNormal[k] = shownNormal[p];
            shownNormal[k + 1] = shownNormal[p + 1];
            shownNormal[k + 2] = shownNormal[p + 2];
          }
        } else {
          shownNormal.set(normal.array.subarray(3 * oldDrawn, 3 * state.wedgeCount), 3 * oldDrawn);
        }
        const count = wedged ? state.wedgeCount : to;
        planNormals(count, (i, out, at) => {
          out[at] = normal.array[at];
          out[at + 1] = normal.array[at + 1];
          out[at + 2] = normal.array[at + 2];
        });
      }
      level = to;
      wedgesDrawn = wedged ? state.wedgeCount : to;
      beginGlide();
      return;
    }
    // shown as it is: the exact positions (a glide still running keeps going
    // toward its ends, now exact)
    for (let v = vertexStart; v < vertexEnd; v++) {
      exact(v, shown, 3 * v);
      if (mark[v]) exact(v, end, 3 * v);
    }
    if (from === 0) for (let v = 0; v < to; v++) exact(v, shown, 3 * v);   // a new mesh
    level = to;
    wedgesDrawn = state.attributes.length ? state.wedgeCount : to;
    if (glidingCount) writeGlide(ease((performance.now() - began) / Math.max(duration, 1)));
    else takeNormals(wedgesDrawn);
  }

  // Called by stream.js once a collapse batch is applied to `opened` but not
  // yet shown (the GPU still draws level `level`): the vanishing vertices glide
  // into their ancestors' new positions and the moved ones to theirs.
  // Resolves when the glide ends (at once when off or too big).
  function coarsen(opened) {
    if (opened !== state || level === 0) return Promise.resolve();
    const to = opened.level, from = level;
    const first = Math.min(opened.vertexStart, to), last = Math.min(opened.vertexEnd, to);
    if (!(to < from) || option('geomorphMs') <= 0 ||
        from - to + Math.max(0, last - first) > option('geomorphMaxVertices')) {
      return Promise.resolve();
    }
    restartFromShown();
    collapseTargets(state.parent, from, to, ancestor);
    for (let v = first; v < last; v++) {      // the survivors the collapses moved
      const k = 3 * v;
      if (!mark[v]) {
        start[k] = shown[k];
        start[k + 1] = shown[k + 1];
        start[k + 2] = shown[k + 2];
      }
      exact(v, end, k);
      addGliding(v);
    }
    for (let v = to; v < from; v++) {        // the vanishing ones, into their ancestors
      const k = 3 * v;
      if (!mark[v]) {
        start[k] = shown[k];
        start[k + 1] = shown[k + 1];
        start[k + 2] = shown[k + 2];
      }
      exact(ancestor[v], end, k);
      addGliding(v);
    }
    // the GPU keeps drawing the old level's faces and wedges until the report;
    // their normals glide to the new level's
    if (normalBuffer()) planNormals(wedgesDrawn, coarseNormal(to, opened.wedgeCount));
    return beginGlide();
  }

  viewer.on('mesh', onMesh);
  viewer.on('level', onLevel);

  return {
    enabled: () => option('geomorphMs') > 0,
    coarsen,
    // Resolves when no glide is running.
    idle: () => finished ?? Promise.resolve(),
    get gliding() { return glidingCount; },
    // For tests and benchmarks: glides started, and the most vertices in one.
    get measure() { return { ...measure }; },
  };
}
