//! The window: winit events in, key states out to the network task, and every display
//! frame the newest mesh drawn from the interpolated vehicle, with the HUD over it.

use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow, bail};
use tokio::sync::mpsc;
use winit::application::ApplicationHandler;
use winit::event::{ElementState, KeyEvent, WindowEvent};
use winit::event_loop::{ActiveEventLoop, EventLoop};
use winit::keyboard::{Key, NamedKey};
use winit::window::{Window, WindowId};

use crate::cockpit::{self, Action, Cockpit, Framed};
use crate::hud::{Numbers, Overlay};
use crate::live::{self, Command, Connection, Shared};
use crate::render::{Gpu, Renderer, Scene, Toggles};
use crate::session::{Session, State};

/// Colour tiles uploaded a display frame at most: 8 tiles of 256² are 2 MiB copied, a
/// fraction of a frame even on a software adapter, and the server streams a few tiles a
/// frame at its default rate (2 MB/s).
pub const MAX_UPLOADS: usize = 8;

/// How the window starts.
#[derive(Clone, Debug)]
pub struct Options {
    pub title: String,
    pub size: (u32, u32),
    pub toggles: Toggles,
    /// Where the session is connected, for the HUD.
    pub server: String,
    /// `server` names several addresses (edges of one world): the HUD says which one is
    /// in use.
    pub edges: bool,
    pub driver: bool,
    pub fov_y_deg: f32,
}

/// What to tell a person with no display.
pub const NO_DISPLAY: &str = "no display to open a window on (DISPLAY and WAYLAND_DISPLAY \
     are unset). Run headless instead, e.g.\n  cargo run --release -p roam-client -- --local \
     data/kossou --headless --frames 300 --screenshot kossou.png\nor give it a virtual \
     display: xvfb-run -a cargo run --release -p roam-client";

/// Whether there is a display to open a window on (X11 or Wayland).
pub fn has_display() -> bool {
    std::env::var_os("DISPLAY").is_some() || std::env::var_os("WAYLAND_DISPLAY").is_some()
}

/// Opens the window on `session` and runs until the person quits or the window closes.
#[allow(
    clippy::print_stdout,
    reason = "how the session ended is the window's last line for its user and for scripts"
)]
pub fn run(runtime: &tokio::runtime::Runtime, session: Session, opts: Options) -> Result<()> {
    if !has_display() {
        bail!("{NO_DISPLAY}");
    }
    let event_loop = EventLoop::new().map_err(|e| anyhow!("{e}: {NO_DISPLAY}"))?;
    let scene = session.scene.clone();
    let budget = session.core().budget();
    let (shared, commands, task) = live::spawn(runtime.handle(), session);
    let mut app = App {
        cockpit: Cockpit::new(budget, opts.toggles, opts.fov_y_deg),
        opts,
        scene: Some(scene),
        shared,
        commands,
        gfx: None,
        clock: Instant::now(),
        drawn: 0,
        occluded: false,
        rest_until: 0.0,
        error: None,
        tick: 0,
        ids: Vec::new(),
    };
    event_loop
        .run_app(&mut app)
        .context("running the window's event loop")?;
    // The goodbye goes out before the process ends (bounded: a dead server does not hold
    // the viewer).
    let _ = app.commands.send(Command::Quit);
    let _ = runtime.block_on(async { tokio::time::timeout(Duration::from_secs(2), task).await });
    match app.shared.connection() {
        Connection::Ended(why) if why == live::QUIT => {
            println!("roam-client: quit; the server heard the goodbye")
        }
        Connection::Ended(why) => println!("roam-client: {why}"),
        Connection::Connected => {
            println!("roam-client: quit without a goodbye (the server did not answer)")
        }
    }
    if let Some(e) = app.error {
        return Err(e);
    }
    Ok(())
}

/// The window and what draws into it.
struct Gfx {
    window: Arc<Window>,
    instance: wgpu::Instance,
    surface: wgpu::Surface<'static>,
    /// The format drawn through: the surface's, or an sRGB view of it.
    view_format: wgpu::TextureFormat,
    config: wgpu::SurfaceConfiguration,
    gpu: Gpu,
    renderer: Renderer,
    overlay: Overlay,
}

struct App {
    opts: Options,
    scene: Option<Scene>,
    shared: Arc<Shared>,
    commands: mpsc::UnboundedSender<Command>,
    gfx: Option<Gfx>,
    /// Keys, toggles, vehicles, camera and rates ([`crate::cockpit`]).
    cockpit: Cockpit,
    clock: Instant,
    /// Frames presented with terrain.
    drawn: u64,
    /// The window is hidden (minimised, covered): nothing is drawn.
    occluded: bool,
    /// No surface texture was to be had: no drawing until then (local seconds).
    rest_until: f64,
    error: Option<anyhow::Error>,
    /// The newest frame's tick and vehicles (for the watching keys and the HUD).
    tick: u64,
    ids: Vec<u16>,
}

impl App {
    fn open(&mut self, event_loop: &ActiveEventLoop) -> Result<Gfx> {
        let scene = self.scene.take().context("the scene was already used")?;
        let attrs = Window::default_attributes()
            .with_title(self.opts.title.clone())
            .with_inner_size(winit::dpi::PhysicalSize::new(
                self.opts.size.0,
                self.opts.size.1,
            ));
        let window = Arc::new(
            event_loop
                .create_window(attrs)
                .context("creating the window")?,
        );
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_with_display_handle_from_env(
                Box::new(event_loop.owned_display_handle()),
            ));
        let surface = instance
            .create_surface(window.clone())
            .context("creating the window's surface")?;
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            compatible_surface: Some(&surface),
            force_fallback_adapter: false,
            ..Default::default()
        }))
        .map_err(|e| {
            anyhow!(
                "no GPU adapter for the window ({e}); {}",
                crate::render::NO_ADAPTER
            )
        })?;
        let gpu = Gpu::open(&adapter)?;
        let size = window.inner_size();
        let (config, view_format) = crate::render::configure_surface(
            &surface,
            &adapter,
            &gpu.device,
            (size.width, size.height),
        )
        .context("the window's surface")?;
        let renderer = Renderer::new(&gpu, view_format, scene);
        let overlay = Overlay::new(&window, &gpu.device, view_format);
        Ok(Gfx {
            window,
            instance,
            surface,
            view_format,
            config,
            gpu,
            renderer,
            overlay,
        })
    }

    fn key(&mut self, event_loop: &ActiveEventLoop, event: &KeyEvent) {
        let name = match &event.logical_key {
            Key::Named(NamedKey::ArrowUp) => "ArrowUp",
            Key::Named(NamedKey::ArrowDown) => "ArrowDown",
            Key::Named(NamedKey::ArrowLeft) => "ArrowLeft",
            Key::Named(NamedKey::ArrowRight) => "ArrowRight",
            Key::Named(NamedKey::Escape) => "Escape",
            Key::Named(NamedKey::Space) => "Space",
            Key::Named(NamedKey::Tab) => "Tab",
            Key::Named(NamedKey::Home) => "Home",
            Key::Named(NamedKey::End) => "End",
            Key::Character(c) => c.as_str(),
            _ => return,
        };
        // A spectator's keys (a replay serves everyone as one): following, and a watched
        // recording's clock.
        let status = self.shared.status();
        if !self.opts.driver || status.replay.is_some() {
            if event.state == ElementState::Pressed && !event.repeat {
                let replay = status.replay.as_ref().map(|r| (r, self.tick));
                match crate::watching::key(name, self.shared.vehicle(), &self.ids, replay) {
                    Some(crate::watching::Ask::Follow(v)) => {
                        let _ = self.commands.send(Command::Follow(v));
                        return;
                    }
                    Some(crate::watching::Ask::Replay(c)) => {
                        let _ = self.commands.send(Command::Replay(c));
                        return;
                    }
                    None => {}
                }
            }
            if cockpit::drive_keys(name).is_some() {
                return;
            }
        }
        if let Some(k) = cockpit::drive_keys(name) {
            match event.state {
                ElementState::Pressed if !event.repeat => self.shared.key_down(k),
                ElementState::Released => self.shared.key_up(k),
                ElementState::Pressed => {}
            }
            return;
        }
        if event.state != ElementState::Pressed || event.repeat {
            return;
        }
        match self.cockpit.press(name) {
            Action::Quit => self.quit(event_loop),
            Action::Budget(b) => {
                let _ = self.commands.send(Command::Budget(b));
            }
            Action::None => {}
        }
    }

    fn quit(&mut self, event_loop: &ActiveEventLoop) {
        let _ = self.commands.send(Command::Quit);
        event_loop.exit();
    }

    /// Takes the newest frame, if any, and draws one display frame.
    #[allow(
        clippy::print_stdout,
        reason = "a line for scripts and tests: the window is up and shows the terrain"
    )]
    fn redraw(&mut self) -> Result<()> {
        let now = self.clock.elapsed().as_secs_f64();
        let Some(gfx) = self.gfx.as_mut() else {
            return Ok(());
        };
        if let Some(a) = self.shared.take_arrived() {
            let started = Instant::now();
            gfx.renderer.apply(&gfx.gpu, &a.terrain);
            let upload_ms = started.elapsed().as_secs_f64() * 1e3;
            self.cockpit.costs(now, a.decode_ms, upload_ms);
            let at = now - a.at.elapsed().as_secs_f64();
            self.tick = a.tick;
            self.ids = a.vehicles.iter().map(|v| v.id).collect();
            self.cockpit.arrived(now, at, a.tick, &a.vehicles, a.ground);
        }
        let (colors, color_bytes, color_tiles, color_capacity) = self.shared.colors(MAX_UPLOADS);
        gfx.renderer.update_colors(&gfx.gpu, &colors);
        self.cockpit
            .received(now, self.shared.bytes_in(), color_bytes);
        let me = self.shared.vehicle();
        let size = (gfx.config.width, gfx.config.height);
        let world_size = gfx.renderer.scene().world_size();
        let Framed {
            view,
            markers,
            followed,
            tell,
        } = self.cockpit.frame(now, me, size, world_size);
        gfx.renderer.set_markers(&markers);
        if let Some(change) = tell {
            let _ = self.commands.send(Command::View(change));
        }

        let started = Instant::now();
        let frame = match gfx.surface.get_current_texture() {
            wgpu::CurrentSurfaceTexture::Success(f)
            | wgpu::CurrentSurfaceTexture::Suboptimal(f) => f,
            lost @ (wgpu::CurrentSurfaceTexture::Outdated | wgpu::CurrentSurfaceTexture::Lost) => {
                if matches!(lost, wgpu::CurrentSurfaceTexture::Lost) {
                    gfx.surface = gfx
                        .instance
                        .create_surface(gfx.window.clone())
                        .context("recreating the window's lost surface")?;
                }
                // The window's size now (it may have changed with no event); none while
                // minimised.
                let size = gfx.window.inner_size();
                if size.width > 0 && size.height > 0 {
                    gfx.config.width = size.width;
                    gfx.config.height = size.height;
                    gfx.surface.configure(&gfx.gpu.device, &gfx.config);
                } else {
                    self.rest_until = now + 0.1;
                }
                return Ok(());
            }
            // Hidden, timed out, or a validation error already reported: try again a
            // little later rather than spin.
            _ => {
                self.rest_until = now + 0.1;
                return Ok(());
            }
        };
        let target = frame.texture.create_view(&wgpu::TextureViewDescriptor {
            format: Some(gfx.view_format),
            ..Default::default()
        });
        gfx.renderer
            .render(&gfx.gpu, &target, size, &view, self.cockpit.toggles);
        let numbers = self.cockpit.hud_shown.then(|| {
            let connection = self.shared.connection();
            let status = self.shared.status();
            let reconnecting = matches!(status.state, State::Reconnecting { .. });
            Numbers {
                triangles: gfx.renderer.triangles(),
                color_mb: color_bytes as f64 / 1e6,
                color_tiles,
                color_capacity,
                latency_ms: self.shared.latency_ms(),
                max_budget: status.welcome.max_budget,
                connected: connection == Connection::Connected && !reconnecting,
                reconnecting_s: status
                    .gaps
                    .current(Instant::now())
                    .filter(|_| reconnecting)
                    .map(|g| g.as_secs_f64()),
                reconnects: status.gaps.reconnects,
                resumed: status.gaps.resumed,
                world_gone: status.world.gone.clone(),
                connection: match (connection, &status.state) {
                    (Connection::Connected, State::Reconnecting { why, attempts }) => {
                        format!("to {} · {why} · attempt {attempts}", self.opts.server)
                    }
                    // Of several edges, the one in use.
                    (Connection::Connected, _) if self.opts.edges || status.edges_learned > 0 => {
                        format!(
                            "connected to {} (of {}) · vehicle #{me} · {}",
                            status.addr,
                            self.opts.server,
                            if self.opts.driver {
                                "driving"
                            } else {
                                "watching"
                            }
                        )
                    }
                    (Connection::Connected, _) => format!(
                        "connected to {} · vehicle #{me} · {}",
                        self.opts.server,
                        if self.opts.driver {
                            "driving"
                        } else {
                            "watching"
                        }
                    ),
                    (Connection::Ended(why), _) => format!("disconnected: {why}"),
                },
                adapter: format!("{} ({:?})", gfx.gpu.adapter.name, gfx.gpu.adapter.backend),
                replay: status
                    .replay
                    .as_ref()
                    .map(|r| crate::watching::replay_line(r, self.tick)),
                ..self.cockpit.numbers(now, followed.as_ref())
            }
        });
        gfx.overlay
            .paint(&gfx.gpu, &gfx.window, &target, size, numbers.as_ref());
        gfx.window.pre_present_notify();
        gfx.gpu.queue.present(frame);
        self.cockpit
            .drawn(now, started.elapsed().as_secs_f64() * 1e3);
        if gfx.renderer.triangles() > 0 {
            self.drawn += 1;
            if self.drawn == 1 {
                // A line for scripts and tests: the window is up and shows the terrain.
                println!(
                    "roam-client: window drawn ({} triangles, {})",
                    gfx.renderer.triangles(),
                    gfx.gpu.adapter.name
                );
            }
        }
        Ok(())
    }
}

impl ApplicationHandler for App {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.gfx.is_some() {
            return;
        }
        match self.open(event_loop) {
            Ok(g) => {
                g.window.request_redraw();
                self.gfx = Some(g);
            }
            Err(e) => {
                self.error = Some(e);
                event_loop.exit();
            }
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _: WindowId, event: WindowEvent) {
        if let Some(g) = self.gfx.as_mut() {
            let _ = g.overlay.state.on_window_event(&g.window, &event);
        }
        match event {
            WindowEvent::CloseRequested => self.quit(event_loop),
            WindowEvent::Focused(false) => self.shared.keys_released(),
            WindowEvent::Occluded(hidden) => self.occluded = hidden,
            WindowEvent::KeyboardInput { event, .. } => self.key(event_loop, &event),
            WindowEvent::Resized(size) => {
                if let Some(g) = self.gfx.as_mut()
                    && size.width > 0
                    && size.height > 0
                {
                    g.config.width = size.width;
                    g.config.height = size.height;
                    g.surface.configure(&g.gpu.device, &g.config);
                }
            }
            WindowEvent::RedrawRequested => {
                if let Err(e) = self.redraw() {
                    self.error = Some(e);
                    event_loop.exit();
                }
            }
            _ => {}
        }
    }

    fn about_to_wait(&mut self, event_loop: &ActiveEventLoop) {
        // Ctrl-C in the terminal: once the goodbye has been said (or the connection is gone).
        if self
            .shared
            .interrupted
            .load(std::sync::atomic::Ordering::Relaxed)
            && self.shared.connection() != Connection::Connected
        {
            event_loop.exit();
            return;
        }
        // Draw continuously: the present waits for the display. Hidden, wake ten times a
        // second to notice Ctrl-C, and draw nothing.
        let now = self.clock.elapsed().as_secs_f64();
        if self.occluded || now < self.rest_until {
            event_loop.set_control_flow(winit::event_loop::ControlFlow::WaitUntil(
                Instant::now() + Duration::from_millis(100),
            ));
        } else if let Some(g) = &self.gfx {
            event_loop.set_control_flow(winit::event_loop::ControlFlow::Wait);
            g.window.request_redraw();
        }
    }
}
