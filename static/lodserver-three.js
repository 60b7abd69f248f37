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
// CSS pixels. Its records come from a source (source.js: a ServerSource for a
// lodserver URL), so that other sources (a progressive file) fit in.

import { ProgressiveMesh } from './progressivemesh.js';
import { ProgressiveScene } from './progressivescene.js';
import { parseMeshUrl, ServerSource } from './source.js';
import { DEFAULTS } from './streamedlevel.js';

export { DEFAULTS, ProgressiveMesh, ProgressiveScene, ServerSource };

export class ProgressiveMeshLoader {
  // Resolves to the object of the mesh at `url` (http://host/meshes/ID),
  // once the server has built it; options: DEFAULTS' keys (errorPixels, ...).
  async load(url, options = {}) {
    const { root, id } = parseMeshUrl(url);
    const source = await ServerSource.open(id, { root });
    return this.fromSource(source, options);
  }

  // The object of a mesh whose records come from `source` (source.js).
  async fromSource(source, options = {}) {
    return source.summary.scene === true
      ? ProgressiveScene.load(source, options)
      : new ProgressiveMesh(source, options);
  }
}
