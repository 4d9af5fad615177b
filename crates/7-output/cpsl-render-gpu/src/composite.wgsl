// Pass 1: every layer warped by its inverse homography, sampled bilinearly (or with the
// Catmull-Rom kernel) at positions rounded to 1/256 px (as the CPU renderer's fixed point),
// composited front to back
// (paper eq. 2): I += T P, T *= 1 - alpha. Output: premultiplied RGBA8 with alpha 1 - T.

@fragment
fn fs(@builtin(position) pos: vec4<f32>) -> @location(0) vec4<f32> {
    return shade(vec2<i32>(floor(pos.xy)));
}

// Catmull-Rom weights of the taps at -1, 0, 1, 2 for fraction f.
fn cubic_weights(f: f32) -> vec4<f32> {
    let f2 = f * f;
    let f3 = f2 * f;
    return 0.5 * vec4<f32>(-f3 + 2.0 * f2 - f, 3.0 * f3 - 5.0 * f2 + 2.0,
                           -3.0 * f3 + 4.0 * f2 + f, f3 - f2);
}

// Catmull-Rom sample of layer k around texel i0 at fraction a, rounded to 0..255, colour at
// most alpha (as the CPU renderer's).
fn cubic(k: i32, i0: vec2<i32>, a: vec2<f32>) -> vec4<f32> {
    let wx = cubic_weights(a.x);
    let wy = cubic_weights(a.y);
    var acc = vec4<f32>(0.0);
    for (var j = 0; j < 4; j++) {
        let y = i0.y + j - 1;
        let row = wx.x * texel(k, vec2<i32>(i0.x - 1, y)) + wx.y * texel(k, vec2<i32>(i0.x, y))
            + wx.z * texel(k, vec2<i32>(i0.x + 1, y)) + wx.w * texel(k, vec2<i32>(i0.x + 2, y));
        acc += wy[j] * row;
    }
    let al = clamp(floor(acc.a + 0.5), 0.0, 255.0);
    return vec4<f32>(min(max(floor(acc.rgb + 0.5), vec3<f32>(0.0)), vec3<f32>(al)), al);
}

fn shade(p: vec2<i32>) -> vec4<f32> {
    let px = vec2<f32>(p);
    var o = vec4<f32>(0.0);
    var t = 1.0;
    for (var k = 0; k < P.layers; k++) {
        let w = warp(k, px);
        if (w.z <= 0.0) {
            continue;
        }
        let fi = floor(w.xy * 256.0 + 0.5);
        let f0 = floor(fi / 256.0);
        let a = (fi - f0 * 256.0) / 256.0;
        let i0 = vec2<i32>(f0);
        if (i0.x < -1 || i0.y < -1 || i0.x >= P.size.x || i0.y >= P.size.y) {
            continue;
        }
        let p00 = texel(k, i0);
        let p01 = texel(k, i0 + vec2<i32>(1, 0));
        let p10 = texel(k, i0 + vec2<i32>(0, 1));
        let p11 = texel(k, i0 + vec2<i32>(1, 1));
        var v: vec4<f32>;
        if (P.cubic == 1) {
            // As the CPU: only where one of the central four texels is covered.
            if (all(p00 + p01 + p10 + p11 == vec4<f32>(0.0))) {
                continue;
            }
            v = cubic(k, i0, a);
        } else {
            v = floor(mix(mix(p00, p01, a.x), mix(p10, p11, a.x), a.y) + 0.5);
        }
        if (v.a <= 0.0) {
            continue;
        }
        o += t * v;
        t *= 1.0 - v.a / 255.0;
        if (t <= 0.0) {
            break;
        }
    }
    let al = q8(o.a);
    return vec4<f32>(min(vec3<f32>(q8(o.r), q8(o.g), q8(o.b)), vec3<f32>(al)), al) / 255.0;
}
