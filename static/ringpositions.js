// The position reader of a version 4 split packet with RING_POSITIONS
// (docs/packets.md, "Positions from the ring"; the reference is
// lodserver/packets/reference.py, ring_prediction and ring_edge_fields).
//
// Such a packet codes each split's edge E less a prediction P from the rings of
// its two vertices, which reads the state after the split's faces: packet_v4.js
// decodes every symbol first (their contexts never depend on the state) and
// keeps each split's seven (E - P, the place l, the rest r); LodState.apply
// then reads the split's six version 3 fields (d1, d2) through this reader, in
// place of the position stream's, exactly when splits.js reaches them: after
// the faces, before the positions. It has the field reader's signed() and
// done() (packet.js), so the apply's record loop and its final check that every
// stream was read run unchanged.
//
// It reads the state's own arrays: parent (vs of each split, set before its
// faces), faces, positions, and the corner blocks ring / ringInfo (fans.js).

const RING_SCALE = 0.625;          // format.RING_SCALE: a power-of-two fraction, exact
const PLACES = 16;                 // the split edge's places, in 16ths
const FIELDS = 7, V3_FIELDS = 6;   // symbols per split; version 3's d1 (3), d2 (3)
const PLACE_COLUMN = 3;            // the place is not zigzagged

// A segment's position symbols, signed, into `out`: E - P and r unzigzagged, the
// place as it is.
export function edgeSymbols(symbols, out) {
  for (let i = 0; i < symbols.length; i++) {
    const u = symbols[i];
    out[i] = i % FIELDS === PLACE_COLUMN ? u : u % 2 === 0 ? u / 2 : -(u + 1) / 2;
  }
}

// packet.positionReader of a split packet from `start`, from every split's seven
// signed symbols (edgeSymbols()).
export function ringPositions(edges, start) {
  return (state) => new RingPositions(state, start, edges);
}

class RingPositions {
  // `edges`: every split's seven signed symbols (E - P, l, r), start .. stop-1.
  constructor(state, start, edges) {
    this.state = state;
    this.start = start;
    this.edges = edges;
    this.at = 0;
    this.length = V3_FIELDS * (edges.length / FIELDS);
    this.fields = new Float64Array(V3_FIELDS);
    this.sums = new Float64Array(6);
  }

  done() {
    return this.at === this.length;
  }

  // The next version 3 field: a split's first resolves the whole split.
  signed() {
    const k = this.at % V3_FIELDS;
    if (k === 0) this.resolve((this.at - k) / V3_FIELDS);
    this.at++;
    return this.fields[k];
  }

  // d1 = r - floor((l E + 8) / 16), d2 = E + 2 d1, with E = (E - P) + P.
  resolve(i) {
    const t = this.start + i, s = this.state.parent[t];
    const { edges, fields, sums } = this;
    const at = FIELDS * i, place = edges[at + 3];
    const ns = this.ringSum(s, t, 0), nt = this.ringSum(t, s, 3);
    for (let a = 0; a < 3; a++) {
      const predicted = ns === 0 || nt === 0 ? 0
        : Math.floor((sums[3 + a] / nt - sums[a] / ns) * RING_SCALE + 0.5);
      const edge = edges[at + a] + predicted;
      const d1 = edges[at + 4 + a] - Math.floor((place * edge + PLACES / 2) / PLACES);
      fields[a] = d1;
      fields[3 + a] = edge + 2 * d1;
    }
  }

  // sums[into .. into+2]: the positions of the two other corners' vertices of
  // every corner of v, but v and `other` (float64, exact: integers); returns
  // how many were summed.
  ringSum(v, other, into) {
    const { faces, positions, ring, ringInfo } = this.state;
    const { sums } = this;
    let x = 0, y = 0, z = 0, n = 0;
    for (let i = ringInfo[4 * v], end = i + ringInfo[4 * v + 1]; i < end; i++) {
      const c = ring[i], f3 = c - c % 3;
      for (let step = 1; step <= 2; step++) {
        const u = faces[f3 + (c - f3 + step) % 3];
        if (u === v || u === other) continue;
        x += positions[3 * u];
        y += positions[3 * u + 1];
        z += positions[3 * u + 2];
        n++;
      }
    }
    sums[into] = x;
    sums[into + 1] = y;
    sums[into + 2] = z;
    return n;
  }
}
