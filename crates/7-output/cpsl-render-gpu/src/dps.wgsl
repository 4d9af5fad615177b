// Pass 2: the Dynamic Pixel Strip (paper eq. 4) as cpsl-render's dps.rs: an uncovered pixel
// (alpha < 1/2) with covered pixels within 2s on two opposite sides along its row or column
// takes (1 - gamma) C_f + gamma C_b of the nearest foreground and background sides found along
// eight directions, gamma from the screen distances sharpened by the Edge-Depth Cache.

@group(0) @binding(2) var image: texture_2d<f32>;

fn img(p: vec2<i32>) -> vec4<f32> {
    return floor(textureLoad(image, p, 0) * 255.0 + 0.5);
}

fn covered(p: vec2<i32>) -> bool {
    return img(p).a >= 128.0;
}

fn alpha_at(k: i32, s: vec2<f32>) -> f32 {
    let f = floor(s);
    let a = s - f;
    let i = vec2<i32>(f);
    let top = mix(texel(k, i).a, texel(k, i + vec2<i32>(1, 0)).a, a.x);
    let bottom = mix(texel(k, i + vec2<i32>(0, 1)).a, texel(k, i + vec2<i32>(1, 1)).a, a.x);
    return mix(top, bottom, a.y) / 255.0;
}

fn visible_layer(p: vec2<i32>) -> i32 {
    for (var k = 0; k < P.layers; k++) {
        let w = warp(k, vec2<f32>(p));
        if (w.z <= 0.0) {
            continue;
        }
        let s = w.xy;
        if (!(s.x > -1.0 && s.y > -1.0 && s.x < f32(P.size.x) && s.y < f32(P.size.y))) {
            continue;
        }
        if (alpha_at(k, s) >= 0.5) {
            return k;
        }
    }
    return -1;
}

fn inside(q: vec2<i32>) -> bool {
    return q.x >= 0 && q.y >= 0 && q.x < P.size.x && q.y < P.size.y;
}

fn near_along(p: vec2<i32>, d: vec2<i32>) -> bool {
    for (var step = 1; step <= P.reach; step++) {
        let q = p + d * step;
        if (!inside(q)) {
            return false;
        }
        if (covered(q)) {
            return true;
        }
    }
    return false;
}

fn log_depth(k: i32) -> f32 {
    return P.log_depth[k / 4][k % 4];
}

fn pair_offsets(f: i32, b: i32) -> vec2<f32> {
    let i = b * 16 + f;
    let v = P.offsets[i / 2];
    if (i % 2 == 0) {
        return v.xy;
    }
    return v.zw;
}

@fragment
fn fs(@builtin(position) pos: vec4<f32>) -> @location(0) vec4<f32> {
    return shade(vec2<i32>(floor(pos.xy)));
}

fn shade(p: vec2<i32>) -> vec4<f32> {
    let here = img(p);
    if (here.a >= 128.0) {
        return here / 255.0;
    }
    if (!((near_along(p, vec2<i32>(1, 0)) && near_along(p, vec2<i32>(-1, 0)))
        || (near_along(p, vec2<i32>(0, 1)) && near_along(p, vec2<i32>(0, -1))))) {
        return here / 255.0;
    }
    var dirs = array<vec2<i32>, 8>(
        vec2<i32>(1, 0), vec2<i32>(-1, 0), vec2<i32>(0, 1), vec2<i32>(0, -1),
        vec2<i32>(1, 1), vec2<i32>(-1, -1), vec2<i32>(1, -1), vec2<i32>(-1, 1));
    var len: array<f32, 8>;
    var at: array<vec2<i32>, 8>;
    var lay: array<i32, 8>;
    for (var d = 0; d < 8; d++) {
        lay[d] = -1;
        for (var step = 1; step <= P.reach; step++) {
            let q = p + dirs[d] * step;
            if (!inside(q)) {
                break;
            }
            if (covered(q)) {
                let k = visible_layer(q);
                if (k >= 0) {
                    len[d] = length(vec2<f32>(dirs[d])) * f32(step);
                    at[d] = q;
                    lay[d] = k;
                }
                break;
            }
        }
    }
    var two_sided = false;
    for (var i = 0; i < 4; i++) {
        two_sided = two_sided || (lay[2 * i] >= 0 && lay[2 * i + 1] >= 0);
    }
    if (!two_sided) {
        return here / 255.0;
    }
    var f = 16;
    var b = -1;
    for (var d = 0; d < 8; d++) {
        if (lay[d] >= 0) {
            f = min(f, lay[d]);
            b = max(b, lay[d]);
        }
    }
    // Nearest side of each layer: the first in direction order among equals, as the CPU does.
    var df = 1e9;
    var db = 1e9;
    var qf = p;
    var qb = p;
    for (var d = 0; d < 8; d++) {
        if (lay[d] == f && len[d] < df) {
            df = len[d];
            qf = at[d];
        }
        if (lay[d] == b && len[d] < db) {
            db = len[d];
            qb = at[d];
        }
    }
    var gamma = 0.0;
    if (f != b) {
        gamma = df / (df + db);
        let off = pair_offsets(f, b);
        let zf = log_depth(f);
        let zb = log_depth(b);
        let r = clamp((zb + off.y - zf - off.x) / (zb - zf), 0.0, 2.0);
        gamma = clamp(0.5 + (gamma - 0.5) * (1.0 + r), 0.0, 1.0);
    }
    let cf = img(qf);
    let cb = img(qb);
    let strip = (1.0 - gamma) * (cf.rgb / max(cf.a, 1.0) * 255.0)
        + gamma * (cb.rgb / max(cb.a, 1.0) * 255.0);
    let t = 1.0 - here.a / 255.0;
    return vec4<f32>(clamp(floor(here.rgb + t * strip + 0.5), vec3<f32>(0.0), vec3<f32>(255.0)) / 255.0, 1.0);
}
