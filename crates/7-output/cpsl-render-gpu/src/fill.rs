//! What a view leaves uncovered (beyond the frame's edge where the viewpoint looks past it)
//! filled from what it covers, on the GPU: the push-pull fill of
//! [`cpsl_core::PremulImage::over_fill`], so that an interactive player shows what the CPU
//! reference writes instead of black.

use crate::{fragment_texture, fragment_uniform, fullscreen_pipeline_with, FILL_WGSL};
use wgpu::util::DeviceExt;

/// The filled view's format.
pub const FILLED_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;

/// The pyramid of one view size.
struct Pyramid {
    /// Levels 1..=n pushed (colour weighted, weight in alpha).
    pushed: Vec<wgpu::TextureView>,
    /// Levels 1..n filled (level n is the pushed top, read normalised).
    pulled: Vec<wgpu::TextureView>,
    out: wgpu::Texture,
    out_view: wgpu::TextureView,
}

/// The push-pull passes and the pyramid of the last view size.
pub struct Fill {
    /// The pyramid levels' format: 32-bit float where the adapter renders into it, else 16.
    level: wgpu::TextureFormat,
    push: wgpu::RenderPipeline,
    pull: wgpu::RenderPipeline,
    pull_out: wgpu::RenderPipeline,
    layout: wgpu::BindGroupLayout,
    /// The level flags: reading an inner level, reading the top.
    inner: wgpu::Buffer,
    top: wgpu::Buffer,
    pyramid: Option<Pyramid>,
}

impl Fill {
    /// The passes of `device` (opened on `adapter`), for views in RGBA8 premultiplied form.
    pub fn new(device: &wgpu::Device, adapter: &wgpu::Adapter) -> Self {
        let renders = |f| {
            adapter
                .get_texture_format_features(f)
                .allowed_usages
                .contains(wgpu::TextureUsages::RENDER_ATTACHMENT)
        };
        let level = match renders(wgpu::TextureFormat::Rgba32Float) {
            true => wgpu::TextureFormat::Rgba32Float,
            false => wgpu::TextureFormat::Rgba16Float,
        };
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("cpsl fill"),
            entries: &[
                fragment_texture(0),
                fragment_texture(1),
                fragment_uniform(2),
            ],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("cpsl fill"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = |entry, format| {
            fullscreen_pipeline_with(
                device,
                "cpsl fill",
                &pipeline_layout,
                FILL_WGSL,
                entry,
                wgpu::ColorTargetState {
                    format,
                    blend: None,
                    write_mask: wgpu::ColorWrites::ALL,
                },
            )
        };
        let flags = |top: u32| {
            device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("cpsl fill level"),
                contents: &[top, 0, 0, 0].map(u32::to_le_bytes).concat(),
                usage: wgpu::BufferUsages::UNIFORM,
            })
        };
        Self {
            level,
            push: pipeline("push", level),
            pull: pipeline("pull", level),
            pull_out: pipeline("pull", FILLED_FORMAT),
            layout,
            inner: flags(0),
            top: flags(1),
            pyramid: None,
        }
    }

    /// Records the fill of `src` (a premultiplied RGBA8 view) and returns the texture that
    /// will hold the filled, opaque view (`FILLED_FORMAT`, `src`'s size; overwritten by the
    /// next call's commands).
    pub fn draw(
        &mut self,
        device: &wgpu::Device,
        encoder: &mut wgpu::CommandEncoder,
        src: &wgpu::Texture,
    ) -> &wgpu::Texture {
        let size = (src.width(), src.height());
        if self
            .pyramid
            .as_ref()
            .map(|p| (p.out.width(), p.out.height()))
            != Some(size)
        {
            self.pyramid = Some(Pyramid::new(device, self.level, size.0, size.1));
        }
        let src = &src.create_view(&Default::default());
        let p = self.pyramid.as_ref().expect("made above");
        let group = |fine: &wgpu::TextureView, coarse: &wgpu::TextureView, top: bool| {
            device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("cpsl fill"),
                layout: &self.layout,
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: wgpu::BindingResource::TextureView(fine),
                    },
                    wgpu::BindGroupEntry {
                        binding: 1,
                        resource: wgpu::BindingResource::TextureView(coarse),
                    },
                    wgpu::BindGroupEntry {
                        binding: 2,
                        resource: if top { &self.top } else { &self.inner }.as_entire_binding(),
                    },
                ],
            })
        };
        let mut pass = |pipeline: &wgpu::RenderPipeline, group: wgpu::BindGroup, dst| {
            let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("cpsl fill"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: dst,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT),
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: None,
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, &group, &[]);
            pass.draw(0..3, 0..1);
        };
        // Level l's pushed values: the view itself at level 0.
        let pushed = |l: usize| if l == 0 { src } else { &p.pushed[l - 1] };
        let n = p.pushed.len();
        for l in 1..=n {
            let fine = pushed(l - 1);
            pass(&self.push, group(fine, fine, false), &p.pushed[l - 1]);
        }
        for l in (0..n).rev() {
            let coarse = if l + 1 == n {
                &p.pushed[n - 1]
            } else {
                &p.pulled[l]
            };
            let g = group(pushed(l), coarse, l + 1 == n);
            if l == 0 {
                pass(&self.pull_out, g, &p.out_view);
            } else {
                pass(&self.pull, g, &p.pulled[l - 1]);
            }
        }
        &p.out
    }
}

impl Pyramid {
    fn new(device: &wgpu::Device, level: wgpu::TextureFormat, width: u32, height: u32) -> Self {
        let texture = |w: u32, h: u32, format| {
            device.create_texture(&wgpu::TextureDescriptor {
                label: Some("cpsl fill"),
                size: wgpu::Extent3d {
                    width: w,
                    height: h,
                    depth_or_array_layers: 1,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format,
                usage: wgpu::TextureUsages::RENDER_ATTACHMENT
                    | wgpu::TextureUsages::TEXTURE_BINDING
                    | wgpu::TextureUsages::COPY_SRC,
                view_formats: &[],
            })
        };
        // Halved (rounding up) until 1x1; at least one level, so that a 1x1 view is
        // normalised as the CPU's top level is.
        let mut sizes = vec![];
        let (mut w, mut h) = (width, height);
        while w > 1 || h > 1 || sizes.is_empty() {
            (w, h) = (w.div_ceil(2), h.div_ceil(2));
            sizes.push((w, h));
        }
        let view = |t: wgpu::Texture| t.create_view(&Default::default());
        let pushed: Vec<_> = sizes
            .iter()
            .map(|&(w, h)| view(texture(w, h, level)))
            .collect();
        let pulled = sizes[..sizes.len() - 1]
            .iter()
            .map(|&(w, h)| view(texture(w, h, level)))
            .collect();
        let out = texture(width, height, FILLED_FORMAT);
        Self {
            pushed,
            pulled,
            out_view: out.create_view(&Default::default()),
            out,
        }
    }
}
