"""The server's compressed GLB levels drawn by three.js: GLTFLoader with meshoptimizer's
MeshoptDecoder (npm ``meshoptimizer``, tests/tools) draws the quantized and the meshopt
level as it draws the float32 one, in the viewer's page, same camera and lights."""

import pytest

from ..io.gltf_tools import TOOLS
from ..meshes import SHARED
from ..server import upload_and_wait
from .pages import settled_and_evaluated
from ..conftest import need
from lodserver.io import load_mesh
from lodserver.io.glb import encode_glb

DECODER = TOOLS / "node_modules" / "meshoptimizer" / "meshopt_decoder.mjs"
VIEWPORT = {"width": 480, "height": 360}

# The start of a page script that draws GLBs beside the viewer: three.js, GLTFLoader and
# MeshoptDecoder (its source passed as ``decoder``) loaded, the viewer's mesh hidden and
# the background's colour taken (``THREE``, ``GLTFLoader``, ``MeshoptDecoder``,
# ``viewer``, ``scene``, ``background``).
LOADER_JS = """
  const THREE = await import('three');
  const { GLTFLoader } = await import('three/addons/loaders/GLTFLoader.js');
  const url = URL.createObjectURL(new Blob([decoder], { type: 'text/javascript' }));
  const { MeshoptDecoder } = await import(url);
  await MeshoptDecoder.ready;
  const viewer = window.lodViewer.scene, { scene } = viewer.three;
  viewer.three.mesh.visible = false;
  const background = viewer.pixels().data.slice(0, 4);
"""

# In the viewer's page: each compression's level of GET /lod?ratio=1&format=glb drawn
# by GLTFLoader in place of the viewer's mesh; per compression its triangles, its
# world bounding box and the RMS difference (0-255, RGB) of its picture from the
# float32 level's, and the share of pixels that picture draws.
DRAW_JS = "async ({ id, decoder }) => {" + LOADER_JS + """
  const found = {};
  let reference = null;
  for (const compress of ['none', 'quantize', 'meshopt']) {
    const response = await fetch(`/meshes/${id}/lod?ratio=1&format=glb&compress=${compress}`);
    const loader = new GLTFLoader().setMeshoptDecoder(MeshoptDecoder);
    const gltf = await loader.parseAsync(await response.arrayBuffer(), '');
    scene.add(gltf.scene);
    gltf.scene.updateMatrixWorld(true);
    let triangles = 0;
    gltf.scene.traverse((o) => { if (o.isMesh) triangles += o.geometry.index.count / 3; });
    const box = new THREE.Box3().setFromObject(gltf.scene);
    const pixels = viewer.pixels().data;
    scene.remove(gltf.scene);
    if (reference === null) reference = pixels;
    let sum = 0, drawn = 0;
    for (let i = 0; i < pixels.length; i += 4) {
      for (let k = 0; k < 3; k++) sum += (pixels[i + k] - reference[i + k]) ** 2;
      const d = Math.abs(pixels[i] - background[0]) + Math.abs(pixels[i + 1] - background[1])
              + Math.abs(pixels[i + 2] - background[2]);
      if (d > 24) drawn++;
    }
    found[compress] = { triangles, min: box.min.toArray(), max: box.max.toArray(),
                        rms: Math.sqrt(sum / (pixels.length * 3 / 4)),
                        drawn: drawn / (pixels.length / 4) };
  }
  return found;
}"""


@pytest.fixture(scope="module")
def duck(server, tmp_path_factory):
    source = SHARED / "Duck.glb"
    if not source.is_file():
        pytest.skip(f"shared mesh not found at {source}")
    # one mesh of Duck (its file, with a camera, would be kept as a scene)
    path = tmp_path_factory.mktemp("duck") / "duck.glb"
    path.write_bytes(encode_glb(load_mesh(source)[0]))
    return upload_and_wait(server, path)


def test_compressed_levels_draw_as_the_float_level(chromium, server, duck):
    if not DECODER.is_file():
        need("meshoptimizer's decoder is not installed: npm ci --prefix tests/tools")
    _, found = settled_and_evaluated(
        chromium, f"{server.base_url}/viewer?mesh={duck['id']}", DRAW_JS,
        {"id": duck["id"], "decoder": DECODER.read_text()}, viewport=VIEWPORT)
    plain = found["none"]
    assert plain["triangles"] == duck["faces"] and plain["drawn"] > 0.02
    size = max(b - a for a, b in zip(plain["min"], plain["max"]))
    for compress in ("quantize", "meshopt"):
        drawn = found[compress]
        assert drawn["triangles"] == plain["triangles"], compress
        # the box within two steps of the 14-bit grid, the picture within 2 levels RMS
        for ours, theirs in zip(drawn["min"] + drawn["max"], plain["min"] + plain["max"]):
            assert abs(ours - theirs) <= 2 * size / (2 ** 14 - 1), (compress, found)
        assert drawn["rms"] < 2.0, (compress, found)
