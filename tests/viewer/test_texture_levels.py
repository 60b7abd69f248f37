"""A chain with texture levels drawn by three.js: GLTFLoader with MeshoptDecoder reads
``/chain?texture_scale=auto&compress=meshopt``, each level's mesh with a material whose
base colour map is that level's image size, and draws the finest level textured."""

from ..conftest import need
from ..meshes import DATA
from ..server import upload_and_wait
from .pages import settled_and_evaluated
from .test_compressed_glb import DECODER, LOADER_JS, VIEWPORT
from lodserver.io import load_mesh
from lodserver.io.glb import encode_glb

# In the viewer's page: the chain parsed by GLTFLoader, the width and height of each
# glTF mesh's base colour map (every mesh, MSFT_lod levels included, through the
# parser), and the share of pixels level 0 draws in place of the viewer's mesh.
DRAW_JS = "async ({ id, decoder }) => {" + LOADER_JS + """
  const response = await fetch(
    `/meshes/${id}/chain?lods=1,0.2,0.05&compress=meshopt&texture_scale=auto`);
  const loader = new GLTFLoader().setMeshoptDecoder(MeshoptDecoder);
  const gltf = await loader.parseAsync(await response.arrayBuffer(), '');
  const meshes = await gltf.parser.getDependencies('mesh');
  const maps = meshes.map((mesh) => {
    const map = (mesh.isGroup ? mesh.children[0] : mesh).material.map;
    return [map.image.width, map.image.height];
  });
  scene.add(gltf.scene);
  gltf.scene.updateMatrixWorld(true);
  const pixels = viewer.pixels().data;
  scene.remove(gltf.scene);
  let drawn = 0;
  for (let i = 0; i < pixels.length; i += 4) {
    const d = Math.abs(pixels[i] - background[0]) + Math.abs(pixels[i + 1] - background[1])
            + Math.abs(pixels[i + 2] - background[2]);
    if (d > 24) drawn++;
  }
  return { maps, drawn: drawn / (pixels.length / 4) };
}"""


def test_texture_levels_draw_in_three(chromium, server, tmp_path):
    if not DECODER.is_file():
        need("meshoptimizer's decoder is not installed: npm ci --prefix tests/tools")
    path = tmp_path / "spot.glb"       # spot with its 1024 px texture embedded
    path.write_bytes(encode_glb(load_mesh(DATA / "spot.obj")[0]))
    spot = upload_and_wait(server, path)
    _, found = settled_and_evaluated(
        chromium, f"{server.base_url}/viewer?mesh={spot['id']}", DRAW_JS,
        {"id": spot["id"], "decoder": DECODER.read_text()}, viewport=VIEWPORT)
    # levels of 1, 0.2 and 0.05 of the faces: sqrt 1, 0.45, 0.22 -> 1, 1/2, 1/4
    assert found["maps"] == [[1024, 1024], [512, 512], [256, 256]], found
    assert found["drawn"] > 0.02, found
