// Mesh layers: each visible triangle rasterised into the layer's source map with its source
// (reference) pixel position, interpolated with perspective correction (clip w = viewer
// depth), which on a planar triangle is exactly its homography; the nearest triangle wins
// where a fold overlaps itself. The composite reads the map instead of a homography.

struct Out {
    @builtin(position) pos: vec4<f32>,
    @location(0) src: vec2<f32>,
};

@vertex
fn vs(@location(0) clip: vec4<f32>, @location(1) src: vec2<f32>) -> Out {
    return Out(clip, src);
}

@fragment
fn fs(v: Out) -> @location(0) vec4<f32> {
    return vec4<f32>(v.src, 1.0, 0.0);
}
