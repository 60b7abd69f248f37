// One progressive mesh as a three.js object (the three.js module's, see
// lodserver-three.js): a LevelMesh (levelmesh.js) drawing a StreamedLevel
// (streamedlevel.js), its level kept where its error, projected through the
// app's camera, covers at most options.errorPixels CSS pixels, vertices
// gliding between levels (geomorph.js).

import * as THREE from 'three';
import { createGeomorph } from './geomorph.js';
import { LevelMesh } from './levelmesh.js';
import { allowedError, DEFAULTS, StreamedLevel } from './streamedlevel.js';

export class ProgressiveMesh extends THREE.Object3D {
  // source: a source (source.js) of a mesh that is not a scene; options: DEFAULTS' keys.
  constructor(source, options = {}) {
    super();
    this.type = 'ProgressiveMesh';
    this.summary = source.summary;
    this.name = this.summary.name ?? '';
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
    const self = this;
    const view = { three: { get mesh() { return self.drawn?.mesh ?? null; } }, rendered() {} };
    this.levels.stream.attachGeomorph(createGeomorph(this.levels.bus, view));
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

  show(state, appearance) {
    this.drawn?.dispose();
    this.drawn = new LevelMesh(state, appearance);
    this.drawn.setLook(this.options);
    this.add(this.drawn.mesh);
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

  // Frees the GPU buffers and textures and stops every fetch.
  dispose() {
    this.levels.close();
    this.drawn?.dispose();
    this.drawn = null;
    this.removeFromParent();
  }
}
