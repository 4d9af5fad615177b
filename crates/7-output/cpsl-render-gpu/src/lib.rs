//! The wgpu renderer of CPSL layers, with the semantics of the CPU reference (`cpsl-render`):
//! per layer the inverse plane-induced homography of its surface ([`cpsl_core::Geometry`]),
//! bilinear premultiplied sampling at positions rounded to 1/256 px with a transparent border,
//! front-to-back compositing (paper eq. 2), then the Dynamic Pixel Strip (paper eq. 4) guided
//! by the Edge-Depth Cache. The shaders are `common.wgsl` followed by `composite.wgsl` or by
//! `dps.wgsl`, next to this file (validated by naga in a test). Each pass runs as a compute
//! shader where the adapter has them and as a full-screen fragment pass where not
//! ([`Passes`]); mesh layers' source maps are rasterised (`mesh.wgsl`). A player shows a view
//! through [`Fill`] (`fill.wgsl`): what the layers leave uncovered, beyond the frame's edge
//! where the viewpoint looks past it, filled by push-pull as the CPU reference fills it
//! ([`PremulImage::over_fill`]), then [`Blit`] onto its window.
//!
//! Runs on any adapter wgpu finds (Vulkan, Metal, GL; on a machine without a GPU, Mesa's
//! lavapipe). [`GpuRenderer::new`] fails with [`GpuError::NoAdapter`] where there is none, so
//! callers can fall back to the CPU renderer.

pub use wgpu;

mod blit;
mod fill;
mod mesh;
pub use blit::Blit;
pub use fill::{Fill, FILLED_FORMAT};

use cpsl_core::{Camera, Edc, Geometry, LayerSet, Pose, PremulImage};
use cpsl_render::{strip_width, DpsConfig, EdgeOffsets, Filter};
use std::time::Duration;
use thiserror::Error;

/// The shader code shared by both passes.
pub const COMMON_WGSL: &str = include_str!("common.wgsl");
/// The compositing pass.
pub const COMPOSITE_WGSL: &str = include_str!("composite.wgsl");
/// The Dynamic Pixel Strip pass.
pub const DPS_WGSL: &str = include_str!("dps.wgsl");
/// The mesh pass: triangles into source maps.
pub const MESH_WGSL: &str = include_str!("mesh.wgsl");
/// The blit onto a window's surface.
pub const BLIT_WGSL: &str = include_str!("blit.wgsl");
/// The push-pull fill of what a view leaves uncovered.
pub const FILL_WGSL: &str = include_str!("fill.wgsl");
/// Most layers per frame.
pub const MAX_LAYERS: usize = 16;
const PARAMS_BYTES: usize = 16 + MAX_LAYERS * 48 + 64 + 128 * 16 + MAX_LAYERS * 4 + 16;
/// Where the per-layer mesh slices start in the parameters.
const MESH_AT: usize = 16 + MAX_LAYERS * 48 + 64 + 128 * 16;
const FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;

/// Errors of the GPU renderer.
#[derive(Debug, Error)]
pub enum GpuError {
    /// No graphics adapter (no GPU and no software Vulkan such as lavapipe).
    #[error("no GPU adapter found ({0}); install a Vulkan driver (e.g. Debian's mesa-vulkan-drivers for lavapipe)")]
    NoAdapter(String),
    /// The device could not be created.
    #[error("GPU device: {0}")]
    Device(String),
    /// The layer set does not fit the renderer.
    #[error("{0}")]
    Layers(String),
    /// Reading the result back failed.
    #[error("GPU readback: {0}")]
    Readback(String),
}

/// How the composite and strip passes run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Passes {
    /// A full-screen triangle with the pass as its fragment shader.
    Fragment,
    /// A compute shader over 8x8 tiles writing a storage texture: the default where the
    /// adapter has compute shaders. On NVIDIA's H100/H200 (compute GPUs whose graphics units
    /// are few) it is many times faster than the fragment form (BENCHMARKS.md).
    Compute,
}

/// A wgpu device with the two render pipelines.
pub struct GpuRenderer {
    device: wgpu::Device,
    queue: wgpu::Queue,
    layout: wgpu::BindGroupLayout,
    composite: wgpu::RenderPipeline,
    dps: wgpu::RenderPipeline,
    /// The compute forms of both passes and the layout of their output, where the adapter
    /// has compute shaders.
    compute: Option<ComputePasses>,
    passes: Passes,
    mesh: wgpu::RenderPipeline,
    /// Bound as the composite where the composite pass itself runs (it reads nothing there).
    dummy: wgpu::TextureView,
    adapter: String,
    handle: wgpu::Adapter,
    filter: Filter,
}

/// The two passes of a view.
#[derive(Clone, Copy)]
enum Pass {
    Composite,
    Strip,
}

struct ComputePasses {
    out: wgpu::BindGroupLayout,
    composite: wgpu::ComputePipeline,
    dps: wgpu::ComputePipeline,
}

/// Layers uploaded to the GPU, with what the strip needs.
pub struct GpuLayers {
    texture: wgpu::TextureView,
    camera: Camera,
    depths: Vec<f64>,
    geometries: Vec<Geometry>,
    /// Per layer, its grid and occupied cells where it is a mesh.
    meshes: Vec<Option<mesh::MeshLayer>>,
    offsets: EdgeOffsets,
}

impl GpuRenderer {
    /// Opens the first adapter wgpu finds (set `WGPU_BACKEND`, e.g. `vulkan` or `gl`, to
    /// choose) and builds the pipelines.
    pub fn new() -> Result<Self, GpuError> {
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        Self::open(&instance, None)
    }

    /// Opens an adapter of `instance` that can present to `surface` (a window's).
    pub fn for_surface(
        instance: &wgpu::Instance,
        surface: &wgpu::Surface<'_>,
    ) -> Result<Self, GpuError> {
        Self::open(instance, Some(surface))
    }

    fn open(
        instance: &wgpu::Instance,
        surface: Option<&wgpu::Surface<'_>>,
    ) -> Result<Self, GpuError> {
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            compatible_surface: surface,
            ..Default::default()
        }))
        .map_err(|e| GpuError::NoAdapter(e.to_string()))?;
        let info = adapter.get_info();
        // GPU timestamps where the adapter has them (for `time_renders`).
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("cpsl"),
            required_features: adapter.features() & wgpu::Features::TIMESTAMP_QUERY,
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device(e.to_string()))?;
        let has_compute = adapter
            .get_downlevel_capabilities()
            .flags
            .contains(wgpu::DownlevelFlags::COMPUTE_SHADERS);
        let stages = match has_compute {
            true => wgpu::ShaderStages::FRAGMENT | wgpu::ShaderStages::COMPUTE,
            false => wgpu::ShaderStages::FRAGMENT,
        };
        let entry = |binding, ty| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: stages,
            ty,
            count: None,
        };
        let tex = |dim| wgpu::BindingType::Texture {
            sample_type: wgpu::TextureSampleType::Float { filterable: false },
            view_dimension: dim,
            multisampled: false,
        };
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("cpsl layers"),
            entries: &[
                entry(0, tex(wgpu::TextureViewDimension::D2Array)),
                entry(
                    1,
                    wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                ),
                entry(2, tex(wgpu::TextureViewDimension::D2)),
                entry(3, tex(wgpu::TextureViewDimension::D2Array)),
                entry(4, tex(wgpu::TextureViewDimension::D2)),
            ],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("cpsl"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = |name: &str, pass: &str| {
            fullscreen_pipeline(
                &device,
                name,
                &pipeline_layout,
                &format!("{COMMON_WGSL}\n{pass}"),
                FORMAT.into(),
            )
        };
        // The composite pass declares no binding 2; a layout may hold more than a shader uses.
        let composite = pipeline("cpsl composite", COMPOSITE_WGSL);
        let dps = pipeline("cpsl dps", DPS_WGSL);
        let compute = has_compute.then(|| {
            let out = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some("cpsl output"),
                entries: &[wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::COMPUTE,
                    ty: wgpu::BindingType::StorageTexture {
                        access: wgpu::StorageTextureAccess::WriteOnly,
                        format: FORMAT,
                        view_dimension: wgpu::TextureViewDimension::D2,
                    },
                    count: None,
                }],
            });
            let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("cpsl compute"),
                bind_group_layouts: &[Some(&layout), Some(&out)],
                immediate_size: 0,
            });
            let pipeline = |name: &str, pass: &str| {
                let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                    label: Some(name),
                    source: wgpu::ShaderSource::Wgsl(format!("{COMMON_WGSL}\n{pass}").into()),
                });
                device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some(name),
                    layout: Some(&layout),
                    module: &module,
                    entry_point: Some("cs"),
                    compilation_options: Default::default(),
                    cache: None,
                })
            };
            ComputePasses {
                composite: pipeline("cpsl composite (compute)", COMPOSITE_WGSL),
                dps: pipeline("cpsl dps (compute)", DPS_WGSL),
                out,
            }
        });
        let mesh = mesh::pipeline(&device);
        let dummy = device
            .create_texture(&wgpu::TextureDescriptor {
                label: Some("cpsl dummy"),
                size: wgpu::Extent3d {
                    width: 1,
                    height: 1,
                    depth_or_array_layers: 1,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format: FORMAT,
                usage: wgpu::TextureUsages::TEXTURE_BINDING,
                view_formats: &[],
            })
            .create_view(&Default::default());
        Ok(Self {
            device,
            queue,
            layout,
            composite,
            dps,
            passes: match compute {
                Some(_) => Passes::Compute,
                None => Passes::Fragment,
            },
            compute,
            mesh,
            dummy,
            adapter: format!("{} ({:?}, {:?})", info.name, info.backend, info.device_type),
            handle: adapter,
            filter: Filter::default(),
        })
    }

    /// The device.
    pub fn device(&self) -> &wgpu::Device {
        &self.device
    }

    /// The queue.
    pub fn queue(&self) -> &wgpu::Queue {
        &self.queue
    }

    /// The adapter (for a surface's capabilities).
    pub fn adapter_handle(&self) -> &wgpu::Adapter {
        &self.handle
    }

    /// How the passes run.
    pub fn passes(&self) -> Passes {
        self.passes
    }

    /// Runs the passes as `passes` from now on; compute where the adapter has no compute
    /// shaders is an error.
    pub fn set_passes(&mut self, passes: Passes) -> Result<(), GpuError> {
        if passes == Passes::Compute && self.compute.is_none() {
            return Err(GpuError::Device(format!(
                "{} has no compute shaders",
                self.adapter
            )));
        }
        self.passes = passes;
        Ok(())
    }

    /// Resamples layers with `filter` from now on (bilinear by default, as the browser player;
    /// [`Filter::Cubic`] as the CPU renderer's Catmull-Rom, 16 texel reads a layer and pixel
    /// instead of 4).
    pub fn set_filter(&mut self, filter: Filter) {
        self.filter = filter;
    }

    /// How layers are resampled.
    pub fn filter(&self) -> Filter {
        self.filter
    }

    /// The adapter's name, backend and type.
    pub fn adapter(&self) -> &str {
        &self.adapter
    }

    /// Uploads a layer set (and its Edge-Depth Cache, for the strip).
    pub fn prepare(&self, set: &LayerSet, edc: Option<&Edc>) -> Result<GpuLayers, GpuError> {
        let cam = *set.camera();
        let n = set.len();
        if n == 0 || n > MAX_LAYERS {
            return Err(GpuError::Layers(format!(
                "{n} layers; the GPU renderer takes 1 to {MAX_LAYERS}"
            )));
        }
        let size = wgpu::Extent3d {
            width: cam.width,
            height: cam.height,
            depth_or_array_layers: n as u32,
        };
        let texture = self.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("cpsl layers"),
            size,
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: FORMAT,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        });
        for (k, l) in set.layers().iter().enumerate() {
            self.queue.write_texture(
                wgpu::TexelCopyTextureInfo {
                    texture: &texture,
                    mip_level: 0,
                    origin: wgpu::Origin3d {
                        x: 0,
                        y: 0,
                        z: k as u32,
                    },
                    aspect: wgpu::TextureAspect::All,
                },
                l.image.as_bytes(),
                wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(4 * cam.width),
                    rows_per_image: Some(cam.height),
                },
                wgpu::Extent3d {
                    depth_or_array_layers: 1,
                    ..size
                },
            );
        }
        Ok(GpuLayers {
            texture: texture.create_view(&wgpu::TextureViewDescriptor {
                dimension: Some(wgpu::TextureViewDimension::D2Array),
                ..Default::default()
            }),
            camera: cam,
            depths: set.layers().iter().map(|l| l.depth).collect(),
            geometries: set.layers().iter().map(|l| l.geometry.clone()).collect(),
            meshes: set
                .layers()
                .iter()
                .map(|l| match &l.geometry {
                    Geometry::Mesh(g) => Some(mesh::MeshLayer {
                        grid: g.clone(),
                        cells: cpsl_render::mesh::occupied_cells(&l.image, g),
                    }),
                    _ => None,
                })
                .collect(),
            offsets: edc.map(EdgeOffsets::from_edc).unwrap_or_default(),
        })
    }

    fn params(&self, layers: &GpuLayers, pose: &Pose, target: &Camera, reach: u32) -> Vec<u8> {
        let mut b = vec![0u8; PARAMS_BYTES];
        let put = |b: &mut [u8], at: usize, v: [u8; 4]| b[at..at + 4].copy_from_slice(&v);
        put(&mut b, 0, (target.width as i32).to_le_bytes());
        put(&mut b, 4, (target.height as i32).to_le_bytes());
        put(&mut b, 8, (layers.depths.len() as i32).to_le_bytes());
        put(&mut b, 12, (reach as i32).to_le_bytes());
        for (k, (&d, g)) in layers.depths.iter().zip(&layers.geometries).enumerate() {
            // A plane the viewer has reached maps nothing (w = -1 everywhere).
            let m = g
                .inverse_homography(d, &layers.camera, target, pose)
                .map(|h| h.0 .0)
                .unwrap_or([[0.0; 3], [0.0; 3], [0.0, 0.0, -1.0]]);
            // Column-major, each column padded to 16 bytes (WGSL mat3x3).
            for (r, row) in m.iter().enumerate() {
                for (c, v) in row.iter().enumerate() {
                    let at = 16 + k * 48 + c * 16 + r * 4;
                    put(&mut b, at, (*v as f32).to_le_bytes());
                }
            }
            let at = 16 + MAX_LAYERS * 48 + k * 4;
            put(&mut b, at, (d.ln() as f32).to_le_bytes());
        }
        let mut slice = 0i32;
        for (k, m) in layers.meshes.iter().enumerate() {
            let v = match m {
                Some(_) => {
                    slice += 1;
                    slice - 1
                }
                None => -1,
            };
            put(&mut b, MESH_AT + k * 4, v.to_le_bytes());
        }
        let filter = (self.filter == Filter::Cubic) as i32;
        put(&mut b, MESH_AT + MAX_LAYERS * 4, filter.to_le_bytes());
        let n = layers.depths.len();
        for f in 0..n {
            for bk in 0..n {
                let (of, ob) = layers.offsets.get(f as u8, bk as u8);
                let at = 16 + MAX_LAYERS * 48 + 64 + (bk * 16 + f) * 8;
                put(&mut b, at, (of as f32).to_le_bytes());
                put(&mut b, at + 4, (ob as f32).to_le_bytes());
            }
        }
        b
    }

    /// A render target for [`GpuRenderer::draw`] (and for reading, copying and sampling).
    pub fn target_texture(&self, cam: &Camera) -> wgpu::Texture {
        self.target(
            cam,
            wgpu::TextureUsages::RENDER_ATTACHMENT
                | wgpu::TextureUsages::TEXTURE_BINDING
                | wgpu::TextureUsages::COPY_SRC,
        )
    }

    fn target(&self, cam: &Camera, usage: wgpu::TextureUsages) -> wgpu::Texture {
        self.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("cpsl target"),
            size: wgpu::Extent3d {
                width: cam.width,
                height: cam.height,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: FORMAT,
            // The compute passes write their output as a storage texture.
            usage: match self.compute {
                Some(_) => usage | wgpu::TextureUsages::STORAGE_BINDING,
                None => usage,
            },
            view_formats: &[],
        })
    }

    /// Records the passes for one view into `encoder`; the result lands in `out` (and the
    /// composite alone in `first`; both from [`GpuRenderer::target_texture`]). Returns the
    /// strip half-width used (0 without the strip).
    #[allow(clippy::too_many_arguments)]
    pub fn draw(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        layers: &GpuLayers,
        pose: &Pose,
        target: &Camera,
        dps: Option<&DpsConfig>,
        first: &wgpu::Texture,
        out: &wgpu::Texture,
    ) -> u32 {
        self.draw_timed(encoder, layers, pose, target, dps, first, out, None)
    }

    /// [`GpuRenderer::draw`], writing GPU timestamps 0 (start of the first pass) and 1 (end of
    /// the last) into `timestamps` when given.
    #[allow(clippy::too_many_arguments)]
    fn draw_timed(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        layers: &GpuLayers,
        pose: &Pose,
        target: &Camera,
        dps: Option<&DpsConfig>,
        first: &wgpu::Texture,
        out: &wgpu::Texture,
        timestamps: Option<&wgpu::QuerySet>,
    ) -> u32 {
        let s = dps.map_or(0, |cfg| {
            strip_width(&layers.camera, &layers.depths, pose, target, cfg)
        });
        let params = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("cpsl params"),
            size: PARAMS_BYTES as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        self.queue
            .write_buffer(&params, 0, &self.params(layers, pose, target, 2 * s));
        // Mesh layers' source maps, drawn first.
        let meshes: Vec<&mesh::MeshLayer> = layers.meshes.iter().flatten().collect();
        let maps = mesh::maps(&self.device, target, meshes.len());
        let homographies = mesh::draw_maps(
            &self.device,
            &self.queue,
            encoder,
            &self.mesh,
            &maps,
            &meshes,
            &layers.camera,
            target,
            pose,
            timestamps,
        );
        let maps = maps.create_view(&wgpu::TextureViewDescriptor {
            dimension: Some(wgpu::TextureViewDimension::D2Array),
            ..Default::default()
        });
        let homographies = homographies.create_view(&Default::default());
        let first_view = first.create_view(&Default::default());
        let bind = |image: &wgpu::TextureView| {
            self.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("cpsl"),
                layout: &self.layout,
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: wgpu::BindingResource::TextureView(&layers.texture),
                    },
                    wgpu::BindGroupEntry {
                        binding: 1,
                        resource: params.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 2,
                        resource: wgpu::BindingResource::TextureView(image),
                    },
                    wgpu::BindGroupEntry {
                        binding: 3,
                        resource: wgpu::BindingResource::TextureView(&maps),
                    },
                    wgpu::BindGroupEntry {
                        binding: 4,
                        resource: wgpu::BindingResource::TextureView(&homographies),
                    },
                ],
            })
        };
        // Pass 1 writes `first` when the strip follows (pass 2 reads it), else `out` directly.
        let passes = match dps {
            Some(_) => vec![
                (Pass::Composite, first, bind(&self.dummy)),
                (Pass::Strip, out, bind(&first_view)),
            ],
            None => vec![(Pass::Composite, out, bind(&self.dummy))],
        };
        let last = passes.len() - 1;
        for (i, (pass, into, group)) in passes.into_iter().enumerate() {
            let view = into.create_view(&Default::default());
            // Where mesh passes ran, the first of them wrote the start.
            let begin = (i == 0 && meshes.is_empty()).then_some(0);
            let end = (i == last).then_some(1);
            let stamps = timestamps.filter(|_| begin.is_some() || end.is_some());
            match (self.passes, &self.compute) {
                (Passes::Compute, Some(c)) => {
                    let output = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
                        label: Some("cpsl output"),
                        layout: &c.out,
                        entries: &[wgpu::BindGroupEntry {
                            binding: 0,
                            resource: wgpu::BindingResource::TextureView(&view),
                        }],
                    });
                    let mut cp = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                        label: Some("cpsl pass"),
                        timestamp_writes: stamps.map(|q| wgpu::ComputePassTimestampWrites {
                            query_set: q,
                            beginning_of_pass_write_index: begin,
                            end_of_pass_write_index: end,
                        }),
                    });
                    cp.set_pipeline(match pass {
                        Pass::Composite => &c.composite,
                        Pass::Strip => &c.dps,
                    });
                    cp.set_bind_group(0, &group, &[]);
                    cp.set_bind_group(1, &output, &[]);
                    cp.dispatch_workgroups(target.width.div_ceil(8), target.height.div_ceil(8), 1);
                }
                _ => {
                    let mut rp = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                        label: Some("cpsl pass"),
                        color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                            view: &view,
                            depth_slice: None,
                            resolve_target: None,
                            ops: wgpu::Operations {
                                load: wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT),
                                store: wgpu::StoreOp::Store,
                            },
                        })],
                        depth_stencil_attachment: None,
                        timestamp_writes: stamps.map(|q| wgpu::RenderPassTimestampWrites {
                            query_set: q,
                            beginning_of_pass_write_index: begin,
                            end_of_pass_write_index: end,
                        }),
                        occlusion_query_set: None,
                        multiview_mask: None,
                    });
                    rp.set_pipeline(match pass {
                        Pass::Composite => &self.composite,
                        Pass::Strip => &self.dps,
                    });
                    rp.set_bind_group(0, &group, &[]);
                    rp.draw(0..3, 0..1);
                }
            }
        }
        s
    }

    /// Renders `layers` from `pose` into a `target`-sized image, with the Dynamic Pixel Strip
    /// when `dps` is given.
    pub fn render(
        &self,
        layers: &GpuLayers,
        pose: &Pose,
        target: &Camera,
        dps: Option<&DpsConfig>,
    ) -> Result<PremulImage, GpuError> {
        let (encoder, out) = self.record(layers, pose, target, dps);
        self.read(encoder, &out)
    }

    /// [`Self::render`] with what the view leaves uncovered filled by `fill`, as an
    /// interactive player shows it: RGB bytes, as [`PremulImage::over_fill`] gives them.
    pub fn render_filled(
        &self,
        fill: &mut Fill,
        layers: &GpuLayers,
        pose: &Pose,
        target: &Camera,
        dps: Option<&DpsConfig>,
    ) -> Result<Vec<u8>, GpuError> {
        let (mut encoder, out) = self.record(layers, pose, target, dps);
        let filled = fill.draw(&self.device, &mut encoder, &out);
        let img = self.read(encoder, filled)?;
        Ok(img.over_background([0, 0, 0]))
    }

    /// The commands of one view and the texture they leave it in.
    fn record(
        &self,
        layers: &GpuLayers,
        pose: &Pose,
        target: &Camera,
        dps: Option<&DpsConfig>,
    ) -> (wgpu::CommandEncoder, wgpu::Texture) {
        let usage = wgpu::TextureUsages::RENDER_ATTACHMENT
            | wgpu::TextureUsages::TEXTURE_BINDING
            | wgpu::TextureUsages::COPY_SRC;
        // Two targets, so that the strip never reads what it writes.
        let out = self.target(target, usage);
        let first = self.target(target, usage);
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("cpsl"),
            });
        self.draw(&mut encoder, layers, pose, target, dps, &first, &out);
        (encoder, out)
    }

    /// Submits `encoder` with a copy of `texture` (RGBA8, premultiplied) and reads it back.
    fn read(
        &self,
        mut encoder: wgpu::CommandEncoder,
        texture: &wgpu::Texture,
    ) -> Result<PremulImage, GpuError> {
        let (w, h) = (texture.width() as usize, texture.height() as usize);
        let row = (4 * w).next_multiple_of(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT as usize);
        let buffer = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("cpsl readback"),
            size: (row * h) as u64,
            usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
            mapped_at_creation: false,
        });
        encoder.copy_texture_to_buffer(
            texture.as_image_copy(),
            wgpu::TexelCopyBufferInfo {
                buffer: &buffer,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(row as u32),
                    rows_per_image: Some(h as u32),
                },
            },
            texture.size(),
        );
        self.queue.submit([encoder.finish()]);
        let slice = buffer.slice(..);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.wait()?;
        rx.recv()
            .map_err(|e| GpuError::Readback(e.to_string()))?
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        let data = slice
            .get_mapped_range()
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        let mut px = Vec::with_capacity(4 * w * h);
        for y in 0..h {
            px.extend_from_slice(&data[y * row..y * row + 4 * w]);
        }
        drop(data);
        buffer.unmap();
        PremulImage::from_premul(w as u32, h as u32, px)
            .map_err(|e| GpuError::Readback(e.to_string()))
    }

    fn wait(&self) -> Result<(), GpuError> {
        self.device
            .poll(wgpu::PollType::Wait {
                submission_index: None,
                timeout: Some(Duration::from_secs(60)),
            })
            .map(|_| ())
            .map_err(|e| GpuError::Readback(e.to_string()))
    }

    /// Fills the view of `layers` from `pose` (rendered once) `frames` times with `fill`, each
    /// submitted and waited for: per fill the wall-clock seconds from submission to completion.
    pub fn time_fills(
        &self,
        fill: &mut Fill,
        layers: &GpuLayers,
        pose: &Pose,
        target: &Camera,
        dps: Option<&DpsConfig>,
        frames: usize,
    ) -> Result<Vec<f64>, GpuError> {
        let (encoder, out) = self.record(layers, pose, target, dps);
        self.queue.submit([encoder.finish()]);
        self.wait()?;
        (0..frames)
            .map(|_| {
                let mut encoder = self.device.create_command_encoder(&Default::default());
                fill.draw(&self.device, &mut encoder, &out);
                let t = std::time::Instant::now();
                self.queue.submit([encoder.finish()]);
                self.wait()?;
                Ok(t.elapsed().as_secs_f64())
            })
            .collect()
    }

    /// Renders `frames` views (no readback), each submitted and waited for: per view the
    /// wall-clock seconds from submission to completion and, where the adapter has timestamp
    /// queries, the seconds the GPU spent between the start of the first pass and the end of
    /// the last.
    pub fn time_renders(
        &self,
        layers: &GpuLayers,
        pose: &Pose,
        target: &Camera,
        dps: Option<&DpsConfig>,
        frames: usize,
    ) -> Result<RenderTimes, GpuError> {
        let usage = wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING;
        let (out, first) = (self.target(target, usage), self.target(target, usage));
        let stamps = self
            .device
            .features()
            .contains(wgpu::Features::TIMESTAMP_QUERY)
            .then(|| {
                let set = self.device.create_query_set(&wgpu::QuerySetDescriptor {
                    label: Some("cpsl timestamps"),
                    ty: wgpu::QueryType::Timestamp,
                    count: 2,
                });
                let buffer = |usage| {
                    self.device.create_buffer(&wgpu::BufferDescriptor {
                        label: Some("cpsl timestamps"),
                        size: 16,
                        usage,
                        mapped_at_creation: false,
                    })
                };
                let resolve =
                    buffer(wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC);
                let read = buffer(wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ);
                (set, resolve, read)
            });
        let period = self.queue.get_timestamp_period() as f64 * 1e-9;
        let mut times = RenderTimes {
            wall: Vec::with_capacity(frames),
            gpu: stamps.as_ref().map(|_| Vec::with_capacity(frames)),
        };
        for _ in 0..frames {
            let mut encoder = self
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("cpsl"),
                });
            let q = stamps.as_ref().map(|s| &s.0);
            self.draw_timed(&mut encoder, layers, pose, target, dps, &first, &out, q);
            if let Some((set, resolve, read)) = &stamps {
                encoder.resolve_query_set(set, 0..2, resolve, 0);
                encoder.copy_buffer_to_buffer(resolve, 0, read, 0, 16);
            }
            let t = std::time::Instant::now();
            self.queue.submit([encoder.finish()]);
            self.wait()?;
            times.wall.push(t.elapsed().as_secs_f64());
            if let (Some((_, _, read)), Some(gpu)) = (&stamps, &mut times.gpu) {
                let slice = read.slice(..);
                slice.map_async(wgpu::MapMode::Read, |_| ());
                self.wait()?;
                let data = slice
                    .get_mapped_range()
                    .map_err(|e| GpuError::Readback(e.to_string()))?;
                let t0 = u64::from_le_bytes(data[0..8].try_into().expect("8 bytes"));
                let t1 = u64::from_le_bytes(data[8..16].try_into().expect("8 bytes"));
                drop(data);
                read.unmap();
                gpu.push(t1.saturating_sub(t0) as f64 * period);
            }
        }
        Ok(times)
    }

    /// Renders `frames` views submitted back to back (one command buffer each, as a player's
    /// loop does, nothing read back) and waits for the last: wall-clock seconds per view. Unlike
    /// [`GpuRenderer::time_renders`], the CPU's recording of a view overlaps the GPU's work
    /// on the one before, so this is the rate a renderer sustains.
    pub fn throughput(
        &self,
        layers: &GpuLayers,
        pose: &Pose,
        target: &Camera,
        dps: Option<&DpsConfig>,
        frames: usize,
    ) -> Result<f64, GpuError> {
        let usage = wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING;
        let (out, first) = (self.target(target, usage), self.target(target, usage));
        let t = std::time::Instant::now();
        for _ in 0..frames {
            let mut encoder = self
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("cpsl"),
                });
            self.draw(&mut encoder, layers, pose, target, dps, &first, &out);
            self.queue.submit([encoder.finish()]);
        }
        self.wait()?;
        Ok(t.elapsed().as_secs_f64() / frames.max(1) as f64)
    }
}

/// Timings of [`GpuRenderer::time_renders`], seconds per view.
#[derive(Debug, Clone)]
pub struct RenderTimes {
    /// From submission to completion, as the host sees it.
    pub wall: Vec<f64>,
    /// GPU timestamps from the first pass's start to the last pass's end, where available.
    pub gpu: Option<Vec<f64>>,
}

/// A pipeline drawing one full-screen triangle (`vs`) with fragment shader `fs` of `source`.
pub(crate) fn fullscreen_pipeline(
    device: &wgpu::Device,
    name: &str,
    layout: &wgpu::PipelineLayout,
    source: &str,
    target: wgpu::ColorTargetState,
) -> wgpu::RenderPipeline {
    fullscreen_pipeline_with(device, name, layout, source, "fs", target)
}

/// A fragment shader's 2D float texture (read with `textureLoad`) at `binding`.
pub(crate) fn fragment_texture(binding: u32) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::FRAGMENT,
        ty: wgpu::BindingType::Texture {
            sample_type: wgpu::TextureSampleType::Float { filterable: false },
            view_dimension: wgpu::TextureViewDimension::D2,
            multisampled: false,
        },
        count: None,
    }
}

/// A fragment shader's uniform buffer at `binding`.
pub(crate) fn fragment_uniform(binding: u32) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::FRAGMENT,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Uniform,
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}

/// A full-screen triangle (vertex entry `vs`) with the fragment entry `fragment` of `source`.
pub(crate) fn fullscreen_pipeline_with(
    device: &wgpu::Device,
    name: &str,
    layout: &wgpu::PipelineLayout,
    source: &str,
    fragment: &str,
    target: wgpu::ColorTargetState,
) -> wgpu::RenderPipeline {
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(name),
        source: wgpu::ShaderSource::Wgsl(source.into()),
    });
    device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some(name),
        layout: Some(layout),
        vertex: wgpu::VertexState {
            module: &module,
            entry_point: Some("vs"),
            compilation_options: Default::default(),
            buffers: &[],
        },
        fragment: Some(wgpu::FragmentState {
            module: &module,
            entry_point: Some(fragment),
            compilation_options: Default::default(),
            targets: &[Some(target)],
        }),
        primitive: Default::default(),
        depth_stencil: None,
        multisample: Default::default(),
        multiview_mask: None,
        cache: None,
    })
}

impl cpsl_render::Renderer for GpuRenderer {
    fn name(&self) -> String {
        self.adapter.clone()
    }

    /// Uploads the frame's layers and renders them (the layers are not kept: a player that
    /// draws one frame many times holds [`GpuLayers`] from [`GpuRenderer::prepare`] instead).
    fn render(
        &self,
        frame: &cpsl_render::FrameLayers,
        pose: &Pose,
        target: &Camera,
        dps: Option<&DpsConfig>,
        out: &mut PremulImage,
    ) -> Result<(), cpsl_render::RenderError> {
        let failed = |e: GpuError| cpsl_render::RenderError {
            renderer: self.adapter.clone(),
            source: Box::new(e),
        };
        let layers = self
            .prepare(&frame.set, frame.edc.as_ref())
            .map_err(failed)?;
        *out = GpuRenderer::render(self, &layers, pose, target, dps).map_err(failed)?;
        Ok(())
    }
}
