//! Mesh layers on the GPU: per view, the triangles both renderers draw
//! ([`cpsl_render::mesh::visible_triangles`]) are rasterised into one slice per mesh layer of
//! a source map (`mesh.wgsl`); the composite and strip passes read it for those layers.

use cpsl_core::{Camera, DepthGrid, Pose};
use std::sync::Arc;

/// The source-map format: source x, y, coverage flag.
pub(crate) const MAP_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba32Float;
const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// Bytes per vertex: clip position (4 x f32) and source position (2 x f32).
const VERTEX_BYTES: u64 = 24;

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
                attributes: &wgpu::vertex_attr_array![0 => Float32x4, 1 => Float32x2],
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

/// The vertices of one mesh layer's visible triangles for the viewer `target` at `pose`.
fn vertices(layer: &MeshLayer, cam: &Camera, target: &Camera, pose: &Pose) -> Vec<f32> {
    let tris = cpsl_render::mesh::visible_triangles(&layer.grid, &layer.cells, cam, target, pose);
    // Depth 1 - near / z in (0, 1), affine in screen space as the rasteriser interpolates it.
    let near = tris
        .iter()
        .flat_map(|t| t.target.map(|v| v.2))
        .fold(f64::MAX, f64::min)
        * 0.999;
    let (w, h) = (target.width as f64, target.height as f64);
    let mut out = Vec::with_capacity(tris.len() * 18);
    for t in &tris {
        for (&(x, y, z), &(u, v)) in t.target.iter().zip(&t.source) {
            // Pixel centres are integers; the framebuffer's are at + 0.5.
            let (nx, ny) = ((x + 0.5) / w * 2.0 - 1.0, 1.0 - (y + 0.5) / h * 2.0);
            out.extend([nx * z, ny * z, z - near, z, u, v].map(|c| c as f32));
        }
    }
    out
}

/// A texture array of `n` source maps of `target`'s size (at least one slice).
pub(crate) fn maps(device: &wgpu::Device, target: &Camera, n: usize) -> wgpu::Texture {
    device.create_texture(&wgpu::TextureDescriptor {
        label: Some("cpsl mesh maps"),
        size: wgpu::Extent3d {
            width: target.width,
            height: target.height,
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

/// Records the passes that fill slice `i` of `maps` with mesh layer `meshes[i]`'s source map.
#[allow(clippy::too_many_arguments)]
pub(crate) fn draw_maps(
    device: &wgpu::Device,
    encoder: &mut wgpu::CommandEncoder,
    pipeline: &wgpu::RenderPipeline,
    maps: &wgpu::Texture,
    meshes: &[&MeshLayer],
    cam: &Camera,
    target: &Camera,
    pose: &Pose,
) {
    use wgpu::util::DeviceExt;
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
    for (i, layer) in meshes.iter().enumerate() {
        let data = vertices(layer, cam, target, pose);
        let buffer = (!data.is_empty()).then(|| {
            let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
            device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("cpsl mesh vertices"),
                contents: &bytes,
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
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        if let Some(buffer) = &buffer {
            pass.set_pipeline(pipeline);
            pass.set_vertex_buffer(0, buffer.slice(..));
            pass.draw(0..(data.len() / 6) as u32, 0..1);
        }
    }
}
