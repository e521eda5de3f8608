//! Tests of the colour scheduler: coarsest first then ring by ring, within the budget,
//! windows that follow the camera without flapping, a belief of what the viewer holds that
//! equals a replay of the messages, and each tile's normals sent right after it.

use std::collections::BTreeSet;

use super::*;

/// 256² texels in tiles of 16, windows of 4: levels of 16, 8, 4, 2 and 1 tiles a side
/// (levels 0 and 1 windowed).
fn layout() -> ColorLayout {
    ColorLayout::new(256, 16, 4).expect("a valid layout")
}

fn cost(m: ColorSend) -> u64 {
    match m {
        ColorSend::Tile { level, x, z } => 100 + u64::from(level) * 7 + u64::from(x + z),
        ColorSend::Normals { level, x, z } => 40 + u64::from(level) * 3 + u64::from(x * z),
        ColorSend::Window { .. } => 0,
    }
}

/// What a viewer holds, from the messages alone (as the viewer keeps it).
struct Replica {
    layout: ColorLayout,
    origins: Vec<(u32, u32)>,
    held: BTreeSet<(u8, u32, u32)>,
    /// Tiles whose normals came.
    lit: BTreeSet<(u8, u32, u32)>,
    /// The message before, for the normals' "right after their tile".
    last: Option<ColorSend>,
}

impl Replica {
    fn new(layout: ColorLayout) -> Replica {
        Replica {
            layout,
            origins: vec![(0, 0); usize::from(layout.levels)],
            held: BTreeSet::new(),
            lit: BTreeSet::new(),
            last: None,
        }
    }

    fn apply(&mut self, m: ColorSend) {
        match m {
            ColorSend::Window { level, x0, z0 } => {
                assert!(self.layout.windowed(level), "{m:?}: a level held whole");
                assert!(self.layout.origin_valid(level, x0, z0), "{m:?}");
                self.origins[usize::from(level)] = (x0, z0);
                let layout = self.layout;
                self.held
                    .retain(|&(l, x, z)| l != level || layout.in_window(l, (x0, z0), x, z));
            }
            ColorSend::Tile { level, x, z } => {
                let origin = self.origins[usize::from(level)];
                assert!(
                    self.layout.in_window(level, origin, x, z),
                    "{m:?} at {origin:?}"
                );
                assert!(self.held.insert((level, x, z)), "{m:?} sent twice");
            }
            ColorSend::Normals { level, x, z } => {
                // Right after its tile, or the coarsest tile's, whose colour went first.
                let coarsest = level + 1 == self.layout.levels;
                assert!(
                    self.last == Some(ColorSend::Tile { level, x, z }) || coarsest,
                    "{m:?} after {:?}",
                    self.last
                );
                assert!(self.held.contains(&(level, x, z)), "{m:?} without its tile");
                assert!(self.lit.insert((level, x, z)), "{m:?} sent twice");
            }
        }
        let layout = self.layout;
        let origins = self.origins.clone();
        self.lit
            .retain(|&(l, x, z)| layout.in_window(l, origins[usize::from(l)], x, z));
        self.last = Some(m);
    }
}

#[test]
fn the_coarsest_tile_comes_first_then_tiles_ring_by_ring() {
    let l = layout();
    let mut s = ColorScheduler::new(l);
    assert_eq!(
        s.first(),
        ColorSend::Tile {
            level: 4,
            x: 0,
            z: 0
        }
    );
    let cam = (40.0, 24.0);
    let (msgs, spent) = s.step(cam, u64::MAX, &cost);
    let tiles: Vec<(u8, u32, u32)> = msgs
        .iter()
        .filter_map(|m| match *m {
            ColorSend::Tile { level, x, z } => Some((level, x, z)),
            ColorSend::Window { .. } | ColorSend::Normals { .. } => None,
        })
        .collect();
    // Level 3 (2×2), 2 (4×4), 1 and 0 (4×4 windows): 4 + 16 + 16 + 16.
    assert_eq!(tiles.len(), 52);
    assert!(!tiles.iter().any(|t| t.0 == 4));
    // Ordered by the distance to the camera in the tile's own tiles, ties coarser first.
    let key = |&(level, x, z): &(u8, u32, u32)| {
        let per = f64::from(l.tile_side(level) << level);
        (
            tile_distance((cam.0 / per, cam.1 / per), x, z),
            -i32::from(level),
        )
    };
    for pair in tiles.windows(2) {
        let (a, b) = (key(&pair[0]), key(&pair[1]));
        assert!(
            a.0 < b.0 || (a.0 == b.0 && a.1 <= b.1),
            "{pair:?}: {a:?} then {b:?}"
        );
    }
    // First the tile under the camera at every level, coarsest first: at (40, 24)
    // texels, tile (2, 1) of level 0 (16 texels), (1, 0) of level 1, (0, 0) above.
    assert_eq!(tiles[..4], [(3, 0, 0), (2, 0, 0), (1, 1, 0), (0, 2, 1)]);
    assert_eq!(spent, msgs.iter().map(msg_cost).sum::<u64>());
    assert!(s.complete());
    // Nothing more while the camera stays.
    assert_eq!(s.step(cam, u64::MAX, &cost), (vec![], 0));
}

fn msg_cost(m: &ColorSend) -> u64 {
    cost(*m)
}

#[test]
fn the_budget_is_respected_and_used() {
    let mut s = ColorScheduler::new(layout());
    s.first();
    let mut total = 0;
    for allowance in [0, 99, 250, 1000, 333, 2000] {
        let (msgs, spent) = s.step((128.0, 128.0), allowance, &cost);
        assert!(spent <= allowance, "{spent} > {allowance}");
        assert_eq!(spent, msgs.iter().map(msg_cost).sum::<u64>());
        total += msgs.len();
        // It stopped only because the next tile did not fit.
        let mut probe = s.clone();
        if let Some(next) = probe
            .step((128.0, 128.0), u64::MAX, &cost)
            .0
            .iter()
            .find(|m| matches!(m, ColorSend::Tile { .. }))
        {
            assert!(spent + msg_cost(next) > allowance, "{next:?} would fit");
        }
    }
    assert!(total > 0);
    assert!(!s.complete());
}

#[test]
fn windows_follow_the_camera_with_hysteresis() {
    let l = layout();
    let mut s = ColorScheduler::new(l);
    let mut replica = Replica::new(l);
    replica.apply(s.first());
    let mut moves = 0;
    // Drive diagonally across the map, one texel a step.
    for t in 0..256 {
        let cam = (f64::from(t), f64::from(t) * 0.5);
        let (msgs, _) = s.step(cam, 300, &cost);
        moves += msgs
            .iter()
            .filter(|m| matches!(m, ColorSend::Window { level: 0, .. }))
            .count();
        for m in msgs {
            replica.apply(m);
        }
        for level in 0..2 {
            // The camera stays within the hysteresis (1 tile at W = 4) of its window's
            // centre, unless the window is against the level's edge on that side.
            let (x0, z0) = s.origin(level);
            let per = 16.0 * f64::from(1u32 << level);
            let room = l.tiles(level) - 4;
            for (c, o) in [(cam.0 / per, x0), (cam.1 / per, z0)] {
                let centre = f64::from(o) + 2.0;
                let ok = (c - centre).abs() <= 1.0
                    || (o == 0 && c < centre)
                    || (o == room && c > centre);
                assert!(ok, "level {level}: camera at tile {c}, window at {o}");
            }
        }
    }
    // Level 0 is 16 tiles a side, the window 4: it moved, but far fewer times than the
    // camera crossed a tile edge (16 + 8 crossings).
    assert!((3..=12).contains(&moves), "{moves} moves");
    // A camera wandering around one spot (within 6 texels, 0.4 tile) moves no window.
    s.step((200.0, 120.0), 0, &cost);
    let before: Vec<_> = (0..2).map(|l| s.origin(l)).collect();
    for k in 0..100 {
        let wobble = f64::from(k % 5) * 3.0 - 6.0;
        let (msgs, _) = s.step((200.0 + wobble, 120.0 - wobble), 0, &cost);
        assert!(msgs.is_empty(), "{msgs:?}");
    }
    assert_eq!(before, (0..2).map(|l| s.origin(l)).collect::<Vec<_>>());
}

#[test]
fn what_it_believes_the_viewer_holds_is_what_the_messages_give() {
    for (cells, tile, window) in [(256, 16, 4), (512, 16, 3), (64, 16, 1), (16, 16, 8)] {
        let l = ColorLayout::new(cells, tile, window).expect("a valid layout");
        let mut s = ColorScheduler::new(l);
        let mut replica = Replica::new(l);
        replica.apply(s.first());
        let mut rng = 0x2545_f491_4f6c_dd1du64;
        let mut cam = (f64::from(cells) / 2.0, f64::from(cells) / 2.0);
        for _ in 0..400 {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            // A wandering camera, sometimes jumping, with a varying allowance.
            let jump = if rng.is_multiple_of(50) { 60.0 } else { 6.0 };
            let step = |r: u64| (r % 1000) as f64 / 500.0 - 1.0;
            cam.0 = (cam.0 + jump * step(rng)).clamp(0.0, f64::from(cells));
            cam.1 = (cam.1 + jump * step(rng >> 20)).clamp(0.0, f64::from(cells));
            let (msgs, _) = s.step(cam, rng >> 54, &cost);
            for m in msgs {
                replica.apply(m);
            }
            let held: BTreeSet<_> = s.held().into_iter().collect();
            assert_eq!(held, replica.held, "{cells} {tile} {window}");
        }
    }
}

/// With normals, every tile's normals come right after it, charged with it: never more
/// normal tiles than colour tiles (the coarsest's come first thing after the first
/// frame), and whatever the allowance, a viewer that holds a tile's normals holds the tile.
#[test]
fn each_tile_s_normals_follow_it() {
    for (cells, tile, window) in [(256, 16, 4), (512, 16, 3), (16, 16, 8)] {
        let l = ColorLayout::new(cells, tile, window).expect("a valid layout");
        let mut s = ColorScheduler::with_normals(l);
        let mut replica = Replica::new(l);
        replica.apply(s.first());
        assert!(!s.complete(), "the coarsest tile's normals are owed");
        // An allowance too small for them sends nothing.
        let coarsest = ColorSend::Normals {
            level: l.levels - 1,
            x: 0,
            z: 0,
        };
        let (msgs, spent) = s.step((8.0, 8.0), cost(coarsest) - 1, &cost);
        assert_eq!(spent, 0);
        for m in msgs {
            assert!(matches!(m, ColorSend::Window { .. }), "{m:?}");
            replica.apply(m);
        }
        let (msgs, spent) = s.step((8.0, 8.0), cost(coarsest), &cost);
        assert_eq!((msgs, spent), (vec![coarsest], cost(coarsest)));
        replica.apply(coarsest);
        let (mut tiles, mut lit) = (1, 1);
        let mut rng = 0x2545_f491_4f6c_dd1du64;
        let mut cam = (f64::from(cells) / 2.0, f64::from(cells) / 2.0);
        for _ in 0..300 {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            let step = |r: u64| (r % 1000) as f64 / 500.0 - 1.0;
            cam.0 = (cam.0 + 12.0 * step(rng)).clamp(0.0, f64::from(cells));
            cam.1 = (cam.1 + 12.0 * step(rng >> 20)).clamp(0.0, f64::from(cells));
            let allowance = rng >> 54;
            let (msgs, spent) = s.step(cam, allowance, &cost);
            assert!(spent <= allowance);
            assert_eq!(spent, msgs.iter().map(msg_cost).sum::<u64>());
            for m in msgs {
                match m {
                    ColorSend::Tile { .. } => tiles += 1,
                    ColorSend::Normals { .. } => lit += 1,
                    ColorSend::Window { .. } => {}
                }
                replica.apply(m);
            }
            assert_eq!(tiles, lit, "normal tiles sent = colour tiles sent");
            let held: BTreeSet<_> = s.held().into_iter().collect();
            assert_eq!(held, replica.held);
            assert_eq!(replica.lit, replica.held, "every held tile has its normals");
        }
        let (_, _) = s.step(cam, u64::MAX, &cost);
        assert!(s.complete());
    }
}

#[test]
fn without_normals_none_are_sent() {
    let mut s = ColorScheduler::new(layout());
    s.first();
    let (msgs, _) = s.step((40.0, 24.0), u64::MAX, &cost);
    assert!(!msgs.iter().any(|m| matches!(m, ColorSend::Normals { .. })));
    assert!(s.complete());
}

/// A viewer's state is sized by its windows, not the map: over a map of 256² texels and
/// one of 32768² (2048 tiles a side at level 0, where a flag per tile of the level was
/// 4 MB), in tiles of 16 and windows of 4, the states differ by the large map's extra
/// levels only, each one window of flags and an origin; and a drive across the large map
/// grows nothing.
#[test]
fn the_state_is_sized_by_the_windows_not_the_map() {
    let small = ColorLayout::new(256, 16, 4).expect("a valid layout");
    let large = ColorLayout::new(32768, 16, 4).expect("a valid layout");
    assert_eq!((small.levels, large.levels), (5, 12));
    let (mut s, mut l) = (ColorScheduler::new(small), ColorScheduler::new(large));
    // Both end in levels of 2 and 1 tiles; the rest fill a 4×4 window.
    let level = 16 + size_of::<(u32, u32)>() + size_of::<Vec<bool>>();
    assert_eq!(
        l.bytes() - s.bytes(),
        usize::from(large.levels - small.levels) * level
    );
    let before = (s.bytes(), l.bytes());
    s.first();
    l.first();
    for t in 0..=200 {
        let f = f64::from(t) / 200.0;
        s.step((256.0 * f, 128.0 * f), u64::MAX, &cost);
        l.step((32768.0 * f, 16384.0 * f), u64::MAX, &cost);
        assert!(s.complete() && l.complete());
    }
    assert_ne!(l.origin(0), (0, 0), "the windows moved");
    assert_eq!((s.bytes(), l.bytes()), before, "a drive grows nothing");
    assert!(l.bytes() < 1024, "{} bytes", l.bytes());
}
