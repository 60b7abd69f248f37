// One progressive mesh as a three.js object (the three.js module's, see
// lodserver-three.js): a LevelMesh (levelmesh.js) drawing a StreamedLevel
// (streamedlevel.js), its level kept where its error, projected through the
// app's camera, covers at most options.errorPixels CSS pixels, vertices
// gliding between levels (geomorph.js).

import * as THREE from 'three';
import { Geomorph } from './geomorph.js';
import { LevelMesh } from './levelmesh.js';
import { allowedError, DEFAULTS, StreamedLevel } from './streamedlevel.js';

// The stream's signals a ProgressiveMesh dispatches as three.js events
// ({ type, detail }), for a page showing what the stream does (the viewer's
// panel): what each detail holds is said at the top of stream.js.
const STREAM_EVENTS = ['mesh', 'level', 'target', 'status', 'stream'];

export class ProgressiveMesh extends THREE.Object3D {
  // source: a source (source.js) of a mesh that is not a scene; options: DEFAULTS' keys.
  // Besides STREAM_EVENTS it dispatches 'change' when it changed without a
  // new level (a texture arrived, a glide moved): a page that draws on demand
  // draws then.
  constructor(source, options = {}) {
    super();
    this.type = 'ProgressiveMesh';
    this.source = source;
    this.summary = source.summary;
    this.name = this.summary.name ?? '';
    // read live by the stream and the geomorph (geomorphMs, errorPixels, ...)
    this.options = { ...DEFAULTS, ...options };
    // the full-detail mesh's bounding sphere in this object's frame (null for a
    // mesh summarised without its box), for framing it
    const { bounds } = this.summary;
    this.boundingSphere = bounds ? new THREE.Box3(new THREE.Vector3(...bounds.min),
      new THREE.Vector3(...bounds.max)).getBoundingSphere(new THREE.Sphere()) : null;
    this.drawn = null;          // the LevelMesh, once the first level is in
    this.levels = new StreamedLevel(source, this.options, {
      onMesh: ({ state, appearance }) => this.show(state, appearance),
      onLevel: ({ dirty }) => this.drawn?.update(dirty),
    });
    // registered after the mesh's own listeners: it glides what they wrote
    this.geomorph = new Geomorph(this.levels.bus, {
      mesh: () => this.drawn?.mesh ?? null,
      rendered: () => this.dispatchEvent({ type: 'change' }),
    });
    this.levels.stream.attachGeomorph(this.geomorph);
    for (const type of STREAM_EVENTS) {
      this.levels.bus.on(type, (detail) => this.dispatchEvent({ type, detail }));
    }
  }

  // The vertices of the level held (0 before the first arrives), and of full detail.
  get level() { return this.levels.level; }
  get fullLevel() { return this.levels.full; }
  // The level being moved to (null before the first level is in).
  get target() { return this.levels.target; }
  // The reason the stream stopped, or null.
  get error() { return this.levels.error; }
  // The geometry bytes received.
  get bytes() { return this.levels.bytes; }
  // The level held (a LodState: levelstate.js), for comparing with the server's.
  get state() { return this.levels.state; }

  // The THREE.Mesh drawing the level (null before the first level is in).
  get mesh() { return this.drawn?.mesh ?? null; }
  // The texture bytes received, and a promise of every texture asked for so far.
  get textureBytes() { return this.drawn?.textures?.textureBytes ?? 0; }
  texturesReady() {
    return this.drawn?.textures?.ready ?? Promise.resolve();
  }

  show(state, appearance) {
    this.drawn?.dispose();
    this.drawn = new LevelMesh(state, appearance, {
      onTexture: () => this.dispatchEvent({ type: 'change' }) });
    this.drawn.setLook(this.options);
    this.add(this.drawn.mesh);
  }

  // Sets options.shading ('smooth' or 'flat') and options.wireframe, and
  // shows the mesh so.
  setLook({ shading = this.options.shading, wireframe = this.options.wireframe } = {}) {
    Object.assign(this.options, { shading, wireframe });
    this.drawn?.setLook(this.options);
    this.dispatchEvent({ type: 'change' });
  }

  // Pins the level at n vertices (null: back to the error budget).
  setLevel(n) {
    this.levels.pin(n);
  }

  // Moves the level to the budget at this camera's view (call it each frame).
  update(camera, renderer) {
    const { bounds } = this.summary;
    this.levels.follow(bounds ? allowedError(this, bounds, {
      camera, renderer, errorPixels: this.options.errorPixels }) : null);
  }

  // Resolves once the level reached its target and nothing is in flight.
  settled() {
    return this.levels.settled();
  }

  // Frees the GPU buffers and textures and stops every fetch (and lets the
  // source go of what it holds for them: a file's image URLs).
  dispose() {
    this.levels.close();
    this.source.close?.();
    this.geomorph.dispose();
    this.drawn?.dispose();
    this.drawn = null;
    this.removeFromParent();
  }
}
