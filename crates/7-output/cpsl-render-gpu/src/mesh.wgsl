// Mesh layers: each pixel's nearest visible triangle, by number (plus one, 0 for none, in the
// four bytes of an RGBA8 texel), into the layer's slice of the triangle map; the composite
// applies that triangle's homography, exactly as for a plane.

struct Out {
    @builtin(position) pos: vec4<f32>,
    @location(0) @interpolate(flat) tri: u32,
};

@vertex
fn vs(@location(0) clip: vec4<f32>, @location(1) tri: u32) -> Out {
    return Out(clip, tri);
}

@fragment
fn fs(v: Out) -> @location(0) vec4<f32> {
    let id = v.tri + 1u;
    return vec4<f32>(
        f32(id & 255u),
        f32((id >> 8u) & 255u),
        f32((id >> 16u) & 255u),
        f32(id >> 24u),
    ) / 255.0;
}
