// Octahedral impostors (lodserver export --impostor): an asset's farthest
// level as grid x grid views baked to one colour atlas and one normal+depth
// atlas, drawn here on one camera-facing quad (one draw call, two triangles).
// The layout is the glTF's extras.impostor (docs/pipeline.md); the mapping
// and each view's basis are lodserver/bake/impostor.py's, which the atlases
// were baked with:
//
//   const gltf = await new GLTFLoader().loadAsync('asset_lod2.glb');
//   scene.add(await Impostor.fromGLTF(gltf));
//
// Each pixel of the quad casts the camera's ray onto the planes of the three
// views nearest the camera's direction (the grid triangle holding it), reads
// each view where the ray crosses its plane, and blends them by the
// barycentric weights; alpha-tested (the material's alphaTest), lit by the
// scene's ambient, hemisphere and directional lights (Lambert) through the
// object-space normals of the normal atlas.

import * as THREE from 'three';

// The GLSL both shaders share: the octahedral mapping of a unit direction
// (centre towards the viewer, y up) to the square [-1, 1]^2 and back, full or
// hemi (the upper half on the whole square), and a view's image basis.
const MAPPING = /* glsl */ `
uniform float grid;
uniform float frame;
uniform bool hemi;
uniform vec3 center;
uniform float radius;
uniform vec3 eye;

vec2 octEncode(vec3 d) {
  if (hemi) {
    d.y = max(d.y, 0.0);
    vec2 t = d.xz / max(abs(d.x) + d.y + abs(d.z), 1e-30);
    return vec2(t.x + t.y, t.x - t.y);
  }
  vec2 p = d.xz / max(abs(d.x) + abs(d.y) + abs(d.z), 1e-30);
  if (d.y < 0.0) {
    vec2 s = vec2(p.x >= 0.0 ? 1.0 : -1.0, p.y >= 0.0 ? 1.0 : -1.0);
    p = (1.0 - abs(p.yx)) * s;
  }
  return p;
}

vec3 octDecode(vec2 p) {
  if (hemi) {
    vec2 t = vec2(p.x + p.y, p.x - p.y) * 0.5;
    return normalize(vec3(t.x, 1.0 - abs(t.x) - abs(t.y), t.y));
  }
  float y = 1.0 - abs(p.x) - abs(p.y);
  if (y < 0.0) {
    vec2 s = vec2(p.x >= 0.0 ? 1.0 : -1.0, p.y >= 0.0 ? 1.0 : -1.0);
    p = (1.0 - abs(p.yx)) * s;
  }
  return normalize(vec3(p.x, y, p.y));
}

void viewBasis(vec3 d, out vec3 right, out vec3 up) {
  vec3 reference = abs(d.y) > 0.999 ? vec3(0.0, 0.0, d.y > 0.0 ? -1.0 : 1.0)
                                    : vec3(0.0, 1.0, 0.0);
  right = normalize(cross(reference, d));
  up = cross(d, right);
}
`;

const VERTEX = /* glsl */ `
${MAPPING}
varying vec3 vPoint;
varying mat3 vNormalMatrix;

void main() {
  vec3 toEye = eye - center;
  float distance = length(toEye);
  vec3 right, up;
  viewBasis(toEye / distance, right, up);
  // the sphere seen from a perspective eye covers more than its radius on the
  // plane through its centre: r D / sqrt(D^2 - r^2)
  float inside = max(distance * distance - radius * radius, 0.0625 * radius * radius);
  float grow = distance / sqrt(inside);
  vPoint = center + (position.x * right + position.y * up) * radius * grow;
  vNormalMatrix = normalMatrix;
  gl_Position = projectionMatrix * modelViewMatrix * vec4(vPoint, 1.0);
}
`;

const FRAGMENT = /* glsl */ `
#define PARALLAX_STEPS 3
#include <common>
#include <lights_pars_begin>
${MAPPING}
uniform sampler2D colorMap;
uniform sampler2D normalMap;
uniform float alphaCutoff;
varying vec3 vPoint;
varying mat3 vNormalMatrix;

// View (column, row) of the grid where the ray from the eye crosses its plane:
// its colour, and its normal and depth in normalDepth; nothing off the view.
vec4 view(vec2 cell, vec3 ray, out vec4 normalDepth) {
  vec3 d = octDecode(cell / (grid - 1.0) * 2.0 - 1.0);
  vec3 right, up;
  viewBasis(d, right, up);
  normalDepth = vec4(0.0);
  float facing = dot(ray, d);
  if (facing > -1e-3) return vec4(0.0);
  // the ray at depth 0 (the view's plane through the centre), then where it
  // is at the depth the view holds there: a perspective eye sees a near part
  // larger than the plane would show it, and the background beside an edge
  // holds the edge's depth, so an edge moves out as far as the mesh's does
  float depth = 0.0;
  vec2 at;
  for (int step = 0; step < PARALLAX_STEPS; step++) {
    vec3 q = eye + ray * ((depth + dot(center - eye, d)) / facing) - center;
    vec2 uv = vec2(dot(q, right), -dot(q, up)) / radius * 0.5 + 0.5;
    if (any(lessThan(uv, vec2(0.0))) || any(greaterThan(uv, vec2(1.0)))) return vec4(0.0);
    // half a pixel of the normal atlas (half the colour atlas's side) in from
    // the view's edge: bilinear filtering stays in the view
    at = (cell + clamp(uv, 1.0 / frame, 1.0 - 1.0 / frame)) / grid;
    normalDepth = texture2D(normalMap, at);
    depth = (normalDepth.a * 2.0 - 1.0) * radius;
  }
  return texture2D(colorMap, at);
}

void main() {
  vec3 ray = normalize(vPoint - eye);
  vec2 g = (octEncode(normalize(eye - center)) * 0.5 + 0.5) * (grid - 1.0);
  vec2 base = clamp(floor(g), vec2(0.0), vec2(grid - 2.0));
  vec2 f = clamp(g - base, 0.0, 1.0);
  vec2 c0 = base;
  vec3 w = vec3(1.0 - f.x - f.y, f.x, f.y);
  if (f.x + f.y > 1.0) {
    c0 = base + 1.0;
    w = vec3(f.x + f.y - 1.0, 1.0 - f.y, 1.0 - f.x);
  }
  vec4 n0, n1, n2;
  vec4 a = view(c0, ray, n0);
  vec4 b = view(base + vec2(1.0, 0.0), ray, n1);
  vec4 c = view(base + vec2(0.0, 1.0), ray, n2);
  float alpha = w.x * a.a + w.y * b.a + w.z * c.a;
  if (alpha < alphaCutoff) discard;
  // colour and normal weighted by each view's alpha too: a view's background
  // holds its edge's colour, not the object's
  vec3 k = w * vec3(a.a, b.a, c.a);
  vec3 albedo = (k.x * a.rgb + k.y * b.rgb + k.z * c.rgb) / max(k.x + k.y + k.z, 1e-6);
  vec3 objectNormal = k.x * (n0.rgb * 2.0 - 1.0) + k.y * (n1.rgb * 2.0 - 1.0)
                    + k.z * (n2.rgb * 2.0 - 1.0);
  vec3 normal = normalize(vNormalMatrix * normalize(objectNormal + vec3(0.0, 0.0, 1e-6)));
  vec3 irradiance = getAmbientLightIrradiance(ambientLightColor);
  #if NUM_HEMI_LIGHTS > 0
    #pragma unroll_loop_start
    for (int i = 0; i < NUM_HEMI_LIGHTS; i++) {
      irradiance += getHemisphereLightIrradiance(hemisphereLights[i], normal);
    }
    #pragma unroll_loop_end
  #endif
  #if NUM_DIR_LIGHTS > 0
    #pragma unroll_loop_start
    for (int i = 0; i < NUM_DIR_LIGHTS; i++) {
      irradiance += saturate(dot(normal, directionalLights[i].direction)) * directionalLights[i].color;
    }
    #pragma unroll_loop_end
  #endif
  gl_FragColor = vec4(BRDF_Lambert(albedo) * irradiance, 1.0);
  #include <tonemapping_fragment>
  #include <colorspace_fragment>
}
`;

// The grid view nearest a unit direction: [column, row] (the bake's rule).
export function nearestView(direction, layout) {
  const hemi = layout.kind === 'hemi';
  const { x, z } = direction;
  const y = hemi ? Math.max(direction.y, 0) : direction.y;
  const total = Math.max(Math.abs(x) + Math.abs(y) + Math.abs(z), 1e-300);
  let a = x / total;
  let b = z / total;
  if (hemi) [a, b] = [a + b, a - b];
  else if (y < 0) [a, b] = [(1 - Math.abs(b)) * (a >= 0 ? 1 : -1), (1 - Math.abs(a)) * (b >= 0 ? 1 : -1)];
  const cell = (p) => Math.min(layout.grid - 1, Math.max(0, Math.round((p + 1) * 0.5 * (layout.grid - 1))));
  return [cell(a), cell(b)];
}

export class ImpostorMaterial extends THREE.ShaderMaterial {
  // colorMap, normalMap: the atlases (textures as GLTFLoader makes them,
  // flipY false); layout: the glTF's extras.impostor.
  constructor({ colorMap, normalMap, layout, alphaTest = 0.5 }) {
    const uniforms = THREE.UniformsUtils.merge([THREE.UniformsLib.lights, {
      grid: { value: layout.grid }, frame: { value: layout.frame },
      hemi: { value: layout.kind === 'hemi' }, center: { value: new THREE.Vector3() },
      radius: { value: layout.radius }, eye: { value: new THREE.Vector3() },
      alphaCutoff: { value: alphaTest },
    }]);
    uniforms.center.value.fromArray(layout.center);
    // set after the merge, which would copy the textures
    uniforms.colorMap = { value: colorMap };
    uniforms.normalMap = { value: normalMap };
    super({ uniforms, vertexShader: VERTEX, fragmentShader: FRAGMENT, lights: true,
            side: THREE.DoubleSide });
    colorMap.colorSpace = THREE.SRGBColorSpace;
    normalMap.colorSpace = THREE.NoColorSpace;
    this.layout = layout;
  }
}

const inverse = new THREE.Matrix4();
const forward = new THREE.Vector3();

export class Impostor extends THREE.Mesh {
  // An impostor of the layout's asset, in the asset's own space.
  constructor({ colorMap, normalMap, layout, alphaTest = 0.5 }) {
    const geometry = new THREE.PlaneGeometry(2, 2);
    geometry.boundingSphere = new THREE.Sphere(new THREE.Vector3().fromArray(layout.center),
                                               layout.radius);
    super(geometry, new ImpostorMaterial({ colorMap, normalMap, layout, alphaTest }));
    this.layout = layout;
  }

  // The impostor of a loaded glTF (GLTFLoader's result) of lodserver export
  // --impostor: the first mesh whose extras name an impostor layout.
  static async fromGLTF(gltf) {
    let found = null;
    gltf.scene.traverse((object) => {
      if (!found && object.isMesh && object.userData?.impostor) found = object;
    });
    if (!found) throw new Error('not an impostor: no mesh of this glTF has extras.impostor');
    const layout = found.userData.impostor;
    const normalMap = await gltf.parser.getDependency('texture', layout.normalTexture);
    return new Impostor({ colorMap: found.material.map, normalMap, layout });
  }

  // The eye in the object's space, each frame before drawing: an orthographic
  // camera's rays are parallel, so its eye goes far back along them.
  onBeforeRender(renderer, scene, camera) {
    const eye = this.material.uniforms.eye.value;
    inverse.copy(this.matrixWorld).invert();
    if (camera.isOrthographicCamera) {
      camera.getWorldDirection(forward);
      eye.copy(this.material.uniforms.center.value).applyMatrix4(this.matrixWorld)
        .addScaledVector(forward, -1e3 * this.layout.radius);
    } else {
      eye.setFromMatrixPosition(camera.matrixWorld);
    }
    eye.applyMatrix4(inverse);
  }

  dispose() {
    this.geometry.dispose();
    this.material.dispose();
  }
}
