// The viewer's tools: render statistics (fps, draw calls, triangles), reset
// view, download the current level as GLB, the collapsible panel, and the
// view kept in the URL (level, camera, auto mode) and the up axis kept per
// mesh (localStorage).
//
// Signals in: 'mesh', 'scene-shown', 'level', 'target', 'frame', 'camera', 'settings'.
// Out: 'reset-view', 'settings' (up, through the caller's change()).

import { routeUrl } from './source.js';

// The frames drawn within this window count towards the fps shown. The scene
// draws on demand, so an idle view shows 0 fps: the rate is of frames drawn.
const FPS_WINDOW_MS = 1000;
const URL_DELAY_MS = 300;            // camera moves write the URL at most this often
const UP_KEY = (id) => `lodserver.up.${id}`;

// The mesh's stored up axis ('Y' or 'Z'), or null.
export function storedUp(id) {
  try {
    const value = window.localStorage.getItem(UP_KEY(id));
    return value === 'Y' || value === 'Z' ? value : null;
  } catch {
    return null;              // storage refused (a private window, say)
  }
}

export function storeUp(id, up) {
  try {
    window.localStorage.setItem(UP_KEY(id), up);
  } catch { /* the choice then lasts for this page only */ }
}

// The view the URL asks for: { mesh, level, camera: { position, target }, auto }
// (each null when absent or malformed).
export function readUrl(href = window.location.href) {
  const params = new URL(href).searchParams;
  const level = Number.parseInt(params.get('level') ?? '', 10);
  const numbers = (params.get('camera') ?? '').split(',').map(Number);
  const camera = numbers.length === 6 && numbers.every(Number.isFinite)
    ? { position: numbers.slice(0, 3), target: numbers.slice(3) } : null;
  const auto = params.get('auto');
  return { mesh: params.get('mesh'), level: Number.isFinite(level) && level > 0 ? level : null,
           camera, auto: auto === '1' ? true : auto === '0' ? false : null };
}

// Sets (or, with null, removes) URL parameters without a new history entry.
export function writeUrl(values) {
  const url = new URL(window.location.href);
  for (const [key, value] of Object.entries(values)) {
    if (value === null || value === undefined) url.searchParams.delete(key);
    else url.searchParams.set(key, value);
  }
  window.history.replaceState(null, '', url);
}

// Numbers short enough for a URL, exact enough for a view (6 significant digits).
const short = (x) => Number(x.toPrecision(6));

// The tools of the panel: `root` is the panel; `viewer` the bus (bus.js) whose
// signals they follow.
export class Tools {
  constructor(viewer, root) {
    this.viewer = viewer;
    this.root = root;
    const $ = (selector) => root.querySelector(selector);
    this.statsRow = $('#render-stats');
    this.download = $('#download');
    this.reset = $('#reset-view');
    this.toggle = $('#panel-toggle');
    this.info = null;           // the mesh's summary (a scene's too)
    this.level = null;          // the level shown and the level moved to
    this.target = null;
    this.sceneRatio = null;     // a scene (animated.js): the ratio of its GLB
    this.cameraTimer = 0;       // the pending write of a moved camera to the URL
    this.frames = [];           // draw times within the fps window, ms
    this.last = { calls: 0, triangles: 0, ms: 0 };   // the last frame's figures
    this.listen();
    this.reset.addEventListener('click', () => this.resetView());
    this.download.addEventListener('click', () => this.downloadLevel());
    this.toggle.addEventListener('click', () => this.togglePanel());
    // the fps falls back to 0 once nothing is drawn
    setInterval(() => { if (this.frames.length) this.showRenderStats(); }, FPS_WINDOW_MS / 2);
    // narrow screens start with the panel folded away
    if (window.matchMedia?.('(max-width: 600px)').matches) this.togglePanel();
    this.setEnabled();
  }

  listen() {
    const { viewer } = this;
    const { settings } = viewer;
    viewer.on('frame', (detail) => {
      this.frames.push(performance.now());
      this.last = detail;
      this.showRenderStats();
    });
    viewer.on('mesh', (detail) => {
      this.info = detail.info;
      this.level = this.target = detail.state.level;
      this.sceneRatio = null;
      this.setEnabled();
    });
    viewer.on('scene-shown', (detail) => {
      this.info = detail.info;
      this.level = this.target = null;
      this.sceneRatio = detail.ratio;
      this.setEnabled();
    });
    viewer.on('level', ({ state }) => {
      this.level = state.level;
      // once the level settles where it was sent: keep it in the URL (not in auto mode,
      // where the camera distance decides)
      if (this.level === this.target) {
        writeUrl({ level: settings.autoByDistance ? null : this.level });
      }
    });
    viewer.on('target', (value) => { this.target = value; });
    viewer.on('camera', ({ position, target: center }) => {
      clearTimeout(this.cameraTimer);
      this.cameraTimer = setTimeout(() => {
        writeUrl({ camera: [...position, ...center].map(short).join(',') });
      }, URL_DELAY_MS);
    });
    viewer.on('settings', (key) => {
      if (key === 'autoByDistance') {
        // auto is the default, and a level in the URL turns it off
        writeUrl({ auto: null, level: settings.autoByDistance ? null : this.level });
      } else if (key === 'up' && this.info) {
        storeUp(this.info.id, settings.up);
      }
    });
  }

  showRenderStats() {
    const { frames, last } = this;
    const now = performance.now();
    while (frames.length && now - frames[0] > FPS_WINDOW_MS) frames.shift();
    this.statsRow.textContent = `${frames.length} fps · ${last.calls} draw call` +
      `${last.calls === 1 ? '' : 's'} · ${last.triangles.toLocaleString()} triangles · ` +
      `${last.ms.toFixed(1)} ms`;
  }

  setEnabled() {
    this.download.disabled = this.reset.disabled = !this.info;
  }

  resetView() {
    clearTimeout(this.cameraTimer);
    writeUrl({ camera: null });
    this.viewer.emit('reset-view');
  }

  // The current level, as the server writes it: the same level, byte for byte
  // the file `lodserver extract` writes; a scene at the ratio it was loaded at.
  // At the mesh's version (an immutable URL), so a download is never of
  // another version than the one shown.
  downloadLevel() {
    const { info, level, sceneRatio } = this;
    if (!info || (level === null && sceneRatio === null)) return;
    const link = document.createElement('a');
    const params = sceneRatio === null ? { vertices: level, format: 'glb' }
      : { ratio: sceneRatio, format: 'glb' };
    link.href = routeUrl(info, 'lod', params);
    const stem = info.name.replace(/\.[^.]*$/, '');
    link.download = sceneRatio === null ? `${stem}-${level}.glb` : `${stem}-${sceneRatio}.glb`;
    document.body.append(link);
    link.click();
    link.remove();
  }

  togglePanel() {
    const collapsed = this.root.classList.toggle('collapsed');
    this.toggle.setAttribute('aria-expanded', String(!collapsed));
    this.toggle.textContent = collapsed ? 'show panel' : 'hide panel';
  }
}
