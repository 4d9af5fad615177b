// Push-pull fill of what a view leaves uncovered, as `PremulImage::over_fill` does on the CPU
// (`cpsl_core::fill::push_pull` with the alpha as weight): full-screen passes, one per
// pyramid level. Each level holds premultiplied colour in rgb and its weight in a.
//
// `push` (level l from level l - 1): each pixel sums its 2x2 block of the finer level and
// clamps the weight to 1, scaling the colour with it. Level 0 is the view itself (RGBA8,
// premultiplied, so its colour is already weighted by its alpha).
//
// `pull` (level l from level l + 1): each pixel keeps its own weighted colour and takes its
// remainder 1 - weight from the bilinear sample of the coarser, already filled level at its
// centre. The top level is normalised (colour over weight) as it is read. Level 0's result
// is opaque.

struct Level {
    // x: 1 when the coarser texture is the top of the pyramid (to normalise).
    flags: vec4<u32>,
};

@group(0) @binding(0) var fine: texture_2d<f32>;
@group(0) @binding(1) var coarse: texture_2d<f32>;
@group(0) @binding(2) var<uniform> L: Level;

@vertex
fn vs(@builtin(vertex_index) i: u32) -> @builtin(position) vec4<f32> {
    let p = vec2<f32>(f32((i << 1u) & 2u), f32(i & 2u));
    return vec4<f32>(p * 2.0 - 1.0, 0.0, 1.0);
}

// Level l from `fine` (level l - 1); `coarse` is not read.
@fragment
fn push(@builtin(position) pos: vec4<f32>) -> @location(0) vec4<f32> {
    let size = vec2<i32>(textureDimensions(fine));
    let p = vec2<i32>(pos.xy) * 2;
    var sum = vec4<f32>(0.0);
    for (var dy = 0; dy < 2; dy++) {
        for (var dx = 0; dx < 2; dx++) {
            let q = p + vec2<i32>(dx, dy);
            if (q.x < size.x && q.y < size.y) {
                sum += textureLoad(fine, q, 0);
            }
        }
    }
    if (sum.a > 1.0) {
        sum = sum / sum.a;
    }
    return sum;
}

// The coarse level's filled colour at texel `q`.
fn filled(q: vec2<i32>) -> vec3<f32> {
    let c = textureLoad(coarse, q, 0);
    if (L.flags.x == 1u) {
        return select(vec3<f32>(0.0), c.rgb / c.a, c.a > 0.0);
    }
    return c.rgb;
}

// Where a fine pixel's centre falls on the coarse level: the two taps and the second's weight.
fn taps(i: i32, n: i32) -> vec3<f32> {
    let s = clamp((f32(i) + 0.5) / 2.0 - 0.5, 0.0, f32(n - 1));
    let i0 = floor(s);
    return vec3<f32>(i0, min(i0 + 1.0, f32(n - 1)), s - i0);
}

// Level l filled from `fine` (level l's pushed values) and `coarse` (level l + 1, filled).
@fragment
fn pull(@builtin(position) pos: vec4<f32>) -> @location(0) vec4<f32> {
    let p = vec2<i32>(pos.xy);
    let n = vec2<i32>(textureDimensions(coarse));
    let tx = taps(p.x, n.x);
    let ty = taps(p.y, n.y);
    let x0 = i32(tx.x);
    let x1 = i32(tx.y);
    let y0 = i32(ty.x);
    let y1 = i32(ty.y);
    let up = (filled(vec2<i32>(x0, y0)) * (1.0 - tx.z) + filled(vec2<i32>(x1, y0)) * tx.z) * (1.0 - ty.z)
        + (filled(vec2<i32>(x0, y1)) * (1.0 - tx.z) + filled(vec2<i32>(x1, y1)) * tx.z) * ty.z;
    let own = textureLoad(fine, p, 0);
    return vec4<f32>(own.rgb + (1.0 - own.a) * up, 1.0);
}
