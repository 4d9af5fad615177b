//! The desktop viewer: a window (winit + wgpu) that plays a package or a layered video, or
//! shows a layer set, from a viewpoint the mouse and keyboard move.
//!
//! Packages and layered videos are decoded on a background thread (a
//! [`cpsl_player::Player`] or [`cpsl_player::LayeredVideo`]) into a bounded queue; the window
//! takes frames from it at the frame rate and renders them with `cpsl-render-gpu`,
//! what the layers leave uncovered filled as the CPU reference fills it (`Fill`).
//! Controls: left drag orbits, right (or shift) drag pans, the wheel dollies, R resets, space
//! plays/pauses, Left/Right step a frame, PageUp/PageDown jump a second, Home goes to the
//! start, S toggles side-by-side stereo, `[` and `]` change the eye separation, D toggles the
//! Dynamic Pixel Strip, F the fill beyond the layers (black without it), C the bicubic
//! (Catmull-Rom) filter against the bilinear one, H the on-screen readout, Esc/Q quit.

use cpsl_core::{Camera, Pose, Vec3};
use cpsl_player::{Frames, PlayerError, Source};
use cpsl_render::{DpsConfig, Filter, FrameLayers};
use cpsl_render_gpu::{wgpu, Blit, Fill, GpuError, GpuLayers, GpuRenderer};
use std::path::PathBuf;
use std::sync::mpsc::{sync_channel, Receiver, Sender, TryRecvError};
use std::sync::Arc;
use std::time::{Duration, Instant};
use thiserror::Error;
use winit::application::ApplicationHandler;
use winit::event::{ElementState, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::keyboard::{Key, ModifiersState, NamedKey};
use winit::window::{Window, WindowId};

/// What the viewer shows and how it starts.
#[derive(Debug, Clone)]
pub struct ViewOptions {
    /// A package or a layer-set folder.
    pub source: PathBuf,
    /// Frame to start at.
    pub frame: u32,
    /// Starting viewer pose (dragging moves away from it, R returns to the reference view).
    pub pose: Option<Pose>,
    /// Start paused.
    pub paused: bool,
    /// Side-by-side stereo (left eye on the left).
    pub stereo: bool,
    /// Distance between the eyes in scene units.
    pub eye_separation: f64,
    /// Render with the Dynamic Pixel Strip.
    pub dps: bool,
    /// Show the on-screen readout.
    pub hud: bool,
    /// How the layers are resampled at start (C toggles).
    pub filter: Filter,
    /// Close after this many seconds (for demos and tests).
    pub exit_after: Option<f64>,
}

/// Why the viewer stopped with an error.
#[derive(Debug, Error)]
pub enum ViewerError {
    /// The package or layer set cannot be played.
    #[error(transparent)]
    Player(#[from] PlayerError),
    /// The GPU renderer failed.
    #[error(transparent)]
    Gpu(#[from] GpuError),
    /// A start frame past the end.
    #[error("--frame {frame}: the input has {frames} frames")]
    NoFrame {
        /// The frame asked for.
        frame: u32,
        /// How many there are.
        frames: u32,
    },
    /// No window can be opened, or its surface fails.
    #[error("{0}")]
    Window(String),
    /// The background decoder failed or stopped.
    #[error("{0}")]
    Decoder(String),
}

type Result<T> = std::result::Result<T, ViewerError>;

/// What the viewer reports to its caller as it starts.
#[derive(Debug, Clone, PartialEq)]
pub enum ViewerEvent {
    /// The window is open on this GPU adapter, with this surface format.
    Opened {
        /// The adapter.
        adapter: String,
        /// The surface format.
        format: String,
    },
    /// The first frame is on screen.
    Shown {
        /// The adapter.
        adapter: String,
    },
}

/// A decoded frame from the background thread, tagged with the seek generation it belongs to.
struct Decoded {
    generation: u64,
    index: u32,
    frame: FrameLayers,
}

/// The background decoder of a package: decodes frame after frame from the requested one
/// (looping at the end) into a bounded queue; a seek starts a new generation.
struct Decoder {
    frames: Receiver<std::result::Result<Decoded, String>>,
    seek: Sender<(u64, u32)>,
    generation: u64,
    pending: Option<Decoded>,
}

impl Decoder {
    fn start(mut player: impl Frames + 'static, first: u32) -> Result<Self> {
        let (tx, rx) = sync_channel::<std::result::Result<Decoded, String>>(8);
        let (seek_tx, seek_rx) = std::sync::mpsc::channel::<(u64, u32)>();
        std::thread::Builder::new()
            .name("cpsl-decode".into())
            .spawn(move || {
                let n = player.frames();
                let (mut generation, mut index) = (0u64, first);
                loop {
                    // The latest seek wins.
                    while let Ok(s) = seek_rx.try_recv() {
                        (generation, index) = s;
                    }
                    let item = player.decode(index).map_err(|e| e.to_string());
                    let failed = item.is_err();
                    let item = item.map(|frame| Decoded {
                        generation,
                        index,
                        frame,
                    });
                    if tx.send(item).is_err() || failed {
                        return; // the window closed, or the package is damaged
                    }
                    index = (index + 1) % n;
                }
            })
            .map_err(|e| ViewerError::Decoder(format!("starting the decoder: {e}")))?;
        Ok(Self {
            frames: rx,
            seek: seek_tx,
            generation: 0,
            pending: None,
        })
    }

    /// Asks for frame `f` next; frames already queued from before are dropped as they come.
    fn seek(&mut self, f: u32) {
        self.generation += 1;
        let _ = self.seek.send((self.generation, f));
        // Unblock the decoder if it waits on a full queue (keeping a frame of the new
        // generation, should one already be there).
        self.pending = None;
        while let Ok(Ok(d)) = self.frames.try_recv() {
            if d.generation == self.generation {
                self.pending = Some(d);
                break;
            }
        }
    }

    /// The next frame of the current generation, if decoded.
    fn next(&mut self) -> Result<Option<Decoded>> {
        if let Some(d) = self.pending.take() {
            return Ok(Some(d));
        }
        loop {
            match self.frames.try_recv() {
                Ok(Ok(d)) if d.generation == self.generation => return Ok(Some(d)),
                Ok(Ok(_)) => continue,
                Ok(Err(e)) => return Err(ViewerError::Decoder(e)),
                Err(TryRecvError::Empty) => return Ok(None),
                Err(TryRecvError::Disconnected) => {
                    return Err(ViewerError::Decoder("the decoder stopped".into()))
                }
            }
        }
    }
}

/// What the window shows and how the viewer has moved.
struct Viewer {
    args: ViewOptions,
    camera: Camera,
    frames: u32,
    fps: f64,
    decoder: Option<Decoder>,
    current: Option<(u32, FrameLayers)>,
    uploaded: Option<GpuLayers>,
    playing: bool,
    stereo: bool,
    dps: bool,
    /// Whether what the layers leave uncovered is filled (`Fill`) or shown black.
    fill: bool,
    hud: bool,
    /// Resampling filter of the layers.
    filter: Filter,
    eye: f64,
    yaw: f64,
    pitch: f64,
    pan: (f64, f64),
    dolly: f64,
    start_pose: Option<Pose>,
    next_due: Instant,
    started: Instant,
    draw_ms: f64,
    frame_ms: f64,
    last_present: Instant,
    drag: Option<(MouseButton, f64, f64)>,
    cursor: (f64, f64),
    modifiers: ModifiersState,
    gfx: Option<Gfx>,
    error: Option<ViewerError>,
    announced: bool,
    events: Box<dyn FnMut(ViewerEvent)>,
}

struct Gfx {
    window: Arc<Window>,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    gpu: GpuRenderer,
    blit: Blit,
    /// What a view leaves uncovered filled from what it covers, as the CPU reference writes.
    fill: Fill,
    first: wgpu::Texture,
    out: wgpu::Texture,
}

impl Viewer {
    fn pose(&self, eye: f64) -> Pose {
        let e = eye * self.eye * 0.5;
        if let Some(p) = &self.start_pose {
            if self.yaw == 0.0 && self.pitch == 0.0 && self.pan == (0.0, 0.0) && self.dolly == 0.0 {
                let r = p.rotation;
                let offset = r * Vec3::new(e, 0.0, 0.0);
                return Pose {
                    rotation: r,
                    translation: p.translation + offset,
                };
            }
        }
        // Orbit about the middle layer's depth on the optical axis.
        let zc = self
            .current
            .as_ref()
            .map(|(_, f)| {
                let l = f.set.layers();
                l[l.len() / 2].depth
            })
            .unwrap_or(1.0);
        let r = Pose::from_euler_deg(Vec3::ZERO, -self.pitch, self.yaw, 0.0).rotation;
        let local = Vec3::new(self.pan.0 + e, self.pan.1, -(zc - self.dolly));
        Pose {
            rotation: r,
            translation: Vec3::new(0.0, 0.0, zc) + r * local,
        }
    }

    fn reset(&mut self) {
        (self.yaw, self.pitch, self.pan, self.dolly) = (0.0, 0.0, (0.0, 0.0), 0.0);
        self.start_pose = None;
    }

    fn seek(&mut self, f: u32) {
        let f = f.min(self.frames.saturating_sub(1));
        if let Some(d) = &mut self.decoder {
            d.seek(f);
            self.next_due = Instant::now();
            // Paused: show the sought frame as soon as it is decoded.
            self.current = self.current.take().map(|(_, fr)| (u32::MAX, fr));
        }
    }

    /// Takes the next decoded frame when it is due (or when a seek waits for it).
    fn advance(&mut self) -> Result<bool> {
        let Some(dec) = &mut self.decoder else {
            return Ok(false);
        };
        let waiting = self.current.as_ref().is_none_or(|(i, _)| *i == u32::MAX);
        if !(waiting || (self.playing && Instant::now() >= self.next_due)) {
            return Ok(false);
        }
        match dec.next()? {
            Some(d) => {
                self.current = Some((d.index, d.frame));
                self.uploaded = None;
                let period = Duration::from_secs_f64(1.0 / self.fps);
                self.next_due = (self.next_due + period).max(Instant::now() - period);
                Ok(true)
            }
            None => Ok(false),
        }
    }

    fn hud_text(&self) -> String {
        let index = self.current.as_ref().map_or(0, |(i, _)| *i);
        let mut t = format!(
            "f {}/{}  {:.1} ms  {:.0} fps",
            index.min(self.frames.saturating_sub(1)) + 1,
            self.frames,
            self.draw_ms,
            1000.0 / self.frame_ms.max(1e-3)
        );
        if !self.playing {
            t.push_str("  paused");
        }
        if self.stereo {
            t.push_str(&format!("  stereo {:.3}", self.eye));
        }
        if self.filter == Filter::Cubic {
            t.push_str("  cubic");
        }
        t
    }

    fn redraw(&mut self) -> Result<()> {
        let hud = self.hud.then(|| self.hud_text());
        let eyes: Vec<f64> = if self.stereo {
            vec![-1.0, 1.0]
        } else {
            vec![0.0]
        };
        let poses: Vec<Pose> = eyes.iter().map(|&e| self.pose(e)).collect();
        let Some(gfx) = &mut self.gfx else {
            return Ok(());
        };
        let Some((_, frame)) = &self.current else {
            return Ok(());
        };
        if self.uploaded.is_none() {
            self.uploaded = Some(gfx.gpu.prepare(&frame.set, frame.edc.as_ref())?);
        }
        gfx.gpu.set_filter(self.filter);
        let layers = self.uploaded.as_ref().expect("uploaded");
        let texture = match gfx.surface.get_current_texture() {
            wgpu::CurrentSurfaceTexture::Success(t)
            | wgpu::CurrentSurfaceTexture::Suboptimal(t) => t,
            wgpu::CurrentSurfaceTexture::Outdated | wgpu::CurrentSurfaceTexture::Lost => {
                gfx.surface.configure(gfx.gpu.device(), &gfx.config);
                return Ok(());
            }
            other => return Err(ViewerError::Window(format!("window surface: {other:?}"))),
        };
        let target = texture.texture.create_view(&Default::default());
        let t0 = Instant::now();
        let dev = gfx.gpu.device();
        let mut encoder = dev.create_command_encoder(&Default::default());
        let (ww, wh) = (gfx.config.width as f32, gfx.config.height as f32);
        let (cw, ch) = (self.camera.width as f32, self.camera.height as f32);
        let slot = ww / poses.len() as f32;
        let scale = (slot / cw).min(wh / ch);
        let cfg = DpsConfig::default();
        let out_view = gfx.out.create_view(&Default::default());
        for (i, pose) in poses.iter().enumerate() {
            gfx.gpu.draw(
                &mut encoder,
                layers,
                pose,
                &self.camera,
                self.dps.then_some(&cfg),
                &gfx.first,
                &gfx.out,
            );
            let shown = if self.fill {
                gfx.fill
                    .draw(dev, &mut encoder, &gfx.out)
                    .create_view(&Default::default())
            } else {
                out_view.clone()
            };
            let (w, h) = (cw * scale, ch * scale);
            let x = i as f32 * slot + ((slot - w) / 2.0).floor();
            let y = ((wh - h) / 2.0).floor();
            gfx.blit.draw(
                dev,
                gfx.gpu.queue(),
                &mut encoder,
                &shown,
                &target,
                [x, y, w, h],
                i == 0,
            );
        }
        if let Some(text) = hud {
            let img = hud_image(&text);
            let tex = dev.create_texture(&wgpu::TextureDescriptor {
                label: Some("cpsl hud"),
                size: wgpu::Extent3d {
                    width: img.0,
                    height: img.1,
                    depth_or_array_layers: 1,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format: wgpu::TextureFormat::Rgba8Unorm,
                usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
                view_formats: &[],
            });
            gfx.gpu.queue().write_texture(
                tex.as_image_copy(),
                &img.2,
                wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(4 * img.0),
                    rows_per_image: Some(img.1),
                },
                tex.size(),
            );
            let view = tex.create_view(&Default::default());
            let rect = [8.0, 8.0, 2.0 * img.0 as f32, 2.0 * img.1 as f32];
            gfx.blit.draw(
                dev,
                gfx.gpu.queue(),
                &mut encoder,
                &view,
                &target,
                rect,
                false,
            );
        }
        gfx.gpu.queue().submit([encoder.finish()]);
        let _ = dev.poll(wgpu::PollType::Wait {
            submission_index: None,
            timeout: Some(Duration::from_secs(10)),
        });
        self.draw_ms = t0.elapsed().as_secs_f64() * 1e3;
        gfx.window.pre_present_notify();
        gfx.gpu.queue().present(texture);
        let now = Instant::now();
        self.frame_ms = 0.9 * self.frame_ms + 0.1 * (now - self.last_present).as_secs_f64() * 1e3;
        self.last_present = now;
        if !self.announced {
            (self.events)(ViewerEvent::Shown {
                adapter: gfx.gpu.adapter().to_string(),
            });
            self.announced = true;
        }
        Ok(())
    }

    fn key(&mut self, key: &Key, event_loop: &ActiveEventLoop) {
        let second = self.fps.round().max(1.0) as u32;
        let at = self
            .current
            .as_ref()
            .map_or(0, |(i, _)| *i)
            .min(self.frames);
        match key {
            Key::Named(NamedKey::Space) => self.playing = !self.playing,
            Key::Named(NamedKey::Escape) => event_loop.exit(),
            Key::Named(NamedKey::ArrowRight) => {
                self.playing = false;
                self.seek((at + 1) % self.frames.max(1));
            }
            Key::Named(NamedKey::ArrowLeft) => {
                self.playing = false;
                self.seek(at.checked_sub(1).unwrap_or(self.frames.saturating_sub(1)));
            }
            Key::Named(NamedKey::PageDown) => self.seek(at + second),
            Key::Named(NamedKey::PageUp) => self.seek(at.saturating_sub(second)),
            Key::Named(NamedKey::Home) => self.seek(0),
            Key::Character(c) => match c.as_str() {
                "q" => event_loop.exit(),
                "r" => self.reset(),
                "s" => self.stereo = !self.stereo,
                "d" => self.dps = !self.dps,
                "f" => self.fill = !self.fill,
                "c" => {
                    self.filter = match self.filter {
                        Filter::Bilinear => Filter::Cubic,
                        Filter::Cubic => Filter::Bilinear,
                    }
                }
                "h" => self.hud = !self.hud,
                "[" => self.eye = (self.eye - 0.005).max(0.0),
                "]" => self.eye += 0.005,
                _ => {}
            },
            _ => {}
        }
    }

    fn init_gfx(&mut self, event_loop: &ActiveEventLoop) -> Result<()> {
        let (w, h) = (self.camera.width, self.camera.height);
        let width = if self.stereo { 2 * w } else { w };
        let attrs = Window::default_attributes()
            .with_title(format!("cpsl view: {}", self.args.source.display()))
            .with_inner_size(winit::dpi::PhysicalSize::new(width, h));
        let window = Arc::new(
            event_loop
                .create_window(attrs)
                .map_err(|e| ViewerError::Window(format!("cannot open a window: {e}")))?,
        );
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let surface = instance
            .create_surface(window.clone())
            .map_err(|e| ViewerError::Window(format!("window surface: {e}")))?;
        let gpu = GpuRenderer::for_surface(&instance, &surface)?;
        let caps = surface.get_capabilities(gpu.adapter_handle());
        // A non-sRGB format shows the rendered bytes as they are (as images and the CPU do).
        let format = caps
            .formats
            .iter()
            .copied()
            .find(|f| !f.is_srgb())
            .or_else(|| caps.formats.first().copied())
            .ok_or_else(|| ViewerError::Window("the window surface offers no format".into()))?;
        let size = window.inner_size();
        let config = wgpu::SurfaceConfiguration {
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
            format,
            color_space: wgpu::SurfaceColorSpace::Auto,
            width: size.width.max(1),
            height: size.height.max(1),
            present_mode: wgpu::PresentMode::AutoVsync,
            desired_maximum_frame_latency: 2,
            alpha_mode: caps.alpha_modes[0],
            view_formats: vec![],
        };
        surface.configure(gpu.device(), &config);
        let blit = Blit::new(gpu.device(), format);
        let fill = Fill::new(gpu.device(), gpu.adapter_handle());
        let (first, out) = (
            gpu.target_texture(&self.camera),
            gpu.target_texture(&self.camera),
        );
        (self.events)(ViewerEvent::Opened {
            adapter: gpu.adapter().to_string(),
            format: format!("{format:?}"),
        });
        self.gfx = Some(Gfx {
            window,
            surface,
            config,
            gpu,
            blit,
            fill,
            first,
            out,
        });
        Ok(())
    }

    fn fail(&mut self, e: ViewerError, event_loop: &ActiveEventLoop) {
        self.error = Some(e);
        event_loop.exit();
    }
}

impl ApplicationHandler for Viewer {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.gfx.is_none() {
            if let Err(e) = self.init_gfx(event_loop) {
                self.fail(e, event_loop);
            }
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _: WindowId, event: WindowEvent) {
        match event {
            WindowEvent::CloseRequested => event_loop.exit(),
            WindowEvent::Resized(size) => {
                if let Some(g) = &mut self.gfx {
                    g.config.width = size.width.max(1);
                    g.config.height = size.height.max(1);
                    g.surface.configure(g.gpu.device(), &g.config);
                }
            }
            WindowEvent::ModifiersChanged(m) => self.modifiers = m.state(),
            WindowEvent::KeyboardInput { event, .. } if event.state == ElementState::Pressed => {
                self.key(&event.logical_key, event_loop)
            }
            WindowEvent::MouseInput { state, button, .. } => {
                self.drag = (state == ElementState::Pressed).then(|| {
                    let b = if self.modifiers.shift_key() {
                        MouseButton::Right
                    } else {
                        button
                    };
                    (b, self.cursor.0, self.cursor.1)
                });
            }
            WindowEvent::CursorMoved { position, .. } => {
                self.cursor = (position.x, position.y);
                if let Some((b, x, y)) = self.drag {
                    let scale = 1.0 / self.camera.width as f64;
                    let (dx, dy) = ((position.x - x) * scale, (position.y - y) * scale);
                    if b == MouseButton::Left {
                        self.yaw += dx * 20.0;
                        self.pitch -= dy * 20.0;
                    } else {
                        self.pan = (self.pan.0 - dx * 0.5, self.pan.1 - dy * 0.5);
                    }
                    self.drag = Some((b, position.x, position.y));
                }
            }
            WindowEvent::MouseWheel { delta, .. } => {
                let d = match delta {
                    MouseScrollDelta::LineDelta(_, y) => y as f64 * 0.02,
                    MouseScrollDelta::PixelDelta(p) => p.y * 0.0005,
                };
                self.dolly += d;
            }
            WindowEvent::RedrawRequested => {
                if let Err(e) = self.redraw() {
                    self.fail(e, event_loop);
                }
            }
            _ => {}
        }
    }

    fn about_to_wait(&mut self, event_loop: &ActiveEventLoop) {
        if let Some(limit) = self.args.exit_after {
            if self.started.elapsed().as_secs_f64() >= limit {
                event_loop.exit();
                return;
            }
        }
        if let Err(e) = self.advance() {
            self.fail(e, event_loop);
            return;
        }
        if let Some(g) = &self.gfx {
            g.window.request_redraw();
        }
        // Redraw at the display's rate (vsync paces presentation); wake for the next frame.
        event_loop.set_control_flow(ControlFlow::WaitUntil(
            Instant::now() + Duration::from_millis(4),
        ));
    }
}

/// Opens the window and runs until it is closed (or `exit_after` passes), telling `events`
/// when the window opens and when the first frame is shown.
pub fn run(a: ViewOptions, events: impl FnMut(ViewerEvent) + 'static) -> Result<()> {
    let (camera, frames, fps, decoder, current) = match Source::open(&a.source)? {
        Source::Package(player) => {
            let m = player.package().manifest().clone();
            if a.frame >= m.frames {
                return Err(ViewerError::NoFrame {
                    frame: a.frame,
                    frames: m.frames,
                });
            }
            let dec = Decoder::start(*player, a.frame)?;
            (m.camera, m.frames, m.frame_rate, Some(dec), None)
        }
        Source::Video(video) => {
            let (camera, frames, fps) = (*video.camera(), video.frames(), video.fps());
            if a.frame >= frames {
                return Err(ViewerError::NoFrame {
                    frame: a.frame,
                    frames,
                });
            }
            (
                camera,
                frames,
                fps,
                Some(Decoder::start(*video, a.frame)?),
                None,
            )
        }
        Source::Still(frame) => (*frame.set.camera(), 1, 30.0, None, Some((0, *frame))),
    };
    let event_loop = EventLoop::new().map_err(|e| {
        ViewerError::Window(format!(
            "cannot open a window (no display: set DISPLAY, or run under Xvfb for a virtual one): {e}"
        ))
    })?;
    let now = Instant::now();
    let mut viewer = Viewer {
        camera,
        frames,
        fps,
        decoder,
        current,
        uploaded: None,
        playing: !a.paused,
        stereo: a.stereo,
        dps: a.dps,
        fill: true,
        hud: a.hud,
        filter: a.filter,
        eye: a.eye_separation,
        yaw: 0.0,
        pitch: 0.0,
        pan: (0.0, 0.0),
        dolly: 0.0,
        start_pose: a.pose,
        next_due: now,
        started: now,
        draw_ms: 0.0,
        frame_ms: 16.7,
        last_present: now,
        drag: None,
        cursor: (0.0, 0.0),
        modifiers: ModifiersState::empty(),
        gfx: None,
        error: None,
        announced: false,
        events: Box::new(events),
        args: a,
    };
    event_loop
        .run_app(&mut viewer)
        .map_err(|e| ViewerError::Window(format!("window events: {e}")))?;
    match viewer.error {
        Some(e) => Err(e),
        None => Ok(()),
    }
}

/// The readout as a small premultiplied RGBA image: white 5x7 glyphs on a dark band.
fn hud_image(text: &str) -> (u32, u32, Vec<u8>) {
    let (gw, gh) = (6u32, 9u32);
    let w = gw * text.chars().count() as u32 + 2;
    let h = gh;
    let mut px = vec![0u8; (w * h * 4) as usize];
    for p in px.chunks_exact_mut(4) {
        p.copy_from_slice(&[0, 0, 0, 160]);
    }
    for (i, c) in text.chars().enumerate() {
        let rows = glyph(c);
        for (ry, bits) in rows.iter().enumerate() {
            for rx in 0..5 {
                if bits & (0x10 >> rx) != 0 {
                    let (x, y) = (1 + i as u32 * gw + rx, 1 + ry as u32);
                    let o = ((y * w + x) * 4) as usize;
                    px[o..o + 4].copy_from_slice(&[255, 255, 255, 255]);
                }
            }
        }
    }
    (w, h, px)
}

/// 5x7 bitmaps (bit 4 is the leftmost column) of the characters the readout uses.
fn glyph(c: char) -> [u8; 7] {
    match c {
        '0' => [0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E],
        '1' => [0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E],
        '2' => [0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F],
        '3' => [0x1F, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0E],
        '4' => [0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02],
        '5' => [0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E],
        '6' => [0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E],
        '7' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08],
        '8' => [0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E],
        '9' => [0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C],
        '.' => [0, 0, 0, 0, 0, 0x0C, 0x0C],
        '/' => [0x01, 0x01, 0x02, 0x04, 0x08, 0x10, 0x10],
        'a' => [0, 0, 0x0E, 0x01, 0x0F, 0x11, 0x0F],
        'd' => [0x01, 0x01, 0x0D, 0x13, 0x11, 0x11, 0x0F],
        'e' => [0, 0, 0x0E, 0x11, 0x1F, 0x10, 0x0E],
        'f' => [0x06, 0x09, 0x08, 0x1C, 0x08, 0x08, 0x08],
        'm' => [0, 0, 0x1A, 0x15, 0x15, 0x11, 0x11],
        'o' => [0, 0, 0x0E, 0x11, 0x11, 0x11, 0x0E],
        'p' => [0, 0, 0x1E, 0x11, 0x1E, 0x10, 0x10],
        'r' => [0, 0, 0x16, 0x19, 0x10, 0x10, 0x10],
        's' => [0, 0, 0x0E, 0x10, 0x0E, 0x01, 0x1E],
        't' => [0x08, 0x08, 0x1C, 0x08, 0x08, 0x09, 0x06],
        'u' => [0, 0, 0x11, 0x11, 0x11, 0x13, 0x0D],
        _ => [0; 7],
    }
}
