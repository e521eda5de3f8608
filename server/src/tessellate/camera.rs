//! The viewer's camera and its view frustum.
//!
//! Angles are in degrees. Yaw follows the vehicle-heading convention (0 faces south/+Z, 90
//! east/+X); pitch is positive looking up; `fov_y_deg` is the vertical field of view.

/// A pinhole camera over the terrain, in world coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    pub eye: [f64; 3],
    pub yaw_deg: f64,
    pub pitch_deg: f64,
    pub fov_y_deg: f64,
    pub width: u32,
    pub height: u32,
}

/// A plane `n·p + d >= 0` on the inside, in world coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WorldPlane {
    pub n: [f64; 3],
    pub d: f64,
}

impl WorldPlane {
    pub fn distance(&self, p: [f64; 3]) -> f64 {
        self.n[0] * p[0] + self.n[1] * p[1] + self.n[2] * p[2] + self.d
    }
}

/// Distance of the near plane in front of the eye, world units.
pub const NEAR: f64 = 0.5;

/// The widest guard band, degrees ([`Camera::frustum_widened`]).
pub const MAX_GUARD_DEG: u8 = 30;

impl Camera {
    /// Unit view direction.
    pub fn forward(&self) -> [f64; 3] {
        let (yaw, pitch) = (self.yaw_deg.to_radians(), self.pitch_deg.to_radians());
        [
            yaw.sin() * pitch.cos(),
            pitch.sin(),
            yaw.cos() * pitch.cos(),
        ]
    }

    /// Pixels per unit of `size / distance` at the centre of the view:
    /// `height / (2 tan(fov_y / 2))`.
    pub fn pixels_per_radian(&self) -> f64 {
        f64::from(self.height) / (2.0 * (self.fov_y_deg.to_radians() / 2.0).tan())
    }

    /// The near, left, right, bottom and top planes (no far plane), normals pointing in.
    pub fn frustum(&self) -> [WorldPlane; 5] {
        self.frustum_widened(0.0)
    }

    /// [`Camera::frustum`] with its left and right planes turned out by `guard_deg` degrees
    /// each: a guard band, what a viewer turning is about to see (a camera turns only about
    /// the vertical: its pitch is the driver's fixed one). 0, or anything not a finite
    /// positive number, for none; at most [`MAX_GUARD_DEG`].
    pub fn frustum_widened(&self, guard_deg: f64) -> [WorldPlane; 5] {
        let guard = if guard_deg.is_finite() && guard_deg > 0.0 {
            guard_deg.min(f64::from(MAX_GUARD_DEG)).to_radians()
        } else {
            0.0
        };
        let f = self.forward();
        // Right = forward × up, normalised; up' = right × forward.
        let r = normalize([-f[2], 0.0, f[0]]);
        let r = if r[0].is_finite() {
            r
        } else {
            [-1.0, 0.0, 0.0]
        };
        let u = cross(r, f);
        let half_v = (self.fov_y_deg.to_radians() / 2.0).clamp(1e-6, 1.5);
        let aspect = f64::from(self.width.max(1)) / f64::from(self.height.max(1));
        // Under a right angle: the side planes stay apart.
        let half_h = ((half_v.tan() * aspect).atan() + guard).min(1.55);
        let through_eye = |n: [f64; 3]| WorldPlane {
            n,
            d: -dot(n, self.eye),
        };
        let side = |axis: [f64; 3], half: f64, sign: f64| {
            let (s, c) = half.sin_cos();
            through_eye(normalize([
                sign * axis[0] * c + f[0] * s,
                sign * axis[1] * c + f[1] * s,
                sign * axis[2] * c + f[2] * s,
            ]))
        };
        [
            WorldPlane {
                n: f,
                d: -dot(f, self.eye) - NEAR,
            },
            side(r, half_h, 1.0),
            side(r, half_h, -1.0),
            side(u, half_v, 1.0),
            side(u, half_v, -1.0),
        ]
    }
}

pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn normalize(a: [f64; 3]) -> [f64; 3] {
    let l = dot(a, a).sqrt();
    [a[0] / l, a[1] / l, a[2] / l]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam(yaw: f64, pitch: f64) -> Camera {
        Camera {
            eye: [10.0, 5.0, 20.0],
            yaw_deg: yaw,
            pitch_deg: pitch,
            fov_y_deg: 60.0,
            width: 1920,
            height: 1080,
        }
    }

    #[test]
    fn heading_convention() {
        let close = |a: [f64; 3], b: [f64; 3]| (0..3).all(|i| (a[i] - b[i]).abs() < 1e-12);
        assert!(close(cam(0.0, 0.0).forward(), [0.0, 0.0, 1.0]));
        assert!(close(cam(90.0, 0.0).forward(), [1.0, 0.0, 0.0]));
        assert!(close(cam(180.0, 0.0).forward(), [0.0, 0.0, -1.0]));
        assert!(close(cam(0.0, 90.0).forward(), [0.0, 1.0, 0.0]));
    }

    #[test]
    fn frustum_contains_what_is_seen() {
        let c = cam(90.0, -10.0);
        let planes = c.frustum();
        let f = c.forward();
        let ahead = [
            c.eye[0] + 100.0 * f[0],
            c.eye[1] + 100.0 * f[1],
            c.eye[2] + 100.0 * f[2],
        ];
        assert!(planes.iter().all(|p| p.distance(ahead) > 0.0));
        // Behind, far left (north when facing east), far right, above and below are out.
        for p in [
            [c.eye[0] - 50.0, c.eye[1], c.eye[2]],
            [c.eye[0] + 10.0, c.eye[1], c.eye[2] - 100.0],
            [c.eye[0] + 10.0, c.eye[1], c.eye[2] + 100.0],
            [c.eye[0] + 10.0, c.eye[1] + 100.0, c.eye[2]],
            [c.eye[0] + 10.0, c.eye[1] - 100.0, c.eye[2]],
        ] {
            assert!(planes.iter().any(|pl| pl.distance(p) < 0.0), "{p:?}");
        }
        // Horizontal half-angle: a point at 59° off-axis (inside 16:9 at 60° vertical: the
        // horizontal half-angle is ~45.7°) is out, one at 40° is in.
        let at = |deg: f64| {
            let a = (90.0 - deg).to_radians();
            [
                c.eye[0] + 100.0 * a.sin(),
                c.eye[1] - 100.0 * 0.17,
                c.eye[2] + 100.0 * a.cos(),
            ]
        };
        assert!(planes.iter().all(|p| p.distance(at(40.0)) > 0.0));
        assert!(planes.iter().any(|p| p.distance(at(59.0)) < 0.0));
    }

    /// A guard band turns the side planes out by its angle, and only them: at 10°, a
    /// point 50° off-axis (out of the view's ~45.7°) is in and one at 60° still out; the
    /// near, top and bottom planes are the view's; nothing, a bad angle, is no guard.
    #[test]
    fn a_guard_band_widens_the_sides_only() {
        let c = cam(90.0, -10.0);
        let at = |deg: f64, up: f64| {
            let a = (90.0 - deg).to_radians();
            [
                c.eye[0] + 100.0 * a.sin(),
                c.eye[1] + 100.0 * up,
                c.eye[2] + 100.0 * a.cos(),
            ]
        };
        let inside = |planes: &[WorldPlane; 5], p| planes.iter().all(|pl| pl.distance(p) > 0.0);
        let (view, guarded) = (c.frustum(), c.frustum_widened(10.0));
        for deg in [50.0, -50.0] {
            assert!(!inside(&view, at(deg, -0.17)), "{deg}° is out of the view");
            assert!(
                inside(&guarded, at(deg, -0.17)),
                "{deg}° is in the guard band"
            );
        }
        assert!(!inside(&guarded, at(60.0, -0.17)));
        assert_eq!(view[0], guarded[0]);
        assert_eq!(view[3..], guarded[3..]);
        for bad in [0.0, -5.0, f64::NAN, f64::INFINITY] {
            assert_eq!(c.frustum_widened(bad), view, "{bad}");
        }
    }

    /// Whatever the guard, the widened pyramid (the side planes, which the tessellator
    /// culls with) holds the view's (what the error measures rely on to cull with both:
    /// `coherent/audit.rs`), though a side plane turned out
    /// drops points behind the eye that the view's kept: every point of a lattice around
    /// the eye in the view is in every guarded frustum, and some point the view's left or
    /// right plane keeps is dropped by the guarded one.
    #[test]
    fn a_guarded_frustum_holds_the_view() {
        // Offsets from the eye: a lattice 12 units either way, half as tall.
        let lattice: Vec<[f64; 3]> = (-12..=12)
            .flat_map(|i| (-12..=12).flat_map(move |j| (-12..=12).map(move |k| (i, j, k))))
            .map(|(i, j, k)| [f64::from(i), f64::from(j) * 0.5, f64::from(k)])
            .collect();
        for (yaw, pitch, fov) in [(90.0, -10.0, 60.0), (200.0, -35.0, 40.0), (10.0, 5.0, 90.0)] {
            let c = Camera {
                fov_y_deg: fov,
                ..cam(yaw, pitch)
            };
            // The pyramid the tessellator culls with: the side planes.
            let view = c.frustum();
            let seen = |p| view[1..].iter().all(|pl| pl.distance(p) >= 0.0);
            let mut dropped = 0;
            for guard in [1.0, 10.0, 30.0] {
                let wide = c.frustum_widened(guard);
                for v in &lattice {
                    let p = [c.eye[0] + v[0], c.eye[1] + v[1], c.eye[2] + v[2]];
                    assert!(
                        !seen(p) || wide[1..].iter().all(|pl| pl.distance(p) >= -1e-9),
                        "{p:?} at {yaw}°, {pitch}°, guard {guard}°"
                    );
                    dropped += (1..3)
                        .any(|s| view[s].distance(p) >= 0.0 && wide[s].distance(p) < 0.0)
                        as u32;
                }
            }
            assert!(dropped > 0, "{yaw}°: a side plane turned out drops nothing");
        }
    }
}
