// A lodserver scene (GET /meshes/{id} says "scene": true: docs/scenes.md) as
// a three.js object (the three.js module's, see lodserver-three.js): the
// whole glTF scene as one GLB from the server (nodes, skins, morph targets,
// materials, animations) loaded by three.js's GLTFLoader, its first clip
// playing, then each part's level streamed (streamedlevel.js) and kept where
// its error, projected through the app's camera, covers at most
// options.errorPixels CSS pixels. A part's meshes take each level as a new
// geometry (partgeometry.js: what the stream does not carry, such as skin
// weights, is kept from the GLB's), so a skinned part keeps animating.
// A part drawn by several primitives (one per material) keeps the GLB's
// geometry: its level would have to be cut by material first.

import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { levelGeometry } from './partgeometry.js';
import { allowedError, DEFAULTS, StreamedLevel } from './streamedlevel.js';

const diagonal = (box) => Math.hypot(...box.max.map((x, k) => x - box.min[k]));

// One part of a scene: the GLB meshes drawing it and its streamed level.
class ScenePart {
  // meshes: the GLB's meshes marked extras.lodserver_part == record.index;
  // box: their box ({ min, max }) in the scene object's frame, posed as loaded.
  // onRefine(part): its meshes took a new level; onStream(part, detail): its
  // stream's state (the 'stream' signal of stream.js).
  constructor(source, record, meshes, box, options, { onRefine, onStream }) {
    this.record = record;
    this.meshes = meshes;
    this.box = box;
    // one geometry shared by every node instancing the part (several: not refined)
    const geometries = new Set(meshes.map((mesh) => mesh.geometry));
    this.original = geometries.size === 1 ? meshes[0].geometry : null;
    // the scene's units a mesh unit of the part is drawn as, from the two boxes
    this.unitScale = record.bounds && diagonal(record.bounds) > 0
      ? diagonal(box) / diagonal(record.bounds) : 1;
    this.levels = null;
    this.shown = null;          // the level the meshes show: null while the GLB's
    this.faces = null;
    this.refined = 0;           // levels taken from the stream
    this.onRefine = onRefine;
    if (!this.original) return;
    const { index, attributes } = this.original;
    this.glbFaces = (index ? index.count : attributes.position.count) / 3;
    this.levels = new StreamedLevel(source.part(record), options, {
      materials: false, onLevel: ({ state }) => this.refine(state) });
    this.levels.bus.on('stream', (detail) => onStream(this, detail));
  }

  // The part's meshes take the geometry of the stream's level.
  refine(state) {
    // a level coarser than the GLB's (the base, before the first packet) would
    // be a step back: the GLB stays until the stream passes it
    if (state.faceCount < this.glbFaces) return;
    const geometry = levelGeometry(state, this.original);
    const old = this.meshes[0].geometry;
    if (old !== this.original) old.dispose();
    for (const mesh of this.meshes) {
      mesh.geometry = geometry;
      if (geometry.morphAttributes.position?.length && !mesh.morphTargetInfluences) {
        mesh.updateMorphTargets();
      }
      // a skinned mesh's bounds (posed) are its own: recomputed when next needed
      if (mesh.isSkinnedMesh) mesh.boundingBox = mesh.boundingSphere = null;
    }
    this.shown = state.level;
    this.faces = state.faceCount;
    this.refined++;
    this.onRefine(this);
  }

  dispose() {
    this.levels?.close();
    const shown = this.meshes[0]?.geometry;
    if (shown && shown !== this.original) shown.dispose();
  }
}

export class ProgressiveScene extends THREE.Object3D {
  // source: a scene's source (source.js); gltf: GLTFLoader's result for its
  // GLB; glb: { bytes: its size, ratio: the level it holds, a fraction of the
  // vertices }. Dispatches 'change' when a part took a new level and
  // 'stream' ({ part, detail }) with each part's stream state.
  constructor(source, gltf, options = {}, glb = { bytes: 0, ratio: 1 }) {
    super();
    this.type = 'ProgressiveScene';
    this.summary = source.summary;
    this.name = this.summary.name ?? '';
    this.options = { ...DEFAULTS, ...options };
    this.root = gltf.scene;
    this.add(this.root);
    this.animations = gltf.animations;
    this.cameras = gltf.cameras;       // the scene's own, for an app to look through
    this.mixer = new THREE.AnimationMixer(this.root);
    this.clock = new THREE.Clock();
    this.disposed = false;
    this.glb = glb;
    if (this.animations.length) this.mixer.clipAction(this.animations[0]).play();
    this.updateMatrixWorld(true);
    // the scene's bounding sphere as loaded, in this object's frame, for framing it
    this.boundingSphere = new THREE.Box3().setFromObject(this.root, true)
      .getBoundingSphere(new THREE.Sphere());
    this.parts = (this.summary.parts ?? []).map((record) => {
      const meshes = [];
      this.root.traverse((object) => {
        if (object.isMesh && object.userData?.lodserver_part === record.index) meshes.push(object);
      });
      const box = new THREE.Box3();
      for (const mesh of meshes) box.union(new THREE.Box3().setFromObject(mesh, true));
      const bounds = box.isEmpty() ? null : { min: box.min.toArray(), max: box.max.toArray() };
      return new ScenePart(source, record, meshes, bounds, this.options, {
        onRefine: () => this.dispatchEvent({ type: 'change' }),
        onStream: (part, detail) => this.dispatchEvent({ type: 'stream', part, detail }),
      });
    });
  }

  // The scene's GLB, at most firstLevelMaxVertices (a progressive file's: at
  // its base levels), loaded as a ProgressiveScene (by options.gltfLoader: an
  // app's own GLTFLoader, with its plugins, or a new one).
  static async load(source, options = {}) {
    const { vertices } = source.summary;
    const first = options.firstLevelMaxVertices ?? DEFAULTS.firstLevelMaxVertices;
    const ratio = Number(Math.min(1, first / Math.max(1, vertices)).toPrecision(6));
    const { buffer, url } = await source.sceneGlb({ ratio });
    const loader = options.gltfLoader ?? new GLTFLoader();
    const gltf = await loader.parseAsync(buffer, new URL('./', url).href);
    return new ProgressiveScene(source, gltf, options, { bytes: buffer.byteLength, ratio });
  }

  get streamed() { return this.parts.filter((part) => part.levels); }
  // Sums over the streamed parts: the vertices of the levels held, and of full detail.
  get level() { return this.streamed.reduce((n, part) => n + part.levels.level, 0); }
  get fullLevel() { return this.streamed.reduce((n, part) => n + part.levels.full, 0); }
  get target() {
    const parts = this.streamed;
    return parts.some((part) => part.levels.target === null) ? null
      : parts.reduce((n, part) => n + part.levels.target, 0);
  }
  get error() { return this.streamed.find((part) => part.levels.error)?.levels.error ?? null; }
  // The bytes received: the GLB and every part's packets.
  get bytes() { return this.glb.bytes + this.streamed.reduce((n, part) => n + part.levels.bytes, 0); }

  // Pins the scene at n vertices, each part at its share (null: back to the budget).
  setLevel(n) {
    const full = this.fullLevel;
    for (const { levels } of this.streamed) {
      levels.pin(n === null || n === undefined ? null : Math.round((n / full) * levels.full));
    }
  }

  // Plays the animation and moves each part's level to the budget at this
  // camera's view (call it each frame).
  update(camera, renderer) {
    if (this.disposed) return;
    this.mixer.update(this.clock.getDelta());
    const { errorPixels } = this.options;
    for (const part of this.streamed) {
      part.levels.follow(part.box ? allowedError(this, part.box, {
        camera, renderer, errorPixels, unitScale: part.unitScale }) : null);
    }
  }

  // Resolves once every part's level reached its target and nothing is in flight.
  async settled() {
    await Promise.all(this.streamed.map((part) => part.levels.settled()));
  }

  // Frees the GPU buffers and textures, stops the animation and every fetch.
  dispose() {
    if (this.disposed) return;
    this.disposed = true;
    this.mixer.stopAllAction();
    for (const part of this.parts) part.dispose();
    this.root.traverse((object) => {
      object.geometry?.dispose();
      for (const material of [object.material ?? []].flat()) {
        for (const value of Object.values(material)) if (value?.isTexture) value.dispose();
        material.dispose();
      }
    });
    this.removeFromParent();
  }
}
