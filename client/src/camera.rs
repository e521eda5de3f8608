//! The camera that rides the vehicle: the vehicle's state interpolated between the
//! server's frames to the display's rate, and a vertically damped look-ahead so rough
//! ground does not jerk the view and slopes ahead are not stared into.
//!
//! Pure: time is a parameter (seconds on any monotonic clock), so the tests drive it.

use std::collections::VecDeque;

use roam_protocol::messages::VehicleView;

/// The world's steps per second (SPEC).
pub const TICKS_PER_S: f64 = 100.0;
/// How far behind the newest estimate of the server's tick the camera is drawn, at least,
/// in ticks: a frame interval at 60 frames/s plus jitter, so there is almost always a frame
/// after. Frames further apart (a big budget, a slow viewer) draw it further behind.
pub const DELAY_TICKS: f64 = 3.0;
/// How far past the newest frame the vehicle is dead-reckoned before it is held.
pub const MAX_EXTRAPOLATION_TICKS: f64 = 5.0;

/// Vehicle states at server ticks, replayed smoothly on the local clock.
#[derive(Clone, Debug, Default)]
pub struct Interpolator {
    samples: VecDeque<(u64, VehicleView)>,
    /// The server's tick at local time `t` is estimated as `t · 100 + offset`.
    offset: Option<f64>,
    last_push: f64,
    /// The mean gap between frames, ticks (a moving average).
    gap: Option<f64>,
}

impl Interpolator {
    /// The state of the vehicle at server `tick` arrived at local time `now_s`.
    pub fn push(&mut self, now_s: f64, tick: u64, v: VehicleView) {
        if self.samples.back().is_some_and(|&(t, _)| tick <= t) {
            return; // late or repeated: what is newer is already here
        }
        // A frame can only arrive late, never early: the least delayed arrival tells the
        // offset. Follow it up at once and down slowly (the clocks drift, a path changes).
        let seen = tick as f64 - now_s * TICKS_PER_S;
        self.offset = Some(match self.offset {
            None => seen,
            Some(o) if seen > o => seen,
            Some(o) => {
                let dt = (now_s - self.last_push).clamp(0.0, 1.0);
                o + (seen - o) * (1.0 - (-dt / 2.0).exp())
            }
        });
        self.last_push = now_s;
        if let Some(&(last, _)) = self.samples.back() {
            let g = (tick - last) as f64;
            self.gap = Some(self.gap.map_or(g, |m| m + (g - m) * 0.1));
        }
        self.samples.push_back((tick, v));
        if self.samples.len() > 64 {
            self.samples.pop_front();
        }
    }

    /// The newest state received.
    pub fn newest(&self) -> Option<&VehicleView> {
        self.samples.back().map(|(_, v)| v)
    }

    /// How far behind the server's estimated tick the vehicle is shown: a gap and a half
    /// between frames and a tick, at least [`DELAY_TICKS`], at most 30.
    pub fn delay_ticks(&self) -> f64 {
        self.gap
            .map_or(DELAY_TICKS, |g| (1.0 + 1.5 * g).clamp(DELAY_TICKS, 30.0))
    }

    /// The vehicle as it should be shown at local time `now_s`.
    pub fn sample(&self, now_s: f64) -> Option<VehicleView> {
        let offset = self.offset?;
        let t = now_s * TICKS_PER_S + offset - self.delay_ticks();
        let &(first_tick, first) = self.samples.front()?;
        let &(last_tick, last) = self.samples.back()?;
        if t <= first_tick as f64 {
            return Some(first);
        }
        if t >= last_tick as f64 {
            // Dead-reckon along the heading for a little, then hold.
            let dt = (t - last_tick as f64).min(MAX_EXTRAPOLATION_TICKS) / TICKS_PER_S;
            let h = last.heading.to_radians();
            return Some(VehicleView {
                x: last.x + last.speed * dt * h.sin(),
                z: last.z + last.speed * dt * h.cos(),
                ..last
            });
        }
        let i = self.samples.partition_point(|&(k, _)| (k as f64) <= t);
        let (ta, a) = self.samples[i - 1];
        let (tb, b) = self.samples[i];
        let f = (t - ta as f64) / (tb - ta) as f64;
        let lerp = |a: f64, b: f64| a + (b - a) * f;
        let turn = (b.heading - a.heading + 540.0).rem_euclid(360.0) - 180.0;
        Some(VehicleView {
            id: b.id,
            x: lerp(a.x, b.x),
            z: lerp(a.z, b.z),
            y: lerp(a.y, b.y),
            speed: lerp(a.speed, b.speed),
            heading: (a.heading + turn * f).rem_euclid(360.0),
        })
    }
}

/// The terrain near a point, as drawn: triangles (world space) within a radius, to find
/// the ground height ahead without the heightfield.
#[derive(Clone, Debug, Default)]
pub struct LocalGround {
    triangles: Vec<[[f32; 3]; 3]>,
}

impl LocalGround {
    /// The triangles of `corners` (three per triangle) that reach within `radius` of
    /// `(x, z)`.
    pub fn near(corners: &[crate::render::vertices::Vertex], x: f32, z: f32, radius: f32) -> Self {
        let triangles = corners
            .chunks_exact(3)
            .filter_map(|t| {
                let p = [t[0].pos, t[1].pos, t[2].pos];
                let (lo_x, hi_x) = (
                    p[0][0].min(p[1][0]).min(p[2][0]),
                    p[0][0].max(p[1][0]).max(p[2][0]),
                );
                let (lo_z, hi_z) = (
                    p[0][2].min(p[1][2]).min(p[2][2]),
                    p[0][2].max(p[1][2]).max(p[2][2]),
                );
                let hit = lo_x <= x + radius
                    && hi_x >= x - radius
                    && lo_z <= z + radius
                    && hi_z >= z - radius;
                hit.then_some(p)
            })
            .collect();
        LocalGround { triangles }
    }

    /// The height of the drawn ground at `(x, z)`, if it is among these triangles.
    pub fn height(&self, x: f64, z: f64) -> Option<f64> {
        let (x, z) = (x as f32, z as f32);
        for [a, b, c] in &self.triangles {
            let d = (b[2] - c[2]) * (a[0] - c[0]) + (c[0] - b[0]) * (a[2] - c[2]);
            if d.abs() < f32::EPSILON {
                continue;
            }
            let wa = ((b[2] - c[2]) * (x - c[0]) + (c[0] - b[0]) * (z - c[2])) / d;
            let wb = ((c[2] - a[2]) * (x - c[0]) + (a[0] - c[0]) * (z - c[2])) / d;
            let wc = 1.0 - wa - wb;
            let eps = -1e-4;
            if wa >= eps && wb >= eps && wc >= eps {
                return Some(f64::from(wa * a[1] + wb * b[1] + wc * c[1]));
            }
        }
        None
    }
}

/// Eye above the vehicle's hover altitude, metres.
pub const EYE_ABOVE_VEHICLE: f64 = 1.5;
/// Pitch on level ground, degrees (the server tessellates for this pitch).
pub const BASE_PITCH_DEG: f64 = -5.0;
/// Distances ahead at which the ground's rise is looked at, metres.
pub const LOOK_AHEAD_M: [f64; 4] = [30.0, 60.0, 120.0, 240.0];
/// The eye's height follows a critically damped spring of this rate (1/s).
pub const EYE_SPRING: f64 = 5.0;
/// The pitch follows its target with this time constant, seconds.
pub const PITCH_TIME_S: f64 = 0.6;

/// Where the camera is and where it looks.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    pub eye: [f64; 3],
    pub yaw_deg: f64,
    pub pitch_deg: f64,
}

/// The damped camera: call [`Rig::update`] once per displayed frame.
#[derive(Clone, Debug, Default)]
pub struct Rig {
    state: Option<RigState>,
}

#[derive(Clone, Copy, Debug)]
struct RigState {
    at_s: f64,
    eye_y: f64,
    eye_vy: f64,
    pitch: f64,
}

impl Rig {
    /// The pose at local time `now_s` for vehicle `v`, with `ground` the drawn terrain's
    /// height where known.
    pub fn update(
        &mut self,
        now_s: f64,
        v: &VehicleView,
        ground: impl Fn(f64, f64) -> Option<f64>,
    ) -> Pose {
        let here = ground(v.x, v.z).unwrap_or(v.y - 2.0);
        let target_y = v.y + EYE_ABOVE_VEHICLE;
        // The rise of the ground ahead, as angles, averaged: uphill looks up, downhill down.
        let (sin_h, cos_h) = v.heading.to_radians().sin_cos();
        let mut sum = 0.0;
        for d in LOOK_AHEAD_M {
            let g = ground(v.x + d * sin_h, v.z + d * cos_h).unwrap_or(here);
            sum += (g - here).atan2(d).to_degrees();
        }
        let target_pitch =
            (BASE_PITCH_DEG + sum / LOOK_AHEAD_M.len() as f64 * 0.8).clamp(-25.0, 25.0);
        let s = match self.state {
            None => RigState {
                at_s: now_s,
                eye_y: target_y,
                eye_vy: 0.0,
                pitch: target_pitch,
            },
            Some(mut s) => {
                let dt = (now_s - s.at_s).clamp(0.0, 0.25);
                // Critically damped spring for the height, in substeps for stability.
                let steps = (dt / 0.004).ceil().max(1.0);
                let h = dt / steps;
                for _ in 0..steps as u32 {
                    let acc = EYE_SPRING * EYE_SPRING * (target_y - s.eye_y)
                        - 2.0 * EYE_SPRING * s.eye_vy;
                    s.eye_vy += acc * h;
                    s.eye_y += s.eye_vy * h;
                }
                s.pitch += (target_pitch - s.pitch) * (1.0 - (-dt / PITCH_TIME_S).exp());
                s.at_s = now_s;
                s
            }
        };
        self.state = Some(s);
        Pose {
            // Never below the ground, however the spring lags a climb.
            eye: [v.x, s.eye_y.max(here + 1.0), v.z],
            yaw_deg: v.heading,
            pitch_deg: s.pitch,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(x: f64, heading: f64) -> VehicleView {
        VehicleView {
            id: 1,
            x,
            z: 0.0,
            y: 2.0,
            speed: 10.0,
            heading,
        }
    }

    #[test]
    fn interpolates_between_frames_at_the_display_rate() {
        let mut i = Interpolator::default();
        // Frames every 20 ms, each 2 ticks on, arriving on time.
        for k in 0..10u64 {
            i.push(k as f64 * 0.02, 2 * k, at(k as f64 * 2.0, 90.0));
        }
        // Frames 2 ticks apart: drawn 1 + 1.5 · 2 = 4 ticks behind.
        assert_eq!(i.delay_ticks(), 4.0);
        // At 0.185 s the server is at tick 18.5; drawn at 14.5, x = 14.5.
        let v = i.sample(0.185).expect("samples");
        assert!((v.x - 14.5).abs() < 1e-9, "{}", v.x);
        // Successive display frames move evenly.
        let xs: Vec<f64> = (0..5)
            .map(|k| i.sample(0.15 + k as f64 / 240.0).expect("samples").x)
            .collect();
        for w in xs.windows(2) {
            assert!((w[1] - w[0] - 100.0 / 240.0).abs() < 1e-9, "{xs:?}");
        }
    }

    #[test]
    fn late_frames_do_not_move_the_clock_back_and_headings_wrap() {
        let mut i = Interpolator::default();
        i.push(0.0, 0, at(0.0, 350.0));
        i.push(0.05, 2, at(2.0, 10.0)); // 30 ms late
        i.push(0.04, 4, at(4.0, 10.0));
        // The offset is the least delayed arrival's.
        let delay = i.delay_ticks() / TICKS_PER_S;
        let v = i.sample(0.03 + delay).expect("samples");
        assert!((v.x - 3.0).abs() < 1e-9, "{}", v.x);
        let v = i.sample(0.01 + delay).expect("samples");
        assert!((v.heading - 0.0).abs() < 1e-9, "{}", v.heading);
        // Older than what is there: ignored.
        i.push(0.06, 3, at(100.0, 0.0));
        assert_eq!(i.newest().map(|v| v.x), Some(4.0));
    }

    #[test]
    fn frames_far_apart_are_drawn_further_behind() {
        let mut i = Interpolator::default();
        for k in 0..50u64 {
            i.push(k as f64 * 0.1, 10 * k, at(k as f64, 90.0));
        }
        assert!((i.delay_ticks() - 16.0).abs() < 0.01, "{}", i.delay_ticks());
        // Between frames, not held at the newest.
        let a = i.sample(4.9).expect("samples").x;
        let b = i.sample(4.95).expect("samples").x;
        assert!(b > a && b < 49.0, "{a} {b}");
    }

    #[test]
    fn extrapolates_a_little_then_holds() {
        let mut i = Interpolator::default();
        i.push(0.0, 0, at(0.0, 90.0));
        i.push(0.01, 1, at(0.1, 90.0));
        assert_eq!(i.delay_ticks(), DELAY_TICKS);
        let v = i
            .sample(0.01 + (DELAY_TICKS + 2.0) / TICKS_PER_S)
            .expect("samples");
        assert!((v.x - 0.3).abs() < 1e-9, "{}", v.x);
        let held = i.sample(10.0).expect("samples");
        assert!((held.x - (0.1 + MAX_EXTRAPOLATION_TICKS / 10.0)).abs() < 1e-9);
    }

    #[test]
    fn a_bump_is_damped_and_a_slope_ahead_raises_the_view() {
        let flat = |_: f64, _: f64| Some(0.0);
        let mut rig = Rig::default();
        let p0 = rig.update(0.0, &at(0.0, 90.0), flat);
        assert!((p0.pitch_deg - BASE_PITCH_DEG).abs() < 1e-9);
        // The vehicle jumps 3 m for one frame: the eye moves far less.
        let mut bumped = at(1.0, 90.0);
        bumped.y += 3.0;
        let p1 = rig.update(1.0 / 60.0, &bumped, flat);
        assert!(
            p1.eye[1] - p0.eye[1] < 0.2,
            "{} -> {}",
            p0.eye[1],
            p1.eye[1]
        );
        // A hill ahead (rising east): the view tilts up, gradually.
        let hill = |x: f64, _: f64| Some((x - 5.0).max(0.0) * 0.3);
        let mut rig = Rig::default();
        rig.update(0.0, &at(0.0, 0.0), hill); // facing south: flat
        let p = rig.update(1.0 / 60.0, &at(0.0, 90.0), hill);
        assert!(p.pitch_deg > BASE_PITCH_DEG && p.pitch_deg < BASE_PITCH_DEG + 3.0);
        let mut last = p.pitch_deg;
        for k in 2..240 {
            last = rig.update(k as f64 / 60.0, &at(0.0, 90.0), hill).pitch_deg;
        }
        assert!(last > 5.0, "{last}");
    }

    #[test]
    fn local_ground_interpolates_the_drawn_triangles() {
        use crate::render::vertices::Vertex;
        let v = |x: f32, y: f32, z: f32| Vertex {
            pos: [x, y, z],
            normal: [0; 4],
        };
        let corners = [
            v(0.0, 0.0, 0.0),
            v(0.0, 10.0, 10.0),
            v(10.0, 0.0, 0.0),
            v(1000.0, 0.0, 1000.0),
            v(1000.0, 0.0, 1010.0),
            v(1010.0, 0.0, 1000.0),
        ];
        let g = LocalGround::near(&corners, 0.0, 0.0, 100.0);
        assert_eq!(g.triangles.len(), 1);
        let h = g.height(2.0, 5.0).expect("inside");
        assert!((h - 5.0).abs() < 1e-5, "{h}");
        assert_eq!(g.height(9.0, 9.0), None);
    }
}
