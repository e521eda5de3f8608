//! The geomorphs' unit tests: a random split/merge stream conforms at every step, a vertex
//! appears on its edge and ends exactly at its height, a reversal continues where it is.

use std::collections::{BTreeMap, BTreeSet};

use roam_protocol::{BitSet, Grid, LiveMesh};

use super::*;
use crate::render::TerrainVertices;

const T: u16 = MORPH_TICKS;

/// A vertex's height on the test maps.
fn height(i: u32) -> u16 {
    (i.wrapping_mul(2_654_435_761) >> 20) as u16
}

/// A random cut closed under parent: `n` random splits (each with its ancestors).
fn random_cut(grid: &Grid, seed: &mut u64, n: usize) -> BitSet {
    let mut set = BitSet::new(grid.vertices());
    let s = grid.size() + 1;
    for _ in 0..n {
        *seed = seed
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        let (x, z) = ((*seed >> 33) as u32 % s, (*seed >> 45) as u32 % s);
        grid.split_closed(&mut set, x, z);
    }
    set
}

/// The diamonds in one cut and not the other, with their heights.
fn toggles(grid: &Grid, before: &BitSet, after: &BitSet) -> Vec<(u32, u16)> {
    (0..grid.vertices() as u32)
        .filter(|&i| before.contains(i) != after.contains(i))
        .map(|i| (i, height(i)))
        .collect()
}

fn corner(grid: &Grid) -> impl Fn(u32) -> Option<u16> + '_ {
    |i| {
        let (x, z) = grid.coords(i);
        (x % grid.size() == 0 && z % grid.size() == 0).then(|| height(i))
    }
}

/// The drawn cut is closed under parent and holds the decoded one; its mesh is the mesh
/// of that cut built afresh, and conforms: every edge inside the map is shared by two
/// triangles, once each way (no crack, no T-junction).
fn check_conforming(m: &Morph, decoded: &BitSet, what: &str) {
    let grid = *m.grid();
    let mut drawn = Vec::new();
    for i in 0..grid.vertices() as u32 {
        if decoded.contains(i) {
            assert!(m.contains(i), "{what}: decoded diamond {i} not drawn");
        }
        if m.contains(i) {
            drawn.push(i);
            let (x, z) = grid.coords(i);
            for (px, pz) in grid.parents(x, z).into_iter().flatten() {
                assert!(
                    m.contains(grid.index(px, pz)),
                    "{what}: {i} drawn without its parent"
                );
            }
        }
    }
    let mut fresh = LiveMesh::new(&grid);
    fresh.update(&grid, drawn.iter().copied(), |i| m.contains(i));
    let set = |l: &LiveMesh| -> BTreeSet<[u32; 3]> {
        l.triangles()
            .map(|t| {
                let k = (0..3).min_by_key(|&j| t[j]).unwrap_or(0);
                [t[k], t[(k + 1) % 3], t[(k + 2) % 3]]
            })
            .collect()
    };
    assert_eq!(set(m.live()), set(&fresh), "{what}: the drawn mesh");
    let mut edges: BTreeMap<(u32, u32), u32> = BTreeMap::new();
    for t in m.live().triangles() {
        for j in 0..3 {
            *edges.entry((t[j], t[(j + 1) % 3])).or_default() += 1;
        }
    }
    let s = grid.size();
    for (&(a, b), &n) in &edges {
        assert_eq!(n, 1, "{what}: edge {a}-{b} used {n} times one way");
        let ((ax, az), (bx, bz)) = (grid.coords(a), grid.coords(b));
        let on_edge = (ax == bx && (ax == 0 || ax == s)) || (az == bz && (az == 0 || az == s));
        assert!(
            on_edge || edges.contains_key(&(b, a)),
            "{what}: edge {a}-{b} has no neighbour (a crack or a T-junction)"
        );
    }
}

/// Random split/merge streams, random tick steps: the drawn mesh conforms at every step,
/// its vertex buffer kept slot by slot equals one built whole, and once the stream stops
/// the drawn cut becomes the decoded one with every vertex exactly at its height.
#[test]
fn a_morphing_mesh_conforms_at_every_step() {
    let scene = crate::render::test_scene(5, 10.0, 0.5);
    let grid = Grid::new(5).expect("a grid");
    let mut seed = 11u64;
    for stream in 0..6 {
        let mut m = Morph::new(grid, T);
        let mut terrain = TerrainVertices::default();
        let mut before = BitSet::new(grid.vertices());
        let (mut extra, mut moving) = (0, 0);
        for round in 0..60 {
            seed = seed
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            let n = (seed >> 40) as usize % 23;
            let now = random_cut(&grid, &mut seed, n);
            let ticks = match (seed >> 40) % 11 {
                0 => None,
                k => Some(k * 3),
            };
            let t = toggles(&grid, &before, &now);
            m.step(&t, |d| now.contains(d), corner(&grid), ticks);
            let what = format!("stream {stream} round {round}");
            check_conforming(&m, &now, &what);
            m.draw(&scene, &mut terrain, corner(&grid));
            let mut whole = TerrainVertices::default();
            let mut copy = m.clone();
            copy.live_mut().take_dirty(&mut Vec::new());
            // A fresh TerrainVertices rewrites every slot.
            copy.draw(&scene, &mut whole, corner(&grid));
            assert_eq!(terrain.corners, whole.corners, "{what}: the vertices");
            extra = extra.max(m.len() - now.len());
            moving = moving.max(m.morphing());
            before = now;
        }
        assert!(
            extra > 0 && moving > 0,
            "the stream morphs: {extra} {moving}"
        );
        // No more changes: within a morph's length everything settles.
        m.step(
            &[],
            |d| before.contains(d),
            corner(&grid),
            Some(u64::from(T)),
        );
        m.step(&[], |d| before.contains(d), corner(&grid), Some(0));
        check_conforming(&m, &before, "settled");
        assert_eq!(m.len(), before.len(), "the drawn cut is the decoded one");
        assert_eq!(m.morphing(), 0);
        for i in 0..grid.vertices() as u32 {
            assert_eq!(m.lift(i), 0.0, "vertex {i} at its height");
        }
    }
}

/// Where a one-diamond-deep split draws vertex `d`, samples: its lift plus its height.
fn drawn_y(m: &Morph, d: u32) -> f32 {
    f32::from(height(d)) + m.lift(d)
}

/// A first split of the root: the centre vertex, its hypotenuse midpoint and the cuts
/// with and without it.
fn root_split() -> (Grid, u32, f32, BitSet, BitSet) {
    let grid = Grid::new(3).expect("a grid");
    let (x, z) = grid.root();
    let d = grid.index(x, z);
    let [a, b] = grid.hypotenuse(x, z);
    let mid =
        0.5 * (f32::from(height(grid.index(a.0, a.1))) + f32::from(height(grid.index(b.0, b.1))));
    let empty = BitSet::new(grid.vertices());
    let mut split = empty.clone();
    split.insert(d);
    (grid, d, mid, empty, split)
}

/// Starts `m` from the empty cut and splits `d` (to the cut `split`) a tick later.
fn start_split(m: &mut Morph, grid: &Grid, d: u32, split: &BitSet) {
    m.step(&[], |_| false, corner(grid), None);
    m.step(
        &[(d, height(d))],
        |i| split.contains(i),
        corner(grid),
        Some(1),
    );
}

/// A split vertex appears at its midpoint, moves linearly with the ticks and ends exactly
/// at its height after [`MORPH_TICKS`]; merged, it goes back and leaves at its midpoint.
#[test]
fn a_vertex_appears_at_its_midpoint_and_ends_exactly_at_its_height() {
    let (grid, d, mid, empty, split) = root_split();
    let h = f32::from(height(d));
    assert_ne!(h, mid, "the test map makes the split visible");
    let mut m = Morph::new(grid, T);
    start_split(&mut m, &grid, d, &split);
    assert_eq!(drawn_y(&m, d), mid, "appears where the surface was");
    for k in 1..=T {
        m.step(&[], |i| split.contains(i), corner(&grid), Some(1));
        let want = mid + (h - mid) * (f32::from(k) / f32::from(T));
        assert!((drawn_y(&m, d) - want).abs() < 1e-2, "tick {k}");
    }
    assert_eq!(m.lift(d), 0.0, "exactly at its height");
    assert_eq!(m.morphing(), 0);
    // Merged: drawn until back at its midpoint, then gone.
    m.step(
        &[(d, height(d))],
        |i| empty.contains(i),
        corner(&grid),
        Some(0),
    );
    assert!(m.contains(d));
    m.step(
        &[],
        |i| empty.contains(i),
        corner(&grid),
        Some(u64::from(T) - 1),
    );
    assert!(m.contains(d), "one tick from its midpoint");
    assert!((drawn_y(&m, d) - (mid + (h - mid) / f32::from(T))).abs() < 1e-2);
    m.step(&[], |i| empty.contains(i), corner(&grid), Some(1));
    assert!(!m.contains(d), "gone once at its midpoint");
    assert_eq!(m.live().triangle_count(), 2);
}

/// A merge mid-morph turns the vertex round where it is, and so does a split again.
#[test]
fn a_re_split_mid_morph_continues_from_where_the_vertex_is() {
    let (grid, d, mid, empty, split) = root_split();
    let h = f32::from(height(d));
    let at = |k: u16| mid + (h - mid) * (f32::from(k) / f32::from(T));
    let mut m = Morph::new(grid, T);
    start_split(&mut m, &grid, d, &split);
    m.step(&[], |i| split.contains(i), corner(&grid), Some(10));
    let y = drawn_y(&m, d);
    assert!((y - at(10)).abs() < 1e-2);
    // Merged at 10 ticks in: drawn where it was, then going back.
    m.step(
        &[(d, height(d))],
        |i| empty.contains(i),
        corner(&grid),
        Some(0),
    );
    assert_eq!(drawn_y(&m, d), y, "no jump at the merge");
    m.step(&[], |i| empty.contains(i), corner(&grid), Some(4));
    let y = drawn_y(&m, d);
    assert!((y - at(6)).abs() < 1e-2);
    // Split again: on from there, towards its height.
    m.step(
        &[(d, height(d))],
        |i| split.contains(i),
        corner(&grid),
        Some(0),
    );
    assert_eq!(drawn_y(&m, d), y, "no jump at the re-split");
    m.step(&[], |i| split.contains(i), corner(&grid), Some(3));
    assert!((drawn_y(&m, d) - at(9)).abs() < 1e-2);
    m.step(&[], |i| split.contains(i), corner(&grid), Some(100));
    assert_eq!(m.lift(d), 0.0);
}

/// A child appearing on an edge whose end is still morphing appears on the edge as
/// drawn, not where the edge will be.
#[test]
fn a_vertex_appears_on_its_edge_as_drawn() {
    let grid = Grid::new(3).expect("a grid");
    let mut m = Morph::new(grid, T);
    m.step(&[], |_| false, corner(&grid), None);
    // One deep split: the diamond and its ancestors, in one frame.
    let mut cut = BitSet::new(grid.vertices());
    grid.split_closed(&mut cut, 3, 2);
    let empty = BitSet::new(grid.vertices());
    m.step(
        &toggles(&grid, &empty, &cut),
        |i| cut.contains(i),
        corner(&grid),
        Some(1),
    );
    check_conforming(&m, &cut, "deep split");
    for i in 0..grid.vertices() as u32 {
        if !cut.contains(i) {
            continue;
        }
        let (x, z) = grid.coords(i);
        let [a, b] = grid.hypotenuse(x, z);
        let y = |(x, z): (u32, u32)| {
            let j = grid.index(x, z);
            f32::from(height(j)) + m.lift(j)
        };
        let mid = 0.5 * (y(a) + y(b));
        assert!(
            (drawn_y(&m, i) - mid).abs() < 1e-2,
            "vertex {i} on its edge as drawn"
        );
    }
}

/// Seen from a camera, a vertex moves at [`MORPH_PX_PER_TICK`] on screen, within its
/// deadline ([`MORPH_TICKS`]) and never faster than over [`MORPH_MIN_TICKS`]: the root
/// split seen from far (a change of a hundredth of a pixel takes the least length,
/// linearly), from near (the deadline, linearly) and in between (the screen speed: as
/// many ticks as its pixels take).
#[test]
fn a_vertex_seen_moves_at_the_screen_speed_within_its_least_and_most_lengths() {
    let (grid, d, mid, _, split) = root_split();
    let h = f32::from(height(d));
    let gap = (h - mid).abs();
    // One world unit a sample and a grid step; the eye far enough that its distance
    // hardly changes as the vertex moves.
    let dist = 1e7f32;
    let (x, z) = grid.coords(d);
    let arrival = |px_per_unit: f32| {
        let mut m = Morph::new(grid, T);
        m.set_view(Some(MorphView {
            eye: [x as f32, h + dist, z as f32],
            px_per_unit,
            h_scale: 1.0,
            v_scale: 1.0,
        }));
        start_split(&mut m, &grid, d, &split);
        let mut path = vec![drawn_y(&m, d)];
        for k in 1..=T {
            m.step(&[], |i| split.contains(i), corner(&grid), Some(1));
            path.push(drawn_y(&m, d));
            if m.lift(d) == 0.0 {
                return (k, path);
            }
        }
        panic!("not at its height by its deadline");
    };
    // The pixels the whole change covers from there, and so the ticks it takes at speed.
    let px = |px_per_unit: f32| gap * px_per_unit / dist;
    let check = |px_per_unit: f32, ticks: u16| {
        let (k, path) = arrival(px_per_unit);
        assert_eq!(k, ticks, "{} px", px(px_per_unit));
        // Evenly: each tick the same share, never back.
        for (j, w) in path.windows(2).enumerate() {
            let step = (w[1] - w[0]).abs();
            assert!(
                (step - gap / f32::from(ticks)).abs() < 1e-2 * gap / f32::from(ticks),
                "{} px, tick {j}: moved {step} of {gap}",
                px(px_per_unit)
            );
        }
    };
    let at = |pixels: f32| pixels * dist / gap;
    check(at(0.01), MORPH_MIN_TICKS);
    check(at(1000.0), T);
    // Between the two: as many ticks as its pixels take at the screen speed.
    let ticks = (MORPH_MIN_TICKS + T) / 2;
    check(at(MORPH_PX_PER_TICK * f32::from(ticks)), ticks);
}

/// Seen from a camera, a far vertex merged mid-morph goes back in the time it spent on
/// the way out, not at once: a reversal keeps its least length too.
#[test]
fn a_reversal_seen_from_far_takes_as_long_as_the_way_out() {
    let (grid, d, mid, empty, split) = root_split();
    let h = f32::from(height(d));
    let (x, z) = grid.coords(d);
    let mut m = Morph::new(grid, T);
    // So far that the whole change is a hundredth of a pixel.
    let dist = 1e7f32;
    m.set_view(Some(MorphView {
        eye: [x as f32, h + dist, z as f32],
        px_per_unit: 0.01 * dist / (h - mid).abs(),
        h_scale: 1.0,
        v_scale: 1.0,
    }));
    start_split(&mut m, &grid, d, &split);
    let out: u16 = 10;
    m.step(
        &[],
        |i| split.contains(i),
        corner(&grid),
        Some(u64::from(out)),
    );
    let y = drawn_y(&m, d);
    let want = mid + (h - mid) * f32::from(out) / f32::from(MORPH_MIN_TICKS);
    assert!(
        (y - want).abs() < 1e-2 * (h - mid).abs(),
        "{y} out of {want}"
    );
    m.step(
        &[(d, height(d))],
        |i| empty.contains(i),
        corner(&grid),
        Some(0),
    );
    for k in 1..out {
        m.step(&[], |i| empty.contains(i), corner(&grid), Some(1));
        assert!(m.contains(d), "back at tick {k} of {out}");
        let back = y + (mid - y) * f32::from(k) / f32::from(out);
        assert!((drawn_y(&m, d) - back).abs() < 1e-2 * (h - mid).abs());
    }
    m.step(&[], |i| empty.contains(i), corner(&grid), Some(1));
    assert!(!m.contains(d), "gone once back at its midpoint");
}
