//! Helpers shared by the tessellator's tests (`tessellate.rs`, `fog.rs`, `guard.rs`):
//! random terrain, cameras over it, the frustum check of a cut, and its error measured
//! both ways.
#![allow(dead_code)] // each test file uses its own subset

use roam_protocol::bintree::{Diamond, Shape};
use roam_server::Heightfield;
use roam_server::terrain::variance::VarianceTree;
use roam_server::tessellate::camera::Camera;
use roam_server::tessellate::{Limits, Mesh, Scales, Tessellator, fogged_error_px, measured_error};

/// A rough random heightfield: smoothed noise plus a few bumps and an optional flat floor.
pub fn terrain(levels: u32, seed: u64, roughness: f64) -> Heightfield {
    let side = (1u32 << levels) + 1;
    let mut state = seed;
    let mut rnd = || {
        state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    };
    let bumps: Vec<[f64; 4]> = (0..4)
        .map(|_| {
            [
                rnd() * side as f64,
                rnd() * side as f64,
                2.0 + rnd() * side as f64 / 3.0,
                rnd() * 20000.0,
            ]
        })
        .collect();
    let floor = rnd() * 8000.0;
    let mut samples = Vec::with_capacity((side * side) as usize);
    for z in 0..side {
        for x in 0..side {
            let mut h = 10000.0 + roughness * rnd() * 3000.0;
            for [bx, bz, r, a] in &bumps {
                let d2 = ((x as f64 - bx).powi(2) + (z as f64 - bz).powi(2)) / (r * r);
                h += a * (-d2).exp();
            }
            samples.push(h.max(10000.0 + floor).min(65535.0) as u16);
        }
    }
    Heightfield::new(side, samples).expect("side is 2^N + 1")
}

pub fn scales() -> Scales {
    Scales { h: 10.0, v: 0.02 }
}

/// Camera at grid position (gx, gz), `above` world units over the ground.
pub fn camera(
    hf: &Heightfield,
    gx: f64,
    gz: f64,
    above: f64,
    yaw: f64,
    pitch: f64,
    fov: f64,
) -> Camera {
    let s = scales();
    let (cx, cz) = (
        gx.clamp(0.0, hf.size() as f64) as u32,
        gz.clamp(0.0, hf.size() as f64) as u32,
    );
    let ground = f64::from(hf.get(cx, cz)) * s.v;
    Camera {
        eye: [gx * s.h, ground + above, gz * s.h],
        yaw_deg: yaw,
        pitch_deg: pitch,
        fov_y_deg: fov,
        width: 640,
        height: 480,
    }
}

pub fn run(
    hf: &Heightfield,
    vt: &VarianceTree,
    cam: &Camera,
    limits: Limits,
) -> (Mesh, Tessellator) {
    let mut t = Tessellator::new(hf.side());
    let mut mesh = Mesh::default();
    t.tessellate(hf, vt, scales(), cam, limits, &mut mesh);
    (mesh, t)
}

/// Every diamond split without being forced (no split child needs it) must not lie wholly
/// outside the frustum, unless it holds the eye's ground position.
pub fn check_frustum(
    hf: &Heightfield,
    vt: &VarianceTree,
    cam: &Camera,
    split: impl Iterator<Item = (u32, u32)>,
) -> Result<(), String> {
    check_frustum_guarded(hf, vt, cam, 0.0, split)
}

/// [`check_frustum`] with the frustum's sides turned out by a guard band of `guard_deg`.
pub fn check_frustum_guarded(
    hf: &Heightfield,
    vt: &VarianceTree,
    cam: &Camera,
    guard_deg: f64,
    split: impl Iterator<Item = (u32, u32)>,
) -> Result<(), String> {
    let size = hf.size();
    let s = scales();
    let split: std::collections::HashSet<(u32, u32)> = split.collect();
    let forced: std::collections::HashSet<(u32, u32)> = split
        .iter()
        .flat_map(|&(x, z)| {
            Diamond::at(x, z, size)
                .expect("split diamonds exist")
                .parents(size)
        })
        .flatten()
        .collect();
    // The view pyramid: the near plane adds nothing to culling (the apex is the eye).
    let planes = &cam.frustum_widened(guard_deg)[1..];
    for &(x, z) in &split {
        if forced.contains(&(x, z)) {
            continue;
        }
        let d = Diamond::at(x, z, size).expect("split diamonds exist");
        let tris: Vec<_> = d.triangles(size).into_iter().flatten().collect();
        let e = f64::from(vt.error(hf, x, z));
        let hts: Vec<f64> = tris
            .iter()
            .flat_map(|t| t.vertices())
            .map(|(vx, vz)| f64::from(hf.get(vx, vz)))
            .collect();
        let lo = (hts.iter().copied().fold(f64::INFINITY, f64::min) - e) * s.v;
        let hi = (hts.iter().copied().fold(f64::NEG_INFINITY, f64::max) + e) * s.v;
        let h = f64::from(d.h());
        let foot: Vec<(f64, f64)> = match d.shape {
            Shape::Square => {
                vec![(-h, -h), (h, -h), (-h, h), (h, h)]
            }
            _ => vec![(-h, 0.0), (h, 0.0), (0.0, -h), (0.0, h)],
        };
        let (ex, ez) = (
            cam.eye[0] / s.h - f64::from(x),
            cam.eye[2] / s.h - f64::from(z),
        );
        let under = match d.shape {
            Shape::Square => ex.abs() <= h && ez.abs() <= h,
            _ => ex.abs() + ez.abs() <= h,
        };
        if under {
            continue;
        }
        for p in planes {
            let outside = foot.iter().all(|&(dx, dz)| {
                [lo, hi].iter().all(|&y| {
                    p.distance([(f64::from(x) + dx) * s.h, y, (f64::from(z) + dz) * s.h]) < -1e-3
                })
            });
            if outside {
                return Err(format!(
                    "diamond ({x}, {z}) h {h} is outside the frustum but split"
                ));
            }
        }
    }
    Ok(())
}

/// `is_split` over row-major grid indices, for a list of split diamonds.
pub fn is_split(hf: &Heightfield, split: &[(u32, u32)]) -> impl Fn(u32) -> bool + use<> {
    let side = hf.side();
    let set: std::collections::HashSet<u32> = split.iter().map(|&(x, z)| z * side + x).collect();
    move |i| set.contains(&i)
}

/// The error `split` leaves at `cam` under `limits`, measured both ways (`measured_error`
/// over the list, `fogged_error_px` over grid indices), which must agree bit for bit.
pub fn measured_both(
    hf: &Heightfield,
    vt: &VarianceTree,
    cam: &Camera,
    limits: Limits,
    split: &[(u32, u32)],
    what: &str,
) -> f32 {
    let measured = measured_error(hf, vt, scales(), cam, limits, split.iter().copied());
    let fogged = fogged_error_px(
        hf,
        vt,
        scales(),
        cam,
        limits.fog_density,
        limits.guard_deg,
        is_split(hf, split),
    );
    assert_eq!(measured.to_bits(), fogged.to_bits(), "{what}");
    measured
}
