// glTF materials as three.js draws them, the same way three.js's GLTFLoader
// does (so a streamed level looks like the server's GLB of it): every channel
// of the metallic-roughness model, image-based light and a filmic tone map.
//
// Channels: base colour (factor, texture, vertex colours), metallic-roughness
// (factors; texture: blue = metal, green = rough), normal (scale), occlusion
// (strength), emissive (factor, texture, KHR_materials_emissive_strength),
// alpha mode and cutoff, double-sided, KHR_texture_transform on any texture,
// KHR_materials_unlit. Colour textures (base colour, emissive) are sRGB; data
// textures (normal, metal-rough, occlusion) are linear (NoColorSpace).
//
// Normal maps without a TANGENT attribute: three.js then builds the tangent
// frame per pixel from screen-space derivatives of the position and the UV,
// whose handedness is the opposite of glTF's (three.js issue 11438), so, like
// GLTFLoader, the green channel's scale is negated.
//
// The images are fetched here (not by an <img>), so the viewer can count
// their bytes: `textureBytes` of the loader.

import * as THREE from 'three';
import { RoomEnvironment } from 'three/addons/environments/RoomEnvironment.js';

// glTF sampler codes -> three.js constants.
const WRAP = { 33071: THREE.ClampToEdgeWrapping, 33648: THREE.MirroredRepeatWrapping,
               10497: THREE.RepeatWrapping };
const FILTER = { 9728: THREE.NearestFilter, 9729: THREE.LinearFilter,
                 9984: THREE.NearestMipmapNearestFilter, 9985: THREE.LinearMipmapNearestFilter,
                 9986: THREE.NearestMipmapLinearFilter, 9987: THREE.LinearMipmapLinearFilter };

// The look every view of a mesh shares (the viewer and the tests' GLTFLoader
// reference render): tone mapping, exposure, the environment's blur and size.
// The room at full strength with a headlight washes a light material out to
// white under ACES; half of it keeps shading and texture contrast.
// environmentSize: the PMREM's cube face, pixels. three.js makes them at least
// 256 px, which under software GL (SwiftShader, headless Chromium) costs seconds
// of GPU time before anything can be drawn: its GGX passes sample 256 times a
// pixel. The room is blurred by environmentSigma (0.04 rad, 2.3 degrees)
// anyway, and a 64 px face resolves 1.4 degrees a texel, so 64 loses little
// (a chart of spheres, roughness 0-1, metal and not: RMS 2.2 of 255 against
// 256 px, the difference on the mirror spheres) for a tenth of the work.
// fill: the light that stands in for the environment until it is made.
export const LOOK = { toneMapping: THREE.ACESFilmicToneMapping, exposure: 1,
                      environmentSigma: 0.04, environmentIntensity: 0.5, environmentSize: 64,
                      headlight: 0.8, fill: { sky: 0xffffff, ground: 0x6b6560, intensity: 1.1 } };

// Tone mapping and the output colour space of a renderer.
export function configureRenderer(renderer) {
  renderer.toneMapping = LOOK.toneMapping;
  renderer.toneMappingExposure = LOOK.exposure;
  renderer.outputColorSpace = THREE.SRGBColorSpace;
}

// three.js's PMREM generator at a cube size below its 256 px minimum. It
// overrides _setSize, a private method of the pinned three.js (0.187, in
// static/vendor): the rest of the generator (capture, blur, GGX and
// integration passes, the mip chain three.js's shaders read) is three.js's own.
class SizedPMREMGenerator extends THREE.PMREMGenerator {
  constructor(renderer, size) {
    super(renderer);
    this.size = size;
  }

  _setSize() {
    this._cubeSize = this.size;
  }
}

// The image-based light: three.js's RoomEnvironment prefiltered by PMREM
// (a cube texture of mip levels by roughness), faces of `size` pixels (a
// power of two, at least 16: three.js integrates its roughest three levels
// from a 16 px mip). Costs GPU time (see LOOK): scene.js makes it after the
// first frame.
export function createEnvironment(renderer, size = LOOK.environmentSize) {
  const generator = new SizedPMREMGenerator(renderer, size);
  const room = new RoomEnvironment();
  const texture = generator.fromScene(room, LOOK.environmentSigma).texture;
  room.dispose();
  generator.dispose();
  return texture;
}

// Loads each glTF texture of a materials document once (a texture used by two
// materials or two channels is one three.js texture per colour space and
// transform), fetching images itself to count their bytes.
export class TextureSet {
  // document: the /materials JSON; baseUrl: what its image uris are relative to;
  // onLoad: called after each texture's image arrives (to draw again).
  constructor(document, baseUrl, onLoad) {
    Object.assign(this, { document, baseUrl, onLoad });
    this.images = new Map();        // image index -> Promise<ImageBitmap>
    this.textures = new Map();      // key -> THREE.Texture
    this.textureBytes = 0;          // image bytes received so far
    this.pending = [];              // the image promises, for `ready`
    this.closed = false;
  }

  image(index) {
    if (!this.images.has(index)) {
      const record = this.document.images?.[index];
      const load = (async () => {
        const response = await fetch(new URL(record.uri, this.baseUrl).href);
        if (!response.ok) throw new Error(`image ${index} answered ${response.status}`);
        const blob = await response.blob();
        this.textureBytes += blob.size;
        // as GLTFLoader's ImageBitmapLoader: no premultiplication, no flip (glTF's
        // UV origin is the image's top left), no colour conversion by the browser
        return createImageBitmap(blob, { premultiplyAlpha: 'none', imageOrientation: 'from-image',
                                         colorSpaceConversion: 'none' });
      })();
      this.images.set(index, load);
      this.pending.push(load.catch(() => null));
    }
    return this.images.get(index);
  }

  // The three.js texture of a glTF textureInfo ({ index, texCoord, extensions }),
  // or null when it names no loadable image.
  texture(info, colorSpace) {
    const record = this.document.textures?.[info?.index];
    const source = record?.source ?? record?.extensions?.EXT_texture_webp?.source;
    if (source === undefined || !this.document.images?.[source]) return null;
    const transform = info.extensions?.KHR_texture_transform;
    const key = JSON.stringify([info.index, colorSpace, transform ?? null, info.texCoord ?? 0]);
    if (this.textures.has(key)) return this.textures.get(key);
    const texture = new THREE.Texture();
    texture.flipY = false;
    texture.colorSpace = colorSpace;
    const sampler = this.document.samplers?.[record.sampler] || {};
    texture.wrapS = WRAP[sampler.wrapS] ?? THREE.RepeatWrapping;
    texture.wrapT = WRAP[sampler.wrapT] ?? THREE.RepeatWrapping;
    texture.magFilter = FILTER[sampler.magFilter] ?? THREE.LinearFilter;
    texture.minFilter = FILTER[sampler.minFilter] ?? THREE.LinearMipmapLinearFilter;
    texture.channel = info.texCoord ?? 0;
    if (transform) {
      // KHR_texture_transform: uv' = T(offset) R(rotation) S(scale) uv, about the origin
      if (transform.offset) texture.offset.fromArray(transform.offset);
      if (transform.rotation) texture.rotation = transform.rotation;
      if (transform.scale) texture.repeat.fromArray(transform.scale);
      if (transform.texCoord !== undefined) texture.channel = transform.texCoord;
    }
    this.image(source).then((bitmap) => {
      if (this.closed) return bitmap.close();
      texture.image = bitmap;
      texture.needsUpdate = true;
      this.onLoad?.();
    }).catch(() => {});          // a missing image leaves the channel's factor alone
    this.textures.set(key, texture);
    return texture;
  }

  // Resolves when every image asked for so far arrived (or failed).
  get ready() {
    return Promise.all(this.pending);
  }

  dispose() {
    this.closed = true;
    for (const texture of this.textures.values()) {
      texture.image?.close?.();
      texture.dispose();
    }
  }
}

// The three.js material of glTF material record `record`.
// options: { textures: TextureSet, vertexColors: bool, tangents: bool (the
// geometry has a TANGENT attribute) }.
export function makeMaterial(record, { textures, vertexColors = false, tangents = false }) {
  const pbr = record.pbrMetallicRoughness || {};
  const [r, g, b, a] = pbr.baseColorFactor || [1, 1, 1, 1];
  const unlit = record.extensions?.KHR_materials_unlit !== undefined;
  const Kind = unlit ? THREE.MeshBasicMaterial : THREE.MeshStandardMaterial;
  const material = new Kind({
    color: new THREE.Color().setRGB(r, g, b, THREE.LinearSRGBColorSpace), opacity: a,
    side: record.doubleSided ? THREE.DoubleSide : THREE.FrontSide,
    vertexColors, name: record.name || '' });
  const map = (info, colorSpace = THREE.NoColorSpace) => textures?.texture(info, colorSpace) ?? null;
  if (pbr.baseColorTexture) material.map = map(pbr.baseColorTexture, THREE.SRGBColorSpace);
  if (record.alphaMode === 'BLEND') {
    material.transparent = true;
    material.depthWrite = false;     // as GLTFLoader: blended surfaces do not hide each other
  } else if (record.alphaMode === 'MASK') {
    material.alphaTest = record.alphaCutoff ?? 0.5;
  }
  if (unlit) return material;
  material.metalness = pbr.metallicFactor ?? 1;
  material.roughness = pbr.roughnessFactor ?? 1;
  if (pbr.metallicRoughnessTexture) {
    material.metalnessMap = material.roughnessMap = map(pbr.metallicRoughnessTexture);
  }
  if (record.normalTexture) {
    material.normalMap = map(record.normalTexture);
    const scale = record.normalTexture.scale ?? 1;
    material.normalScale.set(scale, tangents ? scale : -scale);
  }
  if (record.occlusionTexture) {
    material.aoMap = map(record.occlusionTexture);
    material.aoMapIntensity = record.occlusionTexture.strength ?? 1;
  }
  const [er, eg, eb] = record.emissiveFactor || [0, 0, 0];
  material.emissive.setRGB(er, eg, eb, THREE.LinearSRGBColorSpace);
  if (record.emissiveTexture) material.emissiveMap = map(record.emissiveTexture, THREE.SRGBColorSpace);
  material.emissiveIntensity = record.extensions?.KHR_materials_emissive_strength?.emissiveStrength ?? 1;
  return material;
}

// The material of meshes without materials: a neutral clay, both sides lit
// (open scans show their inside through holes).
export function defaultMaterial() {
  return new THREE.MeshStandardMaterial({ color: 0xd9cfbf, roughness: 0.75, metalness: 0,
                                          side: THREE.DoubleSide, name: 'default' });
}

// The texture channels of a material (for tests and for turning one off).
export const CHANNELS = ['map', 'normalMap', 'metalnessMap', 'roughnessMap', 'aoMap', 'emissiveMap'];
