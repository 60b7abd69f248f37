"""The octahedral impostor drawn by static/impostor.js in headless Chromium (issue 28).

``lodserver export Duck.glb --lods 1,0.01 --separate --impostor`` writes the
farthest level as an impostor; a page of its own (three.js, GLTFLoader, the
module) draws the full-detail Duck and then the impostor from 8 directions
(the cube's corners, none of them a baked view) and compares where each
covers the screen: the intersection over union of the two alpha masks is at
least :data:`MIN_IOU` from every direction. A hemi impostor (the upper half
of the directions) is held to the same from four directions above, and the
full one through an orthographic camera (parallel rays) from four. The page
also gives the module's nearest view of each direction, which must be the
bake's (``nearest_view``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lodserver.bake.impostor import bake_impostor, impostor_glb, nearest_view
from lodserver.io.scene import load_scene
from lodserver.pipeline import export_lods
from lodserver.scene.merge import world_mesh

from ..meshes import SHARED

STATIC = Path(__file__).resolve().parents[2] / "static"
DUCK = SHARED / "Duck.glb"
# Each direction's silhouette overlap, at least: the views are 12 x 12 of 64
# pixels (the export's default) drawn 256 pixels high, so their edges are
# blurred by the magnification and the blend of three neighbouring views.
MIN_IOU = 0.9
DIRECTIONS = [[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]

PAGE = """<!doctype html>
<html><head><link rel="icon" href="data:,"></head><body style="margin: 0">
<script type="importmap">
  { "imports": { "three": "/three/build/three.module.js",
                 "three/addons/": "/three/examples/jsm/" } }
</script>
<script type="module">
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { Impostor, nearestView } from '/static/impostor.js';

const SIZE = 256;
const renderer = new THREE.WebGLRenderer({ alpha: true });
renderer.setSize(SIZE, SIZE);
renderer.setClearColor(0x000000, 0);
document.body.append(renderer.domElement);
const target = new THREE.WebGLRenderTarget(SIZE, SIZE);
const loader = new GLTFLoader();
const mesh = (await loader.loadAsync('/files/Duck.glb')).scene;
const file = new URLSearchParams(location.search).get('impostor');
const impostor = await Impostor.fromGLTF(await loader.loadAsync(`/files/${file}`));
const scene = new THREE.Scene();
scene.add(new THREE.HemisphereLight(0xffffff, 0x444444, 3), mesh, impostor);
const center = new THREE.Vector3().fromArray(impostor.layout.center);
const radius = impostor.layout.radius;
const perspective = new THREE.PerspectiveCamera(40, 1, 0.01 * radius, 100 * radius);
const orthographic = new THREE.OrthographicCamera(-1.1 * radius, 1.1 * radius, 1.1 * radius,
                                                  -1.1 * radius, 0.01 * radius, 100 * radius);
let camera = perspective;

function mask() {
  renderer.setRenderTarget(target);
  renderer.clear();
  renderer.render(scene, camera);
  const pixels = new Uint8Array(4 * SIZE * SIZE);
  renderer.readRenderTargetPixels(target, 0, 0, SIZE, SIZE, pixels);
  renderer.setRenderTarget(null);
  const covered = new Uint8Array(SIZE * SIZE);
  for (let i = 0; i < covered.length; i++) covered[i] = pixels[4 * i + 3] > 0 ? 1 : 0;
  return covered;
}

window.silhouettes = (directions, ortho) => directions.map((d) => {
  camera = ortho ? orthographic : perspective;
  const direction = new THREE.Vector3(...d).normalize();
  camera.position.copy(center).addScaledVector(direction, 3 * radius);
  camera.lookAt(center);
  camera.updateMatrixWorld();
  mesh.visible = true; impostor.visible = false;
  const full = mask();
  mesh.visible = false; impostor.visible = true;
  const baked = mask();
  let both = 0, either = 0, fullCount = 0;
  for (let i = 0; i < full.length; i++) {
    both += full[i] & baked[i];
    either += full[i] | baked[i];
    fullCount += full[i];
  }
  return { iou: both / either, covered: fullCount / full.length,
           view: nearestView(direction, impostor.layout) };
});
window.ready = true;
</script>
</body></html>
"""


# The page's origin: every request answered from the folder by the page's route
# (no server of its own).
ORIGIN = "http://impostor.test"
TYPES = {".html": "text/html", ".js": "text/javascript", ".glb": "model/gltf-binary"}


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """The page, three.js, static/ and the Duck's files: its full detail and the
    export's levels, the farthest an impostor."""
    if not DUCK.is_file():
        pytest.skip(f"the shared meshes are not at {DUCK.parent}")
    folder = tmp_path_factory.mktemp("impostor")
    (folder / "three").symlink_to(STATIC / "vendor" / "three", target_is_directory=True)
    (folder / "static").symlink_to(STATIC, target_is_directory=True)
    files = folder / "files"
    files.mkdir()
    (files / "Duck.glb").write_bytes(DUCK.read_bytes())
    export_lods(DUCK, files / "duck.glb", lods=(1.0, 0.01), separate=True, impostor=True)
    # the upper half only, baked by the library (the export's kind is full)
    full = world_mesh(load_scene(DUCK))
    (files / "duck_hemi.glb").write_bytes(impostor_glb(bake_impostor(full, kind="hemi")))
    (folder / "index.html").write_text(PAGE)
    return folder


def _answer(folder: Path):
    def answer(route):
        path = folder / route.request.url[len(ORIGIN) + 1:].split("?")[0]
        if not path.is_file():
            return route.fulfill(status=404)
        route.fulfill(status=200, body=path.read_bytes(),
                      content_type=TYPES.get(path.suffix, "application/octet-stream"))
    return answer


def _silhouettes(chromium, folder: Path, impostor: str, directions, ortho=False) -> list:
    """What the page measures from each direction, drawing ``files/<impostor>``."""
    page = chromium.new_page(viewport={"width": 256, "height": 256})
    page.route(f"{ORIGIN}/**", _answer(folder))
    failures = []
    page.on("pageerror", lambda error: failures.append(error))
    page.on("console", lambda message: message.type == "error" and failures.append(message.text))
    try:
        page.goto(f"{ORIGIN}/index.html?impostor={impostor}")
        page.wait_for_function("() => window.ready === true", timeout=120_000)
        results = page.evaluate("([directions, ortho]) => window.silhouettes(directions, ortho)",
                                [directions, ortho])
    finally:
        page.close()
    assert not failures, failures
    return results


def test_the_impostor_matches_the_mesh_silhouette_from_8_directions(chromium, folder):
    results = _silhouettes(chromium, folder, "duck_lod1.glb", DIRECTIONS)
    for direction, result in zip(DIRECTIONS, results):
        # the Duck fills a good part of the view: a blank render cannot pass
        assert result["covered"] > 0.1, (direction, result)
        assert result["iou"] >= MIN_IOU, (direction, result)
    unit = np.array(DIRECTIONS, dtype=np.float64) / np.sqrt(3.0)
    assert [result["view"] for result in results] == nearest_view(unit, 12).tolist()


def test_a_hemi_impostor_matches_the_mesh_silhouette_from_above(chromium, folder):
    above = [[x, 1, z] for x in (-1, 1) for z in (-1, 1)]
    results = _silhouettes(chromium, folder, "duck_hemi.glb", above)
    for direction, result in zip(above, results):
        assert result["covered"] > 0.1, (direction, result)
        assert result["iou"] >= MIN_IOU, (direction, result)
    unit = np.array(above, dtype=np.float64) / np.sqrt(3.0)
    assert [result["view"] for result in results] == nearest_view(unit, 12, "hemi").tolist()


def test_the_impostor_matches_the_mesh_silhouette_through_an_orthographic_camera(chromium,
                                                                                folder):
    results = _silhouettes(chromium, folder, "duck_lod1.glb", DIRECTIONS[:4], ortho=True)
    for direction, result in zip(DIRECTIONS, results):
        assert result["covered"] > 0.1, (direction, result)
        assert result["iou"] >= MIN_IOU, (direction, result)
