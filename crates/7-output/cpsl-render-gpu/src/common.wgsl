// Shared by both passes (prepended to each): parameters, the layer texels, the warp and the
// entry points.

struct Params {
    size: vec2<i32>,              // layer (and output) size
    layers: i32,                  // layers in use
    reach: i32,                   // DPS search reach 2s, in pixels
    h: array<mat3x3<f32>, 16>,    // per layer: target pixel -> source pixel
    log_depth: array<vec4<f32>, 4>,
    offsets: array<vec4<f32>, 128>, // EDC mean offsets of pair (f, b) at b * 16 + f: (front, back)
    mesh: array<vec4<i32>, 4>,    // per layer: its slice of the mesh source maps, -1 for a plane
    cubic: i32,                   // 0 bilinear, 1 Catmull-Rom
};

@group(0) @binding(0) var layers: texture_2d_array<f32>;
@group(0) @binding(1) var<uniform> P: Params;
@group(0) @binding(3) var maps: texture_2d_array<f32>;
@group(0) @binding(4) var tri_h: texture_2d<f32>;

// The compute form of each pass writes here (group 1, bound only for it).
@group(1) @binding(0) var out_image: texture_storage_2d<rgba8unorm, write>;

// Both passes run as a full-screen triangle (`vs` + the pass's `fs`) or as a compute shader
// (`cs`) over 8x8 tiles; each calls the pass's `shade(pixel)`.
@compute @workgroup_size(8, 8)
fn cs(@builtin(global_invocation_id) id: vec3<u32>) {
    let size = textureDimensions(out_image);
    if (id.x >= size.x || id.y >= size.y) {
        return;
    }
    textureStore(out_image, vec2<i32>(id.xy), shade(vec2<i32>(id.xy)));
}

@vertex
fn vs(@builtin(vertex_index) i: u32) -> @builtin(position) vec4<f32> {
    let p = vec2<f32>(f32((i << 1u) & 2u), f32(i & 2u));
    return vec4<f32>(p * 2.0 - 1.0, 0.0, 1.0);
}

fn q8(v: f32) -> f32 {
    return clamp(floor(v + 0.5), 0.0, 255.0);
}

// Premultiplied RGBA of layer k at texel t, in 0..255; transparent outside the layer.
fn texel(k: i32, t: vec2<i32>) -> vec4<f32> {
    if (t.x < 0 || t.y < 0 || t.x >= P.size.x || t.y >= P.size.y) {
        return vec4<f32>(0.0);
    }
    return floor(textureLoad(layers, t, k, 0) * 255.0 + 0.5);
}

// Source position of target pixel px on layer k; w <= 0 where its surface is not visible.
fn warp(k: i32, px: vec2<f32>) -> vec3<f32> {
    let slice = P.mesh[k / 4][k % 4];
    if (slice >= 0) {
        // The pixel's triangle (number + 1 in four bytes, 0 for none) and its homography.
        let b = vec4<u32>(round(textureLoad(maps, vec2<i32>(px), slice, 0) * 255.0));
        let id = b.x | (b.y << 8u) | (b.z << 16u) | (b.w << 24u);
        if (id == 0u) {
            return vec3<f32>(0.0, 0.0, -1.0);
        }
        let t = i32(id - 1u);
        let at = vec2<i32>((t % 1024) * 3, t / 1024);
        let p = vec3<f32>(px, 1.0);
        let hm = vec3<f32>(
            dot(textureLoad(tri_h, at, 0).xyz, p),
            dot(textureLoad(tri_h, at + vec2<i32>(1, 0), 0).xyz, p),
            dot(textureLoad(tri_h, at + vec2<i32>(2, 0), 0).xyz, p),
        );
        if (hm.z <= 0.0) {
            return vec3<f32>(0.0, 0.0, -1.0);
        }
        return vec3<f32>(hm.xy / hm.z, 1.0);
    }
    let h = P.h[k] * vec3<f32>(px, 1.0);
    if (h.z <= 0.0) {
        return vec3<f32>(0.0, 0.0, -1.0);
    }
    return vec3<f32>(h.xy / h.z, 1.0);
}
