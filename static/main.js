// The viewer: one settings object, one signal bus, and the parts wired to it.
// Each part (scene, stream, ui, plot) listens to and emits named signals
// instead of reaching into the others.

import { createBus } from './bus.js';
import { firstLevel, guessUpAxis } from './framing.js';
import { createAnimated } from './animated.js';
import { createGeomorph } from './geomorph.js';
import { createErrorPlot } from './plot.js';
import { createScene } from './scene.js';
import { createStream } from './stream.js';
import { createTools, readUrl, storedUp } from './tools.js';
import { createUi } from './ui.js';
import { createUpload } from './upload.js';

const settings = {
  chunkSplits: 4096,          // records per packet request: detail arrives in steps this big
  initialRatio: 1,            // the level to stream to after the base, as a fraction of vertices
  // Stop at what the screen shows: the level follows the view so that its
  // error covers at most errorBudgetPx CSS pixels (off: the level set by hand,
  // full detail by default).
  autoByDistance: true,
  errorBudgetPx: 1,
  shading: 'smooth',          // 'smooth' (vertex normals) or 'flat' (face normals)
  wireframe: false,
  up: 'Y',                    // the up axis: 'Y' or 'Z' (per mesh: tools.js, framing.js)
  // The first level arrives as the base level and one packet to it, applied
  // before anything is drawn (stream.js): a view that wants more than this many
  // vertices at first gets this many, drawn sooner, and packets refine it.
  firstLevelMaxVertices: 4096,
  fov: 40,                    // vertical field of view, degrees
  background: 0x1d2026,
};

function createViewer() {
  return createBus(settings);
}

// Auto mode: the coarsest level whose error projects to at most the budget,
// refined as soon as the view needs more (a zoom, a larger window), coarsened
// only past a hysteresis when it needs less (ErrorCurve.follow).
function followDistance(viewer) {
  let curve = null, pixelsPerUnit = null, target = null;
  const update = (force = false) => {
    const allowed = settings.autoByDistance && curve && pixelsPerUnit
      ? settings.errorBudgetPx / pixelsPerUnit : null;
    viewer.emit('budget', allowed);
    // (before the stream's first target the opening level is on its way)
    if (allowed === null || target === null) return;
    const level = force ? curve.levelFor(allowed) : curve.follow(target, allowed);
    if (level !== null) viewer.emit('goto', level);
  };
  viewer.on('mesh', (detail) => {
    curve = detail.curve;
    target = null;
  });
  viewer.on('target', (value) => {
    const first = target === null;
    target = value;
    // after the stream's own goto has told every listener its target
    if (first) queueMicrotask(() => update());
  });
  viewer.on('view', (value) => {
    pixelsPerUnit = value;
    if (settings.autoByDistance) update();
  });
  viewer.on('settings', (key) => {
    if (key === 'autoByDistance' || key === 'errorBudgetPx') update(true);
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
const panel = document.getElementById('panel');
let scene = null, animated = null;
try {
  scene = createScene(viewer, document.getElementById('viewport'), panel);
  stream.attachGeomorph(createGeomorph(viewer, scene));   // after the scene: it draws over it
  animated = createAnimated(viewer, scene, panel);        // scenes: "scene": true
} catch (error) {
  document.getElementById('viewport').textContent = `cannot draw: ${error.message}`;
}
createErrorPlot(viewer, document.getElementById('plot'));
followDistance(viewer);

// The view the page was opened with (?level=&camera=&auto=), for its first mesh.
let linked = readUrl();
// a level the URL names is kept (full detail on demand), unless it says auto=1
if (linked.auto !== null) settings.autoByDistance = linked.auto;
else if (linked.level !== null) settings.autoByDistance = false;

// The level to fetch first, as the stream opens a mesh (summary: GET /meshes/{id}):
// the coarsest whose error covers at most the pixel budget at the initial
// framing (the auto mode's rule), so the first frame is no shard of the base;
// a level the URL names, if coarser; at most firstLevelMaxVertices. The
// stream then refines to that budget's level in auto mode (the level the URL
// names, else full detail, otherwise). The up axis is chosen here too, before
// the framing: the one kept for this mesh, else a guess from its box.
function chooseFirstLevel(summary) {
  settings.up = storedUp(summary.id) ?? guessUpAxis(summary);
  const wanted = linked.mesh === summary.id ? linked : null;
  if (summary.scene && !(summary.error_curve?.length && summary.bounds)) {
    settings.initialRatio = wanted?.level ? Math.min(1, wanted.level / summary.vertices) : 1;
    return Math.min(summary.vertices, settings.firstLevelMaxVertices);
  }
  const view = scene ? scene.view() : { fov: settings.fov, width: innerWidth, height: innerHeight };
  let level = firstLevel(summary, { ...view, up: settings.up }, settings.errorBudgetPx);
  const stop = wanted?.level ?? (settings.autoByDistance ? level : summary.vertices);
  settings.initialRatio = Math.min(1, stop / summary.vertices);
  if (wanted?.level) level = Math.min(level, wanted.level);
  return Math.min(level, settings.firstLevelMaxVertices);   // the stream keeps it >= the base
}

createUi(viewer, panel, { firstLevel: chooseFirstLevel });
createTools(viewer, panel);
createUpload(viewer, { panel, viewport: document.getElementById('viewport'),
                       note: document.getElementById('view-note') });
// the camera the URL names is the first mesh's, set once it is framed
viewer.on('mesh', ({ info }) => {
  if (linked.camera && linked.mesh === info.id) viewer.emit('camera-set', linked.camera);
  linked = { mesh: null, level: null, camera: null, auto: null };
});

// A small debug API for tests and benchmarks.
window.lodViewer = {
  settings,
  status() {
    const state = stream.state;
    const animation = animated?.status() ?? null;
    if (animation) {       // a scene: its parts' levels added up
      const sum = (key) => animation.parts.reduce((n, part) => n + (part[key] ?? 0), 0);
      return { mesh: stream.info?.id ?? null, scene: true, level: sum('level'),
               faces: sum('faces'), target: sum('target'), bytes: animation.bytes,
               textureBytes: 0, up: settings.up,
               busy: animation.parts.some((part) => part.busy),
               error: animation.parts.find((part) => part.error)?.error ?? null, animation };
    }
    return { mesh: stream.info?.id ?? null, level: state?.level ?? null,
             faces: state?.faceCount ?? null, target: stream.target, bytes: stream.bytes,
             textureBytes: scene?.textureBytes ?? 0, up: settings.up,
             busy: stream.busy, error: stream.failed?.message ?? null };
  },
  // Resolves once the level reached its target and the frame showing it, with
  // its textures and the environment, is drawn.
  async settled() {
    await stream.settled();
    await animated?.settled();
    await scene?.texturesReady();
    await scene?.environmentReady();
    await scene?.rendered();
    return this.status();
  },
  hash: () => hashLevel(stream.state),
  // for tests: the scene's three.js objects and a pixel read-back
  scene,
  animated,
  firstLevel,
};
