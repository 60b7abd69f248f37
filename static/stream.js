// Fetching a mesh: its summary, its base level (and its materials, if any),
// then packets between levels.
//
// The client never refetches a level: it holds one LodState and moves it to
// the target level packet by packet, forward (splits) or backward (collapses).
// Packets are cut at multiples of settings.chunkSplits, so the detail arrives
// in steps the viewer can show, and moving back and forth asks for the same
// packets again, which the browser cache answers (the server marks them
// immutable).
//
// Signals out: 'mesh' (a new mesh is shown), 'level' (the state moved),
// 'target' (the level being moved to), 'status' (text for the user).
// Signals in: 'open' (a mesh id), 'goto' (a level).

import { ErrorCurve } from './curve.js';
import { LodState } from './vsplit.js';

const POLL_MS = 500;

export function createStream(viewer) {
  const { settings } = viewer;
  let info = null;            // GET /meshes/{id}
  let state = null;           // the level held
  let target = null;
  let bytes = 0;              // geometry bytes received: the base level and packets
  let opened = 0;             // counts opens, so work for a mesh closed meanwhile stops
  let opening = null;         // the running open(), if any
  let moving = null;          // the running move() of this mesh: { ticket, done }
  let failed = null;          // the error that stopped the mesh, if any

  async function fetchOk(url, options) {
    const response = await fetch(url, options);
    if (!response.ok) {
      const body = await response.json().catch(() => ({}));
      throw new Error(body.message || `${url} answered ${response.status}`);
    }
    return response;
  }

  async function fetchGeometry(url, ticket) {
    const buffer = await (await fetchOk(url)).arrayBuffer();
    if (ticket === opened) bytes += buffer.byteLength;
    return buffer;
  }

  // The summary of a mesh once it is built, reporting the build's progress.
  async function waitUntilReady(id, ticket) {
    for (;;) {
      const summary = await (await fetchOk(`../meshes/${id}`)).json();
      if (ticket !== opened) return null;
      if (summary.status === 'ready') return summary;
      if (summary.status === 'failed') throw new Error(`the build failed: ${summary.failure}`);
      const percent = Math.round(100 * summary.progress);
      viewer.emit('status', `${summary.name}: ${summary.status} ${percent}%`);
      await new Promise((resolve) => setTimeout(resolve, POLL_MS));
    }
  }

  async function open(id) {
    const ticket = ++opened;
    [info, state, target, bytes, failed] = [null, null, null, 0, null];
    try {
      const summary = await waitUntilReady(id, ticket);
      if (!summary) return;
      viewer.emit('status', `${summary.name}: loading the base level`);
      const base = summary.base_vertices;
      const document = JSON.parse(new TextDecoder().decode(
        await fetchGeometry(`../meshes/${id}/lod?vertices=${base}&format=json`, ticket)));
      if (ticket !== opened) return;
      const appearance = { materialFaces: document.material_faces, materials: null };
      if (document.materials) {
        // the glTF records; their image uris are relative to this document
        const url = new URL(`../meshes/${id}/materials`, window.location.href).href;
        appearance.materials = { document: await (await fetchOk(url)).json(), url };
        if (ticket !== opened) return;
      }
      info = summary;
      state = LodState.fromJson(document, { vertexCapacity: info.vertices,
                                            faceCapacity: info.faces });
      target = state.level;
      viewer.emit('mesh', { info, state, appearance,
                            curve: new ErrorCurve(info, document.error) });
      viewer.emit('level', { state, bytes, dirty: state.takeDirty() });
      goto(Math.round(settings.initialRatio * info.vertices));
    } catch (error) {
      if (ticket === opened) stop(error);
    }
  }

  function stop(error) {
    failed = error;
    viewer.emit('status', `error: ${error.message}`);
  }

  function goto(level) {
    if (!state || failed || !Number.isFinite(level)) return;
    target = Math.min(info.vertices, Math.max(info.base_vertices, Math.round(level)));
    viewer.emit('target', target);
    // A loop left from a mesh opened before ends by itself; this mesh needs its own.
    if (!moving || moving.ticket !== opened) {
      const run = { ticket: opened };
      run.done = move(opened).finally(() => { if (moving === run) moving = null; });
      moving = run;
    }
  }

  // The next level on the way from `from` to `to`: the nearest chunk boundary.
  function nextStop(from, to) {
    const chunk = settings.chunkSplits;
    return to > from ? Math.min(to, (Math.floor(from / chunk) + 1) * chunk)
                     : Math.max(to, (Math.ceil(from / chunk) - 1) * chunk);
  }

  // Follows `target` (which may change meanwhile) one packet at a time.
  async function move(ticket) {
    try {
      while (ticket === opened && state.level !== target) {
        const from = state.level, to = nextStop(from, target);
        const verb = to > from ? 'refining' : 'coarsening';
        viewer.emit('status', `${info.name}: ${verb} to ${target}`);
        const packet = await LodState.readPacket(
          await fetchGeometry(`../meshes/${info.id}/splits?from=${from}&to=${to}`, ticket));
        if (ticket !== opened) return;
        const started = performance.now();
        const records = state.apply(packet);
        const applyMs = performance.now() - started;
        viewer.emit('level', { state, bytes, records, applyMs, dirty: state.takeDirty() });
      }
      if (ticket === opened) viewer.emit('status', `${info.name}`);
    } catch (error) {
      if (ticket === opened) stop(error);
    }
  }

  viewer.on('open', (id) => { opening = open(id); });
  viewer.on('goto', goto);

  return {
    get info() { return info; },
    get state() { return state; },
    get target() { return target; },
    get bytes() { return bytes; },
    get busy() { return moving !== null; },
    get failed() { return failed; },
    // Resolves once the mesh is open, its level reached the target and nothing is in flight.
    async settled() {
      await opening;
      while (moving) await moving.done;
    },
  };
}
