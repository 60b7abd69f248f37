// Nearest points (animated.js: a streamed level takes what its stream does not
// carry, skin weights say, from the GLB vertex nearest each of its vertices).
// No three.js here, so tests can import it alone.

// For each point of `query` (xyz floats, n points), the index of the nearest
// point of `points` (m points): a uniform grid of about one point a cell,
// searched in growing shells until no nearer point can be found.
export function nearestPoints(points, query) {
  const m = points.length / 3, n = query.length / 3;
  const out = new Int32Array(n);
  if (m === 0) return out;
  const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
  for (let i = 0; i < 3 * m; i++) {
    lo[i % 3] = Math.min(lo[i % 3], points[i]);
    hi[i % 3] = Math.max(hi[i % 3], points[i]);
  }
  const side = Math.max(1, Math.ceil(Math.cbrt(m)));
  const extent = Math.max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) || 1;
  const cell = extent / side;
  const dims = [0, 1, 2].map((k) => Math.max(1, Math.ceil((hi[k] - lo[k]) / cell) + 1));
  const cellOf = (x, k) => Math.min(dims[k] - 1, Math.max(0, Math.floor((x - lo[k]) / cell)));
  // counting sort of the points by cell
  const cells = dims[0] * dims[1] * dims[2];
  const start = new Int32Array(cells + 1), order = new Int32Array(m), key = new Int32Array(m);
  for (let i = 0; i < m; i++) {
    key[i] = (cellOf(points[3 * i], 0) * dims[1] + cellOf(points[3 * i + 1], 1)) * dims[2] +
             cellOf(points[3 * i + 2], 2);
    start[key[i] + 1]++;
  }
  for (let c = 0; c < cells; c++) start[c + 1] += start[c];
  const fill = start.slice(0, cells);
  for (let i = 0; i < m; i++) order[fill[key[i]]++] = i;
  const most = Math.max(...dims);
  for (let q = 0; q < n; q++) {
    const x = query[3 * q], y = query[3 * q + 1], z = query[3 * q + 2];
    const c = [cellOf(x, 0), cellOf(y, 1), cellOf(z, 2)];
    let best = -1, bestD = Infinity;
    for (let r = 0; r <= most; r++) {
      // every point in shell r is at least (r - 1) cells away
      if (best >= 0 && (r - 1) * cell * ((r - 1) * cell) > bestD) break;
      for (let i = c[0] - r; i <= c[0] + r; i++) {
        if (i < 0 || i >= dims[0]) continue;
        for (let j = c[1] - r; j <= c[1] + r; j++) {
          if (j < 0 || j >= dims[1]) continue;
          for (let k = c[2] - r; k <= c[2] + r; k++) {
            if (k < 0 || k >= dims[2]) continue;
            const onShell = Math.max(Math.abs(i - c[0]), Math.abs(j - c[1]),
                                     Math.abs(k - c[2])) === r;
            if (!onShell) continue;
            const id = (i * dims[1] + j) * dims[2] + k;
            for (let s = start[id]; s < start[id + 1]; s++) {
              const p = order[s];
              const dx = points[3 * p] - x, dy = points[3 * p + 1] - y, dz = points[3 * p + 2] - z;
              const d = dx * dx + dy * dy + dz * dz;
              if (d < bestD) [best, bestD] = [p, d];
            }
          }
        }
      }
    }
    out[q] = best;
  }
  return out;
}
