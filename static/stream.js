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
//   packetsAhead()), each fetched and inflated as it arrives, and applied
//   strictly in order. A packet that no longer leads to the target (the
//   target moved back) is aborted.
// * Adaptive packets: a packet is `size` records, cut at multiples of `size`
//   (so moving back and forth asks for the same packets again, which the
//   browser cache answers: the server marks them immutable). `size` starts at
//   settings.chunkSplits; after each packet it is set to the largest size
//   that both decodes+applies within settings.frameBudgetMs (or half a drawn
//   frame's cost, when that is longer) at the rate lately measured, and crosses the link within settings.packetPaceMs (latency plus
//   bytes over the bandwidth, both from the packet's Resource Timing entry,
//   which main-thread stalls do not distort), growing at most 4x a packet.
//   Sizes are powers of two times chunkSplits (up to MAX_SPLITS), so the cuts
//   of every size line up.
// * At most one 'level' signal per animation frame: packets applied between
//   two reports are reported together (their dirty ranges merged by the
//   state), so the scene updates its buffers and draws once. Reports are also
//   spaced by settings.reportGap times what a frame costs the main thread
//   (measured: from the frame's first callback to a task posted from it).
//   Under software GL (headless Chromium) a frame blocks the main thread for
//   a long while (the canvas is read back for the compositor), so
//   drawing every packet's level would leave the decoder a fraction of the
//   time; spaced, at least reportGap / (reportGap + 1) of it goes to
//   streaming. The work between two yields is cut at frameBudgetMs. No
//   packet is applied between a report and the frame drawing it: three.js
//   uploads the reported ranges at the draw, from the arrays the decoder
//   changes, so a packet applied meanwhile would show half-uploaded.
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
import { FetchError, routeUrl, ServerSource, sleep } from './source.js';
import { LodState, PacketError } from './vsplit.js';

// (tools.js and animated.js take a route's URL from here, where they take the stream)
export { routeUrl };

const MAX_SPLITS = 1 << 18;        // the largest packet asked for (records)
const MAX_AHEAD = 32;              // the most packets requested ahead (see packetsAhead)
const LINK_BODIES = 8;             // packets the link's rate is measured over (see linkOf)
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
  let size = option('chunkSplits');
  let queue = [];             // packets requested ahead, in order: see request()
  let planned = null;         // the level the last queued packet ends at
  let shown = null;           // the level last reported by 'level'
  let pending = null;         // applied, not yet reported: { records, applyMs }
  let frame = 0;              // a requestAnimationFrame since the last report, pending
  let timer = 0;              // the timeout of a report waiting for its gap
  let framed = true;          // an animation frame has run since the last report
  let reportedAt = -Infinity; // performance.now() of the last report
  let frameCostMs = 16;       // what a drawn frame costs the main thread (moving average)
  let rate = 0;               // records applied per ms (see adapt)
  let lastLink = null;        // the link's figures at the last packet (linkOf)
  let receivedBytes = 0, receivedRecords = 0;   // packets' bytes and records so far (this mesh)
  let holdUntil = null;       // a report held for the rest arriving, until then (restInHand)
  let holdTimer = 0;
  let bodies = [];            // [responseStart, responseEnd, bytes] of the last packets (linkOf)
  // The next packet waits for the last report's frame: three.js uploads the
  // reported ranges when it draws, from the very arrays the decoder changes.
  const waiting = [];
  let geomorph = null;
  const stats = { packets: 0, retries: 0, aborted: 0, largest: 0 };

  function emitStream(name, extra = {}) {
    viewer.emit('stream', { state: name, level: state?.level ?? null, target, size, ...extra });
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
    size = option('chunkSplits');
    rate = 0;
    bodies = [];
    [lastLink, receivedBytes, receivedRecords] = [null, 0, 0];
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
      target = planned = shown = state.level;
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
    abortQueue(0);
    viewer.emit('status', `error: ${error.message}`);
    emitStream('failed', { error: error.message });
  }

  function goto(level, { opening: first = false } = {}) {
    if (!state || failed || !Number.isFinite(level)) return;
    target = Math.min(info.vertices, Math.max(info.base_vertices, Math.round(level)));
    viewer.emit('target', target);
    if (stalled) {
      stalled = null;           // a move of the level retries a stalled stream
      planned = state.level;
    }
    trimQueue();
    refill(opened);
    if (!moving || moving.ticket !== opened) {
      const run = { ticket: opened, opening: first };
      run.done = move(run).finally(() => { if (moving === run) moving = null; });
      moving = run;
    } else if (!first) moving.opening = false;
  }

  // ---- packets ahead ---------------------------------------------------------------

  // The next level on the way from `from` to `to`: the nearest multiple of the
  // packet size.
  function nextStop(from, to) {
    return to > from ? Math.min(to, (Math.floor(from / size) + 1) * size)
                     : Math.max(to, (Math.ceil(from / size) - 1) * size);
  }

  // Request the packet from -> to: { from, to, controller, ready, result (a
  // promise of { packet, bytes, url }) }.
  function request(from, to, ticket) {
    const controller = new AbortController();
    const entry = { from, to, controller, ready: false };
    entry.result = fetchPacket(info, from, to, controller.signal, ticket).then((value) => {
      entry.ready = true;
      return value;
    });
    entry.result.catch(() => {});    // awaited (or dropped) by move()
    return entry;
  }

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

  // Drops the queued packets from index `keep` on.
  function abortQueue(keep) {
    for (const entry of queue.splice(keep)) {
      stats.aborted++;
      entry.controller.abort();
    }
    planned = queue.length ? queue[queue.length - 1].to : state?.level ?? null;
  }

  // Keeps the queued packets that still lead from the state toward the target.
  function trimQueue() {
    if (!state) return;
    const forward = target > state.level;
    let keep = 0;
    for (const { from, to } of queue) {
      const toward = forward ? to > from && to <= target : to < from && to >= target;
      if (!toward || target === state.level) break;
      keep++;
    }
    abortQueue(keep);
  }

  // Packets in flight: settings.packetsAhead, or, where a drawn frame blocks
  // the main thread for long (software GL: seconds at a million triangles),
  // enough to keep the link busy through a frame and its gap (reportGap frames)
  // at packetPaceMs a packet: no packet is requested while the thread is
  // blocked, and two packets ahead would leave the link idle for most of each
  // frame (bench/viewer measures it on a throttled large mesh). At most MAX_AHEAD.
  function packetsAhead() {
    const covered = frameCostMs * (option('reportGap') + 1) / option('packetPaceMs');
    return Math.max(1, option('packetsAhead'), Math.min(MAX_AHEAD, Math.ceil(covered)));
  }

  function refill(ticket) {
    if (!state || failed || stalled) return;
    const ahead = packetsAhead();
    while (queue.length < ahead && planned !== target) {
      const to = nextStop(planned, target);
      queue.push(request(planned, to, ticket));
      planned = to;
    }
  }

  // ---- applying ----------------------------------------------------------------------

  // Reports the packets applied since the last report, now.
  function report() {
    if (timer) clearTimeout(timer);
    timer = 0;
    if (!pending || !state) return;
    const { records, applyMs, morph = false } = pending;
    pending = null;
    holdUntil = null;
    shown = state.level;
    reportedAt = performance.now();
    framed = false;
    // The next frame draws this level; a message posted from its first
    // callback runs once the frame is done: the delay is what it cost.
    if (!frame) frame = requestAnimationFrame(() => {
      const drawn = performance.now();
      const channel = new MessageChannel();
      channel.port1.onmessage = () => {
        frame = 0;
        frameCostMs = 0.5 * frameCostMs + 0.5 * (performance.now() - drawn);
        framed = true;
        for (const resolve of waiting.splice(0)) resolve();
        reportSoon();
      };
      channel.port2.postMessage(null);
    });
    viewer.emit('level', { state, bytes, records, applyMs, morph, dirty: state.takeDirty() });
  }

  // Reports once a frame has run since the last report and the gap has passed.
  function reportSoon() {
    if (!pending || timer || !framed || restInHand()) return;
    const wait = reportedAt + option('reportGap') * frameCostMs - performance.now();
    if (wait <= 0) report();
    else timer = setTimeout(() => {
      timer = 0;
      reportSoon();
    }, wait);
  }

  // The link's figures for a fetched URL: { latencyMs, bytesPerMs } from its
  // Resource Timing entry (null when there is none, e.g. the buffer is full).
  // Packets in flight together share the link, so one body's bytes over its own
  // time would be a share of the link's rate (and shrink packets the more are
  // ahead): the rate is the bytes of the last few bodies over the time any of
  // them was arriving (the union of their intervals).
  function linkOf(url, bytes) {
    const entries = performance.getEntriesByName(new URL(url, window.location.href).href,
                                                 'resource');
    const entry = entries[entries.length - 1];
    // (another origin's timings are zero unless it sends Timing-Allow-Origin)
    if (!entry || !(entry.responseEnd > 0) || !(entry.responseStart > 0)) return null;
    const latencyMs = Math.max(0, entry.responseStart - entry.requestStart);
    bodies.push([entry.responseStart, entry.responseEnd, bytes]);
    if (bodies.length > LINK_BODIES) bodies.shift();
    const sorted = [...bodies].sort((a, b) => a[0] - b[0]);
    let busyMs = 0, until = -Infinity, total = 0;
    for (const [start, end, size] of sorted) {
      busyMs += Math.max(0, end - Math.max(start, until));
      until = Math.max(until, end);
      total += size;
    }
    return { latencyMs, bytesPerMs: total / Math.max(0.1, busyMs) };
  }

  // The packet size after a packet of `records` records, `bytes` bytes,
  // applied in applyMs, over `link` (see linkOf).
  function adapt(records, bytes, applyMs, link) {
    const chunk = option('chunkSplits');
    // records per ms: the fastest lately (a cold JIT or a GC pause makes one
    // packet slow; the rate decays so a lasting slowdown still shrinks packets)
    rate = Math.max(records / Math.max(applyMs, 0.05), 0.7 * rate);
    // where a drawn frame blocks the main thread longer than the budget (software
    // GL), a packet as long as half a frame costs no responsiveness
    const budget = Math.max(option('frameBudgetMs'), 0.5 * frameCostMs);
    let want = budget * rate;
    if (link) {
      const pace = option('packetPaceMs') - link.latencyMs;
      want = Math.min(want, Math.max(0, pace) * link.bytesPerMs * records / Math.max(bytes, 1));
    }
    want = Math.min(want, 4 * size, MAX_SPLITS);
    let next = chunk;
    while (next * 2 <= want) next *= 2;
    size = next;
  }

  // Whether the rest of the way to the target has arrived and applying it should
  // take less than a drawn frame costs: then a frame of the level between is
  // not worth its cost (under software GL a frame of a million triangles blocks
  // the main thread for seconds) and the report waits for the target.
  // Also while the rest is still arriving, if it should arrive (at the link's
  // rate, bytesPerRecord of the packets so far) and be applied within a drawn
  // frame's cost: a frame drawn meanwhile would only delay the full level
  // (on a throttled large mesh, by seconds after its last byte). Held at most
  // twice as long as estimated (holdUntil), so a stalling link still shows
  // what has arrived.
  function restInHand() {
    if (planned !== target || !(rate > 0)) return false;
    let records = 0, missing = 0;
    for (const entry of queue) {
      const count = Math.abs(entry.to - entry.from);
      records += count;
      if (!entry.ready) missing += count;
    }
    if (missing === 0) return records / rate < frameCostMs;
    if (!lastLink || !(receivedRecords > 0)) return false;
    const arriveMs = lastLink.latencyMs
      + missing * (receivedBytes / receivedRecords) / lastLink.bytesPerMs;
    const restMs = arriveMs + records / rate;
    const now = performance.now();
    if (restMs >= frameCostMs) return false;
    if (holdUntil === null) holdUntil = now + 2 * restMs;
    if (now < holdUntil) {
      // look again then, in case no packet arrives to trigger a report
      if (!holdTimer) holdTimer = setTimeout(() => { holdTimer = 0; reportSoon(); },
                                             holdUntil - now + 1);
      return true;
    }
    return false;
  }

  // How long the rest of the way to the target should take to cross the link,
  // ms: its bytes (a record's as in the packets so far) over the link's rate;
  // null before a packet has been measured. Time the page spends waiting on
  // the link, not on its own work (decoding competes with the GPU's for the
  // cores under software GL): scene.js makes the environment at once when
  // this is long enough to hide its GPU work.
  function restEstimateMs() {
    if (!state || target === null || !(receivedRecords > 0) || !lastLink) return null;
    const records = Math.abs(target - state.level);
    return records * (receivedBytes / receivedRecords) / lastLink.bytesPerMs;
  }

  // Follows `target` (which may change meanwhile), the queued packets in order.
  async function move(run) {
    const { ticket } = run;
    let sliceStart = performance.now();
    try {
      while (ticket === opened && !failed && !stalled) {
        refill(ticket);
        const head = queue[0];
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
        if (queue[0] !== head) continue;                    // dropped while arriving
        if (!framed) {
          await new Promise((resolve) => waiting.push(resolve));
          if (ticket !== opened) return;
          if (queue[0] !== head) continue;
        }
        queue.shift();
        const started = performance.now();
        const records = state.apply(got.packet);
        const applyMs = performance.now() - started;
        bytes += got.bytes;
        stats.packets++;
        stats.largest = Math.max(stats.largest, records);
        pending = { records: (pending?.records ?? 0) + records,
                    applyMs: (pending?.applyMs ?? 0) + applyMs, morph: pending?.morph ?? false };
        lastLink = linkOf(got.url, got.bytes) ?? lastLink;
        receivedBytes += got.bytes;
        receivedRecords += records;
        adapt(records, got.bytes, applyMs, lastLink);
        const backward = head.to < head.from;
        const morphing = geomorph && !run.opening && geomorph.enabled();
        if (backward && morphing) {
          // apply what has already arrived in the same direction, then glide
          // the vanishing vertices into their parents, then drop them
          if (queue[0]?.ready && queue[0].to < queue[0].from) continue;
          await geomorph.coarsen(state, shown);
          if (ticket !== opened) return;
          report();
        } else {
          pending.morph = morphing;             // the geomorph glides the new vertices out
          if (!restInHand()) reportSoon();
        }
        if (performance.now() - sliceStart > option('frameBudgetMs')) {
          await yieldTask();
          sliceStart = performance.now();
        }
      }
      if (ticket !== opened) return;
      report();
      if (!failed && !stalled) {
        viewer.emit('status', `${info.name}`);
        emitStream('idle', { ...stats });
      }
    } catch (error) {
      if (ticket !== opened) return;
      report();
      fail(error);
    }
  }

  // A packet failed: a transient failure the retries ran out on stalls the
  // stream (the next move of the level tries again); any other stops the mesh.
  function fail(error) {
    if (error instanceof FetchError && error.transient) {
      stalled = error;
      abortQueue(0);
      viewer.emit('status', `error: ${error.message} (move the level to try again)`);
      emitStream('stalled', { error: error.message });
    } else {
      stop(error instanceof PacketError || error instanceof FetchError ? error
        : new Error(`the packet could not be applied (${error.message})`));
    }
  }

  function stopMoving() {
    for (const entry of queue) entry.controller.abort();
    queue = [];
    pending = null;
    if (timer) clearTimeout(timer);
    timer = 0;
    if (holdTimer) clearTimeout(holdTimer);
    [holdTimer, holdUntil] = [0, null];
    framed = true;
    for (const resolve of waiting.splice(0)) resolve();
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
    get packetSize() { return size; },
    get stats() { return { ...stats }; },
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
