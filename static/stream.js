// Fetching a mesh: its summary, a first level (the base unless the opener
// names another: the base level and one packet to it, in one round trip), its
// materials if any, then packets between levels; at the mesh's version (the
// summary's `urls`), so every response but the summary is cacheable for good.
//
// The client never refetches a level: it holds one LodState and moves it to
// the target level packet by packet, forward (splits) or backward (collapses).
//
// Fast streaming:
// * Pipelined: settings.packetsAhead packets are requested ahead along the
//   way to the target (more where frames block the main thread for long:
//   packetsAhead()), applied strictly in order (packetqueue.js).
// * Adaptive packets: the packets' size follows the rate they are applied at
//   and the link they come over (packetsizer.js).
// * At most one 'level' signal per animation frame, spaced by what frames
//   cost, and no packet applied between a report and the frame drawing it
//   (reportpacer.js).
// * Retries: a failed request (network error, 408, 429, 5xx, a body cut
//   short) is retried with exponential backoff (RETRY_BASE_MS doubling, up to
//   RETRY_MAX_MS, settings.retries times), the status saying so. When the
//   retries run out the stream stalls with the error shown, and the next
//   'goto' (any move of the level) tries again. A packet the server refuses
//   (another 4xx) or that does not decode stops the mesh: reopen it.
// * Geomorphs: with a geomorph attached (attachGeomorph, see geomorph.js),
//   a collapse batch is applied to the state first, then the vanishing
//   vertices glide into their parents on screen, and only then is the level
//   reported (the scene drops their faces); splits are reported at once and
//   the geomorph glides the new vertices out of their parents.
//
// Signals out: 'mesh' (a new mesh is shown), 'level' (the state moved: { state, bytes,
// records, applyMs, morph (glide it: geomorph.js), dirty }),
// 'target' (the level being moved to), 'status' (text for the user),
// 'stream' (the stream's state: { state: 'moving'|'retrying'|'stalled'|'idle'|'failed', ... };
// 'moving' has restMs, the rest of the way's estimated time on the link: see restEstimateMs).
// Signals in: 'open' (a mesh id, or { id, level }: see open()), 'goto' (a level).

import { ErrorCurve } from './curve.js';
import { PacketQueue } from './packetqueue.js';
import { PacketSizer } from './packetsizer.js';
import { ReportPacer } from './reportpacer.js';
import { FetchError, routeUrl, ServerSource, sleep } from './source.js';
import { LodState, PacketError } from './vsplit.js';

// (tools.js and animated.js take a route's URL from here, where they take the stream)
export { routeUrl };

const MAX_AHEAD = 32;              // the most packets requested ahead (see packetsAhead)
const RETRY_BASE_MS = 250;
const RETRY_MAX_MS = 8000;
// Defaults of the settings this module reads (main.js may set them).
const DEFAULTS = { chunkSplits: 4096, packetsAhead: 2, frameBudgetMs: 12, packetPaceMs: 250,
                   retries: 6, reportGap: 3, initialRatio: 1 };

// Yields to the event loop (so a due frame is drawn), without the >= 4 ms
// clamp of nested setTimeout.
function yieldTask() {
  return new Promise((resolve) => {
    const channel = new MessageChannel();
    channel.port1.onmessage = () => resolve();
    channel.port2.postMessage(null);
  });
}

export function createStream(viewer) {
  const { settings } = viewer;
  const option = (key) => settings[key] ?? DEFAULTS[key];
  let info = null;            // GET /meshes/{id}
  let source = null;          // where the records come from (source.js)
  let state = null;           // the level held
  let target = null;
  let bytes = 0;              // geometry bytes received: the first level and packets
  let opened = 0;             // counts opens, so work for a mesh closed meanwhile stops
  let opening = null;         // the running open(), if any
  let moving = null;          // the running move() of this mesh: { ticket, done }
  let failed = null;          // the error that stopped the mesh, if any
  let stalled = null;         // the transient error the retries ran out on, if any
  const sizer = new PacketSizer(option);   // the packets' size, from the link and the rate
  // packets requested ahead, in order (of the mesh open when each was asked for)
  const queue = new PacketQueue((from, to, signal) => fetchPacket(info, from, to, signal, opened));
  let shown = null;           // the level last reported by 'level'
  // when the applied packets are reported ('level')
  const pacer = new ReportPacer(option, { emit: emitLevel, rest: restOfTheWay });
  let geomorph = null;
  const stats = { packets: 0, retries: 0, largest: 0 };

  function emitStream(name, extra = {}) {
    viewer.emit('stream', { state: name, level: state?.level ?? null, target, size: sizer.size,
                            ...extra });
  }

  async function fetchBase(level, ticket) {
    const buffer = await source.base(level);
    if (ticket === opened) bytes += buffer.byteLength;
    return buffer;
  }

  // The source of a mesh once it is built, reporting the build's progress;
  // null once another mesh is opened.
  function waitUntilReady(id, ticket) {
    return ServerSource.open(id, { onProgress(summary) {
      if (ticket !== opened) return false;
      const percent = Math.round(100 * summary.progress);
      viewer.emit('status', `${summary.name}: ${summary.status} ${percent}%`);
      return true;
    } });
  }


  // Opens mesh `id` at `level`: a number of vertices, or a function of the
  // mesh's summary returning one (or a promise of one), e.g. the level a
  // first-frame chooser picks for the view; the base level by default.
  // That level arrives in one round trip: the base level (json: the grid and
  // the state packets start from) and the one packet from the base to it,
  // fetched together, and nothing is drawn until both are in. A packet costs
  // 8-12 bytes a vertex against the json form's ~50 (120 with attributes).
  // Packets then refine it to settings.initialRatio of the vertices.
  //
  // A mesh whose summary says `"scene": true` is not streamed here: the
  // stream emits 'scene' ({ info: the summary, level: the first level chosen,
  // in vertices of the whole scene }) and animated.js takes it from there,
  // opening one stream per part with open(id, { summary: the part's, ... }):
  // a summary given is not fetched (nor is it checked for a scene), and
  // `materials: false` leaves the part's materials to the caller.
  // A source given (source.js: a ServerSource, a file) is read instead of the
  // page's server, its summary as a given one.
  async function open(id, { level, summary: givenSummary = null, source: givenSource = null,
                            materials: withMaterials = true } = {}) {
    const ticket = ++opened;
    stopMoving();
    [info, state, target, bytes, failed, stalled, shown] = [null, null, null, 0, null, null, null];
    sizer.reset();
    const given = givenSource?.summary ?? givenSummary;
    try {
      const found = givenSource ?? (givenSummary ? new ServerSource(givenSummary)
        : await waitUntilReady(id, ticket));
      if (!found || ticket !== opened) return;
      source = found;
      const { summary } = source;
      let first = typeof level === 'function' ? await level(summary) : level;
      if (ticket !== opened) return;
      if (!given && summary.scene === true) {
        info = summary;
        viewer.emit('scene', { info: summary, level: first });
        return;
      }
      const base = summary.base_vertices;
      first = Number.isFinite(first)
        ? Math.min(summary.vertices, Math.max(base, Math.round(first))) : base;
      viewer.emit('status', `${summary.name}: loading level ${first}`);
      const baseLevel = fetchBase(base, ticket);
      // (retried as any packet; not aborted: a new open() drops it by its ticket)
      const packet = first > base
        ? fetchPacket(summary, base, first, new AbortController().signal, ticket)
        : null;
      packet?.catch(() => {});          // awaited below, after the base level
      const document = JSON.parse(new TextDecoder().decode(await baseLevel));
      if (ticket !== opened) return;
      const appearance = { materialFaces: document.material_faces, materials: null };
      const materials = document.materials && withMaterials
        // the glTF records; their image uris are relative to this document
        ? source.materials() : null;
      const held = LodState.fromJson(document, { vertexCapacity: summary.vertices,
                                                 faceCapacity: summary.faces });
      // a first packet that fails (after its retries) leaves the base shown,
      // the failure handled as any packet's (see move())
      let refused = null;
      if (packet) {
        try {
          const got = await packet;
          if (ticket !== opened) return;
          held.apply(got.packet);
          bytes += got.bytes;
        } catch (error) {
          refused = error;
        }
      }
      if (materials) appearance.materials = await materials;
      if (ticket !== opened) return;
      info = summary;
      state = held;
      target = queue.planned = shown = state.level;
      viewer.emit('mesh', { info, state, appearance,
                            curve: new ErrorCurve(info, document.error) });
      viewer.emit('level', { state, bytes, dirty: state.takeDirty() });
      if (refused) fail(refused);
      else goto(Math.round(option('initialRatio') * info.vertices), { opening: true });
    } catch (error) {
      if (ticket === opened) stop(error);
    }
  }

  function stop(error) {
    failed = error;
    queue.abort(0, state?.level ?? null);
    viewer.emit('status', `error: ${error.message}`);
    emitStream('failed', { error: error.message });
  }

  function goto(level, { opening: first = false } = {}) {
    if (!state || failed || !Number.isFinite(level)) return;
    target = Math.min(info.vertices, Math.max(info.base_vertices, Math.round(level)));
    viewer.emit('target', target);
    if (stalled) {
      stalled = null;           // a move of the level retries a stalled stream
      queue.planned = state.level;
    }
    queue.trim(state.level, target);
    refill();
    if (!moving || moving.ticket !== opened) {
      const run = { ticket: opened, opening: first };
      run.done = move(run).finally(() => { if (moving === run) moving = null; });
      moving = run;
    } else if (!first) moving.opening = false;
  }

  // ---- packets ahead ---------------------------------------------------------------

  // One packet of mesh `summary`, retried with backoff while the failure is transient.
  async function fetchPacket(summary, from, to, signal, ticket) {
    const records = source;         // this mesh's, whatever is opened meanwhile
    for (let attempt = 0; ; attempt++) {
      try {
        const { buffer, url } = await records.packet(from, to, { signal });
        const packet = await LodState.readPacket(buffer);
        return { packet, bytes: buffer.byteLength, url };
      } catch (error) {
        if (signal.aborted || ticket !== opened) throw error;
        if (!(error instanceof FetchError && error.transient) || attempt >= option('retries')) {
          throw error;
        }
        const delay = Math.min(RETRY_MAX_MS, RETRY_BASE_MS * 2 ** attempt);
        stats.retries++;
        viewer.emit('status', `${summary.name}: a packet failed (${error.message}); retrying in ` +
                    `${(delay / 1000).toFixed(1)} s (attempt ${attempt + 2} of ` +
                    `${option('retries') + 1})`);
        emitStream('retrying', { attempt: attempt + 1, delayMs: delay, error: error.message });
        await sleep(delay, signal);
      }
    }
  }

  // Packets in flight: settings.packetsAhead, or, where a drawn frame blocks
  // the main thread for long (software GL: seconds at a million triangles),
  // enough to keep the link busy through a frame and its gap (reportGap frames)
  // at packetPaceMs a packet: no packet is requested while the thread is
  // blocked, and two packets ahead would leave the link idle for most of each
  // frame (bench/viewer measures it on a throttled large mesh). At most MAX_AHEAD.
  function packetsAhead() {
    const covered = pacer.frameCostMs * (option('reportGap') + 1) / option('packetPaceMs');
    return Math.max(1, option('packetsAhead'), Math.min(MAX_AHEAD, Math.ceil(covered)));
  }

  function refill() {
    if (!state || failed || stalled) return;
    queue.refill(target, packetsAhead(), (from, to) => sizer.nextStop(from, to));
  }

  // ---- applying ----------------------------------------------------------------------

  // Reports the packets applied since the last one (ReportPacer decides when).
  function emitLevel({ records, applyMs, morph = false }) {
    if (!state) return;
    shown = state.level;
    viewer.emit('level', { state, bytes, records, applyMs, morph, dirty: state.takeDirty() });
  }

  // The rest of the way to the target, for ReportPacer.holding(): { ms: its
  // time to arrive and be applied, arriving: whether some is still on the
  // link }, or null (more packets to ask for, nothing measured yet).
  function restOfTheWay() {
    const { rate } = sizer;
    if (queue.planned !== target || !(rate > 0)) return null;
    const { all: records, missing } = queue.records();
    if (missing === 0) return { ms: records / rate, arriving: false };
    const arriveMs = sizer.linkMs(missing, 1);
    return arriveMs === null ? null : { ms: arriveMs + records / rate, arriving: true };
  }

  // How long the rest of the way to the target should take to cross the link,
  // ms: its bytes (a record's as in the packets so far) over the link's rate;
  // null before a packet has been measured. Time the page spends waiting on
  // the link, not on its own work (decoding competes with the GPU's for the
  // cores under software GL): scene.js makes the environment at once when
  // this is long enough to hide its GPU work.
  function restEstimateMs() {
    if (!state || target === null) return null;
    return sizer.linkMs(Math.abs(target - state.level));
  }

  // Follows `target` (which may change meanwhile), the queued packets in order.
  async function move(run) {
    const { ticket } = run;
    let sliceStart = performance.now();
    try {
      while (ticket === opened && !failed && !stalled) {
        refill();
        const { head } = queue;
        if (!head) break;
        const verb = head.to > head.from ? 'refining' : 'coarsening';
        viewer.emit('status', `${info.name}: ${verb} to ${target}`);
        emitStream('moving', { restMs: restEstimateMs() });
        let got;
        try {
          got = await head.result;
        } catch (error) {
          if (ticket !== opened) return;
          if (head.controller.signal.aborted) continue;     // dropped by a new target
          throw error;
        }
        if (ticket !== opened) return;
        if (queue.head !== head) continue;                  // dropped while arriving
        if (!pacer.framed) {
          await pacer.afterFrame();
          if (ticket !== opened) return;
          if (queue.head !== head) continue;
        }
        queue.shift();
        const started = performance.now();
        const records = state.apply(got.packet);
        const applyMs = performance.now() - started;
        bytes += got.bytes;
        stats.packets++;
        stats.largest = Math.max(stats.largest, records);
        pacer.add(records, applyMs);
        sizer.measure(got.url, got.bytes, records, applyMs, pacer.frameCostMs);
        const backward = head.to < head.from;
        const morphing = geomorph && !run.opening && geomorph.enabled();
        if (backward && morphing) {
          // apply what has already arrived in the same direction, then glide
          // the vanishing vertices into their parents, then drop them
          const next = queue.head;
          if (next?.ready && next.to < next.from) continue;
          await geomorph.coarsen(state, shown);
          if (ticket !== opened) return;
          pacer.now();
        } else {
          pacer.pending.morph = morphing;       // the geomorph glides the new vertices out
          if (!pacer.holding()) pacer.soon();
        }
        if (performance.now() - sliceStart > option('frameBudgetMs')) {
          await yieldTask();
          sliceStart = performance.now();
        }
      }
      if (ticket !== opened) return;
      pacer.now();
      if (!failed && !stalled) {
        viewer.emit('status', `${info.name}`);
        emitStream('idle', { ...stats, aborted: queue.aborted });
      }
    } catch (error) {
      if (ticket !== opened) return;
      pacer.now();
      fail(error);
    }
  }

  // A packet failed: a transient failure the retries ran out on stalls the
  // stream (the next move of the level tries again); any other stops the mesh.
  function fail(error) {
    if (error instanceof FetchError && error.transient) {
      stalled = error;
      queue.abort(0, state?.level ?? null);
      viewer.emit('status', `error: ${error.message} (move the level to try again)`);
      emitStream('stalled', { error: error.message });
    } else {
      stop(error instanceof PacketError || error instanceof FetchError ? error
        : new Error(`the packet could not be applied (${error.message})`));
    }
  }

  function stopMoving() {
    queue.clear();
    pacer.reset();
  }

  viewer.on('open', (detail) => {
    const { id, ...options } = typeof detail === 'object' && detail ? detail : { id: detail };
    opening = open(id, options);
  });
  viewer.on('goto', (level) => goto(level));

  return {
    get info() { return info; },
    get state() { return state; },
    get target() { return target; },
    get bytes() { return bytes; },
    get busy() { return moving !== null; },
    get failed() { return failed; },
    get stalled() { return stalled; },
    get packetSize() { return sizer.size; },
    get stats() { return { ...stats, aborted: queue.aborted }; },
    // Opens a mesh at a first level: open(id, { level }) (see open() above).
    open(id, options = {}) {
      opening = open(id, options);
      return opening;
    },
    // Stops streaming (a scene's part when the scene is closed): nothing more
    // is fetched or reported.
    close() {
      opened++;
      stopMoving();
      [info, state, target, opening, source] = [null, null, null, null, null];
    },
    // The geomorph (geomorph.js) that coarsening waits for.
    attachGeomorph(morph) {
      geomorph = morph;
    },
    // Resolves once the mesh is open, its level reached the target, nothing is
    // in flight and no geomorph is running.
    async settled() {
      await opening;
      while (moving) await moving.done;
      await geomorph?.idle();
    },
  };
}
