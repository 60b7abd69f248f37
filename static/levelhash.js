// The digest of a level the tests compare with the server's json level
// (window.lodViewer.hash(): main.js).

// SHA-256 (hex) of `state`'s (a LodState: levelstate.js) integer grid
// positions then its faces (int32 and uint32, little-endian), then, with
// attributes, its wedges' grid values and its corners' wedges (int32,
// uint32), then with materials its faces' materials (int32).
export async function hashLevel(state) {
  const parts = [new Uint8Array(state.positions.buffer, 0, 12 * state.vertexCount),
                 new Uint8Array(state.faces.buffer, 0, 12 * state.faceCount)];
  if (state.attributes.length) {
    parts.push(new Uint8Array(state.wedges.buffer, 0, 4 * state.components * state.wedgeCount),
               new Uint8Array(state.corners.buffer, 0, 12 * state.faceCount));
  }
  if (state.faceMaterial) {
    parts.push(new Uint8Array(state.faceMaterial.buffer, 0, 4 * state.faceCount));
  }
  const bytes = new Uint8Array(parts.reduce((n, part) => n + part.length, 0));
  parts.reduce((at, part) => {
    bytes.set(part, at);
    return at + part.length;
  }, 0);
  const digest = await crypto.subtle.digest('SHA-256', bytes);
  return [...new Uint8Array(digest)].map((b) => b.toString(16).padStart(2, '0')).join('');
}
