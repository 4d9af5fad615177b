// Camera, pose and the plane-induced homography, exactly as cpsl-core computes them
// (crates/1-base/cpsl-core/src/{camera,pose,homography}.rs), in f64.

/** Row-major 3x3 matrix. */
export type Mat3 = number[][];

export interface Camera {
  width: number;
  height: number;
  fx: number;
  fy: number;
  cx: number;
  cy: number;
}

/** Viewer pose: X_ref = R X_view + t (viewer position t in the reference camera frame). */
export interface Pose {
  rotation: Mat3;
  translation: [number, number, number];
}

export function mul(a: Mat3, b: Mat3): Mat3 {
  const m: Mat3 = [
    [0, 0, 0],
    [0, 0, 0],
    [0, 0, 0],
  ];
  for (let r = 0; r < 3; r++)
    for (let c = 0; c < 3; c++) m[r][c] = a[r][0] * b[0][c] + a[r][1] * b[1][c] + a[r][2] * b[2][c];
  return m;
}

const rotX = (a: number): Mat3 => [
  [1, 0, 0],
  [0, Math.cos(a), -Math.sin(a)],
  [0, Math.sin(a), Math.cos(a)],
];
const rotY = (a: number): Mat3 => [
  [Math.cos(a), 0, Math.sin(a)],
  [0, 1, 0],
  [-Math.sin(a), 0, Math.cos(a)],
];
const rotZ = (a: number): Mat3 => [
  [Math.cos(a), -Math.sin(a), 0],
  [Math.sin(a), Math.cos(a), 0],
  [0, 0, 1],
];

/** `Pose::from_euler_deg`: R = Ry Rx Rz, angles in degrees. */
export function poseFromEuler(t: [number, number, number], rx: number, ry: number, rz: number): Pose {
  const d = Math.PI / 180;
  return { rotation: mul(mul(rotY(ry * d), rotX(rx * d)), rotZ(rz * d)), translation: t };
}

/** Parses `tx,ty,tz,rx,ry,rz` like `Pose::parse`. */
export function parsePose(s: string): Pose {
  const v = s.split(",").map((p) => Number(p.trim()));
  if (v.length !== 6 || v.some((x) => !Number.isFinite(x)))
    throw new Error(`pose '${s}': expected 6 finite numbers tx,ty,tz,rx,ry,rz`);
  return poseFromEuler([v[0], v[1], v[2]], v[3], v[4], v[5]);
}

const K = (c: Camera): Mat3 => [
  [c.fx, 0, c.cx],
  [0, c.fy, c.cy],
  [0, 0, 1],
];
const Kinv = (c: Camera): Mat3 => [
  [1 / c.fx, 0, -c.cx / c.fx],
  [0, 1 / c.fy, -c.cy / c.fy],
  [0, 0, 1],
];

/**
 * `Homography::plane_inverse`: maps target (viewer) pixels to source (layer) pixels for the
 * fronto-parallel plane at `depth`; null when the viewer is on or behind the plane.
 */
export function planeInverse(src: Camera, dst: Camera, pose: Pose, depth: number): Mat3 | null {
  const t = pose.translation;
  const gap = depth - t[2];
  if (!(gap > 1e-6)) return null;
  const m: Mat3 = [
    [gap, 0, t[0]],
    [0, gap, t[1]],
    [0, 0, gap + t[2]],
  ];
  const h = mul(mul(mul(K(src), m), pose.rotation), Kinv(dst));
  return h.map((row) => row.map((v) => v / depth));
}

/** A layer's surface: the fronto-parallel plane at its depth, or the slanted plane `m . X = 1`. */
export type Geometry = { kind: "plane" } | { kind: "slanted"; m: [number, number, number] };

/**
 * `Geometry::inverse_homography`: the inverse homography of a layer at reference depth `depth`
 * on `geometry`; null when the viewer is not on the reference camera's side of its plane.
 */
export function layerInverse(src: Camera, dst: Camera, pose: Pose, depth: number, geometry: Geometry): Mat3 | null {
  if (geometry.kind === "plane") return planeInverse(src, dst, pose, depth);
  const m = geometry.m;
  const t = pose.translation;
  const gap = 1 - (m[0] * t[0] + m[1] * t[1] + m[2] * t[2]);
  if (!(gap > 1e-6 * Math.hypot(m[0], m[1], m[2]))) return null;
  const a: Mat3 = [0, 1, 2].map((r) => [0, 1, 2].map((c) => (r === c ? gap : 0) + t[r] * m[c])) as Mat3;
  return mul(mul(mul(K(src), a), pose.rotation), Kinv(dst));
}

/**
 * Inverse depth `a x + b y + c` in reference pixels of a slanted layer, and the margin below
 * which `Layer::clip_to_geometry` clears its texels (`[0, 0, 1, 0]`: nothing cleared).
 */
export function horizonClip(cam: Camera, geometry: Geometry): [number, number, number, number] {
  if (geometry.kind === "plane") return [0, 0, 1, 0];
  const [mx, my, mz] = geometry.m;
  const a = mx / cam.fx;
  const b = my / cam.fy;
  return [a, b, mz - a * cam.cx - b * cam.cy, Math.abs(a) + Math.abs(b)];
}

/** `Pose::ref_to_view`. */
function refToView(pose: Pose, p: [number, number, number]): [number, number, number] {
  const d = [p[0] - pose.translation[0], p[1] - pose.translation[1], p[2] - pose.translation[2]];
  const r = pose.rotation;
  return [
    r[0][0] * d[0] + r[1][0] * d[1] + r[2][0] * d[2],
    r[0][1] * d[0] + r[1][1] * d[1] + r[2][1] * d[2],
    r[0][2] * d[0] + r[1][2] * d[1] + r[2][2] * d[2],
  ];
}

/**
 * The Dynamic Pixel Strip's half-width `s` (cpsl-render dps.rs): the largest screen-space
 * parallax between neighbouring layers at the image centre, plus one, within [1, max].
 */
export function stripWidth(target: Camera, pose: Pose, depths: number[], max = 8): number {
  const at = (z: number): [number, number] | null => {
    const p = refToView(pose, [0, 0, z]);
    if (!(p[2] > 0)) return null;
    return [target.fx * (p[0] / p[2]) + target.cx, target.fy * (p[1] / p[2]) + target.cy];
  };
  let par = 0;
  for (let i = 0; i + 1 < depths.length; i++) {
    const a = at(depths[i]);
    const b = at(depths[i + 1]);
    if (a && b) par = Math.max(par, Math.hypot(a[0] - b[0], a[1] - b[1]));
  }
  return Math.min(Math.max(Math.ceil(par) + 1, 1), Math.max(max, 1));
}
