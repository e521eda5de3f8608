//! The page's display: the GPU (WebGPU where the browser has it, WebGL2 otherwise) drawing
//! into the canvas with the native viewer's [`Renderer`], one display frame per
//! `requestAnimationFrame` — the newest frame taken from the core and decoded (latest frame
//! wins), the colour tiles uploaded, the [`Cockpit`] riding the vehicle — the keys (the
//! window's, by the same names), a key datagram every 10 ms, and the HUD as text over the
//! canvas. For tests it posts its results once `frames` frames are decoded: frames a
//! second, decode errors, load to first frame, and the canvas read back in the same task
//! as the draw (later it may read as zeros).

use std::cell::RefCell;
use std::rc::Rc;

use roam_client::camera::LocalGround;
use roam_client::cockpit::{self, Action, Cockpit};
use roam_client::core::Taken;
use roam_client::hud::{self, Numbers};
use roam_client::render::{Gpu, Renderer, Scene, TerrainVertices, Toggles};
use roam_client::supervisor::State;
use wasm_bindgen::JsCast;
use wasm_bindgen::prelude::*;
use web_sys::{HtmlCanvasElement, KeyboardEvent};
use web_time::Instant;

use crate::net::Shared;
use crate::page::{self, Options};

/// Colour tiles uploaded a display frame at most (as the window).
const MAX_UPLOADS: usize = 8;
/// Radius of the ground kept for the camera's look-ahead, world units (as the window).
const GROUND_RADIUS: f32 = 600.0;

/// What the browser says when it has neither GPU API.
pub(crate) const NO_GPU: &str = "This browser offers neither WebGPU nor WebGL2, which the viewer \
    draws with. Use a current Chrome, Edge or Firefox, and check that hardware acceleration \
    is on (chrome://gpu).";

/// Why the display cannot start: no GPU, or the browser refused a timer or a listener;
/// in the words the page shows.
#[derive(Debug, thiserror::Error)]
pub(crate) enum GfxError {
    /// Neither WebGPU nor WebGL2 on the canvas (`why`: the browser's or wgpu's words).
    #[error("{NO_GPU} ({why})")]
    NoGpu { why: String },
    /// The adapter gave no device.
    #[error("opening the GPU: {why}")]
    Device { why: String },
    /// The canvas cannot be drawn through on this device.
    #[error("{why}")]
    Surface { why: String },
    /// The browser refused to `what` (start the key timer, listen to the keys).
    #[error("{what}: {why}")]
    Browser { what: &'static str, why: String },
}

/// The canvas and what draws into it.
pub(crate) struct Gfx {
    canvas: HtmlCanvasElement,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    view_format: wgpu::TextureFormat,
    pub gpu: Gpu,
}

impl Gfx {
    /// Opens the GPU on the canvas: `gpu` is `webgpu`, `webgl` or empty (either).
    pub(crate) async fn open(canvas: HtmlCanvasElement, gpu: &str) -> Result<Gfx, GfxError> {
        let no_gpu = |e: &dyn std::fmt::Display| GfxError::NoGpu { why: e.to_string() };
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = match gpu {
            "webgpu" => wgpu::Backends::BROWSER_WEBGPU,
            "webgl" => wgpu::Backends::GL,
            _ => wgpu::Backends::BROWSER_WEBGPU | wgpu::Backends::GL,
        };
        let instance = wgpu::util::new_instance_with_webgpu_detection(desc).await;
        let surface = instance
            .create_surface(wgpu::SurfaceTarget::Canvas(canvas.clone()))
            .map_err(|e| no_gpu(&e))?;
        let adapter = instance
            .request_adapter(&wgpu::RequestAdapterOptions {
                power_preference: wgpu::PowerPreference::HighPerformance,
                compatible_surface: Some(&surface),
                force_fallback_adapter: false,
                ..Default::default()
            })
            .await
            .map_err(|e| no_gpu(&e))?;
        let gpu = Gpu::open_async(&adapter)
            .await
            .map_err(|e| GfxError::Device {
                why: format!("{e:#}"),
            })?;
        let size = pixel_size(&canvas);
        let (config, view_format) =
            roam_client::render::configure_surface(&surface, &adapter, &gpu.device, size).map_err(
                |e| GfxError::Surface {
                    why: format!("{e:#}"),
                },
            )?;
        Ok(Gfx {
            canvas,
            surface,
            config,
            view_format,
            gpu,
        })
    }

    /// The adapter as the HUD and the test report name it.
    pub(crate) fn adapter(&self) -> String {
        format!("{} ({:?})", self.gpu.adapter.name, self.gpu.adapter.backend)
    }

    /// The canvas follows its size on the page (in device pixels).
    fn fit(&mut self) {
        let (w, h) = pixel_size(&self.canvas);
        if (w, h) != (self.config.width, self.config.height) {
            self.canvas.set_width(w);
            self.canvas.set_height(h);
            self.config.width = w;
            self.config.height = h;
            self.surface.configure(&self.gpu.device, &self.config);
        }
    }
}

/// The canvas' size on the page in device pixels.
pub(crate) fn pixel_size(canvas: &HtmlCanvasElement) -> (u32, u32) {
    let ratio = page::window().device_pixel_ratio().max(1.0);
    let w = (f64::from(canvas.client_width()) * ratio).round() as u32;
    let h = (f64::from(canvas.client_height()) * ratio).round() as u32;
    (w.clamp(1, 4096), h.clamp(1, 4096))
}

struct App {
    gfx: Gfx,
    renderer: Renderer,
    live: Shared,
    cockpit: Cockpit,
    options: Options,
    driver: bool,
    clock: Instant,
    terrain: TerrainVertices,
    /// Frames taken and decoded.
    decoded: u64,
    /// Pictures drawn and presented.
    drawn: u64,
    first_frame_ms: Option<f64>,
    hud_at: f64,
    reported: bool,
    /// The state last said: the session's, the world's word, and (for a test) the edges
    /// known, the one in use and the reconnections (a move to another edge may be quicker
    /// than a frame, and must still be heard).
    said: Option<(State, Option<String>, [usize; 3])>,
    /// Recent key change → frame showing it, milliseconds.
    latencies: std::collections::VecDeque<f64>,
    /// The newest frame's tick and vehicles (for the watching keys and the HUD).
    tick: u64,
    ids: Vec<u16>,
}

/// Starts the display, the keys and the key sender; they run as long as the page.
pub(crate) fn start(
    gfx: Gfx,
    scene: Scene,
    live: Shared,
    options: Options,
) -> Result<(), GfxError> {
    let budget = live.borrow().core.budget();
    let renderer = Renderer::new(&gfx.gpu, gfx.view_format, scene);
    let app = Rc::new(RefCell::new(App {
        gfx,
        renderer,
        cockpit: Cockpit::new(budget, Toggles::default(), 60.0),
        driver: !options.spectator,
        live,
        options,
        clock: Instant::now(),
        terrain: TerrainVertices::default(),
        decoded: 0,
        drawn: 0,
        first_frame_ms: None,
        hud_at: 0.0,
        reported: false,
        said: None,
        latencies: std::collections::VecDeque::new(),
        tick: 0,
        ids: Vec::new(),
    }));
    keys(&app)?;
    if app.borrow().driver {
        let live = app.borrow().live.clone();
        let tick = Closure::<dyn FnMut()>::new(move || {
            let mut l = live.borrow_mut();
            if !l.ended() {
                l.send_keys();
            }
        });
        page::window()
            .set_interval_with_callback_and_timeout_and_arguments_0(
                tick.as_ref().unchecked_ref(),
                10,
            )
            .map_err(|e| GfxError::Browser {
                what: "starting the key timer",
                why: format!("{e:?}"),
            })?;
        tick.forget(); // it runs as long as the page
    }
    animate(app);
    Ok(())
}

/// Key presses and releases on the page, by the window's names.
fn keys(app: &Rc<RefCell<App>>) -> Result<(), GfxError> {
    let window = page::window();
    let down = {
        let app = app.clone();
        Closure::<dyn FnMut(KeyboardEvent)>::new(move |e: KeyboardEvent| {
            let key = e.key();
            // The page's key names as the window's.
            let name = match key.as_str() {
                " " => "Space",
                other => other,
            };
            let mut a = app.borrow_mut();
            // A spectator's keys (a replay serves everyone as one): following, and a
            // watched recording's clock.
            let watching = !a.driver || a.live.borrow().replay.is_some();
            if watching && !e.repeat() {
                let ask = {
                    let l = a.live.borrow();
                    let replay = l.replay.as_ref().map(|r| (r, a.tick));
                    roam_client::watching::key(name, l.welcome.vehicle, &a.ids, replay)
                };
                let msg = match ask {
                    Some(roam_client::watching::Ask::Follow(v)) => {
                        Some(roam_protocol::messages::ClientMessage::Follow(v))
                    }
                    Some(roam_client::watching::Ask::Replay(c)) => {
                        Some(roam_protocol::messages::ClientMessage::Replay(c))
                    }
                    None => None,
                };
                if let Some(msg) = msg {
                    e.prevent_default(); // Tab, Space, Home do not move the page
                    a.live.borrow_mut().send(msg);
                    return;
                }
            }
            let name = name.to_string();
            if let Some(k) = cockpit::drive_keys(&name) {
                e.prevent_default(); // the arrows do not scroll the page
                if !e.repeat() && a.driver {
                    a.live.borrow_mut().keys.key_down(k);
                }
                return;
            }
            if e.repeat() || e.ctrl_key() || e.meta_key() || e.alt_key() {
                return;
            }
            match a.cockpit.press(&name) {
                Action::Quit => a.live.borrow_mut().quit(),
                Action::Budget(b) => {
                    let mut l = a.live.borrow_mut();
                    l.core.set_budget(b);
                    l.flush();
                }
                Action::None => {}
            }
        })
    };
    let up = {
        let app = app.clone();
        Closure::<dyn FnMut(KeyboardEvent)>::new(move |e: KeyboardEvent| {
            if let Some(k) = cockpit::drive_keys(&e.key()) {
                app.borrow().live.borrow_mut().keys.key_up(k);
            }
        })
    };
    let blur = {
        let app = app.clone();
        Closure::<dyn FnMut()>::new(move || {
            app.borrow().live.borrow_mut().keys.keys_released();
        })
    };
    // Leaving the page says goodbye (the close code tells the server to free the vehicle
    // rather than hold it for a reconnection).
    let hide = {
        let app = app.clone();
        Closure::<dyn FnMut()>::new(move || {
            app.borrow().live.borrow_mut().leave();
        })
    };
    let fail = |e: JsValue| GfxError::Browser {
        what: "listening to the keys",
        why: format!("{e:?}"),
    };
    window
        .add_event_listener_with_callback("pagehide", hide.as_ref().unchecked_ref())
        .map_err(fail)?;
    hide.forget();
    window
        .add_event_listener_with_callback("keydown", down.as_ref().unchecked_ref())
        .map_err(fail)?;
    window
        .add_event_listener_with_callback("keyup", up.as_ref().unchecked_ref())
        .map_err(fail)?;
    window
        .add_event_listener_with_callback("blur", blur.as_ref().unchecked_ref())
        .map_err(fail)?;
    // They listen as long as the page.
    down.forget();
    up.forget();
    blur.forget();
    Ok(())
}

/// The animation frame's callback, shared with itself to ask for the next frame.
type FrameCallback = Rc<RefCell<Option<Closure<dyn FnMut()>>>>;

/// One display frame per animation frame, as long as the page.
fn animate(app: Rc<RefCell<App>>) {
    let next: FrameCallback = Rc::new(RefCell::new(None));
    let again = next.clone();
    *next.borrow_mut() = Some(Closure::new(move || {
        app.borrow_mut().frame();
        if let Some(f) = again.borrow().as_ref() {
            let _ = page::window().request_animation_frame(f.as_ref().unchecked_ref());
        }
    }));
    if let Some(f) = next.borrow().as_ref() {
        let _ = page::window().request_animation_frame(f.as_ref().unchecked_ref());
    }
}

impl App {
    fn frame(&mut self) {
        let now = self.clock.elapsed().as_secs_f64();
        self.take(now);
        self.status();
        self.gfx.fit();
        let (colors, color_bytes, tiles, capacity, bytes_in, me) = {
            let mut l = self.live.borrow_mut();
            let update = l.colors.drain(MAX_UPLOADS);
            let (resident, capacity) = (l.colors.resident(), l.colors.capacity());
            (
                update,
                l.color_bytes(),
                resident,
                capacity,
                l.bytes_in(),
                l.welcome.vehicle,
            )
        };
        self.renderer.update_colors(&self.gfx.gpu, &colors);
        self.cockpit.received(now, bytes_in, color_bytes);
        let size = (self.gfx.config.width, self.gfx.config.height);
        let framed = self
            .cockpit
            .frame(now, me, size, self.renderer.scene().world_size());
        self.renderer.set_markers(&framed.markers);
        if let Some(change) = framed.tell {
            self.live.borrow_mut().set_view(change);
        }
        let started = Instant::now();
        let texture = match self.gfx.surface.get_current_texture() {
            wgpu::CurrentSurfaceTexture::Success(f)
            | wgpu::CurrentSurfaceTexture::Suboptimal(f) => f,
            _ => {
                self.gfx
                    .surface
                    .configure(&self.gfx.gpu.device, &self.gfx.config);
                return;
            }
        };
        let target = texture.texture.create_view(&wgpu::TextureViewDescriptor {
            format: Some(self.gfx.view_format),
            ..Default::default()
        });
        self.renderer.render(
            &self.gfx.gpu,
            &target,
            size,
            &framed.view,
            self.cockpit.toggles,
        );
        self.gfx.gpu.queue.present(texture);
        self.drawn += 1;
        self.cockpit
            .drawn(now, started.elapsed().as_secs_f64() * 1e3);
        if self.renderer.triangles() > 0 && self.first_frame_ms.is_none() {
            self.first_frame_ms = Some(page::since_load_ms());
            page::say("", false);
        }
        if now - self.hud_at >= 0.25 {
            self.hud_at = now;
            let n = self.numbers(
                now,
                framed.followed.as_ref(),
                (color_bytes, tiles, capacity),
            );
            page::hud(self.cockpit.hud_shown.then(|| hud::lines(&n)).as_deref());
        }
        if !self.reported && self.decoded >= self.options.frames {
            self.reported = true;
            self.report(now, framed.followed);
        }
    }

    /// The newest frame, decoded into the vertices and uploaded.
    fn take(&mut self, now: f64) {
        let mut l = self.live.borrow_mut();
        if !l.core.has_frame() || l.ended() {
            return;
        }
        let started = Instant::now();
        let taken = l.core.take(true);
        l.flush();
        match taken {
            Ok(Taken::Frame(r)) => {
                if let Some(seq) = r.input_seq {
                    let applied = l.keys.applied(seq, r.arrived);
                    self.latencies.extend(applied);
                    while self.latencies.len() > 64 {
                        self.latencies.pop_front();
                    }
                }
                l.gaps.frame(r.arrived);
                let seen = roam_client::render::MorphView::of_vehicle(
                    self.renderer.scene(),
                    &r.vehicles,
                    l.welcome.vehicle,
                    60.0,
                    self.gfx.config.height,
                );
                l.core.set_morph_view(seen);
                l.core
                    .update_vertices(self.renderer.scene(), &mut self.terrain);
                drop(l);
                let decode_ms = started.elapsed().as_secs_f64() * 1e3;
                let ground = match r.vehicles.iter().find(|v| v.id == self.me()) {
                    Some(v) => LocalGround::near(
                        &self.terrain.corners,
                        v.x as f32,
                        v.z as f32,
                        GROUND_RADIUS,
                    ),
                    None => LocalGround::default(),
                };
                let uploading = Instant::now();
                self.renderer.upload_dirty(&self.gfx.gpu, &mut self.terrain);
                let upload_ms = uploading.elapsed().as_secs_f64() * 1e3;
                self.cockpit.costs(now, decode_ms, upload_ms);
                let at = now - r.arrived.elapsed().as_secs_f64();
                self.tick = r.tick;
                self.ids = r.vehicles.iter().map(|v| v.id).collect();
                self.cockpit.arrived(now, at, r.tick, &r.vehicles, ground);
                self.decoded += 1;
            }
            Ok(Taken::Nothing) => {}
            Ok(Taken::Dropped(_)) => l.dropped += 1,
            Err(broken) => l.end(format!(
                "the server sent a frame it could not have: {broken}"
            )),
        }
    }

    fn me(&self) -> u16 {
        self.live.borrow().welcome.vehicle
    }

    /// The message line follows the session's state, and the edge's word that its world
    /// is gone; a test hears of the edges it learns and moves to too.
    fn status(&mut self) {
        let (state, gone, edges) = {
            let l = self.live.borrow();
            let edges = [l.edges.len(), l.edges.index(), l.gaps.reconnects as usize];
            (l.state.clone(), l.world.gone.clone(), edges)
        };
        let now = (state, gone, edges);
        if self.said.as_ref() == Some(&now) {
            return;
        }
        let (state, gone, _) = now.clone();
        let (text, error) = match &state {
            State::Connected if gone.is_some() => (
                format!(
                    "The world behind this server does not answer ({}): showing it as last \
                     seen.",
                    gone.as_deref().unwrap_or_default()
                ),
                true,
            ),
            State::Connected if self.first_frame_ms.is_none() => {
                ("joined; waiting for the first frame…".to_owned(), false)
            }
            State::Connected => (String::new(), false),
            State::Reconnecting { why, attempts } => {
                (format!("{why} — reconnecting (attempt {attempts})…"), true)
            }
            State::Ended(why) if why == "quit" => (
                "You left the server. Reload the page to join again.".to_owned(),
                false,
            ),
            State::Ended(why) => (
                format!("Disconnected: {why}. Reload the page to try again."),
                true,
            ),
        };
        page::say(&text, error);
        // A test hears every change after the first.
        if let (Some(url), Some(_)) = (self.options.report.clone(), &self.said) {
            let kind = match state {
                State::Connected => "connected",
                State::Reconnecting { .. } => "reconnecting",
                State::Ended(_) => "ended",
            };
            let l = self.live.borrow();
            let body = serde_json::json!({
                "state": kind,
                "world_gone": gone,
                "message": text,
                "vehicle": l.welcome.vehicle,
                "reconnects": l.gaps.reconnects,
                "resumed": l.gaps.resumed,
                // The edge it is on or trying (its WebTransport URL) and how many it knows.
                "edge": l.edges.current().url,
                "edges": l.edges.len(),
            })
            .to_string();
            wasm_bindgen_futures::spawn_local(async move { page::post(&url, &body).await });
        }
        self.said = Some(now);
    }

    fn numbers(
        &mut self,
        now: f64,
        followed: Option<&roam_protocol::messages::VehicleView>,
        color: (u64, u32, u32),
    ) -> Numbers {
        let l = self.live.borrow();
        let reconnecting = match &l.state {
            State::Reconnecting { .. } => l.gaps.current(Instant::now()).map(|g| g.as_secs_f64()),
            _ => None,
        };
        let host = page::window().location().host().unwrap_or_default();
        Numbers {
            triangles: self.renderer.triangles(),
            color_mb: color.0 as f64 / 1e6,
            color_tiles: color.1,
            color_capacity: color.2,
            max_budget: l.welcome.max_budget,
            connected: l.state == State::Connected,
            reconnecting_s: reconnecting,
            reconnects: l.gaps.reconnects,
            resumed: l.gaps.resumed,
            world_gone: l.world.gone.clone(),
            latency_ms: {
                let mut v: Vec<f64> = self.latencies.iter().copied().collect();
                v.sort_by(f64::total_cmp);
                v.get(v.len() / 2).copied()
            },
            connection: match &l.state {
                State::Ended(why) => format!("disconnected: {why}"),
                State::Reconnecting { why, attempts } => {
                    format!("to {host} · {why} · attempt {attempts}")
                }
                State::Connected => format!(
                    "connected to {host} · vehicle #{} · {}",
                    l.welcome.vehicle,
                    if self.driver { "driving" } else { "watching" }
                ),
            },
            adapter: self.gfx.adapter(),
            replay: l
                .replay
                .as_ref()
                .map(|r| roam_client::watching::replay_line(r, self.tick)),
            ..self.cockpit.numbers(now, followed)
        }
    }

    /// Posts the test's results: the numbers, and the canvas as a PNG (read back now, in
    /// the task that drew it).
    fn report(&mut self, now: f64, followed: Option<roam_protocol::messages::VehicleView>) {
        let Some(url) = self.options.report.clone() else {
            return;
        };
        let png = self.gfx.canvas.to_data_url().unwrap_or_default();
        let n = self.cockpit.numbers(now, followed.as_ref());
        let l = self.live.borrow();
        let body = serde_json::json!({
            "frames": self.decoded,
            "drawn": self.drawn,
            "decode_errors": l.dropped,
            "fps": n.fps,
            "server_fps": n.server_fps,
            "first_frame_ms": self.first_frame_ms,
            "adapter": self.gfx.adapter(),
            "backend": format!("{:?}", self.gfx.gpu.adapter.backend),
            "triangles": self.renderer.triangles(),
            "vehicle": l.welcome.vehicle,
            "tick": self.tick,
            // Watching a recording: what the server said of it, and the HUD's line.
            "replay": l.replay.as_ref().map(|r| serde_json::json!({
                "start": r.start,
                "end": r.end,
                "speed": r.speed,
                "paused": r.paused,
                "control": r.control,
                "line": roam_client::watching::replay_line(r, self.tick),
            })),
            "edge": l.edges.current().url,
            "edges": l.edges.len(),
            "speed": n.speed,
            "color_tiles": l.colors.resident(),
            "size": [self.gfx.config.width, self.gfx.config.height],
            "png": png,
        })
        .to_string();
        wasm_bindgen_futures::spawn_local(async move { page::post(&url, &body).await });
    }
}
