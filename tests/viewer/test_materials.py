"""The viewer's materials in headless Chromium: at full detail the streamed
mesh looks like the server's own GLB of the same level drawn by three.js's
GLTFLoader, under the same camera, lights, environment and tone mapping, and
each texture channel is used (turning it off changes the picture).

Both pictures are drawn by the viewer's renderer into its canvas (the viewer's
mesh hidden, GLTFLoader's scene added in its place) and read back in the same
task as the draw, so nothing but the meshes and their materials differs.
"""

import struct
import zlib

import numpy as np
import pytest

from lodserver.io.glb import encode_glb
from lodserver.mesh import Materials, Mesh

from ..meshes import SHARED, textured_sphere
from ..server import upload_and_wait
from .pages import settled_and_evaluated

VIEWPORT = {"width": 640, "height": 480}

# In the viewer's page: the RMS difference (0-255, RGB, every pixel) between
# the viewer's picture and GLTFLoader's of GET /lod?ratio=1&format=glb, the
# share of pixels either draws, and per texture channel the RMS difference
# its removal makes to the viewer's picture.
COMPARE_JS = """async ({ id, channels }) => {
  const { GLTFLoader } = await import('three/addons/loaders/GLTFLoader.js');
  const viewer = window.lodViewer.scene, { scene, renderer } = viewer.three;
  const ours = viewer.three.mesh;
  const background = viewer.pixels().data.slice(0, 4);  // a corner: the clear colour
  const rms = (a, b) => {
    let sum = 0, n = 0;
    for (let i = 0; i < a.length; i += 4) {
      for (let k = 0; k < 3; k++) sum += (a[i + k] - b[i + k]) ** 2;
      n += 3;
    }
    return Math.sqrt(sum / n);
  };
  const drawn = (a) => {
    let count = 0;
    for (let i = 0; i < a.length; i += 4) {
      const d = Math.abs(a[i] - background[0]) + Math.abs(a[i + 1] - background[1])
              + Math.abs(a[i + 2] - background[2]);
      if (d > 24) count++;
    }
    return count / (a.length / 4);
  };
  const mine = viewer.pixels().data;
  const response = await fetch(`/meshes/${id}/lod?ratio=1&format=glb`);
  const gltf = await new GLTFLoader().parseAsync(await response.arrayBuffer(), '');
  ours.visible = false;
  scene.add(gltf.scene);
  const theirs = viewer.pixels().data;
  // the material properties that differ from GLTFLoader's (first mesh of each)
  let reference = null;
  gltf.scene.traverse((o) => { if (o.isMesh && !reference) reference = [].concat(o.material)[0]; });
  const describe = (m) => {
    const out = { type: m.type, side: m.side, alphaTest: m.alphaTest, transparent: m.transparent,
                  opacity: m.opacity, metalness: m.metalness, roughness: m.roughness,
                  emissiveIntensity: m.emissiveIntensity, aoMapIntensity: m.aoMapIntensity,
                  color: m.color.toArray(), emissive: m.emissive?.toArray(),
                  // (GLTFLoader negates y on every material; it matters only with a map)
                  normalScale: m.normalMap ? m.normalScale.toArray() : null };
    for (const key of channels) {
      const t = m[key];
      out[key] = t && [t.channel, t.colorSpace, t.offset.toArray(), t.repeat.toArray(),
                       t.rotation, t.flipY, t.wrapS, t.wrapT, t.magFilter, t.minFilter];
    }
    return out;
  };
  const a = describe([].concat(ours.material)[0]), b = describe(reference);
  const mismatches = Object.keys(a).filter((key) => JSON.stringify(a[key]) !== JSON.stringify(b[key]))
    .map((key) => `${key}: ${JSON.stringify(a[key])} vs ${JSON.stringify(b[key])}`);
  scene.remove(gltf.scene);
  ours.visible = true;
  const materials = [].concat(ours.material);
  const used = {};
  for (const channel of channels) {
    const saved = materials.map((m) => m[channel]);
    if (!saved.some(Boolean)) { used[channel] = null; continue; }
    materials.forEach((m) => { m[channel] = null; m.needsUpdate = true; });
    used[channel] = rms(mine, viewer.pixels().data);
    materials.forEach((m, i) => { m[channel] = saved[i]; m.needsUpdate = true; });
  }
  const first = materials[0];
  return {
    rms: rms(mine, theirs), mismatches, drawnViewer: drawn(mine), drawnReference: drawn(theirs), used,
    toneMapping: renderer.toneMapping, aces: viewer.three.THREE.ACESFilmicToneMapping,
    environment: scene.environment !== null,
    colorSpaces: Object.fromEntries(['map', 'emissiveMap', 'normalMap', 'metalnessMap', 'aoMap']
      .filter((key) => first[key]).map((key) => [key, first[key].colorSpace])),
    transform: first.map ? [first.map.offset.x, first.map.offset.y, first.map.repeat.x,
                            first.map.rotation] : null,
    side: first.side, alphaTest: first.alphaTest, emissiveIntensity: first.emissiveIntensity,
  };
}"""
CHANNELS = ["map", "normalMap", "metalnessMap", "roughnessMap", "aoMap", "emissiveMap"]


def png(pixels: np.ndarray) -> bytes:
    """A PNG file of an (h, w, 3) uint8 RGB image."""
    height, width, _ = pixels.shape
    rows = b"".join(b"\0" + pixels[y].tobytes() for y in range(height))

    def chunk(kind, data):
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows))
            + chunk(b"IEND", b""))


def channel_images(size=128) -> list[bytes]:
    """Five distinct images (three.js shares a texture between the uses of one
    image, so each channel gets its own): base colour stripes, metal (blue) and
    rough (green) ramps, a bumpy tangent-space normal map, occlusion rings, an
    emissive checker."""
    u, v = np.meshgrid(np.linspace(0, 1, size), np.linspace(0, 1, size))
    as_rgb = lambda *c: (np.clip(np.stack(c, -1), 0, 1) * 255).astype(np.uint8)  # noqa: E731
    stripes = 0.5 + 0.5 * np.sin(12 * np.pi * u)
    base = as_rgb(0.9 * stripes + 0.1, 0.5 + 0.3 * v, 0.3 + 0.5 * (1 - stripes))
    metal_rough = as_rgb(np.zeros_like(u), 0.2 + 0.7 * v, u)
    dx, dy = 0.5 * np.cos(16 * np.pi * u), 0.5 * np.cos(16 * np.pi * v)
    length = np.sqrt(1 + dx ** 2 + dy ** 2)
    normal = as_rgb(0.5 + 0.5 * dx / length, 0.5 + 0.5 * dy / length, 0.5 + 0.5 / length)
    rings = 0.5 + 0.5 * np.cos(20 * np.pi * np.hypot(u - 0.5, v - 0.5))
    occlusion = as_rgb(rings, rings, rings)
    checker = ((np.floor(8 * u) + np.floor(8 * v)) % 2).astype(float)
    emissive = as_rgb(checker, 0.3 * checker, 0.1 * checker)
    return [png(image) for image in (base, metal_rough, normal, occlusion, emissive)]


def every_channel_sphere() -> Mesh:
    """A UV sphere with normals and one material using every channel the viewer
    draws: base colour (with KHR_texture_transform), metallic-roughness, normal
    (scale), occlusion (strength), emissive (factor, texture,
    KHR_materials_emissive_strength), alpha MASK, double-sided."""
    m = textured_sphere(48, 24)
    transform = {"KHR_texture_transform": {"offset": [0.1, 0.05], "scale": [1.5, 1.5],
                                           "rotation": 0.2}}
    record = {
        "name": "every channel", "doubleSided": True, "alphaMode": "MASK", "alphaCutoff": 0.3,
        "pbrMetallicRoughness": {"baseColorTexture": {"index": 0, "extensions": transform},
                                 "baseColorFactor": [1, 0.9, 0.8, 1], "metallicFactor": 0.8,
                                 "roughnessFactor": 0.7,
                                 "metallicRoughnessTexture": {"index": 1}},
        "normalTexture": {"index": 2, "scale": 0.7},
        "occlusionTexture": {"index": 3, "strength": 0.8},
        "emissiveTexture": {"index": 4}, "emissiveFactor": [0.6, 0.3, 0.1],
        "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 1.5}}}
    images = channel_images()
    materials = Materials({
        "materials": [record], "textures": [{"source": i, "sampler": 0} for i in range(5)],
        "samplers": [{"magFilter": 9729, "minFilter": 9987}],
        "images": [{"mimeType": "image/png", "name": f"channel{i}"} for i in range(5)]},
        tuple(images))
    return Mesh(m.positions, m.faces, m.attributes, np.zeros(m.face_count, np.int32), materials)


def _source(name, tmp_path):
    """An uploadable file for `name`: a shared mesh read and written again as one
    GLB of one mesh (Avocado's .gltf and its files; Duck, whose camera, and
    2CylinderEngine, whose many meshes, would make the server keep the file as a
    scene, drawn from its GLB by GLTFLoader: tests/viewer/test_scenes.py), or the
    generated every-channel sphere."""
    if name == "every-channel":
        path = tmp_path / "every_channel.glb"
        path.write_bytes(encode_glb(every_channel_sphere()))
        return path
    from lodserver.io import load_mesh
    source = SHARED / "Avocado" / "Avocado.gltf" if name == "Avocado" else SHARED / f"{name}.glb"
    if not source.is_file():
        pytest.skip(f"shared mesh not found at {source}")
    path = tmp_path / f"{name}.glb"
    path.write_bytes(encode_glb(load_mesh(source)[0]))
    return path


def _compare(chromium, server, mesh, tmp_path):
    status, result = settled_and_evaluated(
        chromium, f"{server.base_url}/viewer?mesh={mesh['id']}&level={mesh['vertices']}",
        COMPARE_JS, {"id": mesh["id"], "channels": CHANNELS}, viewport=VIEWPORT,
        screenshot=tmp_path / "viewer.png")
    assert status["level"] == mesh["vertices"] and status["error"] is None, status
    return result


@pytest.mark.parametrize("name", ["Avocado", "Duck", "2CylinderEngine", "every-channel"])
def test_full_detail_looks_like_gltfloader_of_the_servers_glb(name, chromium, server, tmp_path):
    mesh = upload_and_wait(server, _source(name, tmp_path))
    result = _compare(chromium, server, mesh, tmp_path)
    # the same look: IBL, ACES filmic; colour textures sRGB, data textures linear
    assert result["environment"] and result["toneMapping"] == result["aces"], result
    for key, space in result["colorSpaces"].items():
        assert space == ("srgb" if key in ("map", "emissiveMap") else ""), (key, space)
    # the first material as GLTFLoader makes it, property by property
    assert result["mismatches"] == [], result["mismatches"]
    # both draw the mesh, and alike: the streamed level's quantized positions,
    # normals and UVs against the GLB's floats leave a few levels of RMS at edges
    assert result["drawnViewer"] > 0.05, result
    assert abs(result["drawnViewer"] - result["drawnReference"]) < 0.01, result
    assert result["rms"] < 4.0, f"{result}; the viewer's picture: {tmp_path / 'viewer.png'}"
    # every texture channel the mesh has is used: turning it off changes pixels
    used = {channel: rms for channel, rms in result["used"].items() if rms is not None}
    expected = {"Avocado": {"map", "normalMap", "metalnessMap", "roughnessMap"},
                "Duck": {"map"}, "2CylinderEngine": set(), "every-channel": set(CHANNELS)}[name]
    assert set(used) == expected, result
    for channel, rms in used.items():
        assert rms > 0.5, (channel, result)


def test_every_channel_is_read_from_the_record(chromium, server, tmp_path):
    """The extension values and factors of the every-channel material reach the
    three.js material (besides changing pixels, checked above)."""
    mesh = upload_and_wait(server, _source("every-channel", tmp_path))
    materials = server.get(f"/meshes/{mesh['id']}/materials").json()
    assert {"KHR_texture_transform", "KHR_materials_emissive_strength"} <= set(
        materials["extensionsUsed"])
    result = _compare(chromium, server, mesh, tmp_path)
    offset_x, offset_y, repeat, rotation = result["transform"]
    assert (offset_x, offset_y, repeat, rotation) == pytest.approx((0.1, 0.05, 1.5, 0.2))
    assert result["side"] == 2 and result["alphaTest"] == pytest.approx(0.3)   # DoubleSide
    assert result["emissiveIntensity"] == pytest.approx(1.5)


def test_materials_document_names_the_extensions_used():
    from lodserver.build import build
    from lodserver.service.materials import materials_document

    document = materials_document(build(every_channel_sphere()))
    assert document["extensionsUsed"] == ["KHR_materials_emissive_strength",
                                          "KHR_texture_transform"]
    record = document["materials"][0]
    assert record["occlusionTexture"] == {"index": 3, "strength": 0.8}
    assert record["alphaMode"] == "MASK" and record["doubleSided"] is True
