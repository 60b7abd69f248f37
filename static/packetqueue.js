// The packets the stream (stream.js) has asked for ahead along the way to its
// target, in order: each fetched and inflated as it arrives, applied strictly
// in order by the stream, aborted once it no longer leads to the target (the
// target moved back).

export class PacketQueue {
  // fetchPacket(from, to, signal): a promise of { packets, bytes, url }.
  constructor(fetchPacket) {
    this.fetchPacket = fetchPacket;
    this.entries = [];          // { from, to, controller, ready, result }, in order
    this.planned = null;        // the level the last entry ends at
    this.aborted = 0;           // entries dropped so far
  }

  get head() { return this.entries[0] ?? null; }

  shift() { return this.entries.shift(); }

  // Asks for the packet from -> to: an entry whose `result` is a promise of
  // { packets, bytes, url }, `ready` once it is in.
  request(from, to) {
    const controller = new AbortController();
    const entry = { from, to, controller, ready: false };
    entry.result = this.fetchPacket(from, to, controller.signal).then((value) => {
      entry.ready = true;
      return value;
    });
    entry.result.catch(() => {});    // awaited (or dropped) by the stream
    this.entries.push(entry);
    this.planned = to;
    return entry;
  }

  // Drops the entries from index `keep` on; `level` (the level held) is then
  // where the way on starts if none is left.
  abort(keep, level) {
    for (const entry of this.entries.splice(keep)) {
      this.aborted++;
      entry.controller.abort();
    }
    this.planned = this.entries.length ? this.entries[this.entries.length - 1].to : level;
  }

  // Drops every entry (another mesh, a stop): not counted as aborted.
  clear() {
    for (const entry of this.entries) entry.controller.abort();
    this.entries = [];
  }

  // Keeps the entries that still lead from `level` toward `target`.
  trim(level, target) {
    const forward = target > level;
    let keep = 0;
    for (const { from, to } of this.entries) {
      const toward = forward ? to > from && to <= target : to < from && to >= target;
      if (!toward || target === level) break;
      keep++;
    }
    this.abort(keep, level);
  }

  // Asks for packets toward `target` until `ahead` are in flight, cut by
  // nextStop(from, to) (packetsizer.js).
  refill(target, ahead, nextStop) {
    while (this.entries.length < ahead && this.planned !== target) {
      this.request(this.planned, nextStop(this.planned, target));
    }
  }

  // The records of the entries, and of those still arriving.
  records() {
    let all = 0, missing = 0;
    for (const entry of this.entries) {
      const count = Math.abs(entry.to - entry.from);
      all += count;
      if (!entry.ready) missing += count;
    }
    return { all, missing };
  }
}
