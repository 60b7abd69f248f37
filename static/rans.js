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
export const MAX_SYMBOLS_PER_BYTE = 256;
const COARSE_BITS = 6;              // the coarse table has a bucket per 64 slots

const EMPTY = new Uint8Array(0);

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

// How a stream's symbols get their contexts (streams_v4.py's Shape; decode()):
// PLAIN, symbol i in context i % period; CLASSED, symbol j of a group of `period`
// in context 8 j + the class of the largest symbol before it in its group, or for
// the first, of the whole previous group; RUNS, the vertex stream of splits, 0 for
// the first gap of a batch run and 1 for the others (`aux`: the runs' lengths less
// one); FACES, the pattern stream of splits, 0 for a record's first new face and
// 1 + p after a face of pattern p (`aux`: the records' face counts).
export const PLAIN = 0, CLASSED = 1, RUNS = 2, FACES = 3;
export const CLASSES = 8;           // magnitude classes of a classed context
export const PATTERNS = 27;         // 3 codes per corner, 3 corners

// The class of a symbol: 0 below 8, then one per power of two, the last 512 and more.
function magnitudeClass(v) {
  if (v < 8) return 0;
  if (v >= 512) return CLASSES - 1;
  return 31 - Math.clz32(v) - 2;
}

// Every context's model before any symbol: its frequencies, starts and coarse table
// (the same for all: each count 1), copied into a reader's flat arrays.
const FIRST = { freq: new Int32Array(ALPHABET), start: new Int32Array(ALPHABET + 1),
                coarse: new Uint8Array(PROB_SCALE >> COARSE_BITS) };
{
  const one = 1 + Math.floor(SHARED / ALPHABET);
  FIRST.freq.fill(one);
  FIRST.freq[0] += PROB_SCALE - one * ALPHABET;
  tables(FIRST.freq, 0, FIRST.start, 0, FIRST.coarse, 0);
}

// start[so ..] from freq[fo ..] (ALPHABET + 1 prefix sums) and the coarse table of
// `coarse` at co: the bucket at every 64th slot.
function tables(freq, fo, start, so, coarse, co) {
  let sum = 0;
  for (let b = 0; b < ALPHABET; b++) {
    start[so + b] = sum;
    sum += freq[fo + b];
  }
  start[so + ALPHABET] = sum;
  for (let i = 0, b = 0; i < PROB_SCALE >> COARSE_BITS; i++) {
    while (start[so + b + 1] <= i << COARSE_BITS) b++;
    coarse[co + i] = b;
  }
}

// rans.py's frequencies() for context c of a reader's models: 1 + count * SHARED //
// total per bucket (integers only, so every decoder gets the same), and what is left
// to the first largest count; the total is known from the symbols coded, and only the
// buckets coded have a count above 1. A function of the arrays, not a method: the
// decoding loop calls it with what it holds in locals.
function build(m, c) {
  const { counts, freq, seen } = m;
  const base = c * ALPHABET;
  const total = ALPHABET + INCREMENT * m.coded[c];
  const one = 1 + floorDiv(SHARED, total);
  freq.fill(one, base, base + ALPHABET);
  let used = one * ALPHABET, top = base;
  for (let i = base, end = base + m.seenCount[c]; i < end; i++) {
    const b = base + seen[i];
    const f = 1 + floorDiv(counts[b] * SHARED, total);
    freq[b] = f;
    used += f - one;
    // the first largest count: a coded bucket's is above the others' 1
    if (counts[b] > counts[top] || (counts[b] === counts[top] && b < top)) top = b;
  }
  freq[top] += PROB_SCALE - used;
  tables(freq, base, m.start, c * (ALPHABET + 1), m.coarse, c * (PROB_SCALE >> COARSE_BITS));
}

function ended(name) {
  return new PacketError(`the packet's ${name} stream ends in the middle of a symbol`);
}

// The symbols of one coded stream, read from `table` (a packet.js stream reader
// at the stream's start: varint symbol count, then unless 0 varint byte length
// and the rANS bytes). decode() reads them all into an array and checks that the
// stream ends where its symbols do. Every malformation is a PacketError.
//
// Each context's adaptive model (counts, and the frequencies and starts rebuilt
// from them on rans.py's schedule) is a row of flat arrays, so the decoding loop
// runs on locals and typed arrays only. A slot's bucket is found from a coarse
// table (the bucket at every 64th slot) and a scan over the starts from there: a
// full slot -> bucket table would be refilled (4096 entries) at every rebuild, and
// a binary search takes seven unpredictable steps where the scan mostly takes none.
export class SymbolReader {
  constructor(table, contexts, name) {
    this.name = name;
    this.count = table.varint();
    this.data = EMPTY;
    this.at = 0;
    this.x = STATE_LOW;
    // every field is set before the stream is checked, so all readers share one
    // shape and decode() stays monomorphic
    const models = this.count === 0 ? 0 : contexts;
    this.counts = new Int32Array(models * ALPHABET).fill(1);
    this.freq = new Int32Array(models * ALPHABET);
    this.start = new Int32Array(models * (ALPHABET + 1));
    this.coarse = new Uint8Array(models * (PROB_SCALE >> COARSE_BITS));
    this.coded = new Int32Array(models);
    this.rebuild = new Int32Array(models).fill(FIRST_REBUILD);
    // the buckets each context has coded, in the order first coded (the others keep
    // their count of 1, and so share one frequency)
    this.seen = new Uint8Array(models * ALPHABET);
    this.seenCount = new Int32Array(models);
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
    for (let c = 0; c < contexts; c++) {
      this.freq.set(FIRST.freq, c * ALPHABET);
      this.start.set(FIRST.start, c * (ALPHABET + 1));
      this.coarse.set(FIRST.coarse, c * (PROB_SCALE >> COARSE_BITS));
    }
  }

  // All `values.length` symbols of the stream (its count), each in the context
  // `rule` gives it (PLAIN, CLASSED, RUNS, FACES above, with `period` and `aux`).
  decode(values, rule, period, aux) {
    const n = values.length;
    if (n !== this.count) throw new Error('decode() reads every symbol of a stream');
    const { data, counts, start, coarse, coded, rebuild, seen, seenCount } = this;
    const length = data.length;
    let x = this.x, at = this.at;
    // the context rules' state
    let j = 0, group = 0, previous = 0, run = 0, left = 0, record = 0, face = 0;
    for (let i = 0; i < n; i++) {
      let c;
      if (rule === PLAIN) {
        c = j;
        if (++j === period) j = 0;
      } else if (rule === CLASSED) {
        if (j === 0) {
          previous = i ? group : 0;
          group = 0;
          c = magnitudeClass(previous);
        } else {
          c = j * CLASSES + magnitudeClass(group);
        }
        if (++j === period) j = 0;
      } else if (rule === RUNS) {
        c = 1;
        if (left === 0) {
          left = aux[run++] + 1;
          c = 0;
        }
        left--;
      } else {
        while (face === aux[record]) {
          record++;
          face = 0;
        }
        c = face === 0 ? 0 : 1 + values[i - 1];
        face++;
      }
      const base = c * ALPHABET;
      const slot = x & SLOT_MASK;
      const so = c * (ALPHABET + 1) + 1;         // start[so + b]: the end of bucket b
      let b = coarse[(c << (PROB_BITS - COARSE_BITS)) + (slot >> COARSE_BITS)];
      let end = start[so + b];
      while (end <= slot) end = start[so + ++b];
      const begin = start[so + b - 1];
      x = (end - begin) * (x >>> PROB_BITS) + slot - begin;
      while (x < STATE_LOW) {
        if (at >= length) throw ended(this.name);
        x = (x << 8) | data[at++];
      }
      // the model learns the bucket
      const k = base + b;
      if (counts[k] === 1) seen[base + seenCount[c]++] = b;
      counts[k] += INCREMENT;
      if (++coded[c] === rebuild[c]) {
        rebuild[c] = coded[c] + Math.min(coded[c], REBUILD_EVERY);
        build(this, c);
      }
      let value = b;
      if (b >= DIRECT) {
        const bits = ((b - DIRECT) >> 1) + 6;             // the value's bit length
        value = POWERS[bits - 1] + ((b - DIRECT) & 1) * POWERS[bits - 2];
        const extra = bits - 2;
        for (let e = 0; e < extra; e += RAW_CHUNK) {
          const size = Math.min(RAW_CHUNK, extra - e);
          value += (x & ((1 << size) - 1)) * POWERS[e];
          x >>>= size;
          while (x < STATE_LOW) {
            if (at >= length) throw ended(this.name);
            x = (x << 8) | data[at++];
          }
        }
      }
      if (rule === CLASSED && value > group) group = value;
      if (rule === FACES && value >= PATTERNS) {
        throw new PacketError(`the packet holds a pattern above ${PATTERNS - 1}`);
      }
      values[i] = value;
    }
    // every byte consumed, the state back at 2^23
    if (x !== STATE_LOW || at !== length) {
      throw new PacketError(`the packet's ${this.name} stream does not end where its ` +
                            'symbols do');
    }
  }
}
