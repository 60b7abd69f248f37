// The three.js scene of the viewer: the object shown (a ProgressiveMesh, or a
// ProgressiveScene: the three.js module's objects, viewedmesh.js opens them),
// rendered on demand (when the camera, the level, a texture or a setting
// changes; a scene's animation, animated.js, asks for a frame at a time while
// it plays), lit by an image-based environment (environment.js: made when it
// costs the first frames least) and a headlight, tone-mapped (materials.js),
// framed by framing.js.
//
// Signals in: 'mesh', 'level', 'settings', 'stream', 'reset-view', 'camera-set'.
// Out: 'view' (pixels per mesh unit at the mesh's nearest point, for choosing
// a level by distance), 'camera' ({ position, target }, after the user moves
// it), 'frame' ({ ms, calls, triangles } after each draw), 'textures' (bytes).

import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { DeferredEnvironment } from './environment.js';
import { fitBox, freeArea, pixelsPerUnit } from './framing.js';
import { configureRenderer, LOOK } from './materials.js';

export class ViewScene {
  // viewer: the bus (settings, signals); container: the element the canvas
  // fills; panel: the element whose box the framing keeps the mesh clear of (or null).
  constructor(viewer, container, panel = null) {
    const { settings } = viewer;
    Object.assign(this, { viewer, container, panel, settings });
    const renderer = this.renderer = new THREE.WebGLRenderer({ antialias: true });
    renderer.setPixelRatio(window.devicePixelRatio);
    renderer.setClearColor(settings.background);
    configureRenderer(renderer);
    container.append(renderer.domElement);
    this.canvas = renderer.domElement;
    const scene = this.scene = new THREE.Scene();
    scene.environmentIntensity = LOOK.environmentIntensity;
    this.environment = new DeferredEnvironment(scene, renderer, () => this.rendered());
    const camera = this.camera = new THREE.PerspectiveCamera(settings.fov, 1, 0.01, 100);
    // A light that follows the camera keeps the side facing the viewer lit; the
    // environment does the rest (and is what metal reflects).
    const headlight = new THREE.DirectionalLight(0xffffff, LOOK.headlight);
    headlight.position.set(0.4, 0.6, 0);
    headlight.target.position.set(0, 0, -1);
    camera.add(headlight, headlight.target);
    scene.add(camera);
    this.controls = this.makeControls();
    this.controlsUp = 'Y';
    this.progressive = null;    // the ProgressiveMesh shown (progressivemesh.js)
    this.mesh = this.state = this.info = null;   // its THREE.Mesh, level and summary
    // A scene (animated.js) drawn instead of a streamed mesh, and its box.
    this.object = this.objectBox = null;
    this.bounds = null;         // { center (world, THREE.Vector3), radius }
    this.userMoved = false;     // until the user moves the camera, the view follows the mesh
    this.frame = null;          // the pending animation frame's promise
    this.draws = 0;             // frames drawn (renderer.info also counts the PMREM's renders)
    this.lastLayout = '';
    const self = this;
    // For tests: the three.js objects.
    this.three = { THREE, renderer, scene, camera, get mesh() { return self.mesh; },
                   get materials() { return self.progressive?.drawn?.materials ?? []; } };

    window.addEventListener('resize', () => this.resize());
    if (panel && window.ResizeObserver) new ResizeObserver(() => this.resize()).observe(panel);
    viewer.on('mesh', (detail) => this.showMesh(detail));
    viewer.on('level', (detail) => this.showLevel(detail));
    viewer.on('settings', (key) => this.applySettings(key));
    viewer.on('stream', (detail) => this.environment.streamIs(detail));
    viewer.on('reset-view', () => {
      if (!this.showing()) return;
      this.userMoved = false;
      this.refit();
    });
    viewer.on('camera-set', ({ position, target }) => {
      if (!this.showing()) return;
      this.userMoved = true;
      camera.position.fromArray(position);
      this.controls.target.fromArray(target);
      this.controls.update();
      this.emitView();
      this.rendered();
    });
    this.resize();
  }

  showing() {
    return this.mesh !== null || this.object !== null;
  }

  makeControls() {
    // OrbitControls fixes its up axis when made: a new one per up axis
    const made = new OrbitControls(this.camera, this.renderer.domElement);
    made.addEventListener('start', () => { this.userMoved = true; });
    made.addEventListener('change', () => {
      this.emitView();
      this.rendered();
      if (this.userMoved) this.viewer.emit('camera', this.cameraState());
    });
    return made;
  }

  draw() {
    const started = performance.now();
    this.draws++;
    this.renderer.render(this.scene, this.camera);
    const { calls, triangles } = this.renderer.info.render;
    this.viewer.emit('frame', { ms: performance.now() - started, calls, triangles });
    if (this.showing()) this.environment.meshDrawn();
  }

  // Resolves after the next frame is drawn.
  rendered() {
    this.frame ??= new Promise((resolve) => requestAnimationFrame(() => {
      this.frame = null;
      this.draw();
      resolve();
    }));
    return this.frame;
  }

  // The free part of the canvas, and the camera's principal point moved to its
  // centre (setViewOffset), so the mesh is centred where the panel is not.
  viewOffset() {
    const { clientWidth: width, clientHeight: height } = this.container;
    const box = this.panel?.getBoundingClientRect();
    const canvasBox = this.container.getBoundingClientRect();
    const rect = box && { left: box.left - canvasBox.left, top: box.top - canvasBox.top,
                          right: box.right - canvasBox.left, width: box.width, height: box.height };
    const free = freeArea(width, height, rect);
    const shiftX = free.x + free.width / 2 - width / 2;
    const shiftY = free.y + free.height / 2 - height / 2;
    if (width > 0 && height > 0) {
      this.camera.setViewOffset(width, height, -shiftX, -shiftY, width, height);
    }
    return { width, height, free };
  }

  // What framing.js needs to frame a box here: { fov, width, height, free, up }.
  view() {
    return { fov: this.camera.fov, ...this.viewOffset(), up: this.settings.up };
  }

  // After the window or the panel changed size. The panel's height changes
  // with its text (stats, status) while streaming: only a change of the space
  // it leaves free, or of the canvas, is any work.
  resize() {
    const { clientWidth: width, clientHeight: height } = this.container;
    const sized = this.renderer.getSize(new THREE.Vector2());
    if (sized.x !== width || sized.y !== height) this.renderer.setSize(width, height);
    this.camera.aspect = width / Math.max(1, height);
    const { free } = this.viewOffset();
    const layout = JSON.stringify([width, height, free]);
    if (layout === this.lastLayout) return;
    this.lastLayout = layout;
    this.camera.updateProjectionMatrix();
    if (this.showing() && !this.userMoved) this.frameMesh();
    this.emitView();
    this.rendered();
  }

  emitView() {
    const { bounds, camera } = this;
    if (!bounds) return;
    const distance = camera.position.distanceTo(bounds.center);
    this.viewer.emit('view', pixelsPerUnit(distance, bounds.radius,
      { fov: camera.fov, height: this.renderer.domElement.clientHeight, near: camera.near }));
  }

  cameraState() {
    return { position: this.camera.position.toArray(), target: this.controls.target.toArray() };
  }

  // The box to frame: the mesh's full-detail box from its summary, else the
  // current level's (the level's grid coordinates, in world units).
  boxToFrame() {
    if (this.object) return this.objectBox;
    if (this.info?.bounds) return this.info.bounds;
    const { positions, vertexCount, grid: { origin, step } } = this.state;
    const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (let i = 0; i < 3 * vertexCount; i++) {
      const k = i % 3;
      if (positions[i] < lo[k]) lo[k] = positions[i];
      if (positions[i] > hi[k]) hi[k] = positions[i];
    }
    return { min: lo.map((q, k) => origin[k] + step * q),
             max: hi.map((q, k) => origin[k] + step * q) };
  }

  // Fits the box into the free part of the view, from the front of the up axis.
  frameMesh() {
    const { camera, settings } = this;
    const { width, height, free } = this.viewOffset();
    const fit = fitBox(this.boxToFrame(),
                       { fov: camera.fov, width, height, free, up: settings.up });
    this.bounds = { center: new THREE.Vector3(...fit.target), radius: fit.radius };
    if (this.controlsUp !== settings.up) {
      camera.up.set(...fit.up);
      this.controls.dispose();
      this.controls = this.makeControls();
      this.controlsUp = settings.up;
    }
    camera.position.set(...fit.position);
    camera.near = fit.near;
    camera.far = fit.far;
    camera.updateProjectionMatrix();
    this.controls.maxDistance = fit.radius * 50;   // well inside the far plane
    this.controls.target.copy(this.bounds.center);
    this.controls.update();
  }

  // Frames the view again and draws it.
  refit() {
    this.frameMesh();
    this.emitView();
    this.rendered();
  }

  // Shows `object`, a ProgressiveMesh (its level drawn once its first level
  // is in: 'mesh'), framed by its full-detail box when its summary has one,
  // so that the view it asks its first level for is the one shown.
  showProgressive(object) {
    this.removeObject(this.object ?? this.progressive);
    this.progressive = object;
    this.scene.add(object);
    this.userMoved = false;
    this.bounds = null;
    this.info = object.summary;
    if (this.info.bounds) this.frameMesh();
  }

  // The first level of the ProgressiveMesh shown is in.
  showMesh({ state, info }) {
    if (!this.progressive) return;
    this.state = state;
    this.info = info;
    this.mesh = this.progressive.mesh;
    this.userMoved = false;
    this.bounds = null;
    if (this.info.bounds) this.frameMesh();
  }

  showLevel() {
    if (!this.mesh) return;
    // Without the mesh's box the view follows the level's, until the user moves
    // it; in auto mode the camera distance picks the level: framing would feed back.
    if (!this.bounds || (!this.info?.bounds && !this.userMoved && !this.settings.autoByDistance)) {
      this.frameMesh();
    }
    this.emitView();
    this.rendered();
  }

  applySettings(key) {
    if (key === 'shading' || key === 'wireframe') {
      this.progressive?.setLook(this.settings);
      this.rendered();
    } else if (key === 'up' && this.showing()) {
      this.userMoved = false;
      this.refit();
    }
  }

  // Resolves once the image-based light is in place (at once before a mesh
  // is shown: it is made after the first frame showing one).
  environmentReady() {
    return this.showing() ? this.environment.ready : Promise.resolve();
  }

  // Shows `root` (a three.js object: a ProgressiveScene, animated.js animates
  // it) in place of the streamed mesh, framed by `box` ({ min, max }, world
  // units); the caller owns and disposes it.
  showObject(root, box) {
    this.removeObject(this.object ?? this.progressive);
    this.object = root;
    this.objectBox = box;
    this.scene.add(root);
    this.userMoved = false;
    this.refit();
  }

  // Removes the object shown (by showObject() or showProgressive()), if it is
  // still `root`; its owner disposes it.
  removeObject(root) {
    if (!root || (this.object !== root && this.progressive !== root)) return;
    this.scene.remove(root);
    this.object = this.objectBox = this.progressive = null;
    this.mesh = this.state = this.info = null;
    this.rendered();
  }

  // Resolves once every texture asked for so far has arrived.
  texturesReady() {
    return this.progressive?.texturesReady() ?? Promise.resolve();
  }

  // For tests: the canvas pixels drawn now (RGBA, bottom row first; read in
  // the same task as the draw, so the drawing buffer still holds them).
  pixels() {
    this.draw();
    const gl = this.renderer.getContext();
    const { drawingBufferWidth: width, drawingBufferHeight: height } = gl;
    const out = new Uint8Array(4 * width * height);
    gl.readPixels(0, 0, width, height, gl.RGBA, gl.UNSIGNED_BYTE, out);
    return { width, height, data: out };
  }
}

