// The viewer's image-based light, made when it costs the first frames least
// (scene.js).
//
// The environment costs GPU time (materials.js: LOOK) and a second compile
// of the mesh's shaders, so it is made once the first frame showing a mesh
// is drawn and the stream has come to rest (or ENVIRONMENT_WAIT_MS after
// that frame, if it is still streaming): a frame it delays would otherwise
// also space the stream's reports (stream.js measures what frames cost).
// But when the stream estimates the rest of its bytes at more than
// ENVIRONMENT_AHEAD_MS on the link (a slow link, a large mesh), it is made at
// once, as a GLB viewer does while its bytes arrive: made at rest it would
// delay the full-detail frame by its GPU work (bench/viewer measures it on a
// throttled large mesh). Until then a hemisphere light stands in for it (the
// same shading, without reflections).

import * as THREE from 'three';
import { createEnvironment, LOOK } from './materials.js';

// The longest the environment waits for the stream to come to rest.
const ENVIRONMENT_WAIT_MS = 5000;
// The stream's estimate of the rest of its bytes' time on the link (ms) beyond
// which the environment is made at once instead: its GPU work (long under
// software GL) then overlaps the download rather than delaying the
// full-detail frame after it.
const ENVIRONMENT_AHEAD_MS = 1500;

export class DeferredEnvironment {
  // scene: the THREE.Scene lit; renderer: the one that prefilters it;
  // onMade(): the environment is in place (draw again).
  constructor(scene, renderer, onMade) {
    this.scene = scene;
    this.renderer = renderer;
    this.onMade = onMade;
    this.fill = new THREE.HemisphereLight(LOOK.fill.sky, LOOK.fill.ground, LOOK.fill.intensity);
    scene.add(this.fill);
    this.due = false;
    this.meshDrawnAt = null;
    this.streaming = true;
    this.restMs = null;         // the stream's estimate of its rest on the link, ms (or null)
    this.timer = 0;
    this.ready = new Promise((resolve) => { this.made = resolve; });
  }

  // The first frame showing a mesh is drawn.
  meshDrawn() {
    if (this.meshDrawnAt !== null) return;
    this.meshDrawnAt = performance.now();
    // a message posted from the frame's callback runs once the frame is
    // shown: the environment's GPU work queues behind it, not before it
    const channel = new MessageChannel();
    channel.port1.onmessage = () => this.soon();
    channel.port2.postMessage(null);
  }

  // The stream's state ('stream' signal: { state, restMs }).
  streamIs({ state: now, restMs = null }) {
    this.streaming = now === 'moving' || now === 'retrying';
    this.restMs = now === 'moving' ? restMs : null;
    this.soon();
  }

  soon() {
    if (this.due || this.meshDrawnAt === null) return;
    const waited = performance.now() - this.meshDrawnAt;
    const longWay = this.restMs !== null && this.restMs > ENVIRONMENT_AHEAD_MS;
    clearTimeout(this.timer);
    if (this.streaming && !longWay && waited < ENVIRONMENT_WAIT_MS) {
      this.timer = setTimeout(() => this.soon(), ENVIRONMENT_WAIT_MS - waited);
      return;
    }
    this.due = true;
    this.scene.environment = createEnvironment(this.renderer);
    this.scene.remove(this.fill);
    this.made();
    this.onMade();
  }
}
