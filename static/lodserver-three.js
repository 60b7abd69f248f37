// lodserver's three.js module: progressive meshes and scenes of a lodserver
// as three.js objects, for any app (plain ES module, no build step; three.js
// 0.187 as the peer import 'three', and 'three/addons/' for scenes'
// GLTFLoader). docs/three.md has the options and an example:
//
//   const object = await new ProgressiveMeshLoader().load('http://host/meshes/ID');
//   scene.add(object);
//   // each frame: object.update(camera, renderer); renderer.render(scene, camera);
//
// The object (a ProgressiveMesh, or a ProgressiveScene of them with its skins
// and animations) refines or coarsens at each update() to the level whose
// error, projected through that camera, covers at most options.errorPixels
// CSS pixels. Its records come from a source: a ServerSource (source.js) for a
// lodserver URL, a StaticSource (staticsource.js) for a progressive file.

import { ProgressiveMesh } from './progressivemesh.js';
import { ProgressiveScene } from './progressivescene.js';
import { parseMeshUrl, ServerSource } from './source.js';
import { NOT_A_SOURCE, StaticSource } from './staticsource.js';
import { DEFAULTS } from './streamedlevel.js';

export { DEFAULTS, ProgressiveMesh, ProgressiveScene, ServerSource, StaticSource };
export { Impostor, ImpostorMaterial } from './impostor.js';

// The StaticSource of a progressive file's URL; an error naming both kinds of
// URL when it is neither.
async function openFile(url) {
  try {
    return await StaticSource.open(url);
  } catch (error) {
    if (error.message.startsWith(NOT_A_SOURCE)) throw error;
    throw new Error(`${NOT_A_SOURCE}: ${url} (${error.message})`);
  }
}

export class ProgressiveMeshLoader {
  // Resolves to the object of the mesh at `url`: a lodserver mesh
  // (http://host/meshes/ID), once the server has built it, or any other URL
  // of a progressive file (a .glb of lodserver export --progressive, or
  // GET /meshes/{id}/progressive) on any static host; options: DEFAULTS' keys
  // (errorPixels, ...).
  async load(url, options = {}) {
    let mesh = null;
    try {
      mesh = parseMeshUrl(url);
    } catch {
      // not a mesh URL: a progressive file, read below
    }
    const source = mesh ? await ServerSource.open(mesh.id, { root: mesh.root })
      : await openFile(url);
    return this.fromSource(source, options);
  }

  // The object of a mesh whose records come from `source` (source.js).
  async fromSource(source, options = {}) {
    return source.summary.scene === true
      ? ProgressiveScene.load(source, options)
      : new ProgressiveMesh(source, options);
  }
}
