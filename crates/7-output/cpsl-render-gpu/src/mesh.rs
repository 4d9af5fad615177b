//! Mesh layers on the GPU: per view, the triangles both renderers draw
//! ([`cpsl_render::mesh::visible_triangles`]) are rasterised by number into one slice per
//! mesh layer of a triangle map (`mesh.wgsl`; RGBA8, renderable everywhere), and their
//! homographies go into a float texture; the composite and strip passes apply, for those
//! layers, the homography of the pixel's triangle.

use cpsl_core::{Camera, DepthGrid, Pose};
use std::sync::Arc;

/// The triangle-map format: triangle number plus one in four bytes.
pub(crate) const MAP_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// Bytes per vertex: clip position (4 x f32) and triangle number (u32).
const VERTEX_BYTES: u64 = 20;
/// Triangles per row of the homography texture (3 texels each).
pub(crate) const TRIS_PER_ROW: u32 = 1024;

/// A mesh layer as uploaded: its grid and occupied cells.
pub(crate) struct MeshLayer {
    pub grid: Arc<DepthGrid>,
    pub cells: Vec<bool>,
}

/// The pipeline drawing triangles into a source map.
pub(crate) fn pipeline(device: &wgpu::Device) -> wgpu::RenderPipeline {
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some("cpsl mesh"),
        source: wgpu::ShaderSource::Wgsl(crate::MESH_WGSL.into()),
    });
    let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some("cpsl mesh"),
        bind_group_layouts: &[],
        immediate_size: 0,
    });
    device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some("cpsl mesh"),
        layout: Some(&layout),
        vertex: wgpu::VertexState {
            module: &module,
            entry_point: Some("vs"),
            compilation_options: Default::default(),
            buffers: &[Some(wgpu::VertexBufferLayout {
                array_stride: VERTEX_BYTES,
                step_mode: wgpu::VertexStepMode::Vertex,
                attributes: &wgpu::vertex_attr_array![0 => Float32x4, 1 => Uint32],
            })],
        },
        fragment: Some(wgpu::FragmentState {
            module: &module,
            entry_point: Some("fs"),
            compilation_options: Default::default(),
            targets: &[Some(MAP_FORMAT.into())],
        }),
        primitive: Default::default(),
        depth_stencil: Some(wgpu::DepthStencilState {
            format: DEPTH_FORMAT,
            depth_write_enabled: Some(true),
            depth_compare: Some(wgpu::CompareFunction::Less),
            stencil: Default::default(),
            bias: Default::default(),
        }),
        multisample: Default::default(),
        multiview_mask: None,
        cache: None,
    })
}

/// The vertices (clip position and triangle number from `first` on) of one mesh layer's
/// visible triangles for the viewer `target` at `pose`, and each triangle's inverse
/// homography (rows padded to 4 floats).
fn triangles(
    layer: &MeshLayer,
    cam: &Camera,
    target: &Camera,
    pose: &Pose,
    first: u32,
) -> (Vec<u8>, Vec<f32>) {
    let tris = cpsl_render::mesh::visible_triangles(&layer.grid, &layer.cells, cam, target, pose);
    // Depth 1 - near / z in (0, 1), affine in screen space as the rasteriser interpolates it.
    let near = tris
        .iter()
        .flat_map(|t| t.target.map(|v| v.2))
        .fold(f64::MAX, f64::min)
        * 0.999;
    let (w, h) = (target.width as f64, target.height as f64);
    let mut verts = Vec::with_capacity(tris.len() * 3 * VERTEX_BYTES as usize);
    let mut homs = Vec::with_capacity(tris.len() * 12);
    for (n, t) in tris.iter().enumerate() {
        for &(x, y, z) in &t.target {
            // Pixel centres are integers; the framebuffer's are at + 0.5.
            let (nx, ny) = ((x + 0.5) / w * 2.0 - 1.0, 1.0 - (y + 0.5) / h * 2.0);
            for c in [nx * z, ny * z, z - near, z] {
                verts.extend_from_slice(&(c as f32).to_le_bytes());
            }
            verts.extend_from_slice(&(first + n as u32).to_le_bytes());
        }
        for row in t.h {
            homs.extend(row.map(|v| v as f32));
            homs.push(0.0);
        }
    }
    (verts, homs)
}

/// A texture array of `n` triangle maps of `target`'s size; without mesh layers one texel,
/// which the shaders never read (bound only because the layout has the slot).
pub(crate) fn maps(device: &wgpu::Device, target: &Camera, n: usize) -> wgpu::Texture {
    let (width, height) = match n {
        0 => (1, 1),
        _ => (target.width, target.height),
    };
    device.create_texture(&wgpu::TextureDescriptor {
        label: Some("cpsl mesh maps"),
        size: wgpu::Extent3d {
            width,
            height,
            depth_or_array_layers: n.max(1) as u32,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: MAP_FORMAT,
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING,
        view_formats: &[],
    })
}

/// The triangles' homographies as a float texture (3 texels per triangle, [`TRIS_PER_ROW`]
/// triangles per row; at least one row).
fn homography_texture(device: &wgpu::Device, queue: &wgpu::Queue, homs: &[f32]) -> wgpu::Texture {
    let per_row = (TRIS_PER_ROW * 12) as usize;
    let rows = homs.len().div_ceil(per_row).max(1);
    let mut data = homs.to_vec();
    data.resize(rows * per_row, 0.0);
    let size = wgpu::Extent3d {
        width: 3 * TRIS_PER_ROW,
        height: rows as u32,
        depth_or_array_layers: 1,
    };
    let texture = device.create_texture(&wgpu::TextureDescriptor {
        label: Some("cpsl mesh homographies"),
        size,
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: wgpu::TextureFormat::Rgba32Float,
        usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        view_formats: &[],
    });
    let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
    queue.write_texture(
        texture.as_image_copy(),
        &bytes,
        wgpu::TexelCopyBufferLayout {
            offset: 0,
            bytes_per_row: Some(3 * TRIS_PER_ROW * 16),
            rows_per_image: Some(rows as u32),
        },
        size,
    );
    texture
}

/// Records the passes that fill slice `i` of `maps` with mesh layer `meshes[i]`'s triangle
/// map, and returns the texture of the triangles' homographies.
#[allow(clippy::too_many_arguments)]
pub(crate) fn draw_maps(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    encoder: &mut wgpu::CommandEncoder,
    pipeline: &wgpu::RenderPipeline,
    maps: &wgpu::Texture,
    meshes: &[&MeshLayer],
    cam: &Camera,
    target: &Camera,
    pose: &Pose,
    timestamps: Option<&wgpu::QuerySet>,
) -> wgpu::Texture {
    use wgpu::util::DeviceExt;
    if meshes.is_empty() {
        return homography_texture(device, queue, &[]);
    }
    let depth = device.create_texture(&wgpu::TextureDescriptor {
        label: Some("cpsl mesh depth"),
        size: wgpu::Extent3d {
            width: target.width,
            height: target.height,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: DEPTH_FORMAT,
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
        view_formats: &[],
    });
    let depth_view = depth.create_view(&Default::default());
    let mut homs = Vec::new();
    for (i, layer) in meshes.iter().enumerate() {
        let (verts, h) = triangles(layer, cam, target, pose, (homs.len() / 12) as u32);
        homs.extend(h);
        let buffer = (!verts.is_empty()).then(|| {
            device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("cpsl mesh vertices"),
                contents: &verts,
                usage: wgpu::BufferUsages::VERTEX,
            })
        });
        let view = maps.create_view(&wgpu::TextureViewDescriptor {
            dimension: Some(wgpu::TextureViewDimension::D2),
            base_array_layer: i as u32,
            array_layer_count: Some(1),
            ..Default::default()
        });
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("cpsl mesh pass"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: &view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT),
                    store: wgpu::StoreOp::Store,
                },
            })],
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: &depth_view,
                depth_ops: Some(wgpu::Operations {
                    load: wgpu::LoadOp::Clear(1.0),
                    store: wgpu::StoreOp::Discard,
                }),
                stencil_ops: None,
            }),
            // The first mesh pass starts the view's GPU time.
            timestamp_writes: timestamps.filter(|_| i == 0).map(|q| {
                wgpu::RenderPassTimestampWrites {
                    query_set: q,
                    beginning_of_pass_write_index: Some(0),
                    end_of_pass_write_index: None,
                }
            }),
            occlusion_query_set: None,
            multiview_mask: None,
        });
        if let Some(buffer) = &buffer {
            pass.set_pipeline(pipeline);
            pass.set_vertex_buffer(0, buffer.slice(..));
            pass.draw(0..(verts.len() / VERTEX_BYTES as usize) as u32, 0..1);
        }
    }
    homography_texture(device, queue, &homs)
}
