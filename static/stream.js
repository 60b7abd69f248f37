// Fetching a mesh's level from its source (source.js, which has its summary):
// a first level (the base unless the opener names another: the base level and
// one packet to it, in one round trip), its materials if any, then packets
// between levels; from a server at the mesh's version (the summary's `urls`),
// so every response but the summary is cacheable for good. One stream per
// mesh (streamedlevel.js), a scene's part each its own.
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
//   short) is retried with exponential backoff (source.js' withRetries,
//   settings.retries times), the status saying so. When the retries run out the stream stalls with the error shown, and the next
//   'goto' (any move of the level) tries again. A packet the server refuses
//   (another 4xx) or that does not decode stops the mesh: reopen it.
// * Geomorphs: with a geomorph attached (attachGeomorph, see geomorph.js),
//   a collapse batch is applied to the state first, then the vanishing
//   vertices glide into their parents on screen, and only then is the level
//   reported (the scene drops their faces); splits are reported at once and
//   the geomorph glides the new vertices out of their parents.
//
// Signals out (on the bus it is made with): 'mesh' (the first level is in:
// { info: the summary, state, appearance, curve }), 'level' (the state moved: { state, bytes,
// records, applyMs, morph (glide it: geomorph.js), dirty }),
// 'target' (the level being moved to), 'status' (text for the user),
// 'stream' (the stream's state: { state: 'moving'|'retrying'|'stalled'|'idle'|'failed', ... };
// 'moving' has restMs, the rest of the way's estimated time on the link: see restEstimateMs).
// Signals in: 'goto' (a level).

import { ErrorCurve } from './curve.js';
import { PacketQueue } from './packetqueue.js';
import { PacketSizer } from './packetsizer.js';
import { ReportPacer } from './reportpacer.js';
import { FetchError, snapLevel, withRetries } from './source.js';
import { LodState, PacketError } from './vsplit.js';

const MAX_AHEAD = 32;              // the most packets requested ahead (see packetsAhead)
// Defaults of the settings this module reads (main.js may set them).
export const STREAM_DEFAULTS = { chunkSplits: 4096, packetsAhead: 2, frameBudgetMs: 12,
                                 packetPaceMs: 250, retries: 6, reportGap: 3, initialRatio: 1 };

// Yields to the event loop (so a due frame is drawn), without the >= 4 ms
// clamp of nested setTimeout.
function yieldTask() {
  return new Promise((resolve) => {
    const channel = new MessageChannel();
    channel.port1.onmessage = () => resolve();
    channel.port2.postMessage(null);
  });
}

// Applies packets in order; the records applied.
function applyAll(state, packets) {
  return packets.reduce((records, packet) => records + state.apply(packet), 0);
}

// One mesh's stream (a scene streams each part with its own). Its bus
// `viewer` (bus.js: a StreamedLevel's) carries its settings (STREAM_DEFAULTS' keys)
// and its signals (see the top).
export class PacketStream {
  constructor(viewer) {
    this.viewer = viewer;
    this.info = null;           // GET /meshes/{id}
    this.source = null;         // where the records come from (source.js)
    this.state = null;          // the level held
    this.target = null;
    this.bytes = 0;             // geometry bytes received: the first level and packets
    this.opened = 0;            // counts opens, so work for a mesh closed meanwhile stops
    this.opening = null;        // the running open(), if any
    this.moving = null;         // the running move() of this mesh: { ticket, done }
    this.failed = null;         // the error that stopped the mesh, if any
    this.stalled = null;        // the transient error the retries ran out on, if any
    this.shown = null;          // the level last reported by 'level'
    this.geomorph = null;       // the geomorph (geomorph.js) coarsening waits for
    this.counts = { packets: 0, retries: 0, largest: 0 };
    const option = (key) => this.option(key);
    this.sizer = new PacketSizer(option);   // the packets' size, from the link and the rate
    // packets requested ahead, in order (of the mesh open when each was asked for)
    this.queue = new PacketQueue((from, to, signal) => this.fetchPacket(
      this.info, from, to, signal, this.opened));
    // when the applied packets are reported ('level')
    this.pacer = new ReportPacer(option, { emit: (pending) => this.emitLevel(pending),
                                           rest: () => this.restOfTheWay() });
    viewer.on('goto', (level) => this.goto(level));
  }

  option(key) {
    return this.viewer.settings[key] ?? STREAM_DEFAULTS[key];
  }

  get busy() { return this.moving !== null; }
  get packetSize() { return this.sizer.size; }
  get stats() { return { ...this.counts, aborted: this.queue.aborted }; }

  emitStream(name, extra = {}) {
    this.viewer.emit('stream', { state: name, level: this.state?.level ?? null,
                                 target: this.target, size: this.sizer.size, ...extra });
  }

  async fetchBase(level, ticket) {
    const buffer = await this.source.base(level);
    if (ticket === this.opened) this.bytes += buffer.byteLength;
    return buffer;
  }

  // Opens the mesh of `source` (source.js: a ServerSource, a file) at a
  // first level (see openMesh); resolves once it is open.
  open(source, options = {}) {
    this.opening = this.openMesh(source, options);
    return this.opening;
  }

  // Opens the mesh of `source` at `level` (vertices; the base level by
  // default). That level arrives in one round trip: the base level (json: the
  // grid and the state packets start from) and the one packet from the base
  // to it, fetched together, and nothing is drawn until both are in. A packet
  // costs 8-12 bytes a vertex against the json form's ~50 (120 with
  // attributes). Packets then refine it to settings.initialRatio of the
  // vertices. `materials: false` leaves the materials to the caller (a scene's
  // part: its GLB's).
  async openMesh(source, { level, materials: withMaterials = true } = {}) {
    const ticket = ++this.opened;
    this.stopMoving();
    [this.info, this.state, this.target, this.bytes] = [null, null, null, 0];
    [this.failed, this.stalled, this.shown] = [null, null, null];
    this.sizer.reset();
    this.source = source;
    const { summary } = source;
    try {
      let first = level;
      const base = summary.base_vertices;
      first = snapLevel(this.source, Number.isFinite(first)
        ? Math.min(summary.vertices, Math.max(base, Math.round(first))) : base);
      this.viewer.emit('status', `${summary.name}: loading level ${first}`);
      const baseLevel = this.fetchBase(base, ticket);
      // (retried as any packet; not aborted: a new open() drops it by its ticket)
      const packet = first > base
        ? this.fetchPacket(summary, base, first, new AbortController().signal, ticket)
        : null;
      packet?.catch(() => {});          // awaited below, after the base level
      const document = JSON.parse(new TextDecoder().decode(await baseLevel));
      if (ticket !== this.opened) return;
      const appearance = { materialFaces: document.material_faces, materials: null };
      const materials = document.materials && withMaterials
        // the glTF records; their image uris are relative to this document
        ? this.source.materials() : null;
      const held = LodState.fromJson(document, { vertexCapacity: summary.vertices,
                                                 faceCapacity: summary.faces });
      // a first packet that fails (after its retries) leaves the base shown,
      // the failure handled as any packet's (see move())
      let refused = null;
      if (packet) {
        try {
          const got = await packet;
          if (ticket !== this.opened) return;
          applyAll(held, got.packets);
          this.bytes += got.bytes;
        } catch (error) {
          refused = error;
        }
      }
      if (materials) appearance.materials = await materials;
      if (ticket !== this.opened) return;
      this.info = summary;
      this.state = held;
      this.target = this.queue.planned = this.shown = this.state.level;
      this.viewer.emit('mesh', { info: this.info, state: this.state, appearance,
                            curve: new ErrorCurve(this.info, document.error) });
      this.viewer.emit('level', { state: this.state, bytes: this.bytes,
                                  dirty: this.state.takeDirty() });
      if (refused) this.fail(refused);
      else this.goto(Math.round(this.option('initialRatio') * this.info.vertices),
                     { opening: true });
    } catch (error) {
      if (ticket === this.opened) this.stop(error);
    }
  }

  stop(error) {
    this.failed = error;
    this.queue.abort(0, this.state?.level ?? null);
    this.viewer.emit('status', `error: ${error.message}`);
    this.emitStream('failed', { error: error.message });
  }

  goto(level, { opening: first = false } = {}) {
    if (!this.state || this.failed || !Number.isFinite(level)) return;
    const { vertices, base_vertices: base } = this.info;
    this.target = snapLevel(this.source, Math.min(vertices, Math.max(base, Math.round(level))));
    this.viewer.emit('target', this.target);
    if (this.stalled) {
      this.stalled = null;           // a move of the level retries a stalled stream
      this.queue.planned = this.state.level;
    }
    this.queue.trim(this.state.level, this.target);
    this.refill();
    if (!this.moving || this.moving.ticket !== this.opened) {
      const run = { ticket: this.opened, opening: first };
      run.done = this.move(run).finally(() => { if (this.moving === run) this.moving = null; });
      this.moving = run;
    } else if (!first) this.moving.opening = false;
  }

  // ---- packets ahead ---------------------------------------------------------------

  // One packet of mesh `summary`, retried with backoff while the failure is transient.
  async fetchPacket(summary, from, to, signal, ticket) {
    const records = this.source;         // this mesh's, whatever is opened meanwhile
    const retries = this.option('retries');
    return withRetries(async () => {
      // (a progressive file's source answers several chunks: one packet each)
      const { buffer, buffers = [buffer], url } = await records.packet(from, to, { signal });
      const packets = [];
      for (const one of buffers) packets.push(await LodState.readPacket(one));
      return { packets, bytes: buffers.reduce((n, one) => n + one.byteLength, 0), url };
    }, {
      retries, signal, giveUp: () => ticket !== this.opened,
      onRetry: ({ attempt, delayMs, error }) => {
        this.counts.retries++;
        this.viewer.emit('status', `${summary.name}: a packet failed (${error.message}); ` +
                         `retrying in ${(delayMs / 1000).toFixed(1)} s (attempt ${attempt + 1} ` +
                         `of ${retries + 1})`);
        this.emitStream('retrying', { attempt, delayMs, error: error.message });
      },
    });
  }

  // Packets in flight: settings.packetsAhead, or, where a drawn frame blocks
  // the main thread for long (software GL: seconds at a million triangles),
  // enough to keep the link busy through a frame and its gap (reportGap frames)
  // at packetPaceMs a packet: no packet is requested while the thread is
  // blocked, and two packets ahead would leave the link idle for most of each
  // frame (bench/viewer measures it on a throttled large mesh). At most MAX_AHEAD.
  packetsAhead() {
    const gap = this.option('reportGap') + 1;
    const covered = this.pacer.frameCostMs * gap / this.option('packetPaceMs');
    return Math.max(1, this.option('packetsAhead'), Math.min(MAX_AHEAD, Math.ceil(covered)));
  }

  refill() {
    if (!this.state || this.failed || this.stalled) return;
    const { source, sizer } = this;
    // a progressive file cuts its own runs of chunks (staticsource.js)
    const cut = source.nextStop ? (from, to) => source.nextStop(from, to, sizer.size)
      : (from, to) => sizer.nextStop(from, to);
    this.queue.refill(this.target, this.packetsAhead(), cut);
  }

  // ---- applying ----------------------------------------------------------------------

  // Reports the packets applied since the last one (ReportPacer decides when).
  emitLevel({ records, applyMs, morph = false }) {
    if (!this.state) return;
    this.shown = this.state.level;
    this.viewer.emit('level', { state: this.state, bytes: this.bytes, records, applyMs, morph,
                                dirty: this.state.takeDirty() });
  }

  // The rest of the way to the target, for ReportPacer.holding(): { ms: its
  // time to arrive and be applied, arriving: whether some is still on the
  // link }, or null (more packets to ask for, nothing measured yet).
  restOfTheWay() {
    const { rate } = this.sizer;
    if (this.queue.planned !== this.target || !(rate > 0)) return null;
    const { all: records, missing } = this.queue.records();
    if (missing === 0) return { ms: records / rate, arriving: false };
    const arriveMs = this.sizer.linkMs(missing, 1);
    return arriveMs === null ? null : { ms: arriveMs + records / rate, arriving: true };
  }

  // How long the rest of the way to the target should take to cross the link,
  // ms: its bytes (a record's as in the packets so far) over the link's rate;
  // null before a packet has been measured. Time the page spends waiting on
  // the link, not on its own work (decoding competes with the GPU's for the
  // cores under software GL): scene.js makes the environment at once when
  // this is long enough to hide its GPU work.
  restEstimateMs() {
    if (!this.state || this.target === null) return null;
    return this.sizer.linkMs(Math.abs(this.target - this.state.level));
  }

  // Follows `target` (which may change meanwhile), the queued packets in order.
  async move(run) {
    const { ticket } = run;
    let sliceStart = performance.now();
    try {
      while (ticket === this.opened && !this.failed && !this.stalled) {
        this.refill();
        const { head } = this.queue;
        if (!head) break;
        const verb = head.to > head.from ? 'refining' : 'coarsening';
        this.viewer.emit('status', `${this.info.name}: ${verb} to ${this.target}`);
        this.emitStream('moving', { restMs: this.restEstimateMs() });
        let got;
        try {
          got = await head.result;
        } catch (error) {
          if (ticket !== this.opened) return;
          if (head.controller.signal.aborted) continue;     // dropped by a new target
          throw error;
        }
        if (ticket !== this.opened) return;
        if (this.queue.head !== head) continue;                  // dropped while arriving
        if (!this.pacer.framed) {
          await this.pacer.afterFrame();
          if (ticket !== this.opened) return;
          if (this.queue.head !== head) continue;
        }
        this.queue.shift();
        const started = performance.now();
        const records = applyAll(this.state, got.packets);
        const applyMs = performance.now() - started;
        this.bytes += got.bytes;
        this.counts.packets++;
        this.counts.largest = Math.max(this.counts.largest, records);
        this.pacer.add(records, applyMs);
        this.sizer.measure(got.url, got.bytes, records, applyMs, this.pacer.frameCostMs);
        const backward = head.to < head.from;
        const morphing = this.geomorph && !run.opening && this.geomorph.enabled();
        if (backward && morphing) {
          // apply what has already arrived in the same direction, then glide
          // the vanishing vertices into their parents, then drop them
          const next = this.queue.head;
          if (next?.ready && next.to < next.from) continue;
          await this.geomorph.coarsen(this.state, this.shown);
          if (ticket !== this.opened) return;
          this.pacer.now();
        } else {
          this.pacer.pending.morph = morphing;       // the geomorph glides the new vertices out
          if (!this.pacer.holding()) this.pacer.soon();
        }
        if (performance.now() - sliceStart > this.option('frameBudgetMs')) {
          await yieldTask();
          sliceStart = performance.now();
        }
      }
      if (ticket !== this.opened) return;
      this.pacer.now();
      if (!this.failed && !this.stalled) {
        this.viewer.emit('status', `${this.info.name}`);
        this.emitStream('idle', { ...this.stats });
      }
    } catch (error) {
      if (ticket !== this.opened) return;
      this.pacer.now();
      this.fail(error);
    }
  }

  // A packet failed: a transient failure the retries ran out on stalls the
  // stream (the next move of the level tries again); any other stops the mesh.
  fail(error) {
    if (error instanceof FetchError && error.transient) {
      this.stalled = error;
      this.queue.abort(0, this.state?.level ?? null);
      this.viewer.emit('status', `error: ${error.message} (move the level to try again)`);
      this.emitStream('stalled', { error: error.message });
    } else {
      this.stop(error instanceof PacketError || error instanceof FetchError ? error
        : new Error(`the packet could not be applied (${error.message})`));
    }
  }

  stopMoving() {
    this.queue.clear();
    this.pacer.reset();
  }

  // Stops streaming (a scene's part when the scene is closed): nothing more
  // is fetched or reported.
  close() {
    this.opened++;
    this.stopMoving();
    [this.info, this.state, this.target] = [null, null, null];
    [this.opening, this.source] = [null, null];
  }

  // The geomorph (geomorph.js) that coarsening waits for.
  attachGeomorph(morph) {
    this.geomorph = morph;
  }

  // Resolves once the mesh is open, its level reached the target, nothing is
  // in flight and no geomorph is running.
  async settled() {
    await this.opening;
    while (this.moving) await this.moving.done;
    await this.geomorph?.idle();
  }
}
