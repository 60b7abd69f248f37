// The level of one progressive mesh in the three.js module (a mesh, or a
// scene's part): its stream (stream.js) from a source (source.js), kept at
// the level the error budget allows at the app's view (follow()) or at a
// level pinned by the app (pin()).
//
// Nothing is fetched before the first follow() or pin(): the first level is
// the one the view asks for, so no level is fetched only to be dropped.

import * as THREE from 'three';
import { Bus } from './bus.js';
import { ErrorCurve } from './curve.js';
import { sphereOf } from './framing.js';
import { PacketStream } from './stream.js';

// The module's options (docs/three.md).
export const DEFAULTS = {
  errorPixels: 1,             // the error budget, CSS pixels
  geomorphMs: 250,            // vertices glide between levels for this long (0: off)
  hysteresis: 2,              // coarsen once the error projects under errorPixels / this
  firstLevelMaxVertices: 4096,  // the first level drawn at most (packets then refine it)
  shading: 'smooth',          // 'smooth' or 'flat' (a streamed mesh's)
  wireframe: false,
};

const scratch = new THREE.Vector3();

// CSS pixels one world unit covers at the nearest point of a world sphere
// (center: a THREE.Vector3, radius), seen through `camera` on renderer's
// canvas (docs/three.md says why the nearest point).
export function pixelsPerUnit(camera, renderer, center, radius) {
  const canvas = renderer.domElement;
  const height = canvas.clientHeight || canvas.height;
  if (camera.isOrthographicCamera) return height * camera.zoom / (camera.top - camera.bottom);
  const distance = camera.getWorldPosition(scratch).distanceTo(center);
  const nearest = Math.max(distance - radius, camera.near);
  const fov = THREE.MathUtils.degToRad(camera.getEffectiveFOV());
  return height / (2 * Math.tan(fov / 2) * nearest);
}

// The error, in mesh units, that `errorPixels` allows for a box `bounds`
// ({ min, max }) in `object`'s frame, drawn by `object`: the box's sphere
// carried into the world by the object's transform; `unitScale` is how many
// of the object's units a mesh unit is drawn as (1 for a mesh drawn by its
// own object; a scene's skinned part is placed by its bones, not its node).
export function allowedError(object, bounds, { camera, renderer, errorPixels, unitScale = 1 }) {
  const { center, radius } = sphereOf(bounds);
  object.updateWorldMatrix(true, false);
  const size = object.matrixWorld.getMaxScaleOnAxis();
  const world = new THREE.Vector3(...center).applyMatrix4(object.matrixWorld);
  const perUnit = pixelsPerUnit(camera, renderer, world, radius * size) * size * unitScale;
  return perUnit > 0 ? errorPixels / perUnit : Infinity;
}

export class StreamedLevel {
  // source: a mesh's (or part's) source; options: DEFAULTS' keys;
  // onMesh({ state, appearance }), onLevel({ state, dirty }): the stream's
  // first level and each move; materials: false leaves them to the caller.
  constructor(source, options, { onMesh = () => {}, onLevel = () => {}, materials = true } = {}) {
    this.source = source;
    this.summary = source.summary;
    this.options = options;
    this.withMaterials = materials;
    // until the first level arrives with the base's exact error
    this.curve = new ErrorCurve(this.summary, this.summary.max_error ?? 0);
    this.target = null;         // the level being moved to
    this.pinned = null;         // the level pin() asked for, or null: the budget's
    this.refresh = false;       // the budget's level is due at once (after pin(null))
    this.opened = false;
    this.closed = false;
    // the stream's and geomorph's settings: the options, read live (an app's or
    // the viewer's change of geomorphMs reaches a running stream), and this
    // level's own first target
    const settings = Object.create(options);
    settings.initialRatio = 1;
    this.bus = new Bus(settings);
    this.stream = new PacketStream(this.bus);
    this.bus.on('mesh', (detail) => {
      this.curve = detail.curve;
      onMesh(detail);
    });
    this.bus.on('level', onLevel);
    this.bus.on('target', (level) => { this.target = level; });
  }

  // The vertices of the level held (0 before the first arrives), and of full detail.
  get level() { return this.stream.state?.level ?? 0; }
  get full() { return this.summary.vertices; }
  get state() { return this.stream.state; }
  get bytes() { return this.stream.bytes; }
  get busy() { return this.stream.busy; }
  // The reason the stream stopped, or null.
  get error() { return this.stream.failed?.message ?? null; }

  // Opens the stream at `level`: the base and one packet to the first level
  // (at most firstLevelMaxVertices), then packets to `level`.
  open(level) {
    this.opened = true;
    const { vertices } = this.summary;
    this.bus.settings.initialRatio = Math.min(1, level / vertices);
    this.stream.open(this.source, { materials: this.withMaterials,
                                    level: Math.min(level, this.options.firstLevelMaxVertices) });
  }

  // Pins the level at n vertices (null: back to the error budget).
  pin(n) {
    if (this.closed) return;
    if (n === null || n === undefined) {
      this.pinned = null;
      this.refresh = true;
      return;
    }
    const { base_vertices: base, vertices } = this.summary;
    this.pinned = Math.min(vertices, Math.max(base, Math.round(n)));
    if (!this.opened) this.open(this.pinned);
    // (the stream reads initialRatio once the first level is in)
    else if (this.target === null) this.bus.settings.initialRatio = this.pinned / vertices;
    else this.bus.emit('goto', this.pinned);
  }

  // Moves toward the level the view allows: `allowed` is the error (mesh
  // units) the budget allows there, null when it cannot be told (full detail).
  follow(allowed) {
    if (this.closed || this.pinned !== null) return;
    if (allowed === null) {
      if (!this.opened) this.open(this.summary.vertices);
      return;
    }
    if (!this.opened) {
      this.open(this.curve.levelFor(allowed));
      return;
    }
    if (this.target === null) return;       // the first level is on its way
    const level = this.refresh ? this.curve.levelFor(allowed)
      : this.curve.follow(this.target, allowed, this.options.hysteresis);
    this.refresh = false;
    if (level !== null && level !== this.target) this.bus.emit('goto', level);
  }

  // Resolves once the level reached its target and nothing is in flight.
  settled() {
    return this.stream.settled();
  }

  // Stops every fetch; nothing more is reported.
  close() {
    this.closed = true;
    this.stream.close();
  }
}
