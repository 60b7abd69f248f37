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

// The tools of the panel: `root` is the panel.
export function createTools(viewer, root) {
  const { settings } = viewer;
  const $ = (selector) => root.querySelector(selector);
  const statsRow = $('#render-stats'), download = $('#download'), reset = $('#reset-view');
  const toggle = $('#panel-toggle');
  let info = null, level = null, target = null, cameraTimer = 0;
  let sceneRatio = null;         // a scene (animated.js): the ratio of its GLB
  const frames = [];             // draw times within the fps window, ms
  let last = { calls: 0, triangles: 0, ms: 0 };

  function showRenderStats() {
    const now = performance.now();
    while (frames.length && now - frames[0] > FPS_WINDOW_MS) frames.shift();
    statsRow.textContent = `${frames.length} fps · ${last.calls} draw call` +
      `${last.calls === 1 ? '' : 's'} · ${last.triangles.toLocaleString()} triangles · ` +
      `${last.ms.toFixed(1)} ms`;
  }

  viewer.on('frame', (detail) => {
    frames.push(performance.now());
    last = detail;
    showRenderStats();
  });
  // the fps falls back to 0 once nothing is drawn
  setInterval(() => { if (frames.length) showRenderStats(); }, FPS_WINDOW_MS / 2);

  function setEnabled() {
    download.disabled = reset.disabled = !info;
  }

  viewer.on('mesh', (detail) => {
    info = detail.info;
    level = target = detail.state.level;
    sceneRatio = null;
    setEnabled();
  });
  viewer.on('scene-shown', (detail) => {
    info = detail.info;
    level = target = null;
    sceneRatio = detail.ratio;
    setEnabled();
  });
  viewer.on('level', ({ state }) => {
    level = state.level;
    // once the level settles where it was sent: keep it in the URL (not in auto mode,
    // where the camera distance decides)
    if (level === target) writeUrl({ level: settings.autoByDistance ? null : level });
  });
  viewer.on('target', (value) => { target = value; });
  viewer.on('camera', ({ position, target: center }) => {
    clearTimeout(cameraTimer);
    cameraTimer = setTimeout(() => {
      writeUrl({ camera: [...position, ...center].map(short).join(',') });
    }, URL_DELAY_MS);
  });
  viewer.on('settings', (key) => {
    if (key === 'autoByDistance') {
      // auto is the default, and a level in the URL turns it off
      writeUrl({ auto: null, level: settings.autoByDistance ? null : level });
    } else if (key === 'up' && info) {
      storeUp(info.id, settings.up);
    }
  });

  reset.addEventListener('click', () => {
    clearTimeout(cameraTimer);
    writeUrl({ camera: null });
    viewer.emit('reset-view');
  });
  // The current level, as the server writes it: the same level, byte for byte
  // the file `lodserver extract` writes; a scene at the ratio it was loaded at.
  // At the mesh's version (an immutable URL), so a download is never of
  // another version than the one shown.
  download.addEventListener('click', () => {
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
  });
  toggle.addEventListener('click', () => {
    const collapsed = root.classList.toggle('collapsed');
    toggle.setAttribute('aria-expanded', String(!collapsed));
    toggle.textContent = collapsed ? 'show panel' : 'hide panel';
  });
  // narrow screens start with the panel folded away
  if (window.matchMedia?.('(max-width: 600px)').matches) toggle.click();
  setEnabled();
}
