// When the stream (stream.js) reports the packets it applied ('level'): at
// most once per animation frame, spaced by options.reportGap times what a
// drawn frame costs the main thread, and held while the rest of the way is
// about to be in hand.
//
// Packets applied between two reports are reported together (their dirty
// ranges merged by the state), so the scene updates its buffers and draws
// once. What a frame costs is measured from the frame's first callback to a
// task posted from it. Under software GL (headless Chromium) a frame blocks
// the main thread for a long while (the canvas is read back for the
// compositor), so drawing every packet's level would leave the decoder a
// fraction of the time; spaced, at least reportGap / (reportGap + 1) of it
// goes to streaming. No packet is applied between a report and the frame
// drawing it (afterFrame()): three.js uploads the reported ranges at the
// draw, from the arrays the decoder changes, so a packet applied meanwhile
// would show half-uploaded.

export class ReportPacer {
  // option(key): the stream's settings (reportGap); emit(pending): reports
  // { records, applyMs, morph }; rest(): the rest of the way's estimate,
  // { ms, arriving } (see holding()) or null when it cannot be told.
  constructor(option, { emit, rest }) {
    this.option = option;
    this.emit = emit;
    this.rest = rest;
    this.frameCostMs = 16;      // what a drawn frame costs the main thread (moving average)
    this.waiting = [];          // resolvers of afterFrame()
    this.reset();
  }

  // Drops what is pending (another mesh, a stop).
  reset() {
    this.pending = null;        // applied, not yet reported: { records, applyMs, morph }
    if (this.timer) clearTimeout(this.timer);
    this.timer = 0;             // the timeout of a report waiting for its gap
    if (this.holdTimer) clearTimeout(this.holdTimer);
    this.holdTimer = 0;
    this.holdUntil = null;      // a report held for the rest arriving, until then (holding)
    this.framed = true;         // an animation frame has run since the last report
    this.reportedAt ??= -Infinity;   // performance.now() of the last report
    this.frame ??= 0;           // a requestAnimationFrame since the last report, pending
    for (const resolve of this.waiting.splice(0)) resolve();
  }

  // A packet of `records` applied in applyMs (morph: the geomorph glides it).
  add(records, applyMs) {
    const { pending } = this;
    this.pending = { records: (pending?.records ?? 0) + records,
                     applyMs: (pending?.applyMs ?? 0) + applyMs, morph: pending?.morph ?? false };
  }

  // Resolves once the last report's frame is drawn (at once if it is).
  afterFrame() {
    return this.framed ? Promise.resolve() : new Promise((resolve) => this.waiting.push(resolve));
  }

  // Reports what is pending, now.
  now() {
    if (this.timer) clearTimeout(this.timer);
    this.timer = 0;
    const { pending } = this;
    if (!pending) return;
    this.pending = null;
    this.holdUntil = null;
    this.reportedAt = performance.now();
    this.framed = false;
    // The next frame draws this level; a message posted from its first
    // callback runs once the frame is done: the delay is what it cost.
    if (!this.frame) this.frame = requestAnimationFrame(() => {
      const drawn = performance.now();
      const channel = new MessageChannel();
      channel.port1.onmessage = () => {
        this.frame = 0;
        this.frameCostMs = 0.5 * this.frameCostMs + 0.5 * (performance.now() - drawn);
        this.framed = true;
        for (const resolve of this.waiting.splice(0)) resolve();
        this.soon();
      };
      channel.port2.postMessage(null);
    });
    this.emit(pending);
  }

  // Reports once a frame has run since the last report and the gap has passed.
  soon() {
    if (!this.pending || this.timer || !this.framed || this.holding()) return;
    const wait = this.reportedAt + this.option('reportGap') * this.frameCostMs - performance.now();
    if (wait <= 0) this.now();
    else this.timer = setTimeout(() => {
      this.timer = 0;
      this.soon();
    }, wait);
  }

  // Whether the rest of the way to the target has arrived and applying it should
  // take less than a drawn frame costs: then a frame of the level between is
  // not worth its cost (under software GL a frame of a million triangles blocks
  // the main thread for seconds) and the report waits for the target.
  // Also while the rest is still arriving (rest().arriving), if it should
  // arrive and be applied within a drawn frame's cost: a frame drawn meanwhile
  // would only delay the full level (on a throttled large mesh, by seconds
  // after its last byte). Held at most twice as long as estimated
  // (holdUntil), so a stalling link still shows what has arrived.
  holding() {
    const rest = this.rest();
    if (rest === null || rest.ms >= this.frameCostMs) return false;
    if (!rest.arriving) return true;
    const now = performance.now();
    if (this.holdUntil === null) this.holdUntil = now + 2 * rest.ms;
    if (now < this.holdUntil) {
      // look again then, in case no packet arrives to trigger a report
      if (!this.holdTimer) {
        this.holdTimer = setTimeout(() => {
          this.holdTimer = 0;
          this.soon();
        }, this.holdUntil - now + 1);
      }
      return true;
    }
    return false;
  }
}
