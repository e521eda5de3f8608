//! What a change of the level of detail shows between two consecutive frames, with the
//! camera's motion cancelled (both drawn meshes seen from the later frame's camera):
//!
//! - [`pop_px`]: the largest screen-space displacement of the drawn surface. Both drawn
//!   meshes are meshes of cuts of one hierarchy, so the mesh of their union refines both,
//!   and the surface's displacement is linear on each of its triangles: it is largest at a
//!   vertex of the union. A vertex's height on a mesh that does not hold it is the mean of
//!   its hypotenuse ends' on that mesh (exact: the surface is linear along the edge it
//!   splits). Only vertices that can differ are visited: those drawn in one cut and not
//!   the other, and those morphing in either. Occlusion is not considered (a hidden pop
//!   counts), so this is an upper bound of what can be seen.
//! - [`luma_diff`]: the mean absolute difference of the luminance (Rec. 709, of the
//!   encoded 0–255 values) over the terrain's pixels of the two images (a pixel is the
//!   terrain's where either image differs from the sky alone).

use std::collections::HashMap;

use roam_protocol::Grid;

use crate::render::math::Mat;
pub(super) use crate::render::math::view_proj;
use crate::render::{Morph, NEAR, Scene};

/// A drawn cut's surface height at grid vertex `i`, samples: its drawn height if it is a
/// vertex of the cut (a map corner's from `corner`, which may know more vertices), else the mean of its hypotenuse
/// ends' (memoised in `memo`).
fn surface(
    m: &Morph,
    corner: &impl Fn(u32) -> Option<u16>,
    i: u32,
    memo: &mut HashMap<u32, f32>,
) -> f32 {
    if let Some(h) = m.height(i) {
        return f32::from(h) + m.lift(i);
    }
    let grid: &Grid = m.grid();
    let (x, z) = grid.coords(i);
    if x.is_multiple_of(grid.size()) && z.is_multiple_of(grid.size()) {
        return f32::from(corner(i).unwrap_or(0));
    }
    if let Some(&y) = memo.get(&i) {
        return y;
    }
    let [a, b] = grid.hypotenuse(x, z);
    let y = 0.5
        * (surface(m, corner, grid.index(a.0, a.1), memo)
            + surface(m, corner, grid.index(b.0, b.1), memo));
    memo.insert(i, y);
    y
}

/// Pixel position of world point `p` under `vp` on a `size` target; `None` behind the
/// near plane.
fn project(vp: &Mat, p: [f32; 3], size: (u32, u32)) -> Option<(f32, f32)> {
    let c = |r: usize| vp[0][r] * p[0] + vp[1][r] * p[1] + vp[2][r] * p[2] + vp[3][r];
    let w = c(3);
    if w < NEAR {
        return None;
    }
    let (x, y) = (c(0) / w, c(1) / w);
    Some((
        (x + 1.0) * 0.5 * size.0 as f32,
        (1.0 - y) * 0.5 * size.1 as f32,
    ))
}

/// The largest screen-space displacement (pixels) of the drawn surface from cut `before`
/// to cut `after`, both seen with `vp` on a `size` target; a map corner's height from
/// `corner`. Vertices projecting outside the target in both are not counted.
pub(super) fn pop_px(
    scene: &Scene,
    before: &Morph,
    after: &Morph,
    corner: impl Fn(u32) -> Option<u16>,
    vp: &Mat,
    size: (u32, u32),
) -> f32 {
    let grid = *after.grid();
    let mut visit: Vec<u32> = before
        .diamonds()
        .filter(|&d| !after.contains(d))
        .chain(after.diamonds().filter(|&d| !before.contains(d)))
        .chain(before.moving().iter().copied())
        .chain(after.moving().iter().copied())
        .collect();
    visit.sort_unstable();
    visit.dedup();
    let (hs, vs) = (scene.h_scale as f32, scene.v_scale as f32);
    let inside =
        |(x, y): (f32, f32)| x >= 0.0 && y >= 0.0 && x < size.0 as f32 && y < size.1 as f32;
    let (mut memo_a, mut memo_b) = (HashMap::new(), HashMap::new());
    let mut worst = 0.0f32;
    for i in visit {
        let ya = surface(before, &corner, i, &mut memo_a);
        let yb = surface(after, &corner, i, &mut memo_b);
        if ya == yb {
            continue;
        }
        let (x, z) = grid.coords(i);
        let at = |y: f32| project(vp, [x as f32 * hs, y * vs, z as f32 * hs], size);
        if let (Some(a), Some(b)) = (at(ya), at(yb))
            && (inside(a) || inside(b))
        {
            let px = ((a.0 - b.0).powi(2) + (a.1 - b.1).powi(2)).sqrt();
            worst = worst.max(px);
        }
    }
    worst
}

/// Rec. 709 luminance of an RGBA pixel's encoded values, 0–255.
fn luma(p: &[u8]) -> f32 {
    0.2126 * f32::from(p[0]) + 0.7152 * f32::from(p[1]) + 0.0722 * f32::from(p[2])
}

/// The mean absolute luminance difference (0–255) between RGBA images `a` and `b` over
/// the pixels where either differs from `sky` (the same view with no terrain); 0 when
/// there are none.
pub(super) fn luma_diff(a: &[u8], b: &[u8], sky: &[u8]) -> f64 {
    let (mut sum, mut n) = (0.0f64, 0u64);
    for ((pa, pb), ps) in a
        .chunks_exact(4)
        .zip(b.chunks_exact(4))
        .zip(sky.chunks_exact(4))
    {
        if pa[..3] == ps[..3] && pb[..3] == ps[..3] {
            continue;
        }
        n += 1;
        sum += f64::from((luma(pa) - luma(pb)).abs());
    }
    if n == 0 { 0.0 } else { sum / n as f64 }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::View;
    use roam_protocol::BitSet;

    fn check_luma(a: &[[u8; 3]], b: &[[u8; 3]], sky: &[[u8; 3]], expected: f64) {
        let rgba =
            |v: &[[u8; 3]]| -> Vec<u8> { v.iter().flat_map(|p| [p[0], p[1], p[2], 255]).collect() };
        let got = luma_diff(&rgba(a), &rgba(b), &rgba(sky));
        assert!((got - expected).abs() < 1e-4, "{got} != {expected}");
    }

    #[test]
    fn luma_differences_count_the_terrains_pixels_only() {
        let s = [9, 9, 9];
        // Sky everywhere: nothing to count.
        check_luma(&[s, s], &[s, s], &[s, s], 0.0);
        // One terrain pixel, unchanged; one changed by 10 grey levels.
        check_luma(
            &[[50; 3], [60; 3], s],
            &[[50; 3], [70; 3], s],
            &[s, s, s],
            5.0,
        );
        // A pixel that is sky in one image and terrain in the other counts.
        check_luma(&[s], &[[109; 3]], &[s], 100.0);
    }

    /// The surface of the root diamond split, seen from the side: the centre vertex moves by
    /// its height less its midpoint, projected; no split, no pop.
    #[test]
    fn a_split_pops_by_its_height_less_its_midpoint() {
        let scene = crate::render::test_scene(2, 10.0, 1.0);
        let grid = Grid::new(2).expect("a grid");
        let (cx, cz) = grid.root();
        let centre = grid.index(cx, cz);
        let height = |i: u32| if i == centre { 100u16 } else { 20 };
        let corner = |i: u32| {
            let (x, z) = grid.coords(i);
            (x % 4 == 0 && z % 4 == 0).then(|| height(i))
        };
        let mut split = BitSet::new(grid.vertices());
        split.insert(centre);
        let follow = |set: &BitSet| {
            let mut m = Morph::new(grid, 0);
            let t: Vec<(u32, u16)> = (0..grid.vertices() as u32)
                .filter(|&i| set.contains(i))
                .map(|i| (i, height(i)))
                .collect();
            m.step(&t, |i| set.contains(i), corner, None);
            m
        };
        let (flat, peak) = (follow(&BitSet::new(grid.vertices())), follow(&split));
        let view = View {
            eye: [20.0, 60.0, -60.0],
            yaw_deg: 0.0,
            pitch_deg: -20.0,
            fov_y_deg: 60.0,
            time_s: 0.0,
        };
        let size = (200, 200);
        let vp = view_proj(&view, size);
        assert_eq!(pop_px(&scene, &flat, &flat, corner, &vp, size), 0.0);
        let pop = pop_px(&scene, &flat, &peak, corner, &vp, size);
        let (a, b) = (
            project(&vp, [20.0, 20.0, 20.0], size).expect("in front"),
            project(&vp, [20.0, 100.0, 20.0], size).expect("in front"),
        );
        let want = ((a.0 - b.0).powi(2) + (a.1 - b.1).powi(2)).sqrt();
        assert!(want > 1.0, "the test's pop is visible: {want}");
        assert!((pop - want).abs() < 1e-3, "{pop} != {want}");
    }
}
