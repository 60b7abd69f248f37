// A progressive file (docs/packets.md, "The progressive file": a GLB with the
// LODSERVER_progressive extension) on any static HTTP host or CDN, as a source
// of the three.js module (source.js has the four things a source gives):
//   the header and JSON chunk     one Range request (two when the JSON is longer
//                                 than HEAD_BYTES)
//   base(level)                   the base level's json form, one Range request
//   packet(from, to)              the chunks from `from` to `to`, one Range request
//                                 (several version 4 packets, applied in order)
//   materials()                   the GLB's material records, its images in one
//                                 Range request
// A host that ignores Range answers 200 with the whole file: it is kept and
// every later read is cut from it, so the file is fetched once either way.
// The file's levels are its chunks' ends (snap()): a stream holds only those.

import { FetchError, fetchOk } from './source.js';

const EXTENSION = 'LODSERVER_progressive';
const READ_VERSIONS = [4];
// The first read: a GLB header and, for most files, the whole JSON chunk.
const HEAD_BYTES = 65536;
const GLB_MAGIC = 0x46546c67;   // 'glTF'
const JSON_CHUNK = 0x4e4f534a;  // 'JSON'

export const NOT_A_SOURCE =
  'not a lodserver mesh URL (http://host/meshes/ID) nor a progressive file';

// Byte ranges of one file: a Range request each, or cuts of the whole file once
// the host answered 200 to one. The file's first bytes, read once, are kept:
// the base and the first chunks of a small file are among them.
export class RangeReader {
  constructor(url) {
    this.url = url;
    this.whole = null;          // the whole file, once a host ignored a Range
    this.head = new ArrayBuffer(0);
  }

  // Bytes [start, end) of the file (fewer past its end), an ArrayBuffer.
  async read(start, end, { signal } = {}) {
    const held = this.head.byteLength;
    if (end <= held) return this.head.slice(start, end);
    if (start < held) return concat(this.head.slice(start), await this.read(held, end, { signal }));
    if (this.whole) return (await this.whole).slice(start, end);
    const response = await fetchOk(this.url, { signal,
                                               headers: { Range: `bytes=${start}-${end - 1}` } });
    if (response.status === 206) return readBody(response);
    this.whole = readBody(response);
    return (await this.whole).slice(start, end);
  }
}

async function readBody(response) {
  try {
    return await response.arrayBuffer();
  } catch (error) {
    if (error.name === 'AbortError') throw error;
    throw new FetchError(`the file was cut short (${error.message})`, true);
  }
}

function concat(a, b) {
  const out = new Uint8Array(a.byteLength + b.byteLength);
  out.set(new Uint8Array(a), 0);
  out.set(new Uint8Array(b), a.byteLength);
  return out.buffer;
}

// The file shared by a source and its parts' sources.
class ProgressiveFile {
  constructor(url, reader, document, jsonBytes) {
    this.url = url;
    this.reader = reader;
    this.document = document;
    this.jsonBytes = jsonBytes;             // the JSON chunk as stored (padded)
    this.record = document.extensions[EXTENSION];
    this.binStart = 20 + jsonBytes.byteLength + 8;
  }

  read(at, length, options) {
    return this.reader.read(this.binStart + at, this.binStart + at + length, options);
  }
}

export class StaticSource {
  // file: the ProgressiveFile; summary: the mesh's (or a scene part's record);
  // part: the extension's record of the part streamed (null for a scene).
  constructor(file, summary, part) {
    this.file = file;
    this.summary = summary;
    this.chunks = part;
    this.levels = part ? [part.base[0], ...part.splits.map((chunk) => chunk[1])] : [];
    this.imageUrls = [];        // the blob: URLs materials() made, revoked by close()
  }

  // Lets go of the images' blob: URLs (the object using this source is disposed).
  close() {
    for (const url of this.imageUrls) URL.revokeObjectURL(url);
    this.imageUrls = [];
  }

  // The source of the progressive file at `url`; a clear error for anything else.
  static async open(url, { signal = null } = {}) {
    const href = new URL(url, window.location.href).href;
    const reader = new RangeReader(href);
    let head = await reader.read(0, HEAD_BYTES, { signal });
    reader.head = head;
    const view = new DataView(head);
    if (head.byteLength < 20 || view.getUint32(0, true) !== GLB_MAGIC
        || view.getUint32(16, true) !== JSON_CHUNK) {
      throw new Error(`${NOT_A_SOURCE}: ${url} is no GLB`);
    }
    const length = view.getUint32(12, true);
    if (20 + length > head.byteLength && head.byteLength < HEAD_BYTES) {
      throw new Error(`${NOT_A_SOURCE}: ${url} is cut short (its JSON chunk ends past the file)`);
    }
    if (20 + length > head.byteLength) {
      head = concat(head, await reader.read(head.byteLength, 20 + length, { signal }));
    }
    const jsonBytes = new Uint8Array(head, 20, length);
    const document = JSON.parse(new TextDecoder().decode(jsonBytes));
    const record = document.extensions?.[EXTENSION];
    if (!record) throw new Error(`${NOT_A_SOURCE}: ${url} has no ${EXTENSION} extension`);
    if (!READ_VERSIONS.includes(record.packetVersion)) {
      throw new Error(`${url} holds packets of version ${record.packetVersion}; this module ` +
                      `reads ${READ_VERSIONS.join(', ')}`);
    }
    const file = new ProgressiveFile(href, reader, document, jsonBytes.slice());
    const summary = { ...record.summary, id: href, status: 'ready' };
    return new StaticSource(file, summary, summary.scene ? null : record.parts[0]);
  }

  // The source of a scene's part (its summary's parts[p]).
  part(record) {
    const part = this.file.record.parts.find((p) => p.part === record.index);
    const { id, name } = this.summary;
    return new StaticSource(this.file, { ...record, id, name: `${name} (${record.name})` }, part);
  }

  // The level of the file nearest `level` that a stream can hold: the end of a
  // chunk, at or above it ('up') or at or below it ('down').
  snap(level, direction = 'up') {
    const { levels } = this;
    if (direction === 'up') return levels.find((x) => x >= level) ?? levels[levels.length - 1];
    return levels.findLast((x) => x <= level) ?? levels[0];
  }

  // The chunk end a request from `from` toward `to` (chunk ends) stops at,
  // for requests of about `records` records (the packet sizer's size): runs
  // of a power of two chunks, cut at multiples of the run in the file's
  // chunks, so that a run's cuts line up with every shorter run's and moving
  // back and forth asks for the same ranges.
  nextStop(from, to, records) {
    const { levels } = this;
    const at = levels.indexOf(this.snap(from, to > from ? 'down' : 'up'));
    const end = levels.indexOf(this.snap(to, to > from ? 'up' : 'down'));
    let run = 1;
    while (2 * run * this.chunks.chunkSplits <= records) run *= 2;
    return levels[end > at ? Math.min(end, (Math.floor(at / run) + 1) * run)
                           : Math.max(end, (Math.ceil(at / run) - 1) * run)];
  }

  async base(level, { signal } = {}) {
    const [at, offset, length] = this.chunks.base;
    if (level !== at) throw new FetchError(`the file's base level is ${at}, not ${level}`, false);
    return this.file.read(offset, length, { signal });
  }

  // The chunks from `from` to `to` (both chunk ends): { buffers, url }, a
  // version 4 packet each, in order.
  async packet(from, to, { signal } = {}) {
    const list = to > from ? this.chunks.splits : this.chunks.collapses;
    const first = list.findIndex((chunk) => chunk[0] === from);
    const last = list.findIndex((chunk) => chunk[1] === to);
    if (first < 0 || last < first) {
      throw new FetchError(`the file has no chunks from level ${from} to ${to}`, false);
    }
    const start = list[first][2];
    const end = list[last][2] + list[last][3];
    const bytes = await this.file.read(start, end - start, { signal });
    if (bytes.byteLength !== end - start) {
      throw new FetchError(`the file answered ${bytes.byteLength} of ${end - start} bytes`, true);
    }
    const buffers = list.slice(first, last + 1).map(([, , at, length]) => (
      bytes.slice(at - start, at - start + length)));
    return { buffers, url: this.file.url };
  }

  // The GLB's material records, each image's uri a blob: URL of its bytes.
  async materials({ signal } = {}) {
    const { document } = this.file;
    const views = document.bufferViews ?? [];
    const images = (document.images ?? []).map((image) => (
      { image, view: views[image.bufferView] }));
    const held = images.filter(({ view }) => view);
    let bytes = null, start = 0;
    if (held.length) {
      start = Math.min(...held.map(({ view }) => view.byteOffset ?? 0));
      const end = Math.max(...held.map(({ view }) => (view.byteOffset ?? 0) + view.byteLength));
      bytes = await this.file.read(start, end - start, { signal });
    }
    const out = {};
    for (const key of ['materials', 'textures', 'samplers', 'extensionsUsed']) {
      if (document[key]) out[key] = document[key];
    }
    out.images = images.map(({ image, view }) => {
      if (!view) return image;
      const at = (view.byteOffset ?? 0) - start;
      const blob = new Blob([bytes.slice(at, at + view.byteLength)], { type: image.mimeType });
      const { bufferView, ...rest } = image;
      const uri = URL.createObjectURL(blob);
      this.imageUrls.push(uri);
      return { ...rest, uri };
    });
    return { document: out, url: this.file.url };
  }

  // The scene's glTF at its base levels (ProgressiveScene.load): the file's
  // JSON and the part of its BIN chunk the glTF document uses, as one GLB.
  async sceneGlb({ signal } = {}) {
    const { glbBytes } = this.file.record;
    const bin = await this.file.read(0, glbBytes, { signal });
    const json = this.file.jsonBytes;
    const out = new Uint8Array(12 + 8 + json.byteLength + 8 + bin.byteLength);
    const view = new DataView(out.buffer);
    view.setUint32(0, GLB_MAGIC, true);
    view.setUint32(4, 2, true);
    view.setUint32(8, out.byteLength, true);
    view.setUint32(12, json.byteLength, true);
    view.setUint32(16, JSON_CHUNK, true);
    out.set(json, 20);
    view.setUint32(20 + json.byteLength, bin.byteLength, true);
    view.setUint32(24 + json.byteLength, 0x004e4942, true);   // 'BIN\0'
    out.set(new Uint8Array(bin), 28 + json.byteLength);
    return { buffer: out.buffer, url: this.file.url };
  }
}
