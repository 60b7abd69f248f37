// The viewer: one settings object, one signal bus, and the parts wired to it.
// Each part (scene, stream, ui, plot) listens to and emits named signals
// instead of reaching into the others.

import { createErrorPlot } from './plot.js';
import { createScene } from './scene.js';
import { createStream } from './stream.js';
import { createUi } from './ui.js';

const settings = {
  chunkSplits: 4096,          // records per packet request: detail arrives in steps this big
  initialRatio: 1,            // the level to stream to after the base, as a fraction of vertices
  autoByDistance: false,      // choose the level from the camera distance ...
  errorBudgetPx: 1,           // ... so that the error covers at most this many CSS pixels
  shading: 'smooth',          // 'smooth' (vertex normals) or 'flat' (face normals)
  fov: 40,                    // vertical field of view, degrees
  background: 0x1d2026,
};

function createViewer() {
  const signals = new EventTarget();
  return {
    settings,
    emit(type, detail) {
      signals.dispatchEvent(new CustomEvent(type, { detail }));
    },
    on(type, listener) {
      signals.addEventListener(type, (event) => listener(event.detail));
    },
  };
}

// Auto mode: the coarsest level whose error projects to at most the budget.
function followDistance(viewer) {
  let curve = null, pixelsPerUnit = null;
  const update = () => {
    const allowed = settings.autoByDistance && curve && pixelsPerUnit
      ? settings.errorBudgetPx / pixelsPerUnit : null;
    viewer.emit('budget', allowed);
    if (allowed !== null) viewer.emit('goto', curve.levelFor(allowed));
  };
  viewer.on('mesh', (detail) => { curve = detail.curve; });
  viewer.on('view', (value) => {
    pixelsPerUnit = value;
    if (settings.autoByDistance) update();
  });
  viewer.on('settings', (key) => {
    if (key === 'autoByDistance' || key === 'errorBudgetPx') update();
  });
}

// SHA-256 of the level's integer grid positions then its faces (int32 and
// uint32, little-endian), then, with attributes, its wedges' grid values and
// its corners' wedges (int32, uint32), then with materials its faces'
// materials (int32): what tests compare with the server's json level.
async function hashLevel(state) {
  const parts = [new Uint8Array(state.positions.buffer, 0, 12 * state.vertexCount),
                 new Uint8Array(state.faces.buffer, 0, 12 * state.faceCount)];
  if (state.attributes.length) {
    parts.push(new Uint8Array(state.wedges.buffer, 0, 4 * state.components * state.wedgeCount),
               new Uint8Array(state.corners.buffer, 0, 12 * state.faceCount));
  }
  if (state.faceMaterial) {
    parts.push(new Uint8Array(state.faceMaterial.buffer, 0, 4 * state.faceCount));
  }
  const bytes = new Uint8Array(parts.reduce((n, part) => n + part.length, 0));
  parts.reduce((at, part) => {
    bytes.set(part, at);
    return at + part.length;
  }, 0);
  const digest = await crypto.subtle.digest('SHA-256', bytes);
  return [...new Uint8Array(digest)].map((b) => b.toString(16).padStart(2, '0')).join('');
}

const viewer = createViewer();
const stream = createStream(viewer);
let scene = null;
try {
  scene = createScene(viewer, document.getElementById('viewport'));
} catch (error) {
  document.getElementById('viewport').textContent = `cannot draw: ${error.message}`;
}
createErrorPlot(viewer, document.getElementById('plot'));
followDistance(viewer);
createUi(viewer, document.getElementById('panel'));

// A small debug API for tests and benchmarks.
window.lodViewer = {
  settings,
  status() {
    const state = stream.state;
    return { mesh: stream.info?.id ?? null, level: state?.level ?? null,
             faces: state?.faceCount ?? null, target: stream.target, bytes: stream.bytes,
             busy: stream.busy, error: stream.failed?.message ?? null };
  },
  // Resolves once the level reached its target and the frame showing it is drawn.
  async settled() {
    await stream.settled();
    await scene?.rendered();
    return this.status();
  },
  hash: () => hashLevel(stream.state),
};
