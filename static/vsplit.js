// The vertex-split decoder's public face (docs/packets.md): what the viewer,
// the tests and the benchmarks import. A port of the reference decoder in
// lodserver/packets/ (reference.py: decode_packet, apply_packet; grids.py:
// state_from_json), which it must match exactly; its parts, one module each:
//
//   packet.js      the header, the fields of the streams, attribute grids
//   packet_v4.js   a version 4 packet read into version 3's fields
//   rans.js        version 4's entropy coder (rANS)
//   levelstate.js  LodState: the level's arrays, dirty ranges, apply()
//   splits.js      split records, and their wedge parts
//   collapses.js   collapse records, and their wedge parts
//   wedges.js      gradient fit, extrapolation, wedge codes
//   fans.js        corners(v), neighbours(v), predicted and listed fans
//   arrays.js      growable scratch

export { LodState } from './levelstate.js';
export { dequantize, PacketError, readPacket } from './packet.js';
