// The mesh the viewer shows, as the three.js module's object: opened through
// ProgressiveMeshLoader (lodserver-three.js) as an app opens one, a
// ProgressiveMesh (progressivemesh.js) or, for a scene, a ProgressiveScene
// (progressivescene.js, played by animated.js). The panel, the plot and the
// tools are UI around it: its stream's signals reach them on the viewer's bus,
// and their choices move its level.
//
// The level: in auto mode (settings.autoByDistance) the object's update()
// keeps it where its error covers at most settings.errorBudgetPx CSS pixels
// at the view (docs/three.md); a level set by hand pins it (setLevel). The
// first level is the view's (or the one the URL names, if coarser), at most
// settings.firstLevelMaxVertices. A scene's parts are pinned at their share of
// the scene's level for the first view: unlike a single mesh, the viewer's
// scene does not follow a zoom.
//
// Signals in: 'open' ({ id }), 'goto' (a level), 'view', 'settings', 'target'.
// Out: the object's 'mesh', 'level', 'target', 'status', 'stream' (stream.js
// says what they hold), 'textures' (bytes), 'budget' (the error the budget
// allows at the view, mesh units, or null), 'status' (a build's progress),
// 'camera-set' (the camera the URL names, once its mesh is framed).

import { makeLoader } from './animated.js';
import { firstLevel, guessUpAxis } from './framing.js';
import { ProgressiveMeshLoader } from './lodserver-three.js';
import { ServerSource } from './source.js';
import { allowedError } from './streamedlevel.js';
import { storedUp } from './tools.js';

// The viewer's settings the object's options follow: setting -> option.
const OPTIONS = { errorBudgetPx: 'errorPixels', geomorphMs: 'geomorphMs',
                  chunkSplits: 'chunkSplits', shading: 'shading', wireframe: 'wireframe' };
// The object's events the viewer's parts hear as signals of the same name.
const RELAYED = ['mesh', 'level', 'target', 'status', 'stream'];

export class ViewedMesh {
  // viewer: the bus; view: the ViewScene (scene.js), or null when the page
  // cannot draw; animation: the SceneAnimation (animated.js), or null;
  // linked: the view the URL names (tools.js readUrl()), for its mesh.
  constructor(viewer, view, animation, linked) {
    this.viewer = viewer;
    this.settings = viewer.settings;
    this.view = view;
    this.animation = animation;
    this.linked = linked;
    this.loader = new ProgressiveMeshLoader();
    this.object = null;         // the ProgressiveMesh or ProgressiveScene shown
    this.summary = null;        // its GET /meshes/{id}
    this.failed = null;         // why the last mesh could not be opened, or null
    this.opened = 0;            // counts opens, so an open overtaken by another stops
    this.opening = null;        // the running open(), if any
    this.textureBytes = 0;
    this.started = false;       // the object's stream has said its first target
    this.unpin = false;         // auto mode from there: the URL named the first stop
    viewer.on('open', ({ id }) => this.open(id));
    viewer.on('goto', (level) => this.goto(level));
    viewer.on('view', () => this.follow());
    viewer.on('settings', (key) => this.applySetting(key));
  }

  get isMesh() { return this.object?.type === 'ProgressiveMesh'; }

  // Opens mesh `id` (once the server has built it, its progress in the status).
  open(id) {
    const ticket = ++this.opened;
    this.close();
    this.opening = this.load(id, ticket);
    return this.opening;
  }

  async load(id, ticket) {
    const stale = () => ticket !== this.opened;
    let scene = false;
    try {
      const source = await ServerSource.open(id, { onProgress: (summary) => {
        if (stale()) return false;
        const percent = Math.round(100 * summary.progress);
        this.viewer.emit('status', `${summary.name}: ${summary.status} ${percent}%`);
        return true;
      } });
      if (!source || stale()) return;
      const { summary } = source;
      this.settings.up = storedUp(summary.id) ?? guessUpAxis(summary);
      const { first, stop } = this.plan(summary);
      const options = { ...this.options(), firstLevelMaxVertices: first };
      scene = summary.scene === true;
      if (scene) {
        options.gltfLoader = makeLoader();
        this.viewer.emit('status', `${summary.name}: loading the scene`);
      }
      const object = await this.loader.fromSource(source, options);
      if (stale()) {
        object.dispose();
        return;
      }
      [this.object, this.summary] = [object, summary];
      if (scene) this.showScene(object, stop);
      else this.showMesh(object, stop);
    } catch (error) {
      if (stale()) return;
      this.failed = error;
      this.viewer.emit('status', scene ? `error: the scene could not be shown (${error.message})`
        : `error: ${error.message}`);
    }
  }

  // The first level to fetch (at most; the object keeps it >= the base) and
  // the level to stop at (null: the budget's, auto mode) of mesh `summary`:
  // the coarsest level whose error covers at most the pixel budget at the
  // initial framing (so the first frame is no shard of the base), or the level
  // the URL names if coarser; a scene without an error curve or a box, at most
  // firstLevelMaxVertices of it. The level the URL names is the stop, also in
  // auto mode (?auto=1), which then follows the view from there.
  plan(summary) {
    const { settings } = this;
    const wanted = this.linked?.mesh === summary.id ? this.linked.level : null;
    const cap = Math.max(summary.base_vertices ?? 0, settings.firstLevelMaxVertices);
    if (summary.scene && !(summary.error_curve?.length && summary.bounds)) {
      return { first: cap, stop: wanted ?? summary.vertices };
    }
    const view = this.view ? this.view.view()
      : { fov: settings.fov, width: innerWidth, height: innerHeight };
    const budget = firstLevel(summary, { ...view, up: settings.up }, settings.errorBudgetPx);
    const auto = settings.autoByDistance;
    const stop = wanted ?? (auto ? (summary.scene ? budget : null) : summary.vertices);
    const first = Math.max(summary.base_vertices ?? 0, Math.min(budget, wanted ?? Infinity, cap));
    return { first, stop };
  }

  // The object's options from the viewer's settings (OPTIONS).
  options() {
    return Object.fromEntries(Object.entries(OPTIONS)
      .filter(([key]) => this.settings[key] !== undefined)
      .map(([key, option]) => [option, this.settings[key]]));
  }

  // The viewer's settings into the object's options (set by hand or by a
  // test between two moves of the level).
  syncOptions() {
    if (this.object) Object.assign(this.object.options, this.options());
  }

  showMesh(object, stop) {
    for (const type of RELAYED) {
      object.addEventListener(type, ({ detail }) => {
        if (this.object === object) this.relay(object, type, detail);
      });
    }
    object.addEventListener('change', () => {
      if (this.object !== object) return;
      if (object.textureBytes !== this.textureBytes) {
        this.textureBytes = object.textureBytes;
        this.viewer.emit('textures', this.textureBytes);
      }
      this.view?.rendered();
    });
    this.view?.showProgressive(object);
    this.unpin = stop !== null && this.settings.autoByDistance;
    if (stop === null) this.follow();
    else object.setLevel(stop);
  }

  showScene(object, stop) {
    this.animation?.show(object);
    object.setLevel(stop);
    this.linked = null;
  }

  relay(object, type, detail) {
    this.viewer.emit(type, detail);
    if (type === 'mesh') {
      // the camera the URL names is the first mesh's, set once it is framed
      const { camera, mesh } = this.linked ?? {};
      if (camera && mesh === detail.info.id) this.viewer.emit('camera-set', camera);
      this.linked = null;
      this.started = false;
    } else if (type === 'target' && !this.started) {
      this.started = true;
      // after every listener heard the first target: the view may ask for
      // another (in auto mode, also after the URL's level)
      queueMicrotask(() => {
        if (this.object !== object) return;
        if (this.unpin) object.setLevel(null);
        this.unpin = false;
        this.follow();
      });
    }
  }

  // Auto mode: the level the budget allows at the view (ErrorCurve.follow:
  // refined as soon as the view needs more, coarsened only past a hysteresis).
  follow() {
    if (!this.isMesh || !this.view) return;
    const object = this.object, { bounds } = this.summary;
    const auto = this.settings.autoByDistance;
    this.syncOptions();
    const { camera, renderer } = this.view;
    this.viewer.emit('budget', auto && bounds ? allowedError(object, bounds, {
      camera, renderer, errorPixels: this.settings.errorBudgetPx }) : null);
    if (auto) object.update(camera, renderer);
  }

  // A level set by hand (ui.js ends auto mode first).
  goto(level) {
    if (!this.isMesh) return;
    this.syncOptions();
    this.object.setLevel(level);
  }

  applySetting(key) {
    if (!this.isMesh) return;
    this.syncOptions();
    if (key === 'autoByDistance' || key === 'errorBudgetPx') {
      // back to the budget's level at once, without the hysteresis
      if (this.settings.autoByDistance) this.object.setLevel(null);
      this.follow();
    }
  }

  // Frees the object shown, stops its fetches.
  close() {
    const object = this.object;
    [this.object, this.summary, this.failed, this.textureBytes] = [null, null, null, 0];
    if (!object) return;
    if (object.type === 'ProgressiveScene') this.animation?.close();
    else this.view?.removeObject(object);
    object.dispose();
  }

  // Resolves once the mesh is open and its level reached its target.
  async settled() {
    await this.opening;
    await this.object?.settled();
  }
}
