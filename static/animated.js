// Scenes (GET /meshes/{id} says "scene": true): the whole glTF scene
// at the first level chosen for the view, as the server writes it (one GLB:
// node tree, skins, morph targets, cameras, lights, materials, animations),
// loaded by three.js's GLTFLoader and played by an AnimationMixer, then each
// part refined by its own packet stream (stream.js, one per part).
//
// The GLB's materials are GLTFLoader's (materials.js builds streamed meshes'
// the same way), lit by the scene's environment and tone map (scene.js).
// Drawn on demand: a frame while an animation plays (one after another), or
// when something changed (a clip, the scrubber, a refined part, the camera).
//
// Refining a part: every mesh of the GLB whose glTF mesh carries
// `extras.lodserver_part == p` (GLTFLoader puts extras in userData) gets, at
// each report of part p's stream, a new geometry made from the stream's level:
// positions, and every attribute the packets carry (NORMAL, TEXCOORD_n,
// COLOR_0, TANGENT, JOINTS_0/WEIGHTS_0 -> skinIndex/skinWeight, TARGET{t}_* ->
// morph targets). What the stream does not carry is kept from the GLB's
// geometry: as it is when the level has as many vertices as the GLB's
// (the server writes them in the same order), else each vertex takes the
// values of the GLB vertex nearest to it (partgeometry.js). So a skinned mesh
// keeps animating while it streams, before and after packets carry skins.
// Nodes instancing a part share its geometry. A part drawn by several
// primitives (one per material) keeps the GLB's geometry: its level would
// have to be cut by material first.
//
// Signals in: 'scene' (stream.js: { info, level }), 'open', 'mesh' (another
// mesh: this scene closes). Out: 'status', 'scene-shown' ({ info, ratio: the GLB's }).

import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { createBus } from './bus.js';
import { levelGeometry } from './partgeometry.js';
import { createStream, routeUrl } from './stream.js';

// Frames drawn for the scrubber: at most this often is its text rewritten.
const LABEL_MS = 100;

// A GLTFLoader whose images load as <img> (img-src allows blob:) rather than
// fetched ImageBitmaps: the page's connect-src 'self' refuses fetches of blob: URLs.
function makeLoader() {
  const loader = new GLTFLoader();
  loader.register((parser) => {
    parser.textureLoader = new THREE.TextureLoader(parser.options.manager);
    return { name: 'lodserver_images' };
  });
  return loader;
}

export function createAnimated(viewer, view, root) {
  const { settings } = viewer;
  const $ = (selector) => root.querySelector(selector);
  const box = $('#animation'), clipSelect = $('#clip-select'), playButton = $('#play-pause');
  const scrubber = $('#time-scrubber'), label = $('#time-label');
  let current = null;         // the open scene: see open()
  let opened = 0;

  // ---- the animation -------------------------------------------------------------

  function showTime() {
    if (!current?.action) return;
    const { time } = current.action, { duration } = current.action.getClip();
    scrubber.value = String(duration > 0 ? time / duration : 0);
    label.textContent = `${time.toFixed(2)} / ${duration.toFixed(2)} s`;
  }

  // While playing: advance the mixer by the time since the last frame, draw, again.
  function loop(scene) {
    if (current !== scene || !scene.playing) return;
    const now = performance.now();
    scene.mixer.update((now - scene.last) / 1000);
    scene.last = now;
    if (now - scene.labelled > LABEL_MS) {
      scene.labelled = now;
      showTime();
    }
    view.rendered().then(() => loop(scene));
  }

  function play(playing) {
    if (!current?.action) return;
    current.playing = playing;
    playButton.textContent = playing ? 'pause' : 'play';
    if (playing) {
      current.last = performance.now();
      loop(current);
    } else {
      showTime();
      view.rendered();
    }
  }

  function chooseClip(index) {
    const scene = current;
    if (!scene?.clips[index]) return;
    scene.action?.stop();
    scene.action = scene.mixer.clipAction(scene.clips[index]);
    scene.action.play();
    scene.clip = index;
    clipSelect.value = String(index);
    scene.mixer.update(0);              // pose at the clip's first frame
    showTime();
    view.rendered();
  }

  // Sets the clip's time (seconds) and draws that pose.
  function setTime(seconds) {
    const action = current?.action;
    if (!action) return;
    const duration = action.getClip().duration;
    action.time = Math.min(Math.max(0, seconds), duration);
    current.mixer.update(0);
    showTime();
    view.rendered();
  }

  clipSelect.addEventListener('change', () => chooseClip(Number(clipSelect.value)));
  playButton.addEventListener('click', () => play(!current?.playing));
  scrubber.addEventListener('input', () => {
    if (!current?.action) return;
    if (current.playing) play(false);      // scrubbing pauses
    setTime(Number(scrubber.value) * current.action.getClip().duration);
  });

  // ---- parts ---------------------------------------------------------------------

  // Part p's meshes take the geometry of its stream's level (see the top).
  function refine(part, state) {
    // a level coarser than the GLB's (the base, before the first packet) would
    // be a step back: the GLB stays until the stream passes it
    if (!part.original || state.faceCount < part.glbFaces) return;
    const geometry = levelGeometry(state, part.original);
    const old = part.meshes[0].geometry;
    if (old !== part.original) old.dispose();
    for (const mesh of part.meshes) {        // the nodes instancing the part share it
      mesh.geometry = geometry;
      if (geometry.morphAttributes.position?.length && !mesh.morphTargetInfluences) {
        mesh.updateMorphTargets();
      }
      // a skinned mesh's bounds (posed) are its own: recomputed when next
      // needed (culling, raycasts); a plain mesh uses its new geometry's
      if (mesh.isSkinnedMesh) mesh.boundingBox = mesh.boundingSphere = null;
    }
    part.level = state.level;
    part.faces = state.faceCount;
    part.refined++;
    view.rendered();
  }

  function openPart(scene, record, ratio) {
    const meshes = [];
    scene.root.traverse((object) => {
      if (object.isMesh && object.userData?.lodserver_part === record.index) meshes.push(object);
    });
    // one geometry shared by every node instancing the part; several: one per
    // primitive (see the top: not refined)
    const geometries = new Set(meshes.map((mesh) => mesh.geometry));
    const part = { index: record.index, name: record.name, meshes, refined: 0,
                   level: null, faces: null, vertices: record.vertices, stream: null,
                   original: geometries.size === 1 ? meshes[0].geometry : null };
    scene.parts.push(part);
    if (!part.original) return;
    const { index, attributes } = part.original;
    part.glbFaces = (index ? index.count : attributes.position.count) / 3;
    const bus = createBus(settings);
    part.stream = createStream(bus);
    bus.on('level', ({ state }) => {
      if (current === scene) refine(part, state);
    });
    bus.on('stream', ({ state: now, error }) => {
      if (current !== scene) return;
      part.idle = now === 'idle';
      if (now === 'failed') {
        viewer.emit('status', `${scene.info.name}: part ${part.name || part.index}: ${error}`);
      } else if (scene.parts.every((each) => each.idle || !each.stream)) {
        const sum = (key) => scene.parts.reduce((n, each) => n + (each[key] ?? 0), 0);
        viewer.emit('status', `${scene.info.name}: ${scene.parts.length} part` +
                    `${scene.parts.length === 1 ? '' : 's'}, ${sum('faces').toLocaleString()} ` +
                    'faces drawn');
      }
    });
    const summary = { ...record, id: scene.info.id, name: `${scene.info.name} (${record.name})` };
    part.stream.open(scene.info.id, { summary, materials: false,
                                      level: Math.round(ratio * record.vertices) });
  }

  // ---- opening and closing ---------------------------------------------------------

  function close() {
    opened++;
    if (!current) return;
    const scene = current;
    current = null;
    for (const part of scene.parts) {
      part.stream?.close();
      if (part.original && part.meshes[0].geometry !== part.original) {
        part.meshes[0].geometry.dispose();
        part.original.dispose();
      }
    }
    scene.mixer.stopAllAction();
    view.removeObject(scene.root);
    scene.root.traverse((object) => {
      object.geometry?.dispose();
      for (const material of [object.material ?? []].flat()) {
        for (const value of Object.values(material)) if (value?.isTexture) value.dispose();
        material.dispose();
      }
    });
    box.hidden = true;
  }

  async function open({ info, level }) {
    close();
    const ticket = opened;
    const base = info.base_vertices ?? 0;
    const ratio = Math.min(1, Math.max(level ?? info.vertices, base) / info.vertices);
    viewer.emit('status', `${info.name}: loading the scene`);
    try {
      const shortRatio = Number(ratio.toPrecision(6));
      const url = routeUrl(info, 'lod', { ratio: shortRatio, format: 'glb' });
      const response = await fetch(url);
      if (!response.ok) {
        const body = await response.json().catch(() => ({}));
        throw new Error(body.message || `the server answered ${response.status}`);
      }
      const buffer = await response.arrayBuffer();
      if (ticket !== opened) return;
      const gltf = await makeLoader().parseAsync(buffer, new URL('./', url).href);
      if (ticket !== opened) return;
      const scene = { info, root: gltf.scene, clips: gltf.animations, parts: [],
                      mixer: new THREE.AnimationMixer(gltf.scene), action: null, clip: null,
                      playing: false, last: 0, labelled: 0, bytes: buffer.byteLength,
                      cameras: gltf.cameras };
      current = scene;
      scene.root.updateMatrixWorld(true);
      const bounds = new THREE.Box3().setFromObject(scene.root, true);
      view.showObject(scene.root, { min: bounds.min.toArray(), max: bounds.max.toArray() });
      clipSelect.replaceChildren(...scene.clips.map(
        (clip, i) => new Option(clip.name || `animation ${i}`, String(i))));
      box.hidden = scene.clips.length === 0;
      if (scene.clips.length) {
        chooseClip(0);
        play(true);
      }
      viewer.emit('scene-shown', { info, ratio: shortRatio });
      viewer.emit('status', `${info.name}: ${scene.clips.length} animation` +
                  `${scene.clips.length === 1 ? '' : 's'}; refining ${info.parts?.length ?? 0} part` +
                  `${info.parts?.length === 1 ? '' : 's'}`);
      for (const record of info.parts ?? []) openPart(scene, record, ratio);
    } catch (error) {
      if (ticket === opened) viewer.emit('status', `error: the scene could not be shown (${error.message})`);
    }
  }

  viewer.on('scene', (detail) => { open(detail); });
  viewer.on('open', close);
  viewer.on('mesh', close);

  return {
    get open() { return current !== null; },
    // Resolves once every part's stream has reached its target.
    async settled() {
      const scene = current;
      if (!scene) return;
      await Promise.all(scene.parts.map((part) => part.stream?.settled()));
    },
    // The scene's state, for tests and benchmarks.
    status() {
      const scene = current;
      if (!scene) return null;
      const parts = scene.parts.map(({ index, name, level, faces, vertices, refined, stream,
                                       meshes }) => (
        { index, name, level, faces, vertices, refined, target: stream?.target ?? null,
          attributes: meshes[0]?.geometry.userData.lodserver ?? null,
          bytes: stream?.bytes ?? 0, busy: stream?.busy ?? false,
          error: stream?.failed?.message ?? null }));
      const action = scene.action;
      return { parts, bytes: scene.bytes + parts.reduce((n, part) => n + part.bytes, 0),
               clips: scene.clips.map((clip) => ({ name: clip.name, duration: clip.duration })),
               clip: scene.clip, playing: scene.playing, time: action?.time ?? null,
               cameras: scene.cameras.length };
    },
    play: () => play(true),
    pause: () => play(false),
    chooseClip,
    setTime,
    // World boxes ({ min, max }) of part p's meshes as posed now (skinning and
    // morphs applied), or of the whole scene.
    box(part = null) {
      if (!current) return null;
      const meshes = part === null ? [current.root]
        : current.parts.find((each) => each.index === part)?.meshes ?? [];
      const out = new THREE.Box3();
      current.root.updateMatrixWorld(true);
      for (const mesh of meshes) out.union(new THREE.Box3().setFromObject(mesh, true));
      return { min: out.min.toArray(), max: out.max.toArray() };
    },
    get three() { return current ? { root: current.root, mixer: current.mixer } : null; },
  };
}
