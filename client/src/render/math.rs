//! Column-major 4×4 matrices for the camera: a right-handed view looking down −Z and a
//! reversed, infinite perspective (depth 1 at the near plane, 0 at infinity), which keeps
//! depth precise across a 100 km map: the water surface half a metre above the lake bed
//! does not fight with it 20 km away.

pub(crate) type Mat = [[f32; 4]; 4];

pub(crate) fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub(crate) fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub(crate) fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// `v` scaled to unit length; straight up for a zero vector.
pub(crate) fn normalize(v: [f32; 3]) -> [f32; 3] {
    let l = dot(v, v).sqrt();
    if l > 0.0 {
        [v[0] / l, v[1] / l, v[2] / l]
    } else {
        [0.0, 1.0, 0.0]
    }
}

/// The product `a · b`.
pub(crate) fn mul(a: Mat, b: Mat) -> Mat {
    let mut m = [[0.0; 4]; 4];
    for c in 0..4 {
        for r in 0..4 {
            m[c][r] = (0..4).map(|k| a[k][r] * b[c][k]).sum();
        }
    }
    m
}

/// Reversed infinite perspective: clip z is `near`, w is the distance in front, so depth is
/// `near / distance`.
pub(crate) fn perspective(fov_y: f32, aspect: f32, near: f32) -> Mat {
    let f = 1.0 / (fov_y / 2.0).tan();
    [
        [f / aspect, 0.0, 0.0, 0.0],
        [0.0, f, 0.0, 0.0],
        [0.0, 0.0, 0.0, -1.0],
        [0.0, 0.0, near, 0.0],
    ]
}

/// The inverse of [`perspective`].
pub(crate) fn perspective_inverse(fov_y: f32, aspect: f32, near: f32) -> Mat {
    let f = 1.0 / (fov_y / 2.0).tan();
    [
        [aspect / f, 0.0, 0.0, 0.0],
        [0.0, 1.0 / f, 0.0, 0.0],
        [0.0, 0.0, 0.0, 1.0 / near],
        [0.0, 0.0, -1.0, 0.0],
    ]
}

/// The view-projection matrix `view` has on a `size` target, as the renderer draws it
/// (the pop measure projects with the same).
pub(crate) fn view_proj(view: &super::View, size: (u32, u32)) -> Mat {
    let aspect = size.0 as f32 / size.1.max(1) as f32;
    let fov = view.fov_y_deg.clamp(1.0, 179.0).to_radians();
    mul(
        perspective(fov, aspect, super::NEAR),
        look(view.eye, view.yaw_deg, view.pitch_deg),
    )
}

/// The unit direction of a heading (0 faces south, +Z; 90 east, +X) and pitch (up positive).
pub(crate) fn forward(yaw_deg: f32, pitch_deg: f32) -> [f32; 3] {
    let (yaw, pitch) = (yaw_deg.to_radians(), pitch_deg.to_radians());
    [
        yaw.sin() * pitch.cos(),
        pitch.sin(),
        yaw.cos() * pitch.cos(),
    ]
}

/// The view matrix of a camera at `eye` looking along `yaw_deg` and `pitch_deg`.
pub(crate) fn look(eye: [f32; 3], yaw_deg: f32, pitch_deg: f32) -> Mat {
    let f = forward(yaw_deg, pitch_deg);
    let s = normalize(cross(f, [0.0, 1.0, 0.0]));
    let u = cross(s, f);
    [
        [s[0], u[0], -f[0], 0.0],
        [s[1], u[1], -f[1], 0.0],
        [s[2], u[2], -f[2], 0.0],
        [-dot(s, eye), -dot(u, eye), dot(f, eye), 1.0],
    ]
}

/// The inverse of [`look`]: a rotation R (rows s, u, −f) then a translation, undone by Rᵀ
/// and the eye.
pub(crate) fn look_inverse(eye: [f32; 3], yaw_deg: f32, pitch_deg: f32) -> Mat {
    let l = look(eye, yaw_deg, pitch_deg);
    [
        [l[0][0], l[1][0], l[2][0], 0.0],
        [l[0][1], l[1][1], l[2][1], 0.0],
        [l[0][2], l[1][2], l[2][2], 0.0],
        [eye[0], eye[1], eye[2], 1.0],
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn apply(m: Mat, v: [f32; 4]) -> [f32; 4] {
        let mut o = [0.0; 4];
        for (r, o) in o.iter_mut().enumerate() {
            *o = (0..4).map(|k| m[k][r] * v[k]).sum();
        }
        o
    }

    #[test]
    fn inverses_undo() {
        let (fov, aspect, near) = (1.0, 1.7, 0.5);
        let (eye, yaw, pitch) = ([10.0, 20.0, 30.0], 53.0, -7.0);
        let m = mul(perspective(fov, aspect, near), look(eye, yaw, pitch));
        let inv = mul(
            look_inverse(eye, yaw, pitch),
            perspective_inverse(fov, aspect, near),
        );
        let id = mul(inv, m);
        for (c, col) in id.iter().enumerate() {
            for (r, &v) in col.iter().enumerate() {
                let want = if c == r { 1.0 } else { 0.0 };
                assert!((v - want).abs() < 1e-4, "({c},{r}) = {v}");
            }
        }
    }

    #[test]
    fn depth_is_reversed() {
        let p = perspective(1.0, 1.0, 0.5);
        let depth = |d: f32| {
            let c = apply(p, [0.0, 0.0, -d, 1.0]);
            c[2] / c[3]
        };
        assert!((depth(0.5) - 1.0).abs() < 1e-6);
        assert!(depth(10.0) > depth(20_000.0) && depth(20_000.0) > 0.0);
        // A point ahead lands mid-screen: the camera looks where `forward` says.
        let eye = [5.0, 6.0, 7.0];
        let f = forward(90.0, 0.0);
        let at = [eye[0] + 100.0 * f[0], eye[1], eye[2] + 100.0 * f[2], 1.0];
        let c = apply(mul(p, look(eye, 90.0, 0.0)), at);
        assert!(
            c[0].abs() < 1e-3 && c[1].abs() < 1e-3 && c[3] > 0.0,
            "{c:?}"
        );
    }
}
