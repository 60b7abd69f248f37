// A streamed level drawn by three.js: one THREE.Mesh whose buffers follow a
// LodState (levelstate.js) as packets move it.
//
// The buffers are allocated at full detail once per mesh. A level is a prefix
// of the vertices and of the faces (the prefix layout), so showing one is a
// draw range, and a packet re-uploads only the ranges it changed. The index
// buffer *is* the decoder's face array; positions are decoded from the grid
// (origin + q * step: the origin goes into the mesh's transform, so the floats
// stay small).
//
// A mesh with attributes is drawn with one vertex per wedge (a UV seam or a
// hard edge has a vertex per side): its position is its vertex's, its normal,
// UVs and colour its own, and the index buffer is the decoder's wedge-per-corner
// array. Normals come from the stream when it has them, else they are computed
// per vertex and shared by the vertex's wedges. Faces are drawn in one group
// per material, each group a prefix of a range of the index buffer (a level's
// faces of one material are a prefix of that material's faces, in slot order).

import * as THREE from 'three';
import { dequantize } from './vsplit.js';
import { defaultMaterial, makeMaterial, TextureSet } from './materials.js';

// three.js attribute names of glTF's.
const ATTRIBUTE_NAMES = { NORMAL: 'normal', TANGENT: 'tangent', TEXCOORD_0: 'uv',
                          TEXCOORD_1: 'uv1', COLOR_0: 'color' };

// Area-weighted unit vertex normals of the state's level into out[3v ..]
// (every vertex of a level lies on one of its faces). Computed on grid
// coordinates: the same directions, without reading the floats back.
export function levelNormals(state, out) {
  const q = state.positions, faces = state.faces;
  out.fill(0, 0, 3 * state.vertexCount);
  for (let c = 0; c < 3 * state.faceCount; c += 3) {
    const a = 3 * faces[c], b = 3 * faces[c + 1], d = 3 * faces[c + 2];
    const ux = q[b] - q[a], uy = q[b + 1] - q[a + 1], uz = q[b + 2] - q[a + 2];
    const vx = q[d] - q[a], vy = q[d + 1] - q[a + 1], vz = q[d + 2] - q[a + 2];
    const x = uy * vz - uz * vy, y = uz * vx - ux * vz, z = ux * vy - uy * vx;
    out[a] += x; out[a + 1] += y; out[a + 2] += z;
    out[b] += x; out[b + 1] += y; out[b + 2] += z;
    out[d] += x; out[d + 1] += y; out[d + 2] += z;
  }
  for (let i = 0; i < 3 * state.vertexCount; i += 3) {
    const length = Math.hypot(out[i], out[i + 1], out[i + 2]) || 1;
    out[i] /= length;
    out[i + 1] /= length;
    out[i + 2] /= length;
  }
}

export class LevelMesh {
  // state: the LodState drawn (its arrays are read at each update());
  // appearance: { materialFaces, materials: { document, url } | null } (stream.js);
  // onTexture(): a texture arrived (draw again).
  constructor(state, appearance = null, { onTexture = () => {} } = {}) {
    this.state = state;
    this.textures = null;
    this.groups = null;         // per-material index ranges, when there are several
    this.smooth = true;         // computed normals are smooth (per vertex), else flat shading
    const geometry = new THREE.BufferGeometry();
    const dynamic = (array, size) => new THREE.BufferAttribute(array, size)
      .setUsage(THREE.DynamicDrawUsage);
    const wedged = state.attributes.length > 0;
    const capacity = wedged ? state.wedgeCapacity : state.vertexCapacity;
    geometry.setAttribute('position', dynamic(new Float32Array(3 * capacity), 3));
    geometry.setAttribute('normal', dynamic(new Float32Array(3 * capacity), 3));
    for (const a of state.attributes) {
      if (a.name === 'NORMAL' || !ATTRIBUTE_NAMES[a.name]) continue;
      geometry.setAttribute(ATTRIBUTE_NAMES[a.name],
                            dynamic(new Float32Array(a.width * capacity), a.width));
    }
    // computed normals per vertex (wedge meshes without NORMAL)
    this.vertexNormals = wedged && !state.attributes.some((a) => a.name === 'NORMAL')
      ? new Float32Array(3 * state.vertexCapacity) : null;
    this.fallback = defaultMaterial();
    // per draw group: the mesh's materials, then the default
    this.materials = [this.fallback];
    let drawn = this.fallback;
    if (appearance?.materials) {
      const { document, url } = appearance.materials;
      this.textures = new TextureSet(document, url, onTexture);
      const has = (name) => state.attributes.some((a) => a.name === name);
      const options = { textures: this.textures, vertexColors: has('COLOR_0'),
                        tangents: has('TANGENT') };
      this.materials = [...document.materials.map((record) => makeMaterial(record, options)),
                        this.fallback];
      // one group per material that has faces (the last: faces without a material)
      const counts = appearance.materialFaces || [];
      const used = counts.map((n, g) => (n > 0 ? g : -1)).filter((g) => g >= 0);
      if (used.length === 1) drawn = this.materials[used[0]];
      else if (used.length > 1) this.groups = this.makeGroups(counts);
    }
    const index = this.groups ? this.groups.index : wedged ? state.corners : state.faces;
    geometry.setIndex(dynamic(index, 1));
    this.mesh = new THREE.Mesh(geometry, this.groups ? this.materials : drawn);
    this.mesh.position.set(...state.grid.origin);
    // The bounding sphere would count the unused slots of the buffers.
    this.mesh.frustumCulled = false;
  }

  // Index ranges per material: material g's faces in slot order fill
  // [start[g], start[g] + count[g]) of the faces of the index buffer.
  makeGroups(counts) {
    const start = new Int32Array(counts.length);
    for (let g = 1; g < counts.length; g++) start[g] = start[g - 1] + counts[g - 1];
    return { start, filled: new Int32Array(counts.length), faces: 0,
             slot: new Int32Array(this.state.faceCapacity),       // face -> place in the index
             index: new Uint32Array(3 * this.state.faceCapacity) };
  }

  // Shows the state's level after packets changed `dirty` (state.takeDirty()).
  update(dirty) {
    if (this.state.attributes.length) this.showWedges(dirty);
    else this.showVertices(dirty);
    if (this.smooth) this.updateNormals();
    this.mesh.geometry.setDrawRange(0, this.groups ? Infinity : 3 * this.state.faceCount);
  }

  // Shading ('smooth' or 'flat') and wireframe on every material of the mesh.
  setLook({ shading = 'smooth', wireframe = false } = {}) {
    const smooth = shading === 'smooth';
    for (const each of this.materials) {
      each.flatShading = !smooth;
      each.wireframe = wireframe;
      each.needsUpdate = true;
    }
    this.smooth = smooth;
    if (smooth) this.updateNormals();       // flat shading needs none: not kept up
  }

  dispose() {
    this.mesh.removeFromParent();
    this.mesh.geometry.dispose();
    for (const each of this.materials) each.dispose();
    this.textures?.dispose();
    this.textures = null;
  }

  // Follows the level's faces (their wedges, or vertices without attributes)
  // into the per-material ranges and sets the draw groups.
  updateGroups(dirty) {
    const { state, groups } = this;
    const { faceMaterial, faceCount } = state;
    const corners = state.attributes.length ? state.corners : state.faces;
    const { start, filled, slot, index } = groups;
    const group = (f) => (faceMaterial[f] >= 0 ? faceMaterial[f] : start.length - 1);
    for (; groups.faces > faceCount; groups.faces--) filled[group(groups.faces - 1)]--;
    for (; groups.faces < faceCount; groups.faces++) {
      const g = group(groups.faces);
      slot[groups.faces] = start[g] + filled[g]++;
    }
    const first = Math.floor(dirty.cornerStart / 3), last = Math.ceil(dirty.cornerEnd / 3);
    for (let f = first; f < Math.min(last, faceCount); f++) {
      const at = 3 * slot[f];
      index[at] = corners[3 * f];
      index[at + 1] = corners[3 * f + 1];
      index[at + 2] = corners[3 * f + 2];
    }
    const { geometry } = this.mesh;
    geometry.clearGroups();
    for (let g = 0; g < start.length; g++) {
      if (filled[g] > 0) geometry.addGroup(3 * start[g], 3 * filled[g], g);
    }
    if (last > first) geometry.index.needsUpdate = true;
  }

  // The wedge buffers after a packet: the positions of the touched vertices'
  // wedges, the attributes of the touched wedges.
  showWedges(dirty) {
    const { geometry } = this.mesh;
    const position = geometry.getAttribute('position');
    const { positions, ring, ringInfo, corners, wedgeVertex, wedges, components } = this.state;
    const { step } = this.state.grid;
    const p = position.array;
    let low = Infinity, high = -1;
    for (const v of dirty.vertices) {
      const x = positions[3 * v] * step, y = positions[3 * v + 1] * step;
      const z = positions[3 * v + 2] * step;
      for (let i = ringInfo[4 * v], end = i + ringInfo[4 * v + 1]; i < end; i++) {
        const w = corners[ring[i]];
        p[3 * w] = x;
        p[3 * w + 1] = y;
        p[3 * w + 2] = z;
        if (w < low) low = w;
        if (w > high) high = w;
      }
    }
    const streamed = this.state.attributes.filter((a) => ATTRIBUTE_NAMES[a.name]);
    const buffers = streamed.map((a) => geometry.getAttribute(ATTRIBUTE_NAMES[a.name]));
    for (const w of dirty.wedges) {
      const v = wedgeVertex[w];
      p[3 * w] = positions[3 * v] * step;
      p[3 * w + 1] = positions[3 * v + 1] * step;
      p[3 * w + 2] = positions[3 * v + 2] * step;
      streamed.forEach((a, i) => {
        dequantize(a, wedges, components * w + a.offset, buffers[i].array, a.width * w);
      });
      if (w < low) low = w;
      if (w > high) high = w;
    }
    if (high >= low) {
      position.addUpdateRange(3 * low, 3 * (high - low + 1));
      position.needsUpdate = true;
      streamed.forEach((a, i) => {
        buffers[i].addUpdateRange(a.width * low, a.width * (high - low + 1));
        buffers[i].needsUpdate = true;
      });
    }
    const { cornerStart, cornerEnd } = dirty;
    if (this.groups) this.updateGroups(dirty);
    else if (cornerEnd > cornerStart) {
      geometry.index.addUpdateRange(cornerStart, cornerEnd - cornerStart);
      geometry.index.needsUpdate = true;
    }
  }

  showVertices(dirty) {
    const { geometry } = this.mesh;
    const position = geometry.getAttribute('position');
    const { vertexStart, vertexEnd, cornerStart, cornerEnd } = dirty;
    if (this.groups) this.updateGroups(dirty);
    if (vertexEnd > vertexStart) {
      const { step } = this.state.grid;
      for (let i = 3 * vertexStart; i < 3 * vertexEnd; i++) {
        position.array[i] = this.state.positions[i] * step;
      }
      position.addUpdateRange(3 * vertexStart, 3 * (vertexEnd - vertexStart));
      position.needsUpdate = true;
    }
    if (!this.groups && cornerEnd > cornerStart) {
      geometry.index.addUpdateRange(cornerStart, cornerEnd - cornerStart);
      geometry.index.needsUpdate = true;
    }
  }

  // Area-weighted vertex normals of the current level (levelNormals).
  updateNormals() {
    const { state, vertexNormals } = this;
    if (state.attributes.length && !vertexNormals) return;    // normals from the stream
    const normal = this.mesh.geometry.getAttribute('normal');
    const n = vertexNormals || normal.array;
    levelNormals(state, n);
    let count = state.vertexCount;
    if (vertexNormals) {       // each wedge takes its vertex's normal
      const out = normal.array, { wedgeVertex } = state;
      count = state.wedgeCount;
      for (let w = 0; w < count; w++) {
        const v = 3 * wedgeVertex[w];
        out[3 * w] = n[v];
        out[3 * w + 1] = n[v + 1];
        out[3 * w + 2] = n[v + 2];
      }
    }
    normal.addUpdateRange(0, 3 * count);
    normal.needsUpdate = true;
  }
}
