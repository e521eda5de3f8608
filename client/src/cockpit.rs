//! What a viewer does each display frame, minus the window: the keys by name (the window's
//! and the browser page's keys are spelled alike: `ArrowUp`, `Escape`, `f`, `+`), the
//! toggles and the budget, every vehicle replayed smoothly ([`Interpolator`]), the damped
//! camera ([`Rig`]) on the drawn ground, when to tell the server the camera moved or the
//! fog was toggled (it weighs errors by the fog only while it is drawn), and the HUD's
//! rates. The native window (`window.rs`) and the page (`roam-web`) differ only in
//! where the keys come from and what is drawn into; both keep one [`Cockpit`].
//! Time is a parameter (local seconds), never read here.

use std::collections::{HashMap, HashSet};

use roam_protocol::keys::Keys;
use roam_protocol::messages::{MAX_BUDGET, MIN_BUDGET, VehicleView, ViewChange};

use crate::camera::{Interpolator, LocalGround, Rig};
use crate::hud::{Numbers, Rate};
use crate::render::{Marker, Toggles, View};

/// What a key pressed asks of the viewer beyond its own state.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Action {
    /// Nothing more (a toggle, the HUD, an unknown key).
    None,
    /// Say goodbye and stop (`q`, Escape).
    Quit,
    /// Ask the server for this triangle budget (`+`, `-`).
    Budget(u32),
}

/// The arrows drive: the keys an arrow key holds, by its name.
pub fn drive_keys(name: &str) -> Option<Keys> {
    match name {
        "ArrowUp" => Some(Keys::UP),
        "ArrowDown" => Some(Keys::DOWN),
        "ArrowLeft" => Some(Keys::LEFT),
        "ArrowRight" => Some(Keys::RIGHT),
        _ => None,
    }
}

/// What one display frame draws.
#[derive(Clone, Debug)]
pub struct Framed {
    pub view: View,
    /// Every other vehicle in view.
    pub markers: Vec<Marker>,
    /// The followed vehicle, where it is drawn now (none before its first frame).
    pub followed: Option<VehicleView>,
    /// The camera to tell the server, when it has moved enough since last told.
    pub tell: Option<ViewChange>,
}

/// The viewer's state between display frames.
#[derive(Debug)]
pub struct Cockpit {
    pub toggles: Toggles,
    pub hud_shown: bool,
    pub fov_y_deg: f32,
    /// Kept unrounded so ×√2 then ÷√2 comes back exactly.
    budget: f64,
    interpolators: HashMap<u16, Interpolator>,
    rig: Rig,
    ground: LocalGround,
    /// The camera last told to the server, and when.
    told: Option<(f64, ViewChange)>,
    frames: Rate,
    frame_ms: Rate,
    server_frames: Rate,
    bytes: Rate,
    color_bytes: Rate,
    decode_ms: Rate,
    upload_ms: Rate,
    last_bytes: u64,
    last_color_bytes: u64,
}

impl Cockpit {
    pub fn new(budget: u32, toggles: Toggles, fov_y_deg: f32) -> Cockpit {
        Cockpit {
            toggles,
            hud_shown: true,
            fov_y_deg,
            budget: f64::from(budget),
            interpolators: HashMap::new(),
            rig: Rig::default(),
            ground: LocalGround::default(),
            told: None,
            frames: Rate::default(),
            frame_ms: Rate::default(),
            server_frames: Rate::default(),
            bytes: Rate::default(),
            color_bytes: Rate::default(),
            decode_ms: Rate::default(),
            upload_ms: Rate::default(),
            last_bytes: 0,
            last_color_bytes: 0,
        }
    }

    /// The budget asked for, rounded.
    pub fn budget(&self) -> u32 {
        self.budget.round() as u32
    }

    /// A key other than an arrow pressed (not a repeat), by its name: toggles flip here;
    /// what else it asks comes back.
    pub fn press(&mut self, name: &str) -> Action {
        let t = &mut self.toggles;
        match name {
            "Escape" | "q" | "Q" => return Action::Quit,
            "f" | "F" => t.fog = !t.fog,
            "l" | "L" => t.lighting = !t.lighting,
            "w" | "W" => t.wireframe = !t.wireframe,
            "r" | "R" => t.water = !t.water,
            "v" | "V" => t.vehicles = !t.vehicles,
            "d" | "D" => t.detail = !t.detail,
            "h" | "H" => self.hud_shown = !self.hud_shown,
            "+" | "=" => return self.set_budget(self.budget * std::f64::consts::SQRT_2),
            "-" | "_" => return self.set_budget(self.budget / std::f64::consts::SQRT_2),
            _ => {}
        }
        Action::None
    }

    /// The budget is kept unrounded here (so `+` then `-` returns to where it was) and
    /// sent rounded; the session clamps it with the protocol's limit and owns it.
    fn set_budget(&mut self, b: f64) -> Action {
        self.budget = b.clamp(f64::from(MIN_BUDGET), f64::from(MAX_BUDGET));
        Action::Budget(self.budget())
    }

    /// A decoded frame reached the display at local time `now`; it arrived at `at`.
    /// Vehicles not in it are forgotten.
    pub fn arrived(
        &mut self,
        now: f64,
        at: f64,
        tick: u64,
        vehicles: &[VehicleView],
        ground: LocalGround,
    ) {
        self.server_frames.add(now, 1.0);
        for v in vehicles {
            self.interpolators
                .entry(v.id)
                .or_default()
                .push(at, tick, *v);
        }
        let present: HashSet<u16> = vehicles.iter().map(|v| v.id).collect();
        self.interpolators.retain(|id, _| present.contains(id));
        self.ground = ground;
    }

    /// The time a frame took to decode and to upload, milliseconds.
    pub fn costs(&mut self, now: f64, decode_ms: f64, upload_ms: f64) {
        self.decode_ms.add(now, decode_ms);
        self.upload_ms.add(now, upload_ms);
    }

    /// Frame and colour bytes received so far (a reconnection's counts never go back).
    pub fn received(&mut self, now: f64, bytes: u64, color_bytes: u64) {
        self.bytes
            .add(now, bytes.saturating_sub(self.last_bytes) as f64);
        self.last_bytes = bytes;
        self.color_bytes.add(
            now,
            color_bytes.saturating_sub(self.last_color_bytes) as f64,
        );
        self.last_color_bytes = color_bytes;
    }

    /// A display frame drawn, taking `ms` on the CPU.
    pub fn drawn(&mut self, now: f64, ms: f64) {
        self.frame_ms.add(now, ms);
        self.frames.add(now, 1.0);
    }

    /// What to draw at local time `now` riding vehicle `me`, in a target of `size` pixels
    /// over a map `world_size` wide.
    pub fn frame(&mut self, now: f64, me: u16, size: (u32, u32), world_size: f32) -> Framed {
        let followed = self.interpolators.get(&me).and_then(|i| i.sample(now));
        let markers = self
            .interpolators
            .iter()
            .filter(|(id, _)| **id != me)
            .filter_map(|(id, i)| {
                let v = i.sample(now)?;
                Some(Marker {
                    pos: [v.x as f32, v.y as f32, v.z as f32],
                    heading_deg: v.heading as f32,
                    color: Marker::color_of(*id),
                })
            })
            .collect();
        let mut tell = None;
        let view = match &followed {
            Some(v) => {
                let ground = &self.ground;
                let pose = self.rig.update(now, v, |x, z| ground.height(x, z));
                // The server tessellates for this camera, told when it has moved enough, and
                // at once when the fog is turned on or off (it weighs errors by the fog
                // only while it is drawn).
                let change = ViewChange {
                    pitch_deg: pose.pitch_deg as f32,
                    eye_above: (pose.eye[1] - v.y) as f32,
                    viewport: [size.0, size.1],
                    fog: self.toggles.fog,
                };
                let moved = self.told.is_none_or(|(at, t)| {
                    t.fog != change.fog
                        || (now - at >= 0.1
                            && ((t.pitch_deg - change.pitch_deg).abs() > 0.5
                                || (t.eye_above - change.eye_above).abs() > 0.5
                                || t.viewport != change.viewport))
                });
                if moved {
                    tell = Some(change);
                    self.told = Some((now, change));
                }
                View {
                    eye: pose.eye.map(|c| c as f32),
                    yaw_deg: pose.yaw_deg as f32,
                    pitch_deg: pose.pitch_deg as f32,
                    fov_y_deg: self.fov_y_deg,
                    time_s: now as f32,
                }
            }
            // Before the first frame: above the map's centre, looking across it.
            None => {
                let c = world_size / 2.0;
                View {
                    eye: [c, 500.0, c],
                    yaw_deg: 0.0,
                    pitch_deg: -10.0,
                    fov_y_deg: self.fov_y_deg,
                    time_s: now as f32,
                }
            }
        };
        Framed {
            view,
            markers,
            followed,
            tell,
        }
    }

    /// The HUD's numbers that the cockpit keeps (rates, the budget, the toggles, the
    /// followed vehicle's speed and heading); the caller fills in the connection's.
    pub fn numbers(&mut self, now: f64, followed: Option<&VehicleView>) -> Numbers {
        let (speed, heading_deg) = followed.map_or((0.0, 0.0), |v| (v.speed, v.heading));
        Numbers {
            fps: self.frames.per_second(now),
            frame_ms: self.frame_ms.mean(now),
            server_fps: self.server_frames.per_second(now),
            kb_per_s: self.bytes.amount_per_second(now) / 1000.0,
            color_kb_per_s: self.color_bytes.amount_per_second(now) / 1000.0,
            decode_ms: self.decode_ms.mean(now),
            upload_ms: self.upload_ms.mean(now),
            speed,
            heading_deg,
            budget: self.budget(),
            toggles: self.toggles,
            ..Numbers::default()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cockpit() -> Cockpit {
        Cockpit::new(20_000, Toggles::default(), 60.0)
    }

    #[test]
    fn keys_by_name_toggle_quit_and_change_the_budget() {
        let check = |name: &str, expected: Action| {
            let mut c = cockpit();
            assert_eq!(c.press(name), expected, "{name}");
            c
        };
        let c = check("f", Action::None);
        assert_ne!(c.toggles.fog, Toggles::default().fog);
        let c = check("W", Action::None);
        assert_ne!(c.toggles.wireframe, Toggles::default().wireframe);
        assert!(!check("h", Action::None).hud_shown);
        check("q", Action::Quit);
        check("Escape", Action::Quit);
        check("+", Action::Budget(28_284));
        check("-", Action::Budget(14_142));
        check("x", Action::None);
        assert_eq!(drive_keys("ArrowLeft"), Some(Keys::LEFT));
        assert_eq!(drive_keys("a"), None);
    }

    #[test]
    fn the_budget_comes_back_after_up_then_down_and_stays_in_the_protocols_range() {
        let mut c = cockpit();
        c.press("+");
        assert_eq!(c.press("-"), Action::Budget(20_000));
        for _ in 0..100 {
            c.press("+");
        }
        assert_eq!(c.budget(), MAX_BUDGET);
        for _ in 0..200 {
            c.press("-");
        }
        assert_eq!(c.budget(), MIN_BUDGET);
    }

    #[test]
    fn the_camera_rides_the_vehicle_and_is_told_to_the_server_when_it_moves() {
        let mut c = cockpit();
        let before = c.frame(0.0, 3, (800, 600), 1000.0);
        assert!(before.followed.is_none() && before.tell.is_none());
        assert_eq!(before.view.eye, [500.0, 500.0, 500.0]);
        let v = |id: u16, x: f64| VehicleView {
            id,
            x,
            y: 10.0,
            z: 40.0,
            heading: 90.0,
            speed: 5.0,
        };
        for tick in 0..4u64 {
            let t = tick as f64 * 0.01;
            c.arrived(
                t,
                t,
                tick,
                &[v(3, 100.0 + t), v(7, 300.0)],
                LocalGround::default(),
            );
        }
        let f = c.frame(1.0, 3, (800, 600), 1000.0);
        let me = f.followed.expect("the followed vehicle is drawn");
        assert_eq!(me.id, 3);
        assert_eq!(f.markers.len(), 1, "the other vehicle is a marker");
        assert!(f.tell.is_some_and(|t| t.viewport == [800, 600]));
        assert!(f.view.eye[1] > 10.0, "the eye rides above the vehicle");
        // Not told again until it moves (nor within 0.1 s).
        assert!(c.frame(1.05, 3, (800, 600), 1000.0).tell.is_none());
        assert!(c.frame(1.5, 3, (800, 600), 1000.0).tell.is_none());
        assert!(c.frame(1.6, 3, (1024, 600), 1000.0).tell.is_some());
        // The fog toggled is told at once (within the 0.1 s too), both ways.
        let fog = Toggles::default().fog;
        assert!(f.tell.is_some_and(|t| t.fog == fog));
        c.press("f");
        let told = c.frame(1.61, 3, (1024, 600), 1000.0).tell;
        assert!(told.is_some_and(|t| t.fog != fog), "{told:?}");
        assert!(c.frame(1.62, 3, (1024, 600), 1000.0).tell.is_none());
        c.press("F");
        let told = c.frame(1.63, 3, (1024, 600), 1000.0).tell;
        assert!(told.is_some_and(|t| t.fog == fog), "{told:?}");
        let n = c.numbers(1.6, f.followed.as_ref());
        assert_eq!((n.speed, n.budget), (5.0, 20_000));
        // A frame without vehicle 7 forgets it.
        c.arrived(1.7, 1.7, 5, &[v(3, 101.0)], LocalGround::default());
        assert!(c.frame(1.8, 3, (1024, 600), 1000.0).markers.is_empty());
    }
}
