//! A viewer's camera: the default one a hello implies, and the viewer's changes to it,
//! clamped.

use roam_protocol::messages::ViewChange;

use crate::tessellate::camera::Camera;

/// The camera a viewer's hello asks for, before it is placed at a vehicle: its field of
/// view (a value that is not a number is taken as the usual 60°) and viewport, clamped,
/// looking slightly down.
pub(super) fn default_camera(fov_y_deg: f32, viewport: [u32; 2]) -> Camera {
    let fov = f64::from(fov_y_deg);
    Camera {
        eye: [0.0; 3],
        yaw_deg: 0.0,
        pitch_deg: roam_protocol::messages::DEFAULT_PITCH_DEG,
        fov_y_deg: if fov.is_finite() {
            fov.clamp(1.0, 179.0)
        } else {
            60.0
        },
        width: viewport[0].clamp(1, 16_384),
        height: viewport[1].clamp(1, 16_384),
    }
}

/// `camera` changed as the viewer asked; anything out of range is clamped, anything not a
/// number ignored.
pub fn apply_view(camera: &mut Camera, v: &ViewChange) {
    if v.pitch_deg.is_finite() {
        camera.pitch_deg = f64::from(v.pitch_deg).clamp(-89.0, 89.0);
    }
    // Slightly below the hover altitude too: the viewer's damped eye lags a climb.
    if v.eye_above.is_finite() {
        camera.eye[1] += f64::from(v.eye_above).clamp(-10.0, 1000.0);
    }
    camera.width = v.viewport[0].clamp(1, 16_384);
    camera.height = v.viewport[1].clamp(1, 16_384);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_view_change_is_clamped_and_nan_ignored() {
        let base = Camera {
            eye: [10.0, 20.0, 30.0],
            ..default_camera(60.0, [1280, 720])
        };
        let check = |v: ViewChange, pitch: f64, eye_y: f64, size: (u32, u32)| {
            let mut c = base;
            apply_view(&mut c, &v);
            assert_eq!(
                (c.pitch_deg, c.eye[1], (c.width, c.height)),
                (pitch, eye_y, size)
            );
        };
        let v = |pitch_deg, eye_above, viewport| ViewChange {
            pitch_deg,
            eye_above,
            viewport,
            fog: true,
        };
        check(v(12.0, 1.5, [800, 600]), 12.0, 21.5, (800, 600));
        check(
            v(f32::NAN, f32::INFINITY, [0, 99_999]),
            base.pitch_deg,
            20.0,
            (1, 16_384),
        );
        check(v(-500.0, -30.0, [640, 480]), -89.0, 10.0, (640, 480));
    }

    #[test]
    fn a_hello_camera_is_clamped() {
        let c = default_camera(f32::NAN, [0, 1 << 20]);
        assert_eq!((c.fov_y_deg, c.width, c.height), (60.0, 1, 16_384));
        assert_eq!(default_camera(500.0, [640, 480]).fov_y_deg, 179.0);
    }
}
