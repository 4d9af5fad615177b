// Pass 1: every layer warped by its inverse homography, sampled bilinearly at positions
// rounded to 1/256 px (as the CPU renderer's fixed point), composited front to back
// (paper eq. 2): I += T P, T *= 1 - alpha. Output: premultiplied RGBA8 with alpha 1 - T.

@fragment
fn fs(@builtin(position) pos: vec4<f32>) -> @location(0) vec4<f32> {
    return shade(vec2<i32>(floor(pos.xy)));
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
        let top = mix(texel(k, i0), texel(k, i0 + vec2<i32>(1, 0)), a.x);
        let bottom = mix(texel(k, i0 + vec2<i32>(0, 1)), texel(k, i0 + vec2<i32>(1, 1)), a.x);
        let v = floor(mix(top, bottom, a.y) + 0.5);
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
