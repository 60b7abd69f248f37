// The three.js scene: one mesh drawn from the decoder's arrays, rendered on
// demand (when the camera, the level, a texture or a setting changes; a glTF
// scene's animation, animated.js, asks for a frame at a time while it plays:
// showObject() puts such a scene here in place of the mesh), lit by an image-based environment and a headlight, tone-mapped
// (materials.js), framed by framing.js. The environment is made once the first
// frame showing a mesh is drawn and the stream rests, or at once if the stream
// has a long way to go (it costs GPU time; a hemisphere light stands in until then).
//
// The buffers are allocated at full detail once per mesh. A level is a prefix
// of the vertices and of the faces (the prefix layout), so showing one is a
// draw range, and a packet re-uploads only the ranges it changed. The index
// buffer *is* the decoder's face array; positions are decoded from the grid
// (origin + q * step: the origin goes into the mesh's transform, so the floats
// stay small).
//
// A mesh with attributes is drawn with one vertex per wedge (a UV seam or a
// hard edge has a vertex per side): its position is its vertex's, its normal,
// UVs and colour its own, and the index buffer is the decoder's wedge-per-corner
// array. Normals come from the stream when it has them, else they are computed
// per vertex and shared by the vertex's wedges. Faces are drawn in one group
// per material, each group a prefix of a range of the index buffer (a level's
// faces of one material are a prefix of that material's faces, in slot order).
//
// Signals in: 'mesh', 'level', 'settings', 'reset-view', 'camera-set'.
// Out: 'view' (pixels per mesh unit at the mesh's nearest point, for choosing
// a level by distance), 'camera' ({ position, target }, after the user moves
// it), 'frame' ({ ms, calls, triangles } after each draw), 'textures' (bytes).

import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { dequantize } from './vsplit.js';
import { configureRenderer, createEnvironment, defaultMaterial, LOOK, makeMaterial,
         TextureSet } from './materials.js';
import { fitBox, freeArea, pixelsPerUnit } from './framing.js';

// The longest the environment waits for the stream to come to rest (see createScene).
const ENVIRONMENT_WAIT_MS = 5000;
// The stream's estimate of the rest of its bytes' time on the link (ms) beyond
// which the environment is made at once instead: its GPU work (long under
// software GL) then overlaps the download rather than delaying the
// full-detail frame after it.
const ENVIRONMENT_AHEAD_MS = 1500;

// three.js attribute names of glTF's.
const ATTRIBUTE_NAMES = { NORMAL: 'normal', TANGENT: 'tangent', TEXCOORD_0: 'uv',
                          TEXCOORD_1: 'uv1', COLOR_0: 'color' };

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

  const fallback = defaultMaterial();
  let mesh = null, state = null, info = null, textures = null;
  // A loaded glTF scene (animated.js) drawn instead of a streamed mesh, and its box.
  let object = null, objectBox = null;
  const showing = () => mesh !== null || object !== null;
  let materials = [fallback];     // per draw group: the mesh's materials, then the default
  let groups = null;              // per-material index ranges, when there are several
  let vertexNormals = null;       // computed normals per vertex (wedge meshes without NORMAL)
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
    if (!mesh) return;
    scene.remove(mesh);
    mesh.geometry.dispose();
    for (const old of materials) if (old !== fallback) old.dispose();
    textures?.dispose();
    textures = null;
  }

  function showMesh({ state: opened, appearance, info: summary }) {
    disposeMesh();
    state = opened;
    info = summary || null;
    const geometry = new THREE.BufferGeometry();
    const dynamic = (array, size) => new THREE.BufferAttribute(array, size)
      .setUsage(THREE.DynamicDrawUsage);
    const wedged = state.attributes.length > 0;
    const capacity = wedged ? state.wedgeCapacity : state.vertexCapacity;
    geometry.setAttribute('position', dynamic(new Float32Array(3 * capacity), 3));
    geometry.setAttribute('normal', dynamic(new Float32Array(3 * capacity), 3));
    for (const a of state.attributes) {
      if (a.name === 'NORMAL' || !ATTRIBUTE_NAMES[a.name]) continue;
      geometry.setAttribute(ATTRIBUTE_NAMES[a.name],
                            dynamic(new Float32Array(a.width * capacity), a.width));
    }
    vertexNormals = wedged && !state.attributes.some((a) => a.name === 'NORMAL')
      ? new Float32Array(3 * state.vertexCapacity) : null;
    materials = [fallback];
    groups = null;
    let drawn = fallback;
    if (appearance?.materials) {
      const { document, url } = appearance.materials;
      textures = new TextureSet(document, url, () => {
        viewer.emit('textures', textures?.textureBytes ?? 0);
        render();
      });
      const has = (name) => state.attributes.some((a) => a.name === name);
      const options = { textures, vertexColors: has('COLOR_0'), tangents: has('TANGENT') };
      materials = [...document.materials.map((record) => makeMaterial(record, options)), fallback];
      // one group per material that has faces (the last: faces without a material)
      const counts = appearance.materialFaces || [];
      const used = counts.map((n, g) => (n > 0 ? g : -1)).filter((g) => g >= 0);
      if (used.length === 1) drawn = materials[used[0]];
      else if (used.length > 1) groups = makeGroups(counts);
    }
    applyLook();
    const index = groups ? groups.index : wedged ? state.corners : state.faces;
    geometry.setIndex(dynamic(index, 1));
    mesh = new THREE.Mesh(geometry, groups ? materials : drawn);
    mesh.position.set(...state.grid.origin);
    // The bounding sphere would count the unused slots of the buffers.
    mesh.frustumCulled = false;
    scene.add(mesh);
    userMoved = false;
    bounds = null;
    if (info?.bounds) frameMesh();
  }

  // Index ranges per material: material g's faces in slot order fill
  // [start[g], start[g] + count[g]) of the faces of the index buffer.
  function makeGroups(counts) {
    const start = new Int32Array(counts.length);
    for (let g = 1; g < counts.length; g++) start[g] = start[g - 1] + counts[g - 1];
    return { start, filled: new Int32Array(counts.length), faces: 0,
             slot: new Int32Array(state.faceCapacity),       // face -> place in the index
             index: new Uint32Array(3 * state.faceCapacity) };
  }

  // Follows the level's faces (their wedges, or vertices without attributes)
  // into the per-material ranges and sets the draw groups.
  function updateGroups(dirty) {
    const { faceMaterial, faceCount } = state;
    const corners = state.attributes.length ? state.corners : state.faces;
    const { start, filled, slot, index } = groups;
    const group = (f) => (faceMaterial[f] >= 0 ? faceMaterial[f] : start.length - 1);
    for (; groups.faces > faceCount; groups.faces--) filled[group(groups.faces - 1)]--;
    for (; groups.faces < faceCount; groups.faces++) {
      const g = group(groups.faces);
      slot[groups.faces] = start[g] + filled[g]++;
    }
    const first = Math.floor(dirty.cornerStart / 3), last = Math.ceil(dirty.cornerEnd / 3);
    for (let f = first; f < Math.min(last, faceCount); f++) {
      const at = 3 * slot[f];
      index[at] = corners[3 * f];
      index[at + 1] = corners[3 * f + 1];
      index[at + 2] = corners[3 * f + 2];
    }
    const { geometry } = mesh;
    geometry.clearGroups();
    for (let g = 0; g < start.length; g++) {
      if (filled[g] > 0) geometry.addGroup(3 * start[g], 3 * filled[g], g);
    }
    if (last > first) geometry.index.needsUpdate = true;
  }

  // The wedge buffers after a packet: the positions of the touched vertices'
  // wedges, the attributes of the touched wedges.
  function showWedges(dirty) {
    const { geometry } = mesh;
    const position = geometry.getAttribute('position');
    const { positions, head, next, corners, wedgeVertex, wedges, components } = state;
    const { step } = state.grid;
    const p = position.array;
    let low = Infinity, high = -1;
    for (const v of dirty.vertices) {
      const x = positions[3 * v] * step, y = positions[3 * v + 1] * step;
      const z = positions[3 * v + 2] * step;
      for (let c = head[v]; c !== -1; c = next[c]) {
        const w = corners[c];
        p[3 * w] = x;
        p[3 * w + 1] = y;
        p[3 * w + 2] = z;
        if (w < low) low = w;
        if (w > high) high = w;
      }
    }
    const streamed = state.attributes.filter((a) => ATTRIBUTE_NAMES[a.name]);
    const buffers = streamed.map((a) => geometry.getAttribute(ATTRIBUTE_NAMES[a.name]));
    for (const w of dirty.wedges) {
      const v = wedgeVertex[w];
      p[3 * w] = positions[3 * v] * step;
      p[3 * w + 1] = positions[3 * v + 1] * step;
      p[3 * w + 2] = positions[3 * v + 2] * step;
      streamed.forEach((a, i) => {
        dequantize(a, wedges, components * w + a.offset, buffers[i].array, a.width * w);
      });
      if (w < low) low = w;
      if (w > high) high = w;
    }
    if (high >= low) {
      position.addUpdateRange(3 * low, 3 * (high - low + 1));
      position.needsUpdate = true;
      streamed.forEach((a, i) => {
        buffers[i].addUpdateRange(a.width * low, a.width * (high - low + 1));
        buffers[i].needsUpdate = true;
      });
    }
    const { cornerStart, cornerEnd } = dirty;
    if (groups) updateGroups(dirty);
    else if (cornerEnd > cornerStart) {
      geometry.index.addUpdateRange(cornerStart, cornerEnd - cornerStart);
      geometry.index.needsUpdate = true;
    }
  }

  function showVertices(dirty) {
    const { geometry } = mesh;
    const position = geometry.getAttribute('position');
    const { vertexStart, vertexEnd, cornerStart, cornerEnd } = dirty;
    if (groups) updateGroups(dirty);
    if (vertexEnd > vertexStart) {
      const { step } = state.grid;
      for (let i = 3 * vertexStart; i < 3 * vertexEnd; i++) {
        position.array[i] = state.positions[i] * step;
      }
      position.addUpdateRange(3 * vertexStart, 3 * (vertexEnd - vertexStart));
      position.needsUpdate = true;
    }
    if (!groups && cornerEnd > cornerStart) {
      geometry.index.addUpdateRange(cornerStart, cornerEnd - cornerStart);
      geometry.index.needsUpdate = true;
    }
  }

  function showLevel({ dirty }) {
    if (!mesh) return;
    if (state.attributes.length) showWedges(dirty);
    else showVertices(dirty);
    if (settings.shading === 'smooth') updateNormals();
    mesh.geometry.setDrawRange(0, groups ? Infinity : 3 * state.faceCount);
    // Without the mesh's box the view follows the level's, until the user moves
    // it; in auto mode the camera distance picks the level: framing would feed back.
    if (!bounds || (!info?.bounds && !userMoved && !settings.autoByDistance)) frameMesh();
    emitView();
    render();
  }

  // Area-weighted vertex normals of the current level (every vertex of a
  // level lies on one of its faces). Computed on grid coordinates: the same
  // directions, without reading the floats back.
  function updateNormals() {
    if (state.attributes.length && !vertexNormals) return;    // normals from the stream
    const normal = mesh.geometry.getAttribute('normal');
    const n = vertexNormals || normal.array, q = state.positions, faces = state.faces;
    n.fill(0, 0, 3 * state.vertexCount);
    for (let c = 0; c < 3 * state.faceCount; c += 3) {
      const a = 3 * faces[c], b = 3 * faces[c + 1], d = 3 * faces[c + 2];
      const ux = q[b] - q[a], uy = q[b + 1] - q[a + 1], uz = q[b + 2] - q[a + 2];
      const vx = q[d] - q[a], vy = q[d + 1] - q[a + 1], vz = q[d + 2] - q[a + 2];
      const x = uy * vz - uz * vy, y = uz * vx - ux * vz, z = ux * vy - uy * vx;
      n[a] += x; n[a + 1] += y; n[a + 2] += z;
      n[b] += x; n[b + 1] += y; n[b + 2] += z;
      n[d] += x; n[d + 1] += y; n[d + 2] += z;
    }
    for (let i = 0; i < 3 * state.vertexCount; i += 3) {
      const length = Math.hypot(n[i], n[i + 1], n[i + 2]) || 1;
      n[i] /= length;
      n[i + 1] /= length;
      n[i + 2] /= length;
    }
    let count = state.vertexCount;
    if (vertexNormals) {       // each wedge takes its vertex's normal
      const out = normal.array, { wedgeVertex } = state;
      count = state.wedgeCount;
      for (let w = 0; w < count; w++) {
        const v = 3 * wedgeVertex[w];
        out[3 * w] = n[v];
        out[3 * w + 1] = n[v + 1];
        out[3 * w + 2] = n[v + 2];
      }
    }
    normal.addUpdateRange(0, 3 * count);
    normal.needsUpdate = true;
  }

  // Shading and wireframe on every material of the mesh.
  function applyLook() {
    for (const each of materials) {
      each.flatShading = settings.shading === 'flat';
      each.wireframe = settings.wireframe;
      each.needsUpdate = true;
    }
  }

  function applySettings(key) {
    if ((key === 'shading' || key === 'wireframe') && mesh) {
      applyLook();
      if (settings.shading === 'smooth') updateNormals();
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
    texturesReady: () => textures?.ready ?? Promise.resolve(),
    get textureBytes() { return textures?.textureBytes ?? 0; },
    // How many frames of the view were drawn.
    get draws() { return draws; },
    // For tests: the three.js objects, and the canvas pixels drawn now
    // (RGBA, bottom row first; read in the same task as the draw, so the
    // drawing buffer still holds them).
    three: { THREE, renderer, scene, camera, get mesh() { return mesh; },
             get materials() { return materials; } },
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
