// The fair GLB baseline of bench/viewer/streaming.py: fetch the full-detail
// GLB, parse it with three.js's GLTFLoader and draw it once, as any GLB viewer
// must, with the viewer's look (static/materials.js: tone mapping, the 64 px
// RoomEnvironment PMREM, its intensity; the headlight and the background of
// static/scene.js and static/main.js, copied below).
//
// materials.js is imported rather than copied: it imports only three.js (not
// the viewer), and importing keeps the baseline's look the viewer's when LOOK
// changes.
//
// The GLB's best case: its fetch starts as soon as the script runs and the
// environment is made while its bytes arrive (the viewer makes it after its
// first frame). Times are performance.now() (ms from the navigation's start),
// in window.bench.marks:
//   script: the module runs (three.js loaded); environment: the PMREM made;
//   last_byte: the GLB's last byte (resource timing's responseEnd);
//   received: the script holds its bytes (after the environment: the main
//   thread was busy making it);
//   parsed: GLTFLoader done; drawn: renderer.render() returned inside an
//   animation frame (what the viewer's settled() resolves after);
//   next_frame: the following animation frame (the drawn frame's GPU work done
//   enough for the compositor to move on).
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { configureRenderer, createEnvironment, LOOK } from './materials.js';

const FOV = 40, BACKGROUND = 0x1d2026;          // static/main.js's defaults
const bench = { marks: {}, done: false, error: null, bytes: null, triangles: null };
window.bench = bench;
const mark = (name) => { bench.marks[name] = performance.now(); };
const frame = () => new Promise((resolve) => requestAnimationFrame(resolve));

async function run(url) {
  mark('script');
  const download = fetch(url).then((response) => {
    if (!response.ok) throw new Error(`the GLB answered ${response.status}`);
    return response.arrayBuffer();
  });

  // static/scene.js's renderer, camera and lights
  const renderer = new THREE.WebGLRenderer({ antialias: true });
  renderer.setPixelRatio(window.devicePixelRatio);
  renderer.setClearColor(BACKGROUND);
  renderer.setSize(innerWidth, innerHeight);
  configureRenderer(renderer);
  document.body.append(renderer.domElement);
  const scene = new THREE.Scene();
  scene.environmentIntensity = LOOK.environmentIntensity;
  const camera = new THREE.PerspectiveCamera(FOV, innerWidth / innerHeight, 0.01, 100);
  const headlight = new THREE.DirectionalLight(0xffffff, LOOK.headlight);
  headlight.position.set(0.4, 0.6, 0);
  headlight.target.position.set(0, 0, -1);
  camera.add(headlight, headlight.target);
  scene.add(camera);
  scene.environment = createEnvironment(renderer);
  mark('environment');

  const buffer = await download;
  mark('received');
  const entry = performance.getEntriesByName(new URL(url, location.href).href).at(-1);
  bench.marks.last_byte = entry ? entry.responseEnd : performance.now();
  bench.bytes = { body: buffer.byteLength, transfer: entry?.transferSize ?? null };
  const gltf = await new GLTFLoader().parseAsync(buffer, '');
  mark('parsed');

  // framed about as the viewer frames it (its box's front face within 2/3 of
  // the view, no panel): the 1200x800 bunny is 460 px high here, 550 px in the
  // viewer, so this frame shades ~0.7 of the viewer's pixels (the GLB's favour)
  scene.add(gltf.scene);
  const box = new THREE.Box3().setFromObject(gltf.scene);
  const size = box.getSize(new THREE.Vector3()), center = box.getCenter(new THREE.Vector3());
  const tan = Math.tan(THREE.MathUtils.degToRad(FOV / 2)), fill = 0.66;
  const distance = Math.max(size.y / (2 * tan), size.x / (2 * tan * camera.aspect)) / fill
    + size.z / 2;
  const radius = size.length() / 2;
  camera.near = Math.max(1e-4, (distance - radius) * 0.5);
  camera.far = (distance + radius) * 2;
  camera.position.copy(center).add(new THREE.Vector3(0, 0, distance));
  camera.lookAt(center);
  camera.updateProjectionMatrix();

  await new Promise((resolve) => requestAnimationFrame(() => {
    renderer.render(scene, camera);
    mark('drawn');
    resolve();
  }));
  bench.triangles = renderer.info.render.triangles;
  await frame();
  mark('next_frame');
}

run(new URLSearchParams(location.search).get('glb'))
  .catch((error) => { bench.error = String(error); })
  .finally(() => { bench.done = true; });
