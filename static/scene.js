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
// A mesh with attributes is drawn with one vertex per wedge (a UV seam or a
// hard edge has a vertex per side): its position is its vertex's, its normal,
// UVs and colour its own, and the index buffer is the decoder's wedge-per-corner
// array. Normals come from the stream when it has them, else they are computed
// per vertex and shared by the vertex's wedges. Materials come from the mesh's
// /materials (glTF records: base colour, its texture, metalness, roughness,
// alpha); faces are drawn in one group per material, each group a prefix of a
// range of the index buffer (a level's faces of one material are a prefix of
// that material's faces, in slot order).
//
// Signals in: 'mesh', 'level', 'settings'. Out: 'view' (pixels per mesh unit
// at the mesh's nearest point, for choosing a level by distance).

import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { dequantize } from './vsplit.js';

// glTF sampler codes -> three.js constants.
const WRAP = { 33071: THREE.ClampToEdgeWrapping, 33648: THREE.MirroredRepeatWrapping,
               10497: THREE.RepeatWrapping };
const FILTER = { 9728: THREE.NearestFilter, 9729: THREE.LinearFilter,
                 9984: THREE.NearestMipmapNearestFilter, 9985: THREE.LinearMipmapNearestFilter,
                 9986: THREE.NearestMipmapLinearFilter, 9987: THREE.LinearMipmapLinearFilter };
// three.js attribute names of glTF's.
const ATTRIBUTE_NAMES = { NORMAL: 'normal', TEXCOORD_0: 'uv', TEXCOORD_1: 'uv1', COLOR_0: 'color' };

// The three.js material of a glTF material record (metallic-roughness; textures:
// base colour only), its texture loaded from the record's image uri.
function makeMaterial(record, document, baseUrl, loadTexture, hasColors) {
  const pbr = record.pbrMetallicRoughness || {};
  const [r, g, b, a] = pbr.baseColorFactor || [1, 1, 1, 1];
  const material = new THREE.MeshStandardMaterial({
    color: new THREE.Color().setRGB(r, g, b, THREE.LinearSRGBColorSpace),
    metalness: pbr.metallicFactor ?? 1, roughness: pbr.roughnessFactor ?? 1,
    side: THREE.DoubleSide, vertexColors: hasColors, name: record.name || '' });
  if (record.alphaMode === 'BLEND') {
    material.transparent = true;
    material.opacity = a;
    material.depthWrite = false;
  } else if (record.alphaMode === 'MASK') {
    material.alphaTest = record.alphaCutoff ?? 0.5;
  }
  const reference = pbr.baseColorTexture;
  const texture = reference && document.textures?.[reference.index];
  const image = texture && document.images?.[texture.source];
  if (image?.uri) {
    const map = loadTexture(new URL(image.uri, baseUrl).href);
    map.flipY = false;                 // glTF UVs: origin at the top left
    map.colorSpace = THREE.SRGBColorSpace;
    const sampler = document.samplers?.[texture.sampler] || {};
    map.wrapS = WRAP[sampler.wrapS] ?? THREE.RepeatWrapping;
    map.wrapT = WRAP[sampler.wrapT] ?? THREE.RepeatWrapping;
    map.magFilter = FILTER[sampler.magFilter] ?? THREE.LinearFilter;
    map.minFilter = FILTER[sampler.minFilter] ?? THREE.LinearMipmapLinearFilter;
    map.channel = reference.texCoord === 1 ? 1 : 0;
    material.map = map;
  }
  return material;
}

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
  const textureLoader = new THREE.TextureLoader();
  let mesh = null, state = null;
  let materials = [material];     // per draw group: the mesh's materials, then the default
  let groups = null;              // per-material index ranges, when there are several
  let vertexNormals = null;       // computed normals per vertex (wedge meshes without NORMAL)
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

  function showMesh({ state: opened, appearance }) {
    if (mesh) {
      scene.remove(mesh);
      mesh.geometry.dispose();
      for (const old of materials) {
        if (old === material) continue;
        old.map?.dispose();
        old.dispose();
      }
    }
    state = opened;
    const geometry = new THREE.BufferGeometry();
    const dynamic = (array, size) => new THREE.BufferAttribute(array, size)
      .setUsage(THREE.DynamicDrawUsage);
    const wedged = state.attributes.length > 0;
    const capacity = wedged ? state.wedgeCapacity : state.vertexCapacity;
    geometry.setAttribute('position', dynamic(new Float32Array(3 * capacity), 3));
    geometry.setAttribute('normal', dynamic(new Float32Array(3 * capacity), 3));
    for (const a of state.attributes) {
      if (a.name === 'NORMAL') continue;
      geometry.setAttribute(ATTRIBUTE_NAMES[a.name],
                            dynamic(new Float32Array(a.width * capacity), a.width));
    }
    vertexNormals = wedged && !state.attributes.some((a) => a.name === 'NORMAL')
      ? new Float32Array(3 * state.vertexCapacity) : null;
    materials = [material];
    groups = null;
    let drawn = material;
    if (appearance?.materials) {
      const { document, url } = appearance.materials;
      const hasColors = state.attributes.some((a) => a.name === 'COLOR_0');
      const loadTexture = (href) => textureLoader.load(href, () => render());
      materials = [...document.materials.map(
        (record) => makeMaterial(record, document, url, loadTexture, hasColors)), material];
      // one group per material that has faces (the last: faces without a material)
      const counts = appearance.materialFaces || [];
      const used = counts.map((n, g) => (n > 0 ? g : -1)).filter((g) => g >= 0);
      if (used.length === 1) drawn = materials[used[0]];
      else if (used.length > 1) groups = makeGroups(counts);
    }
    for (const each of materials) each.flatShading = settings.shading === 'flat';
    const index = groups ? groups.index : wedged ? state.corners : state.faces;
    geometry.setIndex(dynamic(index, 1));
    mesh = new THREE.Mesh(geometry, groups ? materials : drawn);
    mesh.position.set(...state.grid.origin);
    // The bounding sphere would count the unused slots of the buffers.
    mesh.frustumCulled = false;
    scene.add(mesh);
    userMoved = false;
    bounds = null;
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
    const buffers = state.attributes.map((a) => geometry.getAttribute(ATTRIBUTE_NAMES[a.name]));
    for (const w of dirty.wedges) {
      const v = wedgeVertex[w];
      p[3 * w] = positions[3 * v] * step;
      p[3 * w + 1] = positions[3 * v + 1] * step;
      p[3 * w + 2] = positions[3 * v + 2] * step;
      state.attributes.forEach((a, i) => {
        dequantize(a, wedges, components * w + a.offset, buffers[i].array, a.width * w);
      });
      if (w < low) low = w;
      if (w > high) high = w;
    }
    if (high >= low) {
      position.addUpdateRange(3 * low, 3 * (high - low + 1));
      position.needsUpdate = true;
      state.attributes.forEach((a, i) => {
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

  function showLevel({ dirty }) {
    const { geometry } = mesh;
    if (state.attributes.length) {
      showWedges(dirty);
      if (vertexNormals && settings.shading === 'smooth') updateNormals();
      geometry.setDrawRange(0, groups ? Infinity : 3 * state.faceCount);
      if (!bounds || (!userMoved && !settings.autoByDistance)) frameLevel();
      emitView();
      render();
      return;
    }
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
    if (settings.shading === 'smooth') updateNormals();
    geometry.setDrawRange(0, groups ? Infinity : 3 * state.faceCount);
    // In auto mode the camera distance picks the level: framing each level would feed back.
    if (!bounds || (!userMoved && !settings.autoByDistance)) frameLevel();
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

  function applySettings(key) {
    if (key === 'shading' && mesh) {
      for (const each of materials) {
        each.flatShading = settings.shading === 'flat';
        each.needsUpdate = true;
      }
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
