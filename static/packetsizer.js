// How many records the stream (stream.js) asks for in a packet, from what the
// last packets cost: the rate they were applied at, and the link they came
// over (latency and bytes per ms, from Resource Timing, which main-thread
// stalls do not distort).
//
// A packet is `size` records, cut at multiples of `size` (so moving back and
// forth asks for the same packets again, which the browser cache answers: the
// server marks them immutable). After each packet `size` is set to the
// largest size that both decodes+applies within options.frameBudgetMs (or
// half a drawn frame's cost, when that is longer) at the rate lately
// measured, and whose body holds the link for at most its pace (see
// adapt), growing at most 4x a packet. Sizes are powers of two times
// options.chunkSplits (up to MAX_SPLITS), so the cuts of every size line up.
//
// The pace is options.packetPaceMs, so that a new target does not wait long
// behind the packets asked for; but never less than the frames between two
// reports take (options.reportGap + 1 drawn frames, reportpacer.js), nor than
// twice the request's round trip (the size is rounded down to a power of two,
// which may halve it). A level shows only at a report, so where a frame
// blocks the main thread for long (software GL: seconds at a million
// triangles) a smaller packet shows nothing sooner, and costs a round trip
// and a plan that reaches the target later (the pacer holds its reports for
// the target only once the whole way is asked for). The round trip is not
// taken out of the pace: requests are pipelined (stream.js), so a request's
// round trip passes while the bodies ahead of it arrive, and those bodies
// cover it only when they are at least as long.

const MAX_SPLITS = 1 << 18;        // the largest packet asked for (records)
const LINK_BODIES = 8;             // packets the link's rate is measured over (see linkOf)

export class PacketSizer {
  // option(key): the stream's settings (chunkSplits, frameBudgetMs, packetPaceMs).
  constructor(option) {
    this.option = option;
    this.reset();
  }

  // A new mesh: nothing measured yet.
  reset() {
    this.size = this.option('chunkSplits');
    this.rate = 0;              // records applied per ms (see adapt)
    this.link = null;           // the link's figures at the last packet (linkOf)
    this.receivedBytes = 0;     // packets' bytes and records so far
    this.receivedRecords = 0;
    this.bodies = [];           // [responseStart, responseEnd, bytes] of the last packets
  }

  // The next level on the way from `from` to `to`: the nearest multiple of the
  // packet size.
  nextStop(from, to) {
    const { size } = this;
    return to > from ? Math.min(to, (Math.floor(from / size) + 1) * size)
                     : Math.max(to, (Math.ceil(from / size) - 1) * size);
  }

  // After a packet from `url` of `bytes` bytes and `records` records,
  // applied in applyMs, while a drawn frame costs frameCostMs.
  measure(url, bytes, records, applyMs, frameCostMs) {
    this.link = this.linkOf(url, bytes) ?? this.link;
    this.receivedBytes += bytes;
    this.receivedRecords += records;
    this.adapt(records, bytes, applyMs, frameCostMs);
  }

  // The link's figures for a fetched URL: { latencyMs, bytesPerMs } from its
  // Resource Timing entry (null when there is none, e.g. the buffer is full).
  // Packets in flight together share the link, so one body's bytes over its own
  // time would be a share of the link's rate (and shrink packets the more are
  // ahead): the rate is the bytes of the last few bodies over the time any of
  // them was arriving (the union of their intervals).
  linkOf(url, bytes) {
    const entries = performance.getEntriesByName(new URL(url, window.location.href).href,
                                                 'resource');
    const entry = entries[entries.length - 1];
    // (another origin's timings are zero unless it sends Timing-Allow-Origin)
    if (!entry || !(entry.responseEnd > 0) || !(entry.responseStart > 0)) return null;
    const latencyMs = Math.max(0, entry.responseStart - entry.requestStart);
    const { bodies } = this;
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
  // applied in applyMs, over this.link (see linkOf).
  adapt(records, bytes, applyMs, frameCostMs) {
    const { option, link } = this;
    // records per ms: the fastest lately (a cold JIT or a GC pause makes one
    // packet slow; the rate decays so a lasting slowdown still shrinks packets)
    this.rate = Math.max(records / Math.max(applyMs, 0.05), 0.7 * this.rate);
    // where a drawn frame blocks the main thread longer than the budget (software
    // GL), a packet as long as half a frame costs no responsiveness
    const budget = Math.max(option('frameBudgetMs'), 0.5 * frameCostMs);
    let want = budget * this.rate;
    if (link) {
      const paceMs = Math.max(option('packetPaceMs'), (option('reportGap') + 1) * frameCostMs,
                              2 * link.latencyMs);
      want = Math.min(want, paceMs * link.bytesPerMs * records / Math.max(bytes, 1));
    }
    want = Math.min(want, 4 * this.size, MAX_SPLITS);
    let next = option('chunkSplits');
    while (next * 2 <= want) next *= 2;
    this.size = next;
  }

  // How long `records` more records should take to cross the link, ms: their
  // bytes (a record's as in the packets so far) over the link's rate, plus
  // `latency` times its latency; null before a packet has been measured.
  linkMs(records, latency = 0) {
    const { link, receivedBytes, receivedRecords } = this;
    if (!link || !(receivedRecords > 0)) return null;
    return latency * link.latencyMs
      + records * (receivedBytes / receivedRecords) / link.bytesPerMs;
  }
}
