// The three.js scene: one mesh drawn from the decoder's arrays, rendered on
// demand (when the camera, the level or a setting changes; nothing animates).
//
// The buffers are allocated at full detail once per mesh. A level is a prefix
// of the vertices and of the faces (the prefix layout), so showing one is a
// draw range, and a packet re-uploads only the ranges it changed. The index
// buffer *is* the decoder's face array; positions are decoded from the grid
// (origin + q * step: the origin goes into the mesh's transform, so the floats
// stay small).
//
// Signals in: 'mesh', 'level', 'settings'. Out: 'view' (pixels per mesh unit
// at the mesh's nearest point, for choosing a level by distance).

import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

export function createScene(viewer, container) {
  const { settings } = viewer;
  const renderer = new THREE.WebGLRenderer({ antialias: true });
  renderer.setPixelRatio(window.devicePixelRatio);
  renderer.setClearColor(settings.background);
  container.append(renderer.domElement);

  const scene = new THREE.Scene();
  const camera = new THREE.PerspectiveCamera(settings.fov, 1, 0.01, 100);
  // A light that follows the camera keeps the side facing the viewer lit.
  const headlight = new THREE.DirectionalLight(0xffffff, 2.2);
  headlight.position.set(0.4, 0.6, 0);
  headlight.target.position.set(0, 0, -1);
  camera.add(headlight, headlight.target);
  scene.add(camera, new THREE.HemisphereLight(0xf0f4ff, 0x40382c, 0.9));
  const controls = new OrbitControls(camera, renderer.domElement);

  // Open meshes (scans) show their inside through holes: light both sides.
  const material = new THREE.MeshStandardMaterial({ color: 0xd9cfbf, roughness: 0.75,
                                                    side: THREE.DoubleSide });
  let mesh = null, state = null;
  let bounds = null;          // { center (world), radius }
  let userMoved = false;      // until the user moves the camera, the view follows the mesh
  let frame = null;           // the pending animation frame's promise

  function render() {
    if (!frame) {
      frame = new Promise((resolve) => requestAnimationFrame(() => {
        frame = null;
        renderer.render(scene, camera);
        resolve();
      }));
    }
    return frame;
  }

  function resize() {
    const { clientWidth: width, clientHeight: height } = container;
    renderer.setSize(width, height);
    camera.aspect = width / Math.max(1, height);
    camera.updateProjectionMatrix();
    emitView();
    render();
  }

  // How many CSS pixels one mesh unit covers at the mesh's nearest point.
  function emitView() {
    if (!bounds) return;
    const distance = Math.max(camera.position.distanceTo(bounds.center) - bounds.radius,
                              camera.near);
    const height = renderer.domElement.clientHeight;
    const halfFov = THREE.MathUtils.degToRad(camera.fov) / 2;
    viewer.emit('view', height / (2 * Math.tan(halfFov) * distance));
  }

  // Looks at the box of the current level from the front, a little above and right.
  function frameLevel() {
    const { positions, vertexCount } = state;
    const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (let i = 0; i < 3 * vertexCount; i++) {
      const k = i % 3;
      if (positions[i] < lo[k]) lo[k] = positions[i];
      if (positions[i] > hi[k]) hi[k] = positions[i];
    }
    const { origin, step } = state.grid;
    const center = new THREE.Vector3(...lo.map((q, k) => origin[k] + step * (q + hi[k]) / 2));
    const radius = Math.max(step, step * Math.hypot(...hi.map((q, k) => q - lo[k])) / 2);
    bounds = { center, radius };
    const distance = 1.15 * radius / Math.sin(THREE.MathUtils.degToRad(camera.fov) / 2);
    const direction = new THREE.Vector3(0.35, 0.25, 1).normalize();
    camera.position.copy(center).addScaledVector(direction, distance);
    camera.near = radius / 100;
    camera.far = radius * 100;
    camera.updateProjectionMatrix();
    controls.maxDistance = radius * 50;   // well inside the far plane
    controls.target.copy(center);
    controls.update();
  }

  function showMesh({ state: opened }) {
    if (mesh) {
      scene.remove(mesh);
      mesh.geometry.dispose();
    }
    state = opened;
    const geometry = new THREE.BufferGeometry();
    const dynamic = (array, size) => new THREE.BufferAttribute(array, size)
      .setUsage(THREE.DynamicDrawUsage);
    geometry.setAttribute('position', dynamic(new Float32Array(3 * state.vertexCapacity), 3));
    geometry.setAttribute('normal', dynamic(new Float32Array(3 * state.vertexCapacity), 3));
    geometry.setIndex(dynamic(state.faces, 1));
    mesh = new THREE.Mesh(geometry, material);
    mesh.position.set(...state.grid.origin);
    // The bounding sphere would count the unused slots of the buffers.
    mesh.frustumCulled = false;
    scene.add(mesh);
    userMoved = false;
    bounds = null;
  }

  function showLevel({ dirty }) {
    const { geometry } = mesh;
    const position = geometry.getAttribute('position');
    const { vertexStart, vertexEnd, cornerStart, cornerEnd } = dirty;
    if (vertexEnd > vertexStart) {
      const { step } = state.grid;
      for (let i = 3 * vertexStart; i < 3 * vertexEnd; i++) {
        position.array[i] = state.positions[i] * step;
      }
      position.addUpdateRange(3 * vertexStart, 3 * (vertexEnd - vertexStart));
      position.needsUpdate = true;
    }
    if (cornerEnd > cornerStart) {
      geometry.index.addUpdateRange(cornerStart, cornerEnd - cornerStart);
      geometry.index.needsUpdate = true;
    }
    if (settings.shading === 'smooth') updateNormals();
    geometry.setDrawRange(0, 3 * state.faceCount);
    // In auto mode the camera distance picks the level: framing each level would feed back.
    if (!bounds || (!userMoved && !settings.autoByDistance)) frameLevel();
    emitView();
    render();
  }

  // Area-weighted vertex normals of the current level (every vertex of a
  // level lies on one of its faces). Computed on grid coordinates: the same
  // directions, without reading the floats back.
  function updateNormals() {
    const normal = mesh.geometry.getAttribute('normal');
    const n = normal.array, q = state.positions, faces = state.faces;
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
    normal.addUpdateRange(0, 3 * state.vertexCount);
    normal.needsUpdate = true;
  }

  function applySettings(key) {
    if (key === 'shading' && mesh) {
      material.flatShading = settings.shading === 'flat';
      material.needsUpdate = true;
      if (!material.flatShading) updateNormals();
      render();
    }
  }

  controls.addEventListener('start', () => { userMoved = true; });
  controls.addEventListener('change', () => {
    emitView();
    render();
  });
  window.addEventListener('resize', resize);
  viewer.on('mesh', showMesh);
  viewer.on('level', showLevel);
  viewer.on('settings', applySettings);
  material.flatShading = settings.shading === 'flat';
  resize();

  return {
    canvas: renderer.domElement,
    // Resolves after the next frame is drawn.
    rendered: render,
  };
}
