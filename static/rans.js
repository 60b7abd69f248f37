// The entropy coder of version 4 packets: byte-oriented rANS with adaptive
// per-context frequencies (docs/packets.md, "Version 4", "The coder"). A twin of
// the reference decoder, lodserver/packets/rans.py (SymbolReader, Context), which
// it must match symbol for symbol.
//
// The state x stays in [2^23, 2^31) and every product below 2^31, so the
// arithmetic is int32-safe; a symbol's value (below 2^44) is built from its
// bucket and extra bits by multiplication, not shifts, as JavaScript's bit
// operators truncate to 32 bits.

import { PacketError } from './packet.js';

const PROB_BITS = 12;
const PROB_SCALE = 1 << PROB_BITS;
const SLOT_MASK = PROB_SCALE - 1;
const STATE_LOW = 1 << 23;
const STATE_HIGH = 2 ** 31;
const DIRECT = 32;                  // values below this are their own bucket
const MAX_BIT_LENGTH = 44;
const ALPHABET = DIRECT + 2 * (MAX_BIT_LENGTH - 5);
const RAW_CHUNK = 16;               // extra bits come at most this many at a time
const FIRST_REBUILD = 16, REBUILD_EVERY = 64, INCREMENT = 32;
const SHARED = PROB_SCALE - ALPHABET;   // every bucket keeps a frequency of 1
// A symbol takes at least log2(4096 / 3987) bits of the state (3987: the largest
// frequency, every other bucket keeping 1), so a stream of L bytes codes fewer than
// 210 L symbols: a count past this bound is refused before anything is allocated.
const MAX_SYMBOLS_PER_BYTE = 256;
const COARSE_BITS = 6;              // the coarse table has a bucket per 64 slots

// 2^k as a float, for values past 32 bits.
const POWERS = Float64Array.from({ length: MAX_BIT_LENGTH + 1 }, (_, k) => 2 ** k);

// floor(a / b) of integers a >= 0, b > 0 whose product a can pass 2^31: exact in
// a float, floored, then corrected for the division's rounding.
function floorDiv(a, b) {
  let q = Math.floor(a / b);
  if (q * b > a) q--;
  else if ((q + 1) * b <= a) q++;
  return q;
}

// One context's adaptive model: counts, and the frequencies and starts rebuilt
// from them on rans.py's schedule. A slot's bucket is found from a coarse table
// (the bucket at every 64th slot) and a scan over the starts from there: a full
// slot -> bucket table would be refilled (4096 entries) at every rebuild, and a
// binary search takes seven unpredictable steps where the scan mostly takes none.
class Model {
  constructor() {
    this.counts = new Int32Array(ALPHABET).fill(1);
    this.freq = new Int32Array(ALPHABET);
    this.start = new Int32Array(ALPHABET + 1);
    this.coarse = new Uint8Array(PROB_SCALE >> COARSE_BITS);
    this.coded = 0;
    this.rebuild = FIRST_REBUILD;
    this.build();
  }

  // rans.py's frequencies(): 1 + count * SHARED // total per bucket (integers only,
  // so every decoder gets the same), and what is left to the first largest count.
  build() {
    const { counts, freq, start } = this;
    let total = 0, top = 0;
    for (let b = 0; b < ALPHABET; b++) {
      total += counts[b];
      if (counts[b] > counts[top]) top = b;
    }
    // most buckets keep their count of 1: their share is computed once
    const one = 1 + floorDiv(SHARED, total);
    let used = 0;
    for (let b = 0; b < ALPHABET; b++) {
      const f = counts[b] === 1 ? one : 1 + floorDiv(counts[b] * SHARED, total);
      freq[b] = f;
      used += f;
    }
    freq[top] += PROB_SCALE - used;
    for (let b = 0; b < ALPHABET; b++) start[b + 1] = start[b] + freq[b];
    const { coarse } = this;
    for (let i = 0, b = 0; i < coarse.length; i++) {
      while (start[b + 1] <= i << COARSE_BITS) b++;
      coarse[i] = b;
    }
  }

  // The bucket whose [start, start + freq) holds `slot`.
  bucket(slot) {
    const { start } = this;
    let b = this.coarse[slot >> COARSE_BITS];
    while (start[b + 1] <= slot) b++;
    return b;
  }

  update(b) {
    this.counts[b] += INCREMENT;
    if (++this.coded === this.rebuild) {
      this.rebuild = this.coded + Math.min(this.coded, REBUILD_EVERY);
      this.build();
    }
  }
}

// The symbols of one coded stream, read from `table` (a packet.js stream reader
// at the stream's start: varint symbol count, then unless 0 varint byte length
// and the rANS bytes). read(context) gives the next symbol; done() checks that
// the stream ends where its symbols do. Every malformation is a PacketError.
export class SymbolReader {
  constructor(table, contexts, name) {
    this.name = name;
    this.count = table.varint();
    this.left = this.count;
    this.models = new Array(contexts).fill(null);
    this.data = null;
    this.at = 0;
    this.x = STATE_LOW;
    if (this.count === 0) return;
    const data = table.bytes(table.varint());
    if (data.length < 4) {
      throw new PacketError(`the packet's ${name} stream is shorter than its state`);
    }
    if (this.count > MAX_SYMBOLS_PER_BYTE * data.length) {
      throw new PacketError(`the packet's ${name} stream holds more symbols than its bytes ` +
                            'can code');
    }
    const x = (data[0] | (data[1] << 8) | (data[2] << 16) | (data[3] << 24)) >>> 0;
    if (x < STATE_LOW || x >= STATE_HIGH) {
      throw new PacketError(`the packet's ${name} stream starts with a bad state`);
    }
    this.data = data;
    this.at = 4;
    this.x = x;
  }

  // `context` is in [0, contexts): the callers compute it from symbols they checked.
  read(context) {
    if (this.left <= 0) {
      throw new PacketError(`the packet's ${this.name} stream holds fewer symbols than its ` +
                            'records read');
    }
    this.left--;
    let model = this.models[context];
    if (model === null) model = this.models[context] = new Model();
    const { data } = this;
    let x = this.x, at = this.at;
    const slot = x & SLOT_MASK;
    const b = model.bucket(slot);
    x = model.freq[b] * (x >>> PROB_BITS) + slot - model.start[b];
    while (x < STATE_LOW) {
      if (at >= data.length) throw this.ended();
      x = (x << 8) | data[at++];
    }
    model.update(b);
    if (b < DIRECT) {
      this.x = x;
      this.at = at;
      return b;
    }
    const n = ((b - DIRECT) >> 1) + 6;             // the value's bit length
    let value = POWERS[n - 1] + ((b - DIRECT) & 1) * POWERS[n - 2];
    const extra = n - 2;
    for (let k = 0; k < extra; k += RAW_CHUNK) {
      const size = Math.min(RAW_CHUNK, extra - k);
      value += (x & ((1 << size) - 1)) * POWERS[k];
      x >>>= size;
      while (x < STATE_LOW) {
        if (at >= data.length) throw this.ended();
        x = (x << 8) | data[at++];
      }
    }
    this.x = x;
    this.at = at;
    return value;
  }

  ended() {
    return new PacketError(`the packet's ${this.name} stream ends in the middle of a symbol`);
  }

  // Every symbol read, every byte consumed, the state back at 2^23.
  done() {
    if (this.left !== 0 || this.x !== STATE_LOW ||
        this.at !== (this.data === null ? 0 : this.data.length)) {
      throw new PacketError(`the packet's ${this.name} stream does not end where its ` +
                            'symbols do');
    }
  }
}
