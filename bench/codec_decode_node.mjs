// The browser decoder (static/vsplit.js) timed in node, for bench/codec_decode_speed.py:
// node codec_decode_node.mjs PACKETS ROUNDS STATIC...
//
// PACKETS is a folder the Python side wrote: level.json ({ document, capacity }) and
// one file per packet named in packets.json. Each round times, for every build's
// static/ folder in turn (alternating, so the machine's load falls on all alike) and
// every packet on a fresh state from the json level: LodState.readPacket and
// LodState.apply, in CPU time (process.cpuUsage: what the load inflates less than
// wall time). Prints one JSON line per round and build: { build, times: { packet:
// [read ms, apply ms] }, ends: { packet: [vertices, faces, hash] } }.

import { readFileSync } from 'node:fs';
import { join } from 'node:path';
import { pathToFileURL } from 'node:url';

const [folder, rounds, ...builds] = process.argv.slice(2);
const { document, capacity } = JSON.parse(readFileSync(join(folder, 'level.json')));
const names = JSON.parse(readFileSync(join(folder, 'packets.json')));
const packets = names.map((name) => new Uint8Array(readFileSync(join(folder, name))));
const modules = [];
for (const build of builds) {
  modules.push((await import(pathToFileURL(join(build, 'vsplit.js')).href)).LodState);
}

const cpu = () => {
  const used = process.cpuUsage();
  return (used.user + used.system) / 1000;
};

// positions and faces of the level reached, folded into one number
const hash = (state) => {
  let h = 0;
  const p = state.positions, f = state.faces;
  for (let k = 0; k < 3 * state.vertexCount; k++) h = (Math.imul(h, 31) + p[k]) | 0;
  for (let k = 0; k < 3 * state.faceCount; k++) h = (Math.imul(h, 31) + f[k]) | 0;
  return [state.vertexCount, state.faceCount, h];
};

for (let round = 0; round < Number(rounds); round++) {
  for (let b = 0; b < builds.length; b++) {
    const LodState = modules[b];
    const times = {}, ends = {};
    for (let i = 0; i < packets.length; i++) {
      const state = LodState.fromJson(document, capacity);
      const t0 = cpu();
      const packet = await LodState.readPacket(packets[i].slice());
      const t1 = cpu();
      state.apply(packet);
      const t2 = cpu();
      times[names[i]] = [t1 - t0, t2 - t1];
      ends[names[i]] = hash(state);
    }
    console.log(JSON.stringify({ build: builds[b], times, ends }));
  }
}
