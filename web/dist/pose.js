// Camera, pose and the plane-induced homography, exactly as cpsl-core computes them
// (crates/1-base/cpsl-core/src/{camera,pose,homography}.rs), in f64.
export function mul(a, b) {
    const m = [
        [0, 0, 0],
        [0, 0, 0],
        [0, 0, 0],
    ];
    for (let r = 0; r < 3; r++)
        for (let c = 0; c < 3; c++)
            m[r][c] = a[r][0] * b[0][c] + a[r][1] * b[1][c] + a[r][2] * b[2][c];
    return m;
}
const rotX = (a) => [
    [1, 0, 0],
    [0, Math.cos(a), -Math.sin(a)],
    [0, Math.sin(a), Math.cos(a)],
];
const rotY = (a) => [
    [Math.cos(a), 0, Math.sin(a)],
    [0, 1, 0],
    [-Math.sin(a), 0, Math.cos(a)],
];
const rotZ = (a) => [
    [Math.cos(a), -Math.sin(a), 0],
    [Math.sin(a), Math.cos(a), 0],
    [0, 0, 1],
];
/** `Pose::from_euler_deg`: R = Ry Rx Rz, angles in degrees. */
export function poseFromEuler(t, rx, ry, rz) {
    const d = Math.PI / 180;
    return { rotation: mul(mul(rotY(ry * d), rotX(rx * d)), rotZ(rz * d)), translation: t };
}
/** Parses `tx,ty,tz,rx,ry,rz` like `Pose::parse`. */
export function parsePose(s) {
    const v = s.split(",").map((p) => Number(p.trim()));
    if (v.length !== 6 || v.some((x) => !Number.isFinite(x)))
        throw new Error(`pose '${s}': expected 6 finite numbers tx,ty,tz,rx,ry,rz`);
    return poseFromEuler([v[0], v[1], v[2]], v[3], v[4], v[5]);
}
const K = (c) => [
    [c.fx, 0, c.cx],
    [0, c.fy, c.cy],
    [0, 0, 1],
];
const Kinv = (c) => [
    [1 / c.fx, 0, -c.cx / c.fx],
    [0, 1 / c.fy, -c.cy / c.fy],
    [0, 0, 1],
];
/**
 * `Homography::plane_inverse`: maps target (viewer) pixels to source (layer) pixels for the
 * fronto-parallel plane at `depth`; null when the viewer is on or behind the plane.
 */
export function planeInverse(src, dst, pose, depth) {
    const t = pose.translation;
    const gap = depth - t[2];
    if (!(gap > 1e-6))
        return null;
    const m = [
        [gap, 0, t[0]],
        [0, gap, t[1]],
        [0, 0, gap + t[2]],
    ];
    const h = mul(mul(mul(K(src), m), pose.rotation), Kinv(dst));
    return h.map((row) => row.map((v) => v / depth));
}
/**
 * `Geometry::inverse_homography`: the inverse homography of a layer at reference depth `depth`
 * on `geometry`; null when the viewer is not on the reference camera's side of its plane.
 */
export function layerInverse(src, dst, pose, depth, geometry) {
    if (geometry.kind === "plane")
        return planeInverse(src, dst, pose, depth);
    if (geometry.kind === "mesh")
        return null;
    const m = geometry.m;
    const t = pose.translation;
    const gap = 1 - (m[0] * t[0] + m[1] * t[1] + m[2] * t[2]);
    if (!(gap > 1e-6 * Math.hypot(m[0], m[1], m[2])))
        return null;
    const a = [0, 1, 2].map((r) => [0, 1, 2].map((c) => (r === c ? gap : 0) + t[r] * m[c]));
    return mul(mul(mul(K(src), a), pose.rotation), Kinv(dst));
}
/**
 * Inverse depth `a x + b y + c` in reference pixels of a slanted layer, and the margin below
 * which `Layer::clip_to_geometry` clears its texels (`[0, 0, 1, 0]`: nothing cleared).
 */
export function horizonClip(cam, geometry) {
    if (geometry.kind !== "slanted")
        return [0, 0, 1, 0];
    const [mx, my, mz] = geometry.m;
    const a = mx / cam.fx;
    const b = my / cam.fy;
    return [a, b, mz - a * cam.cx - b * cam.cy, Math.abs(a) + Math.abs(b)];
}
/**
 * The visible triangles of a mesh layer for the viewer at `pose`, as the Rust renderers select
 * them (`cpsl_render::mesh::visible_triangles`, without its test for empty cells: their
 * texels are transparent). `clip`: per vertex the clip position (x, y, z, w = viewer depth,
 * framebuffer rows following image rows) and the triangle's number from `first` on, 5 floats;
 * `h`: per triangle the inverse homography of its plane (`Geometry::inverse_homography`), row
 * by row, each row padded to 4 floats.
 */
export function meshTriangles(cam, grid, pose, first) {
    const { step, cols, rows, inv } = grid;
    const vx = (i) => Math.min(i * step, cam.width) - 0.5;
    const vy = (j) => Math.min(j * step, cam.height) - 0.5;
    // Reference point, target position and viewer depth per vertex (NaN depth behind the viewer).
    const ref = [];
    const px = new Float64Array(cols * rows * 3);
    for (let j = 0; j < rows; j++)
        for (let i = 0; i < cols; i++) {
            const k = j * cols + i;
            const z = 1 / inv[k];
            ref.push([((vx(i) - cam.cx) / cam.fx) * z, ((vy(j) - cam.cy) / cam.fy) * z, z]);
            const p = refToView(pose, ref[k]);
            if (!(p[2] > 1e-9)) {
                px[3 * k + 2] = NaN;
                continue;
            }
            px.set([(cam.fx * p[0]) / p[2] + cam.cx, (cam.fy * p[1]) / p[2] + cam.cy, p[2]], 3 * k);
        }
    const tris = [];
    const hs = [];
    let near = Infinity;
    for (let cj = 0; cj + 1 < rows; cj++)
        for (let ci = 0; ci + 1 < cols; ci++)
            for (const ids of [
                [ci, cj, ci + 1, cj, ci + 1, cj + 1],
                [ci, cj, ci + 1, cj + 1, ci, cj + 1],
            ]) {
                const k = [0, 1, 2].map((v) => ids[2 * v + 1] * cols + ids[2 * v]);
                if (!k.every((q) => px[3 * q + 2] > 0))
                    continue;
                const [a, b, c] = k.map((q) => [px[3 * q], px[3 * q + 1], px[3 * q + 2]]);
                if (!((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]) > 0))
                    continue;
                // The plane m . X = 1 through the three reference points.
                const m = solve3(k.map((q) => ref[q]), [1, 1, 1]);
                const h = m && layerInverse(cam, cam, pose, 1, { kind: "slanted", m });
                if (!h || !h.flat().every(Number.isFinite))
                    continue;
                tris.push(k);
                hs.push(h);
                near = Math.min(near, a[2], b[2], c[2]);
            }
    near *= 0.999;
    const clip = new Float32Array(tris.length * 15);
    const h = new Float32Array(tris.length * 12);
    tris.forEach((k, t) => {
        k.forEach((q, v) => {
            const [x, y, z] = [px[3 * q], px[3 * q + 1], px[3 * q + 2]];
            const nx = ((x + 0.5) / cam.width) * 2 - 1;
            const ny = ((y + 0.5) / cam.height) * 2 - 1;
            clip.set([nx * z, ny * z, z - near, z, first + t], (3 * t + v) * 5);
        });
        hs[t].forEach((row, r) => h.set(row, t * 12 + r * 4));
    });
    return { clip, h };
}
/** Solves `a x = b` (Cramer's rule); null when `a` is singular. */
function solve3(a, b) {
    const det = (m) => m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) -
        m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0]) +
        m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
    const d = det(a);
    if (!(Math.abs(d) > 1e-300))
        return null;
    return [0, 1, 2].map((c) => det(a.map((row, r) => row.map((v, j) => (j === c ? b[r] : v)))) / d);
}
/** `Pose::ref_to_view`. */
function refToView(pose, p) {
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
export function stripWidth(target, pose, depths, max = 8) {
    const at = (z) => {
        const p = refToView(pose, [0, 0, z]);
        if (!(p[2] > 0))
            return null;
        return [target.fx * (p[0] / p[2]) + target.cx, target.fy * (p[1] / p[2]) + target.cy];
    };
    let par = 0;
    for (let i = 0; i + 1 < depths.length; i++) {
        const a = at(depths[i]);
        const b = at(depths[i + 1]);
        if (a && b)
            par = Math.max(par, Math.hypot(a[0] - b[0], a[1] - b[1]));
    }
    return Math.min(Math.max(Math.ceil(par) + 1, 1), Math.max(max, 1));
}
