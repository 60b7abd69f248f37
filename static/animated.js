// Scenes in the viewer (GET /meshes/{id} says "scene": true): the panel's
// part of a ProgressiveScene (progressivescene.js, the three.js module's:
// the whole glTF scene as one GLB, skins, morph targets, cameras, lights,
// materials, animations, then each part refined by its own packet stream).
// This plays its clips (a chooser, play/pause, a time scrubber), draws it on
// demand (a frame while an animation plays, one after another, or when
// something changed: a clip, the scrubber, a refined part, the camera) and
// says in the status how its parts stream.
//
// Signals out: 'status', 'scene-shown' ({ info, ratio: the GLB's }).

import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';

// Frames drawn for the scrubber: at most this often is its text rewritten.
const LABEL_MS = 100;

// A GLTFLoader whose images load as <img> (img-src allows blob:) rather than
// fetched ImageBitmaps: the page's connect-src 'self' refuses fetches of blob: URLs.
export function makeLoader() {
  const loader = new GLTFLoader();
  loader.register((parser) => {
    parser.textureLoader = new THREE.TextureLoader(parser.options.manager);
    return { name: 'lodserver_images' };
  });
  return loader;
}

const plural = (n, word) => `${n} ${word}${n === 1 ? '' : 's'}`;

export class SceneAnimation {
  // viewer: the bus; view: the ViewScene (scene.js) drawing it; root: the panel.
  constructor(viewer, view, root) {
    this.viewer = viewer;
    this.view = view;
    const $ = (selector) => root.querySelector(selector);
    this.section = $('#animation');
    this.clipSelect = $('#clip-select');
    this.playButton = $('#play-pause');
    this.scrubber = $('#time-scrubber');
    this.label = $('#time-label');
    this.object = null;         // the ProgressiveScene shown
    this.action = null;         // the clip's AnimationAction
    this.clip = null;           // its index
    this.playing = false;
    this.last = 0;              // when the mixer was last advanced, ms
    this.labelled = 0;          // when the time label was last written, ms
    this.clipSelect.addEventListener('change', () => this.chooseClip(Number(this.clipSelect.value)));
    this.playButton.addEventListener('click', () => this.play(!this.playing));
    this.scrubber.addEventListener('input', () => {
      if (!this.action) return;
      if (this.playing) this.play(false);      // scrubbing pauses
      this.setTime(Number(this.scrubber.value) * this.action.getClip().duration);
    });
  }

  get open() { return this.object !== null; }
  get clips() { return this.object?.animations ?? []; }

  // Shows `object` (a ProgressiveScene), its first clip playing.
  show(object) {
    this.close();
    this.object = object;
    const { summary } = object;
    object.addEventListener('change', () => this.view.rendered());
    object.addEventListener('stream', ({ part, detail }) => this.partStream(object, part, detail));
    const bounds = new THREE.Box3().setFromObject(object, true);
    this.view.showObject(object, { min: bounds.min.toArray(), max: bounds.max.toArray() });
    const clips = this.clips;
    this.clipSelect.replaceChildren(...clips.map(
      (clip, i) => new Option(clip.name || `animation ${i}`, String(i))));
    this.section.hidden = clips.length === 0;
    if (clips.length) {
      this.chooseClip(0);
      this.play(true);
    }
    this.viewer.emit('scene-shown', { info: summary, ratio: object.glb.ratio });
    this.viewer.emit('status', `${summary.name}: ${plural(clips.length, 'animation')}; ` +
                     `refining ${plural(summary.parts?.length ?? 0, 'part')}`);
  }

  // A part's stream changed state: a failure, or every part at rest, is said.
  partStream(object, part, { state, error }) {
    if (this.object !== object) return;
    part.idle = state === 'idle';
    const { name } = object.summary;
    if (state === 'failed') {
      this.viewer.emit('status', `${name}: part ${part.record.name || part.record.index}: ${error}`);
    } else if (object.parts.every((each) => each.idle || !each.levels)) {
      const faces = object.parts.reduce((n, each) => n + (each.faces ?? 0), 0);
      this.viewer.emit('status', `${name}: ${plural(object.parts.length, 'part')}, ` +
                       `${faces.toLocaleString()} faces drawn`);
    }
  }

  // Stops playing and forgets the scene (its owner disposes it).
  close() {
    if (!this.object) return;
    this.playing = false;
    this.view.removeObject(this.object);
    this.object = this.action = this.clip = null;
    this.section.hidden = true;
  }

  showTime() {
    if (!this.action) return;
    const { time } = this.action, { duration } = this.action.getClip();
    this.scrubber.value = String(duration > 0 ? time / duration : 0);
    this.label.textContent = `${time.toFixed(2)} / ${duration.toFixed(2)} s`;
  }

  // While playing: advance the mixer by the time since the last frame, draw, again.
  loop(object) {
    if (this.object !== object || !this.playing) return;
    const now = performance.now();
    object.mixer.update((now - this.last) / 1000);
    this.last = now;
    if (now - this.labelled > LABEL_MS) {
      this.labelled = now;
      this.showTime();
    }
    this.view.rendered().then(() => this.loop(object));
  }

  play(playing) {
    if (!this.action) return;
    const wasPlaying = this.playing;
    this.playing = playing;
    this.playButton.textContent = playing ? 'pause' : 'play';
    if (playing && !wasPlaying) {
      this.last = performance.now();
      this.loop(this.object);
    } else if (!playing) {
      this.showTime();
      this.view.rendered();
    }
  }

  pause() {
    this.play(false);
  }

  chooseClip(index) {
    const object = this.object;
    if (!object?.animations[index]) return;
    this.action?.stop();
    this.action = object.mixer.clipAction(object.animations[index]);
    this.action.play();
    this.clip = index;
    this.clipSelect.value = String(index);
    object.mixer.update(0);              // pose at the clip's first frame
    this.showTime();
    this.view.rendered();
  }

  // Sets the clip's time (seconds) and draws that pose.
  setTime(seconds) {
    if (!this.action) return;
    const duration = this.action.getClip().duration;
    this.action.time = Math.min(Math.max(0, seconds), duration);
    this.object.mixer.update(0);
    this.showTime();
    this.view.rendered();
  }

  // Resolves once every part's stream has reached its target.
  async settled() {
    await this.object?.settled();
  }

  // The scene's state, for tests and benchmarks.
  status() {
    const object = this.object;
    if (!object) return null;
    const parts = object.parts.map(({ record: { index, name, vertices }, shown, faces, refined,
                                      levels, meshes }) => (
      { index, name, level: shown, faces, vertices, refined, target: levels?.target ?? null,
        attributes: meshes[0]?.geometry.userData.lodserver ?? null,
        bytes: levels?.bytes ?? 0, busy: levels?.busy ?? false, error: levels?.error ?? null }));
    return { parts, bytes: object.bytes,
             clips: this.clips.map((clip) => ({ name: clip.name, duration: clip.duration })),
             clip: this.clip, playing: this.playing, time: this.action?.time ?? null,
             cameras: object.cameras.length };
  }

  // World boxes ({ min, max }) of part p's meshes as posed now (skinning and
  // morphs applied), or of the whole scene.
  box(part = null) {
    const object = this.object;
    if (!object) return null;
    const meshes = part === null ? [object.root]
      : object.parts.find((each) => each.record.index === part)?.meshes ?? [];
    const out = new THREE.Box3();
    object.root.updateMatrixWorld(true);
    for (const mesh of meshes) out.union(new THREE.Box3().setFromObject(mesh, true));
    return { min: out.min.toArray(), max: out.max.toArray() };
  }

  get three() { return this.object ? { root: this.object.root, mixer: this.object.mixer } : null; }
}
