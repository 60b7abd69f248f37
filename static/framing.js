// Framing a mesh: its box fitted into the part of the viewport the panel
// leaves free (aspect ratio included), from the front of its up axis; how
// many pixels a mesh unit covers; and the first level worth drawing.
//
// Functions of plain numbers and arrays (and a three.js camera where one is
// moved), so the stream can pick the first level before any level is fetched.
//
// Units: positions and errors in mesh units, sizes in CSS pixels, angles in degrees.

import { ErrorCurve } from './curve.js';

// From the box's centre towards the camera, in the (right, up, front) frame of
// the up axis: in front, a little above and to the right.
const VIEW_DIRECTION = [0.35, 0.25, 1];
// The box fills at most this share of the free area's smaller side.
const MARGIN = 1.08;

// (right, up, front) unit axes for up axis 'Y' (glTF's) or 'Z' (CAD, many scans).
export function axesFor(up) {
  return up === 'Z' ? { right: [1, 0, 0], up: [0, 0, 1], front: [0, -1, 0] }
                    : { right: [1, 0, 0], up: [0, 1, 0], front: [0, 0, 1] };
}

const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const normalize = (a) => { const n = Math.hypot(...a) || 1; return a.map((x) => x / n); };
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                         a[0] * b[1] - a[1] * b[0]];

// The up axis a mesh is probably modelled in: glTF says Y; other formats say
// nothing, and a scan or a CAD part standing on Z is taller in Z than in Y
// while a Y-up one is the other way round (or flat, then Y).
// info: GET /meshes/{id} (file_type, bounds). Returns 'Y' or 'Z'.
export function guessUpAxis(info) {
  if (!info?.bounds || ['glb', 'gltf'].includes(info.file_type)) return 'Y';
  const { min, max } = info.bounds;
  const [, dy, dz] = max.map((x, k) => x - min[k]);
  return dz > 1.2 * dy ? 'Z' : 'Y';
}

// The centre and radius of a box {min, max}.
export function sphereOf(box) {
  const center = box.min.map((x, k) => (x + box.max[k]) / 2);
  const radius = Math.hypot(...box.max.map((x, k) => x - box.min[k])) / 2;
  return { center, radius };
}

// The part of the viewport (width x height) a panel rectangle (or null) leaves
// free: the larger of the strip right of it and the strip above it.
// Returns { x, y, width, height } in viewport pixels (y down).
export function freeArea(width, height, panel) {
  if (!panel || panel.width === 0 || panel.height === 0) return { x: 0, y: 0, width, height };
  const right = { x: panel.right, y: 0, width: width - panel.right, height };
  const above = { x: 0, y: 0, width, height: panel.top };
  const area = (r) => Math.max(0, r.width) * Math.max(0, r.height);
  const best = area(right) >= area(above) ? right : above;
  // a panel covering most of the screen: use the screen, under the panel
  return area(best) < 0.2 * width * height ? { x: 0, y: 0, width, height } : best;
}

// Where the camera goes to see the whole box in `free` of a width x height
// viewport with vertical field of view fov: the box's eight corners inside the
// frustum of the free area, looked at along the up axis' view direction.
// Returns { position, target, up, distance, near, far, radius }.
export function fitBox(box, { fov, width, height, free = null, up = 'Y' }) {
  free = free || { x: 0, y: 0, width, height };
  const axes = axesFor(up);
  const [a, b, c] = VIEW_DIRECTION;
  const back = normalize(axes.right.map((x, k) => a * x + b * axes.up[k] + c * axes.front[k]));
  const side = normalize(cross(axes.up, back));
  const lift = cross(back, side);
  const tanV = Math.tan((fov * Math.PI) / 360);
  // the free area's half-angles (the camera's principal point is moved to its centre)
  const tanY = tanV * free.height / height, tanX = tanV * free.width / height;
  const { center, radius } = sphereOf(box);
  let distance = 0;
  for (let corner = 0; corner < 8; corner++) {
    const p = [0, 1, 2].map((k) => ((corner >> k) & 1 ? box.max[k] : box.min[k]) - center[k]);
    const depth = dot(p, back);            // towards the camera
    distance = Math.max(distance, depth + Math.abs(dot(p, side)) / tanX,
                        depth + Math.abs(dot(p, lift)) / tanY);
  }
  distance = Math.max(distance * MARGIN, radius * 1e-3, 1e-9);
  return { position: center.map((x, k) => x + distance * back[k]), target: center,
           up: axes.up, distance, radius: Math.max(radius, 1e-9),
           // as close as a hundredth of the mesh and out to where the controls stop
           near: Math.max(radius, 1e-9) / 100, far: Math.max(radius * 100, distance * 4) };
}

// How many CSS pixels one mesh unit covers at the nearest point of a sphere
// (center, radius) seen from `distance`, in a viewport `height` pixels tall.
export function pixelsPerUnit(distance, radius, { fov, height, near = 1e-9 }) {
  const nearest = Math.max(distance - radius, near);
  return height / (2 * Math.tan((fov * Math.PI) / 360) * nearest);
}

// The first level to draw: the coarsest whose error, at the mesh's nearest
// point seen from the initial framing, projects to at most budgetPx pixels
// (the same rule as the auto mode). info: GET /meshes/{id} (bounds,
// error_curve, base_vertices, vertices, max_error); view: { fov, width,
// height, free, up } as for fitBox. Without bounds (a mesh recorded before
// they were), full detail: never a shard.
export function firstLevel(info, view, budgetPx) {
  if (!info.bounds) return info.vertices;
  const fit = fitBox(info.bounds, view);
  const scale = pixelsPerUnit(fit.distance, fit.radius, { ...view, near: fit.near });
  const curve = new ErrorCurve(info, info.max_error ?? 0);
  return curve.levelFor(budgetPx / scale);
}
