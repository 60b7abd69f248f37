// A scene part's level as a three.js geometry: what the part's stream
// carries (positions, and NORMAL, TEXCOORD_n, COLOR_0, TANGENT, JOINTS_0 /
// WEIGHTS_0 -> skinIndex / skinWeight, TARGET{t}_* -> morph targets), and
// what it does not kept from the GLB's geometry of the part: as it is when the
// level has as many vertices as the GLB's (the server writes them in the same
// order), else each vertex takes the values of the GLB vertex nearest to it.
// (animated.js in the viewer, progressivescene.js in the three.js module.)

import * as THREE from 'three';
import { nearestPoints } from './nearest.js';
import { dequantize } from './vsplit.js';

// glTF attribute names -> three.js's (GLTFLoader's names).
const THREE_NAMES = { NORMAL: 'normal', TANGENT: 'tangent', TEXCOORD_0: 'uv', TEXCOORD_1: 'uv1',
                      TEXCOORD_2: 'uv2', TEXCOORD_3: 'uv3', COLOR_0: 'color',
                      JOINTS_0: 'skinIndex', WEIGHTS_0: 'skinWeight' };
const MORPH = /^TARGET(\d+)_(POSITION|NORMAL|TANGENT)$/;

// attribute's rows picked by `rows` (an index per new vertex): a new attribute
// of the same type, width and normalisation.
function pickRows(attribute, rows) {
  const { itemSize, normalized } = attribute;
  const source = attribute.array;
  const out = new source.constructor(itemSize * rows.length);
  for (let v = 0; v < rows.length; v++) {
    for (let k = 0; k < itemSize; k++) out[itemSize * v + k] = source[itemSize * rows[v] + k];
  }
  return new THREE.BufferAttribute(out, itemSize, normalized);
}

// A three.js geometry of `state`'s level (a LodState: see levelstate.js):
// one vertex per wedge when it has attributes, else per vertex; `original`
// (the GLB's geometry of the part) supplies what the stream does not carry.
export function levelGeometry(state, original) {
  const wedged = state.attributes.length > 0;
  const count = wedged ? state.wedgeCount : state.vertexCount;
  const { origin, step } = state.grid;
  const position = new Float32Array(3 * count);
  for (let w = 0; w < count; w++) {
    const v = wedged ? state.wedgeVertex[w] : w;
    for (let k = 0; k < 3; k++) position[3 * w + k] = origin[k] + step * state.positions[3 * v + k];
  }
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute('position', new THREE.BufferAttribute(position, 3));
  // a copy: the state changes its arrays in place as packets arrive
  const corners = wedged ? state.corners : state.faces;
  geometry.setIndex(new THREE.BufferAttribute(corners.slice(0, 3 * state.faceCount), 1));
  const morphs = {};
  for (const a of state.attributes) {
    const values = new Float32Array(a.width * count);
    for (let w = 0; w < count; w++) {
      dequantize(a, state.wedges, state.components * w + a.offset, values, a.width * w);
    }
    const attribute = new THREE.BufferAttribute(values, a.width);
    const morph = MORPH.exec(a.name);
    if (morph) {
      const key = morph[2].toLowerCase();
      (morphs[key] ??= [])[Number(morph[1])] = attribute;
    } else if (THREE_NAMES[a.name]) {
      geometry.setAttribute(THREE_NAMES[a.name], attribute);
    }
  }
  for (const [key, list] of Object.entries(morphs)) geometry.morphAttributes[key] = list;
  if (Object.keys(morphs).length) geometry.morphTargetsRelative = true;     // glTF: deltas
  // where each attribute came from (status(), tests)
  const streamed = [...Object.keys(geometry.attributes), ...Object.keys(morphs).map(
    (key) => `morph ${key}`)].filter((name) => name !== 'position');
  const kept = transfer(original, geometry);
  if (!geometry.hasAttribute('normal') && original.hasAttribute('normal')) {
    geometry.computeVertexNormals();
  }
  geometry.userData.lodserver = { streamed, kept: kept.names, from: kept.from };
  return geometry;
}

// Copies to `geometry` the attributes and morph targets of `original` it lacks
// (normals excepted: computed from the level instead): as they are with as many
// vertices (the same order: the server writes a part's GLB vertices in its
// level's order), else the nearest original vertex's. What it copied:
// { names, from: 'same order' | 'nearest' | null (nothing) }.
function transfer(original, geometry) {
  const names = [];
  const count = geometry.getAttribute('position').count;
  const source = original.getAttribute('position');
  const same = source.count === count;
  let rows = null;
  const pick = (attribute) => {
    if (same) return attribute;
    rows ??= nearestPoints(source.array, geometry.getAttribute('position').array);
    return pickRows(attribute, rows);
  };
  for (const [name, attribute] of Object.entries(original.attributes)) {
    if (name === 'position' || name === 'normal' || geometry.hasAttribute(name)) continue;
    if (attribute.isInterleavedBufferAttribute) continue;     // not written by lodserver
    geometry.setAttribute(name, pick(attribute));
    names.push(name);
  }
  for (const [name, list] of Object.entries(original.morphAttributes)) {
    if (geometry.morphAttributes[name]?.length) continue;
    geometry.morphAttributes[name] = list.map(pick);
    geometry.morphTargetsRelative = original.morphTargetsRelative;
    names.push(`morph ${name}`);
  }
  return { names, from: names.length ? (same ? 'same order' : 'nearest') : null };
}
