//! `cargo bench -p roam-protocol --bench change_sizes`: what a change frame costs, in
//! bytes (no time is measured): bytes a change on clustered toggles, and change frames
//! against format 1's delta for viewpoint-dependent cuts as the eye moves, on a synthetic
//! 2^12 + 1 grid and the bundled `data/kossou`. Prints one JSON object a line. Every frame
//! it codes is also decoded and checked (the round trip of `tests/it/common`, through its
//! reference decoder).
// A benchmark prints its figures (JSON), and shares helpers with the tests by path.
#![allow(unreachable_pub, clippy::print_stdout)]

#[path = "../tests/it/common/mod.rs"]
mod common;

use common::*;
use roam_protocol::{BitSet, ChangeEncoder, Grid, MeshEncoder};

/// A viewpoint-dependent cut, roughly as a tessellator makes one: a diamond of half-size
/// `h` at distance `d` from the eye is split when `(k·h + roughness) / d` exceeds 1 (its
/// ancestors too).
fn lod(grid: &Grid, heights: &[u16], eye: (f64, f64), k: f64) -> BitSet {
    let mut set = BitSet::new(grid.vertices());
    let mut seen = BitSet::new(grid.vertices());
    let mut stack = vec![grid.root()];
    while let Some((x, z)) = stack.pop() {
        if seen.contains(grid.index(x, z)) {
            continue; // a diamond has up to two parents
        }
        seen.insert(grid.index(x, z));
        let (m, _) = grid.classify(x, z);
        let [(ax, az), (bx, bz)] = grid.hypotenuse(x, z);
        let hv = |x, z| f64::from(heights[grid.index(x, z) as usize]);
        let rough = (hv(x, z) - (hv(ax, az) + hv(bx, bz)) / 2.0).abs() / 8.0;
        let d = ((f64::from(x) - eye.0).powi(2) + (f64::from(z) - eye.1).powi(2)).sqrt() + 1.0;
        if (k * f64::from(1u32 << m) + rough) / d > 1.0 {
            grid.split_closed(&mut set, x, z);
            stack.extend(grid.children(x, z).into_iter().flatten());
        }
    }
    set
}

fn read_pgm(bytes: &[u8]) -> (u32, Vec<u16>) {
    let mut fields = Vec::new();
    let mut at = 0;
    while fields.len() < 4 {
        while bytes[at].is_ascii_whitespace() {
            at += 1;
        }
        let start = at;
        while !bytes[at].is_ascii_whitespace() {
            at += 1;
        }
        fields.push(
            std::str::from_utf8(&bytes[start..at])
                .expect("ascii")
                .to_owned(),
        );
    }
    assert_eq!(fields[0], "P5");
    let side: u32 = fields[1].parse().expect("a width");
    let raster = &bytes[at + 1..];
    let h = raster
        .chunks_exact(2)
        .map(|c| u16::from_be_bytes([c[0], c[1]]))
        .collect();
    (side, h)
}

/// Bytes of the change frame from `base` to `now` with no heights in it (every change
/// coded as a merge): what the positions cost.
fn positions_only(grid: &Grid, h: &[u16], step: u16, base: &BitSet, now: &BitSet) -> usize {
    let list = changes(base, now, &mut Rng(0));
    let mut out = Vec::new();
    ChangeEncoder::new(*grid, step)
        .encode(&list, |_| false, h, 0, 0, 0, &mut out)
        .expect("encodes");
    out.len() - 26
}

fn main() {
    // ~20 random toggles clustered in a 64-wide window of a 2^12 + 1 grid, against a
    // viewpoint-dependent cut.
    let grid = Grid::new(12).expect("valid");
    let h = heights(&grid, 8, 1);
    let mut rng = Rng(8);
    let mut dec = Reference::new(grid);
    let a = lod(&grid, &h, (1500.0, 2200.0), 24.0);
    let base = key_frame(&grid, &h, 1, &a, &mut dec);
    let (mut bytes, mut positions, mut changed, mut splits) = (0, 0, 0, 0);
    for _ in 0..50 {
        let mut now = a.clone();
        let at = (1300 + rng.below(400), 2000 + rng.below(400), 64);
        for _ in 0..20 {
            toggle(&grid, &mut now, &mut rng, at);
        }
        let list = changes(&a, &now, &mut rng);
        let (payload, _) = check(&grid, &h, 1, &base, &now, &mut dec);
        bytes += payload.len() - 26;
        positions += positions_only(&grid, &h, 1, &a, &now);
        changed += list.len();
        splits += list.iter().filter(|&&i| now.contains(i)).count();
    }
    println!(
        "{{\"case\":\"clustered toggles\",\"terrain\":\"2^12+1 synthetic\",\"triangles\":{},\"changes_per_frame\":{:.1},\"splits_per_frame\":{:.1},\"bytes_per_change\":{:.2},\"position_bytes_per_change\":{:.2},\"header_bytes\":26}}",
        base.triangles,
        changed as f64 / 50.0,
        splits as f64 / 50.0,
        bytes as f64 / changed as f64,
        positions as f64 / changed as f64,
    );
    // A moving eye: consecutive viewpoint-dependent cuts, each against the frame before or
    // the one four frames before; format 1's delta beside.
    let mut terrain = vec![("2^12+1 synthetic".to_owned(), grid, h, 1u16)];
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../data/kossou/hf.pgm");
    if let Ok(pgm) = std::fs::read(path) {
        let (side, hk) = read_pgm(&pgm);
        let g = Grid::new((side - 1).trailing_zeros()).expect("2^N + 1");
        let step = roam_protocol::height_step(&hk);
        terrain.push((format!("kossou 2^10+1 (step {step})"), g, hk, step));
    }
    for (name, grid, h, step) in &terrain {
        for (speed, k) in [
            (0.25, 24.0),
            (1.0, 24.0),
            (4.0, 24.0),
            (0.25, 64.0),
            (1.0, 64.0),
        ] {
            let sets: Vec<BitSet> = (0..12)
                .map(|f| {
                    let t = f64::from(f) * speed;
                    let s = grid.size() as f64;
                    lod(grid, h, (s * 0.4 + t, s * 0.5 + 0.6 * t), k)
                })
                .collect();
            let mut dec = Reference::new(*grid);
            let mut cuts = vec![key_frame(grid, h, *step, &sets[0], &mut dec)];
            for s in &sets[1..4] {
                let last = cuts.last().expect("a cut").clone();
                cuts.push(check(grid, h, *step, &last, s, &mut dec).1);
            }
            for back in [1, 4] {
                let (mut v2, mut v1, mut pos, mut n, mut tris) = (0, 0, 0, 0, 0);
                for f in 4..sets.len() {
                    let base = &cuts[f - back];
                    n += changes(&base.split, &sets[f], &mut rng).len();
                    let (payload, cut) = check(grid, h, *step, base, &sets[f], &mut dec);
                    let mut delta = Vec::new();
                    MeshEncoder::with_step(*grid, *step)
                        .encode(&sets[f], h, Some(&base.split), &mut delta)
                        .expect("encodes");
                    v2 += payload.len();
                    v1 += delta.len();
                    pos += positions_only(grid, h, *step, &base.split, &sets[f]);
                    tris += cut.triangles as usize;
                    if back == 1 {
                        cuts.push(cut);
                    }
                }
                let frames = sets.len() - 4;
                println!(
                    "{{\"case\":\"moving eye\",\"terrain\":\"{name}\",\"cells_per_frame\":{speed},\"k\":{k},\"against\":\"t-{back}\",\"triangles\":{},\"changes\":{},\"change_frame_bytes\":{},\"bytes_per_change\":{:.2},\"position_bytes_per_change\":{:.2},\"format1_delta_bytes\":{}}}",
                    tris / frames,
                    n / frames,
                    v2 / frames,
                    v2 as f64 / n.max(1) as f64,
                    pos as f64 / n.max(1) as f64,
                    v1 / frames,
                );
            }
        }
    }
}
