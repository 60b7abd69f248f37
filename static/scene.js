// The three.js scene: one mesh drawn from the decoder's arrays, rendered on
// demand (when the camera, the level, a texture or a setting changes; a glTF
// scene's animation, animated.js, asks for a frame at a time while it plays:
// showObject() puts such a scene here in place of the mesh), lit by an image-based environment and a headlight, tone-mapped
// (materials.js), framed by framing.js. The environment is made once the first
// frame showing a mesh is drawn and the stream rests, or at once if the stream
// has a long way to go (it costs GPU time; a hemisphere light stands in until then).
//
// The mesh itself, its buffers following the stream's level, is a LevelMesh
// (levelmesh.js).
//
// Signals in: 'mesh', 'level', 'settings', 'reset-view', 'camera-set'.
// Out: 'view' (pixels per mesh unit at the mesh's nearest point, for choosing
// a level by distance), 'camera' ({ position, target }, after the user moves
// it), 'frame' ({ ms, calls, triangles } after each draw), 'textures' (bytes).

import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { configureRenderer, createEnvironment, LOOK } from './materials.js';
import { fitBox, freeArea, pixelsPerUnit } from './framing.js';
import { LevelMesh } from './levelmesh.js';

// The longest the environment waits for the stream to come to rest (see createScene).
const ENVIRONMENT_WAIT_MS = 5000;
// The stream's estimate of the rest of its bytes' time on the link (ms) beyond
// which the environment is made at once instead: its GPU work (long under
// software GL) then overlaps the download rather than delaying the
// full-detail frame after it.
const ENVIRONMENT_AHEAD_MS = 1500;

// panel: the element whose box the framing keeps the mesh clear of (or null).
export function createScene(viewer, container, panel = null) {
  const { settings } = viewer;
  const renderer = new THREE.WebGLRenderer({ antialias: true });
  renderer.setPixelRatio(window.devicePixelRatio);
  renderer.setClearColor(settings.background);
  configureRenderer(renderer);
  container.append(renderer.domElement);

  const scene = new THREE.Scene();
  scene.environmentIntensity = LOOK.environmentIntensity;
  // The environment costs GPU time (materials.js: LOOK) and a second compile
  // of the mesh's shaders, so it is made once the first frame showing a mesh
  // is drawn and the stream has come to rest (or ENVIRONMENT_WAIT_MS after
  // that frame, if it is still streaming): a frame it delays would otherwise
  // also space the stream's reports (stream.js measures what frames cost).
  // But when the stream estimates the rest of its bytes at more than
  // ENVIRONMENT_AHEAD_MS on the link (a slow link, a large mesh), it is made at once, as a
  // GLB viewer does while its bytes arrive: made at rest it would delay the
  // full-detail frame by its GPU work (bench/viewer measures it on a throttled
  // large mesh). Until then a hemisphere light stands in for it (the same shading,
  // without reflections).
  const fill = new THREE.HemisphereLight(LOOK.fill.sky, LOOK.fill.ground, LOOK.fill.intensity);
  scene.add(fill);
  let environmentDue = false, environmentMade = null, meshDrawnAt = null, streaming = true;
  let environmentTimer = 0;
  let streamRestMs = null;        // the stream's estimate of its rest on the link, ms (or null)
  const environmentReady = new Promise((resolve) => { environmentMade = resolve; });
  const camera = new THREE.PerspectiveCamera(settings.fov, 1, 0.01, 100);
  // A light that follows the camera keeps the side facing the viewer lit; the
  // environment does the rest (and is what metal reflects).
  const headlight = new THREE.DirectionalLight(0xffffff, LOOK.headlight);
  headlight.position.set(0.4, 0.6, 0);
  headlight.target.position.set(0, 0, -1);
  camera.add(headlight, headlight.target);
  scene.add(camera);
  let controls = makeControls(), controlsUp = 'Y';

  let drawn = null;               // the LevelMesh shown
  let mesh = null, state = null, info = null;
  // A loaded glTF scene (animated.js) drawn instead of a streamed mesh, and its box.
  let object = null, objectBox = null;
  const showing = () => mesh !== null || object !== null;
  let bounds = null;              // { center (world, THREE.Vector3), radius }
  let userMoved = false;          // until the user moves the camera, the view follows the mesh
  let frame = null;               // the pending animation frame's promise
  let draws = 0;                  // frames drawn (renderer.info also counts the PMREM's renders)

  function makeControls() {
    // OrbitControls fixes its up axis when made: a new one per up axis
    const made = new OrbitControls(camera, renderer.domElement);
    made.addEventListener('start', () => { userMoved = true; });
    made.addEventListener('change', () => {
      emitView();
      render();
      if (userMoved) viewer.emit('camera', cameraState());
    });
    return made;
  }

  function draw() {
    const started = performance.now();
    draws++;
    renderer.render(scene, camera);
    const { calls, triangles } = renderer.info.render;
    viewer.emit('frame', { ms: performance.now() - started, calls, triangles });
    if (showing() && meshDrawnAt === null) {
      meshDrawnAt = performance.now();
      // a message posted from the frame's callback runs once the frame is
      // shown: the environment's GPU work queues behind it, not before it
      const channel = new MessageChannel();
      channel.port1.onmessage = environmentSoon;
      channel.port2.postMessage(null);
    }
  }

  function environmentSoon() {
    if (environmentDue || meshDrawnAt === null) return;
    const waited = performance.now() - meshDrawnAt;
    const longWay = streamRestMs !== null && streamRestMs > ENVIRONMENT_AHEAD_MS;
    if (streaming && !longWay && waited < ENVIRONMENT_WAIT_MS) {
      clearTimeout(environmentTimer);
      environmentTimer = setTimeout(environmentSoon, ENVIRONMENT_WAIT_MS - waited);
      return;
    }
    clearTimeout(environmentTimer);
    environmentDue = true;
    makeEnvironment();
  }

  function makeEnvironment() {
    scene.environment = createEnvironment(renderer);
    scene.remove(fill);
    environmentMade();
    render();
  }

  function render() {
    if (!frame) {
      frame = new Promise((resolve) => requestAnimationFrame(() => {
        frame = null;
        draw();
        resolve();
      }));
    }
    return frame;
  }

  // The free part of the canvas, and the camera's principal point moved to its
  // centre (setViewOffset), so the mesh is centred where the panel is not.
  function viewOffset() {
    const { clientWidth: width, clientHeight: height } = container;
    const box = panel?.getBoundingClientRect();
    const canvasBox = container.getBoundingClientRect();
    const rect = box && { left: box.left - canvasBox.left, top: box.top - canvasBox.top,
                          right: box.right - canvasBox.left, width: box.width, height: box.height };
    const free = freeArea(width, height, rect);
    const shiftX = free.x + free.width / 2 - width / 2, shiftY = free.y + free.height / 2 - height / 2;
    if (width > 0 && height > 0) camera.setViewOffset(width, height, -shiftX, -shiftY, width, height);
    return { width, height, free };
  }

  // After the window or the panel changed size. The panel's height changes
  // with its text (stats, status) while streaming: only a change of the space
  // it leaves free, or of the canvas, is any work.
  let lastLayout = '';
  function resize() {
    const { clientWidth: width, clientHeight: height } = container;
    const sized = renderer.getSize(new THREE.Vector2());
    if (sized.x !== width || sized.y !== height) renderer.setSize(width, height);
    camera.aspect = width / Math.max(1, height);
    const { free } = viewOffset();
    const layout = JSON.stringify([width, height, free]);
    if (layout === lastLayout) return;
    lastLayout = layout;
    camera.updateProjectionMatrix();
    if (showing() && !userMoved) frameMesh();
    emitView();
    render();
  }

  function emitView() {
    if (!bounds) return;
    const distance = camera.position.distanceTo(bounds.center);
    viewer.emit('view', pixelsPerUnit(distance, bounds.radius,
      { fov: camera.fov, height: renderer.domElement.clientHeight, near: camera.near }));
  }

  function cameraState() {
    return { position: camera.position.toArray(), target: controls.target.toArray() };
  }

  // The box to frame: the mesh's full-detail box from its summary, else the
  // current level's (the level's grid coordinates, in world units).
  function boxToFrame() {
    if (object) return objectBox;
    if (info?.bounds) return info.bounds;
    const { positions, vertexCount } = state;
    const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (let i = 0; i < 3 * vertexCount; i++) {
      const k = i % 3;
      if (positions[i] < lo[k]) lo[k] = positions[i];
      if (positions[i] > hi[k]) hi[k] = positions[i];
    }
    const { origin, step } = state.grid;
    return { min: lo.map((q, k) => origin[k] + step * q), max: hi.map((q, k) => origin[k] + step * q) };
  }

  // Fits the box into the free part of the view, from the front of the up axis.
  function frameMesh() {
    const { width, height, free } = viewOffset();
    const fit = fitBox(boxToFrame(), { fov: camera.fov, width, height, free, up: settings.up });
    bounds = { center: new THREE.Vector3(...fit.target), radius: fit.radius };
    if (controlsUp !== settings.up) {
      camera.up.set(...fit.up);
      controls.dispose();
      controls = makeControls();
      controlsUp = settings.up;
    }
    camera.position.set(...fit.position);
    camera.near = fit.near;
    camera.far = fit.far;
    camera.updateProjectionMatrix();
    controls.maxDistance = fit.radius * 50;   // well inside the far plane
    controls.target.copy(bounds.center);
    controls.update();
  }

  function disposeMesh() {
    if (object) scene.remove(object);
    object = objectBox = null;
    drawn?.dispose();
    drawn = mesh = null;
  }

  function showMesh({ state: opened, appearance, info: summary }) {
    disposeMesh();
    state = opened;
    info = summary || null;
    drawn = new LevelMesh(state, appearance, { onTexture: () => {
      viewer.emit('textures', drawn?.textures?.textureBytes ?? 0);
      render();
    } });
    drawn.setLook(settings);
    mesh = drawn.mesh;
    scene.add(mesh);
    userMoved = false;
    bounds = null;
    if (info?.bounds) frameMesh();
  }

  function showLevel({ dirty }) {
    if (!mesh) return;
    drawn.update(dirty);
    // Without the mesh's box the view follows the level's, until the user moves
    // it; in auto mode the camera distance picks the level: framing would feed back.
    if (!bounds || (!info?.bounds && !userMoved && !settings.autoByDistance)) frameMesh();
    emitView();
    render();
  }

  function applySettings(key) {
    if ((key === 'shading' || key === 'wireframe') && mesh) {
      drawn.setLook(settings);
      render();
    } else if (key === 'up' && showing()) {
      userMoved = false;
      frameMesh();
      emitView();
      render();
    }
  }

  window.addEventListener('resize', resize);
  if (panel && window.ResizeObserver) new ResizeObserver(() => resize()).observe(panel);
  viewer.on('mesh', showMesh);
  viewer.on('level', showLevel);
  viewer.on('settings', applySettings);
  viewer.on('stream', ({ state: now, restMs = null }) => {
    streaming = now === 'moving' || now === 'retrying';
    streamRestMs = now === 'moving' ? restMs : null;
    environmentSoon();
  });
  viewer.on('reset-view', () => {
    if (!showing()) return;
    userMoved = false;
    frameMesh();
    emitView();
    render();
  });
  viewer.on('camera-set', ({ position, target }) => {
    if (!showing()) return;
    userMoved = true;
    camera.position.fromArray(position);
    controls.target.fromArray(target);
    controls.update();
    emitView();
    render();
  });
  resize();

  return {
    canvas: renderer.domElement,
    // What framing.js needs to frame a box here: { fov, width, height, free, up }.
    view: () => ({ fov: camera.fov, ...viewOffset(), up: settings.up }),
    // Resolves after the next frame is drawn.
    rendered: render,
    // Resolves once the image-based light is in place (at once before a mesh
    // is shown: it is made after the first frame showing one).
    environmentReady: () => (showing() ? environmentReady : Promise.resolve()),
    // Shows `root` (a three.js object: a glTF scene, animated.js draws and
    // animates it) in place of the streamed mesh, framed by `box` ({ min, max },
    // world units); the caller owns and disposes it.
    showObject(root, box) {
      disposeMesh();
      mesh = state = info = null;
      object = root;
      objectBox = box;
      scene.add(root);
      userMoved = false;
      frameMesh();
      emitView();
      render();
    },
    // Removes the object showObject() showed, if it is still `root`.
    removeObject(root) {
      if (object !== root) return;
      scene.remove(object);
      object = objectBox = null;
      render();
    },
    // Resolves once every texture asked for so far has arrived.
    texturesReady: () => drawn?.textures?.ready ?? Promise.resolve(),
    get textureBytes() { return drawn?.textures?.textureBytes ?? 0; },
    // How many frames of the view were drawn.
    get draws() { return draws; },
    // For tests: the three.js objects, and the canvas pixels drawn now
    // (RGBA, bottom row first; read in the same task as the draw, so the
    // drawing buffer still holds them).
    three: { THREE, renderer, scene, camera, get mesh() { return mesh; },
             get materials() { return drawn?.materials ?? []; } },
    pixels() {
      draw();
      const gl = renderer.getContext();
      const { drawingBufferWidth: width, drawingBufferHeight: height } = gl;
      const out = new Uint8Array(4 * width * height);
      gl.readPixels(0, 0, width, height, gl.RGBA, gl.UNSIGNED_BYTE, out);
      return { width, height, data: out };
    },
  };
}
