//! The heads-up display (egui): what the viewer sees of the session's numbers, drawn over
//! the frame; and the rates it shows, measured over a sliding second.

use std::collections::VecDeque;

use crate::render::Toggles;

/// Events per second and amounts per second over the last second.
#[derive(Clone, Debug, Default)]
pub struct Rate {
    events: VecDeque<(f64, f64)>,
}

impl Rate {
    /// `amount` happened at `now_s`.
    pub fn add(&mut self, now_s: f64, amount: f64) {
        self.events.push_back((now_s, amount));
        self.trim(now_s);
    }

    fn trim(&mut self, now_s: f64) {
        while self.events.front().is_some_and(|&(t, _)| t <= now_s - 1.0) {
            self.events.pop_front();
        }
        // Bounded whatever the caller does.
        while self.events.len() > 4096 {
            self.events.pop_front();
        }
    }

    /// Events in the last second.
    pub fn per_second(&mut self, now_s: f64) -> f64 {
        self.trim(now_s);
        self.events.len() as f64
    }

    /// The amounts of the last second, summed.
    pub fn amount_per_second(&mut self, now_s: f64) -> f64 {
        self.trim(now_s);
        self.events.iter().map(|&(_, a)| a).sum()
    }

    /// The mean amount of the last second's events.
    pub fn mean(&mut self, now_s: f64) -> Option<f64> {
        self.trim(now_s);
        let n = self.events.len();
        (n > 0).then(|| self.amount_per_second(now_s) / n as f64)
    }
}

/// What the HUD shows.
#[derive(Clone, Debug, Default)]
pub struct Numbers {
    pub fps: f64,
    /// Mean time to draw a frame (CPU side, from acquiring the surface to presenting), ms.
    pub frame_ms: Option<f64>,
    pub triangles: usize,
    pub server_fps: f64,
    pub kb_per_s: f64,
    /// Colour tile bytes a second and in all (MB), and the tiles resident out of the most
    /// held.
    pub color_kb_per_s: f64,
    pub color_mb: f64,
    pub color_tiles: u32,
    pub color_capacity: u32,
    pub latency_ms: Option<f64>,
    pub decode_ms: Option<f64>,
    pub upload_ms: Option<f64>,
    /// m/s.
    pub speed: f64,
    /// SPEC heading: 0 faces south, 90 east.
    pub heading_deg: f64,
    /// The budget asked for, and the most the server serves (0: not known).
    pub budget: u32,
    pub max_budget: u32,
    pub toggles: Toggles,
    pub connection: String,
    pub connected: bool,
    /// While reconnecting: the time without frames so far, seconds.
    pub reconnecting_s: Option<f64>,
    /// Connections made again after a loss, and of those the ones that got the vehicle
    /// back.
    pub reconnects: u32,
    pub resumed: u32,
    /// The edge says the world behind it does not answer: why (the frames show it as
    /// last seen).
    pub world_gone: Option<String>,
    pub adapter: String,
    /// Watching a recording: its line ([`crate::watching::replay_line`]).
    pub replay: Option<String>,
}

/// The HUD's first line: the connection, a reconnection going on, or the ones there were.
fn connection_line(n: &Numbers) -> String {
    if let Some(gap) = n.reconnecting_s {
        return format!("reconnecting… {gap:.1} s  ({})", n.connection);
    }
    match n.reconnects {
        0 => n.connection.clone(),
        r => format!(
            "{}  · reconnected {r}×{}",
            n.connection,
            if n.resumed < r {
                format!(" ({} with the vehicle back)", n.resumed)
            } else {
                String::new()
            }
        ),
    }
}

/// The budget as the HUD says it: the one served, and the one asked when the server's
/// cap is below it.
fn budget_text(n: &Numbers) -> String {
    if n.max_budget > 0 && n.max_budget < n.budget {
        format!(
            "budget {} (the server's most; {} asked)",
            n.max_budget, n.budget
        )
    } else {
        format!("budget {}", n.budget)
    }
}

/// The compass bearing (clockwise from north) of a SPEC heading, and its point of the
/// compass.
pub fn bearing(heading_deg: f64) -> (f64, &'static str) {
    let b = (180.0 - heading_deg).rem_euclid(360.0);
    const POINTS: [&str; 8] = ["N", "NE", "E", "SE", "S", "SW", "W", "NW"];
    let i = ((b + 22.5) / 45.0) as usize % 8;
    (b, POINTS[i])
}

/// The HUD's lines: the connection, then (while the edge says so) the world gone, then
/// the numbers.
pub fn lines(n: &Numbers) -> Vec<String> {
    let on = |b: bool, name: &str, key: char| {
        if b {
            format!("[{key}] {name}")
        } else {
            format!("[{key}] ({name} off)")
        }
    };
    let t = n.toggles;
    let ms = |v: Option<f64>| v.map_or("–".to_string(), |v| format!("{v:.1} ms"));
    let (b, point) = bearing(n.heading_deg);
    let world = n
        .world_gone
        .as_ref()
        .map(|why| format!("the world does not answer ({why}): showing it as last seen"));
    [connection_line(n)]
        .into_iter()
        .chain(n.replay.clone())
        .chain(world)
        .chain([
            format!(
                "{:.0} fps  ({} a frame)  {}",
                n.fps,
                ms(n.frame_ms),
                n.adapter
            ),
            format!("{} triangles  ({}, [+]/[-])", n.triangles, budget_text(n)),
            format!(
                "server {:.0} frames/s  {:.1} KB/s in",
                n.server_fps, n.kb_per_s
            ),
            format!(
                "colour {:.1} KB/s in ({:.1} MB)  {}/{} tiles",
                n.color_kb_per_s, n.color_mb, n.color_tiles, n.color_capacity
            ),
            format!(
                "decode {}  upload {}  input→frame {}",
                ms(n.decode_ms),
                ms(n.upload_ms),
                ms(n.latency_ms)
            ),
            format!(
                "{:.0} km/h  heading {:.0}° ({point}, bearing {b:.0}°)",
                n.speed * 3.6,
                n.heading_deg
            ),
            [
                on(t.fog, "fog", 'f'),
                on(t.lighting, "lighting", 'l'),
                on(t.wireframe, "wireframe", 'w'),
                on(t.water, "water", 'r'),
                on(t.vehicles, "vehicles", 'v'),
                on(t.detail, "detail", 'd'),
            ]
            .join("  "),
            if n.replay.is_some() {
                "[Tab]/[1]–[9] follow · [h] hides this · [q]/Esc quits".to_string()
            } else {
                "arrows drive · [h] hides this · [q]/Esc quits".to_string()
            },
        ])
        .collect()
}

/// Lays the HUD out for this egui pass.
pub fn show(ctx: &egui::Context, n: &Numbers) {
    egui::Area::new(egui::Id::unique("hud"))
        .fixed_pos(egui::pos2(8.0, 8.0))
        .show(ctx, |ui| {
            egui::Frame::new()
                .fill(egui::Color32::from_black_alpha(150))
                .corner_radius(4.0)
                .inner_margin(8.0)
                .show(ui, |ui| {
                    // One line each, however narrow the window.
                    ui.style_mut().wrap_mode = Some(egui::TextWrapMode::Extend);
                    for (i, line) in lines(n).into_iter().enumerate() {
                        let mut text = egui::RichText::new(line).monospace().size(13.0);
                        // The connection lost, or the world gone (its line is the second).
                        let alarm = (i == 0 && !n.connected) || (i == 1 && n.world_gone.is_some());
                        text = if alarm {
                            text.color(egui::Color32::from_rgb(255, 120, 100))
                        } else {
                            text.color(egui::Color32::from_gray(230))
                        };
                        ui.label(text);
                    }
                });
        });
}

/// egui's state and renderer for a window (native: its input comes through winit).
#[cfg(not(target_arch = "wasm32"))]
pub struct Overlay {
    pub ctx: egui::Context,
    pub state: egui_winit::State,
    renderer: egui_wgpu::Renderer,
}

#[cfg(not(target_arch = "wasm32"))]
impl Overlay {
    pub fn new(
        window: &winit::window::Window,
        device: &wgpu::Device,
        format: wgpu::TextureFormat,
    ) -> Overlay {
        let ctx = egui::Context::default();
        let state = egui_winit::State::new(
            ctx.clone(),
            egui::ViewportId::ROOT,
            window,
            Some(window.scale_factor() as f32),
            None,
            Some(device.limits().max_texture_dimension_2d as usize),
        );
        let renderer = egui_wgpu::Renderer::new(device, format, Default::default());
        Overlay {
            ctx,
            state,
            renderer,
        }
    }

    /// Draws the HUD over `target`, which already holds the frame.
    pub fn paint(
        &mut self,
        gpu: &crate::render::Gpu,
        window: &winit::window::Window,
        target: &wgpu::TextureView,
        size: (u32, u32),
        numbers: Option<&Numbers>,
    ) {
        let input = self.state.take_egui_input(window);
        let mut out = self.ctx.run_pass(input, |ctx| {
            if let Some(n) = numbers {
                show(ctx, n);
            }
        });
        self.state
            .handle_platform_output(window, out.platform_output);
        let jobs = self.ctx.tessellate(out.shapes, out.pixels_per_point);
        // Texture changes are applied every frame (egui's contract), the HUD shown or not.
        for (id, deltas) in out.textures_delta.set.drain() {
            for delta in deltas {
                self.renderer
                    .update_texture(&gpu.device, &gpu.queue, id, &delta);
            }
        }
        let screen = egui_wgpu::ScreenDescriptor {
            size_in_pixels: [size.0, size.1],
            pixels_per_point: out.pixels_per_point,
        };
        let mut encoder = gpu.device.create_command_encoder(&Default::default());
        let extra =
            self.renderer
                .update_buffers(&gpu.device, &gpu.queue, &mut encoder, &jobs, &screen);
        {
            let mut pass = encoder
                .begin_render_pass(&wgpu::RenderPassDescriptor {
                    label: Some("hud"),
                    color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                        view: target,
                        depth_slice: None,
                        resolve_target: None,
                        ops: wgpu::Operations {
                            load: wgpu::LoadOp::Load,
                            store: wgpu::StoreOp::Store,
                        },
                    })],
                    depth_stencil_attachment: None,
                    timestamp_writes: None,
                    occlusion_query_set: None,
                    multiview_mask: None,
                })
                .forget_lifetime();
            self.renderer.render(&mut pass, &jobs, &screen);
        }
        gpu.queue
            .submit(extra.into_iter().chain([encoder.finish()]));
        for id in out.textures_delta.free.drain() {
            self.renderer.free_texture(&id);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bearings_follow_the_spec_heading() {
        let check = |heading: f64, want: (f64, &str)| assert_eq!(bearing(heading), want);
        check(0.0, (180.0, "S"));
        check(90.0, (90.0, "E"));
        check(180.0, (0.0, "N"));
        check(270.0, (270.0, "W"));
        check(53.0, (127.0, "SE"));
    }

    #[test]
    fn rates_cover_the_last_second() {
        let mut r = Rate::default();
        for k in 0..120 {
            r.add(k as f64 / 60.0, 1000.0);
        }
        // At t = 119/60 the last second holds the events after t − 1.
        let now = 119.0 / 60.0;
        assert_eq!(r.per_second(now), 60.0);
        assert_eq!(r.amount_per_second(now), 60_000.0);
        assert_eq!(r.mean(now), Some(1000.0));
        assert_eq!(r.per_second(10.0), 0.0);
        assert_eq!(r.mean(10.0), None);
    }

    #[test]
    fn the_hud_names_every_number_and_toggle() {
        let n = Numbers {
            fps: 60.0,
            triangles: 65_536,
            budget: 65_536,
            speed: 10.0,
            toggles: Toggles {
                fog: false,
                ..Toggles::default()
            },
            connection: "connected".into(),
            color_kb_per_s: 250.0,
            color_mb: 3.25,
            color_tiles: 40,
            color_capacity: 449,
            ..Numbers::default()
        };
        let text = lines(&n).join("\n");
        for want in [
            "60 fps",
            "65536 triangles",
            "budget 65536",
            "frames/s",
            "KB/s",
            "input→frame",
            "36 km/h",
            "heading",
            "(fog off)",
            "[l] lighting",
            "connected",
            "colour 250.0 KB/s in (3.2 MB)  40/449 tiles",
        ] {
            assert!(text.contains(want), "{want:?} missing from\n{text}");
        }
    }

    #[test]
    fn the_hud_shows_a_reconnection_and_the_servers_cap() {
        let mut n = Numbers {
            budget: 65_536,
            max_budget: 16_384,
            connection: "connected to 10.0.0.1:4433".into(),
            reconnecting_s: Some(2.345),
            ..Numbers::default()
        };
        let first = |n: &Numbers| lines(n)[0].clone();
        assert!(
            first(&n).starts_with("reconnecting… 2.3 s"),
            "{}",
            first(&n)
        );
        n.reconnecting_s = None;
        n.reconnects = 2;
        n.resumed = 1;
        assert!(
            first(&n).ends_with("reconnected 2× (1 with the vehicle back)"),
            "{}",
            first(&n)
        );
        n.resumed = 2;
        assert!(first(&n).ends_with("reconnected 2×"), "{}", first(&n));
        // The world gone is a line of its own, under the connection, while it lasts.
        let count = lines(&n).len();
        n.world_gone = Some("no answer for 1.5 s".into());
        let shown = lines(&n);
        assert_eq!(shown.len(), count + 1);
        assert_eq!(
            shown[1],
            "the world does not answer (no answer for 1.5 s): showing it as last seen"
        );
        let text = lines(&n).join("\n");
        assert!(
            text.contains("budget 16384 (the server's most; 65536 asked)"),
            "{text}"
        );
    }
}
