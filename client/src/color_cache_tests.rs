//! The colour cache's unit tests: windows, masks, hostile messages, the bound.

use super::*;

/// 64 cells in tiles of 8, a window of 2: levels of 8, 4, 2, 1 tiles a side; S = 16.
fn layout() -> ColorLayout {
    ColorLayout::new(64, 8, 2).expect("a valid layout")
}

fn cache(keep: Keep) -> ColorCache {
    ColorCache::new(layout(), 6, 8, keep).expect("the layout fits the grid")
}

/// A tile's payload: `side²` texels of a colour made from `seed`, position-dependent.
fn payload(side: u32, seed: u8) -> Vec<u8> {
    let rgb: Vec<u8> = (0..side * side)
        .flat_map(|i| [seed, (i % 251) as u8, seed.wrapping_mul(3)])
        .collect();
    let mut out = Vec::new();
    colormap::encode(side, &rgb, &mut out).expect("a valid tile");
    out
}

fn bit(mask: &[u32; MASK_WORDS], i: usize) -> bool {
    mask[i / 32] >> (i % 32) & 1 == 1
}

fn count(mask: &[u32; MASK_WORDS]) -> u32 {
    mask.iter().map(|w| w.count_ones()).sum()
}

#[test]
fn a_layout_must_fit_the_grid_and_the_window_asked() {
    let e = ColorCache::new(layout(), 7, 8, Keep::Masks).expect_err("128 cells expected");
    assert_eq!(e.field, "Welcome.color.cells");
    let e = ColorCache::new(layout(), 6, 1, Keep::Masks).expect_err("window 2 > 1");
    assert_eq!(e.field, "Welcome.color.window");
    let bad = ColorLayout {
        levels: 9,
        ..layout()
    };
    let e = ColorCache::new(bad, 6, 8, Keep::Masks).expect_err("levels do not add up");
    assert_eq!(e.field, "Welcome.color");
    let c = cache(Keep::Masks);
    assert_eq!(c.layer_side(), 16);
    // 2² tiles at levels 0, 1 and 2; 1 at level 3.
    assert_eq!(c.capacity(), 4 + 4 + 4 + 1);
}

#[test]
fn tiles_set_their_slot_bits_and_are_uploaded_where_the_toroid_puts_them() {
    let mut c = cache(Keep::Texels);
    c.apply_tile(3, 0, 0, &payload(8, 1))
        .expect("the coarsest tile");
    assert!(c.has_coarsest());
    c.apply_window(0, 3, 5).expect("inside level 0");
    c.apply_tile(0, 3, 5, &payload(8, 2))
        .expect("in the window");
    c.apply_tile(0, 4, 6, &payload(8, 3))
        .expect("in the window");
    // Slot (z mod 2)·2 + (x mod 2): (3, 5) → 3, (4, 6) → 0.
    let m = c.resident_mask(0);
    assert!(bit(&m, 3) && bit(&m, 0) && count(&m) == 2, "{m:?}");
    assert_eq!(
        count(&c.drawn_mask(0)),
        0,
        "nothing drawn before the upload"
    );
    assert_eq!(c.resident(), 3);
    assert_eq!(c.queued(), 3);
    let u = c.drain(2);
    assert_eq!(u.uploads.len(), 2);
    // Oldest first: the coarsest tile, then (3, 5) at ((3·8) mod 16, (5·8) mod 16).
    assert_eq!((u.uploads[0].layer, u.uploads[0].size), (3, 8));
    let second = &u.uploads[1];
    assert_eq!(
        (second.layer, second.x, second.y, second.size),
        (0, 8, 8, 8)
    );
    assert_eq!(second.texels.len(), 8 * 8 * 4);
    assert_eq!(&second.texels[..4], &[2, 0, 6, 255]);
    assert_eq!(u.levels[0].origin, [3, 5]);
    assert!(bit(&u.levels[0].drawn, 3) && !bit(&u.levels[0].drawn, 0));
    assert_eq!(c.texels_held(), 64, "the uploaded texels are freed");
    let rest = c.drain(usize::MAX);
    assert_eq!(rest.uploads.len(), 1);
    assert_eq!(rest.levels[0].drawn, c.resident_mask(0));
    assert_eq!(c.texels_held(), 0);
    assert!(c.drain(usize::MAX).uploads.is_empty());
    assert_eq!(
        c.bytes(),
        [1, 2, 3]
            .map(|s| payload(8, s).len() as u64)
            .iter()
            .sum::<u64>()
    );
}

#[test]
fn a_window_move_drops_the_tiles_it_leaves_and_their_uploads() {
    let mut c = cache(Keep::Texels);
    for (x, z) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
        c.apply_tile(0, x, z, &payload(8, 9))
            .expect("in the first window");
    }
    assert_eq!(count(&c.resident_mask(0)), 4);
    c.drain(1); // (0, 0) uploaded and drawn
    c.apply_window(0, 1, 1).expect("inside");
    // Only (1, 1) stays.
    assert!(c.is_resident(0, 1, 1));
    assert!(!c.is_resident(0, 0, 0) && !c.is_resident(0, 1, 0) && !c.is_resident(0, 0, 1));
    assert_eq!(c.resident(), 1);
    assert_eq!(count(&c.drawn_mask(0)), 0, "(0, 0) was drawn and is gone");
    assert_eq!(c.queued(), 1, "the uploads of dropped tiles are dropped");
    let u = c.drain(usize::MAX);
    assert_eq!(u.uploads.len(), 1);
    assert_eq!((u.uploads[0].x, u.uploads[0].y), (8, 8));
    // A tile of the old window is now refused.
    let e = c
        .apply_tile(0, 0, 0, &payload(8, 9))
        .expect_err("left the window");
    assert_eq!(e.field, "ColorTile.x/z");
    // Moving back does not bring anything back.
    c.apply_window(0, 0, 0).expect("inside");
    assert_eq!(c.resident(), 1);
}

#[test]
fn hostile_messages_are_refused_naming_the_field_and_change_nothing() {
    let mut c = cache(Keep::Texels);
    let good = payload(8, 5);
    let cases: Vec<(ServerMessage, &str)> = vec![
        (
            ServerMessage::ColorTile {
                level: 4,
                x: 0,
                z: 0,
                data: good.clone(),
            },
            "ColorTile.level",
        ),
        (
            ServerMessage::ColorTile {
                level: 0,
                x: 8,
                z: 0,
                data: good.clone(),
            },
            "ColorTile.x/z",
        ),
        (
            ServerMessage::ColorTile {
                level: 0,
                x: 2,
                z: 0,
                data: good.clone(),
            },
            "ColorTile.x/z",
        ),
        (
            ServerMessage::ColorTile {
                level: 0,
                x: 0,
                z: u32::MAX,
                data: good.clone(),
            },
            "ColorTile.x/z",
        ),
        // A tile of another size, a cut one, junk, too long.
        (
            ServerMessage::ColorTile {
                level: 0,
                x: 0,
                z: 0,
                data: payload(4, 5),
            },
            "ColorTile.data",
        ),
        (
            ServerMessage::ColorTile {
                level: 0,
                x: 0,
                z: 0,
                data: good[..good.len() - 1].to_vec(),
            },
            "ColorTile.data",
        ),
        (
            ServerMessage::ColorTile {
                level: 0,
                x: 0,
                z: 0,
                data: vec![0xff; 40],
            },
            "ColorTile.data",
        ),
        (
            ServerMessage::ColorTile {
                level: 0,
                x: 0,
                z: 0,
                data: vec![0; colormap::max_len(8) + 1],
            },
            "ColorTile.data",
        ),
        (
            ServerMessage::ColorWindow {
                level: 9,
                x0: 0,
                z0: 0,
            },
            "ColorWindow.level",
        ),
        // Level 2 (2 tiles a side) is held whole.
        (
            ServerMessage::ColorWindow {
                level: 2,
                x0: 0,
                z0: 0,
            },
            "ColorWindow.level",
        ),
        (
            ServerMessage::ColorWindow {
                level: 0,
                x0: 7,
                z0: 0,
            },
            "ColorWindow.x0/z0",
        ),
        (
            ServerMessage::ColorWindow {
                level: 1,
                x0: 0,
                z0: u32::MAX,
            },
            "ColorWindow.x0/z0",
        ),
    ];
    for (msg, field) in cases {
        let e = c.apply(&msg).expect_err("hostile");
        assert_eq!(e.field, field, "{msg:?}: {e}");
        assert_eq!((c.resident(), c.queued(), c.bytes()), (0, 0, 0), "{e}");
        assert_eq!(c.origin(0), Some((0, 0)));
    }
    assert_eq!(c.apply(&ServerMessage::Bye(messages_reason())), Ok(false));
}

fn messages_reason() -> roam_protocol::messages::Reason {
    roam_protocol::messages::Reason::Shutdown
}

#[test]
fn without_texels_only_residency_is_kept() {
    let mut c = cache(Keep::Masks);
    c.apply_tile(0, 1, 1, &payload(8, 4))
        .expect("in the window");
    assert!(c.is_resident(0, 1, 1));
    assert_eq!((c.texels_held(), c.queued()), (0, 0));
    assert!(c.drain(usize::MAX).uploads.is_empty());
    assert_eq!(count(&c.drawn_mask(0)), 0);
}

/// A deterministic walk of windows and tiles: whatever the server does within the
/// protocol, and however rarely the renderer drains, the cache stays within its bound.
#[test]
fn the_cache_never_exceeds_its_bound() {
    let l = layout();
    let mut c = cache(Keep::Texels);
    let bound_texels = usize::from(l.levels) * (c.layer_side() as usize).pow(2);
    let slots = c.capacity() as usize;
    let payloads: Vec<Vec<u8>> = (0..l.levels).map(|v| payload(l.tile_side(v), v)).collect();
    let mut state = 0x1234_5678_9abc_def0u64;
    let mut next = |n: u32| {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state % u64::from(n)) as u32
    };
    let mut most = 0;
    for step in 0..3_000 {
        let level = next(u32::from(l.levels)) as u8;
        let room = l.tiles(level) - l.window_tiles(level);
        if l.windowed(level) && next(4) == 0 {
            c.apply_window(level, next(room + 1), next(room + 1))
                .expect("inside");
        } else {
            let (x0, z0) = c.origin(level).expect("a level");
            let w = l.window_tiles(level);
            let (x, z) = (x0 + next(w), z0 + next(w));
            c.apply_tile(level, x, z, &payloads[usize::from(level)])
                .expect("in the window");
        }
        if step % 97 == 0 {
            c.drain(3);
        }
        assert!(c.texels_held() <= bound_texels);
        assert!(c.queued() <= slots);
        assert!(c.resident() as usize <= slots);
        for v in 0..l.levels {
            let (r, d) = (c.resident_mask(v), c.drawn_mask(v));
            assert!(
                r.iter().zip(&d).all(|(r, d)| d & !r == 0),
                "drawn ⊆ resident"
            );
        }
        most = most.max(c.texels_held());
    }
    assert!(most > bound_texels / 2, "the walk filled the cache: {most}");
    assert_eq!(
        c.resident(),
        (0..l.levels)
            .map(|v| count(&c.resident_mask(v)))
            .sum::<u32>()
    );
}

#[test]
fn a_whole_map_fills_every_window_with_its_pyramid() {
    let l = layout();
    // Texel (x, z) is (x, z, 7): the coarser levels average it.
    let rgb: Vec<u8> = (0..64u32 * 64)
        .flat_map(|i| [(i % 64) as u8, (i / 64) as u8, 7])
        .collect();
    let mut c = ColorCache::whole(l, &rgb).expect("the layout's map");
    assert_eq!(c.resident(), c.capacity());
    let u = c.drain(usize::MAX);
    assert_eq!(u.uploads.len() as u32, c.capacity());
    let coarsest = u.uploads.iter().find(|u| u.layer == 3).expect("level 3");
    // Level 3 is 8 texels a side: texel (0, 0) averages the 8 × 8 block at the origin.
    assert_eq!(&coarsest.texels[..4], &[4, 4, 7, 255]);
    assert!(ColorCache::whole(l, &rgb[3..]).is_err());
    assert_eq!(window_for(8192), 8);
    assert_eq!(window_for(2048), 8);
    assert_eq!(window_for(1024), 4);
    assert_eq!(window_for(100), 1);
}

/// A counting cache (a load generator's) makes tiles resident and counts their bytes
/// without decoding them, keeps the coarsest tile's payload (what a reconnection compares),
/// and still refuses a tile outside its level's window.
#[test]
fn a_counting_cache_checks_places_and_counts_bytes_without_decoding() {
    let (coarsest, tile) = (payload(8, 1), payload(8, 2));
    let mut counted = cache(Keep::Counted);
    let mut masks = cache(Keep::Masks);
    for c in [&mut counted, &mut masks] {
        for (level, x, z, data) in [(3, 0, 0, &coarsest), (0, 0, 0, &tile)] {
            let msg = ServerMessage::ColorTile {
                level,
                x,
                z,
                data: data.clone(),
            };
            assert_eq!(c.apply(&msg), Ok(true));
        }
    }
    assert_eq!(counted.resident(), masks.resident());
    assert_eq!(counted.bytes(), masks.bytes());
    assert_eq!(counted.coarsest(), &coarsest[..], "the payload, undecoded");
    assert_eq!(masks.coarsest().len(), 8 * 8 * 3, "decoded RGB");
    // Bytes that would not decode are counted all the same: nothing decodes them.
    let junk = ServerMessage::ColorTile {
        level: 0,
        x: 1,
        z: 0,
        data: vec![0xff; 7],
    };
    assert_eq!(counted.apply(&junk), Ok(true));
    assert!(masks.apply(&junk).is_err());
    let outside = ServerMessage::ColorTile {
        level: 0,
        x: 5,
        z: 5,
        data: tile.clone(),
    };
    let e = counted.apply(&outside).expect_err("outside the window");
    assert_eq!(e.field, "ColorTile.x/z");
}
