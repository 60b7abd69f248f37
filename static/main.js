// The viewer: one settings object, one signal bus, and the parts wired to it.
// The mesh shown is the three.js module's object (viewedmesh.js opens it as
// an app does); the view, the panel, the plot, the tools and the upload are
// UI around it, each listening to and emitting named signals instead of
// reaching into the others.

import { SceneAnimation } from './animated.js';
import { Bus } from './bus.js';
import { firstLevel } from './framing.js';
import { hashLevel } from './levelhash.js';
import { ErrorPlot } from './plot.js';
import { ViewScene } from './scene.js';
import { readUrl, Tools } from './tools.js';
import { Panel } from './ui.js';
import { Upload } from './upload.js';
import { ViewedMesh } from './viewedmesh.js';

const settings = {
  chunkSplits: 4096,          // records per packet request: detail arrives in steps this big
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

const viewer = new Bus(settings);
const panel = document.getElementById('panel');
const viewport = document.getElementById('viewport');
let scene = null, animated = null;
try {
  scene = new ViewScene(viewer, viewport, panel);
  animated = new SceneAnimation(viewer, scene, panel);   // scenes: "scene": true
} catch (error) {
  viewport.textContent = `cannot draw: ${error.message}`;
}
new ErrorPlot(viewer, document.getElementById('plot'));

// The view the page was opened with (?level=&camera=&auto=), for its first mesh.
const linked = readUrl();
// a level the URL names is kept (full detail on demand), unless it says auto=1
if (linked.auto !== null) settings.autoByDistance = linked.auto;
else if (linked.level !== null) settings.autoByDistance = false;
const viewed = new ViewedMesh(viewer, scene, animated, linked);

new Panel(viewer, panel);
new Tools(viewer, panel);
new Upload(viewer, { panel, viewport, note: document.getElementById('view-note') });

// A small debug API for tests and benchmarks.
window.lodViewer = {
  settings,
  status() {
    const animation = animated?.status() ?? null;
    const id = viewed.summary?.id ?? null;
    if (animation) {       // a scene: its parts' levels added up
      const sum = (key) => animation.parts.reduce((n, part) => n + (part[key] ?? 0), 0);
      return { mesh: id, scene: true, level: sum('level'),
               faces: sum('faces'), target: sum('target'), bytes: animation.bytes,
               textureBytes: 0, up: settings.up,
               busy: animation.parts.some((part) => part.busy),
               error: animation.parts.find((part) => part.error)?.error ?? null, animation };
    }
    const object = viewed.isMesh ? viewed.object : null;
    const state = object?.state ?? null;
    return { mesh: id, level: state?.level ?? null, faces: state?.faceCount ?? null,
             target: object?.target ?? null, bytes: object?.bytes ?? 0,
             textureBytes: object?.textureBytes ?? 0, up: settings.up,
             busy: object?.levels.busy ?? false,
             error: object?.error ?? viewed.failed?.message ?? null };
  },
  // Resolves once the level reached its target and the frame showing it, with
  // its textures and the environment, is drawn.
  async settled() {
    await viewed.settled();
    await scene?.texturesReady();
    await scene?.environmentReady();
    await scene?.rendered();
    return this.status();
  },
  hash: () => hashLevel(viewed.object.state),
  // for tests: the scene's three.js objects and a pixel read-back
  scene,
  animated,
  viewed,
  firstLevel,
};
