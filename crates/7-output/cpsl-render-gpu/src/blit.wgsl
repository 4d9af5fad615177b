// Copies an RGBA8 image onto a rectangle of the target, nearest-neighbour (1:1 when the
// rectangle has the image's size); blending (premultiplied) is set in the pipeline.

struct Rect {
    r: vec4<f32>,   // x, y, width, height in target pixels
};

@group(0) @binding(0) var src: texture_2d<f32>;
@group(0) @binding(1) var<uniform> R: Rect;

@vertex
fn vs(@builtin(vertex_index) i: u32) -> @builtin(position) vec4<f32> {
    let p = vec2<f32>(f32((i << 1u) & 2u), f32(i & 2u));
    return vec4<f32>(p * 2.0 - 1.0, 0.0, 1.0);
}

@fragment
fn fs(@builtin(position) pos: vec4<f32>) -> @location(0) vec4<f32> {
    let size = vec2<f32>(textureDimensions(src));
    let rel = (pos.xy - R.r.xy) / R.r.zw;
    let p = vec2<i32>(clamp(floor(rel * size), vec2<f32>(0.0), size - 1.0));
    return textureLoad(src, p, 0);
}
