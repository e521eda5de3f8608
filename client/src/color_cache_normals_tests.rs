//! The colour cache's normal tiles: decoded into their slots and uploaded as two-byte
//! codes, dropped with the window, refused when hostile, and bounded like the colour.

use roam_protocol::normals;

use super::*;

/// 64 cells in tiles of 8, a window of 2: levels of 8, 4, 2, 1 tiles a side; S = 16.
fn layout() -> ColorLayout {
    ColorLayout::new(64, 8, 2).expect("a valid layout")
}

fn cache(keep: Keep) -> ColorCache {
    ColorCache::new(layout(), 6, 8, keep).expect("the layout fits the grid")
}

/// A tile's normals on the wire: `side²` codes made from `seed`.
fn normal_payload(side: u32, seed: u8) -> (Vec<u8>, Vec<u8>) {
    let codes: Vec<[u8; 2]> = (0..side * side)
        .map(|i| {
            [
                seed.wrapping_add((i % 13) as u8),
                128u8.wrapping_add((i / side) as u8),
            ]
        })
        .collect();
    let mut out = Vec::new();
    normals::encode_tile(side, &codes, &mut out).expect("a valid tile");
    (out, codes.into_iter().flatten().collect())
}

fn tile(level: u8, x: u32, z: u32, seed: u8) -> ServerMessage {
    let side = layout().tile_side(level);
    ServerMessage::NormalTile {
        level,
        x,
        z,
        data: normal_payload(side, seed).0,
    }
}

fn count(mask: &[u32; MASK_WORDS]) -> u32 {
    mask.iter().map(|w| w.count_ones()).sum()
}

#[test]
fn normal_tiles_land_in_their_slots_as_two_byte_codes() {
    let mut c = cache(Keep::Texels);
    c.apply_window(0, 3, 5).expect("inside level 0");
    assert_eq!(c.apply(&tile(0, 3, 5, 40)), Ok(true));
    assert_eq!(c.apply(&tile(3, 0, 0, 90)), Ok(true));
    assert!(c.has_normals(0, 3, 5) && c.has_normals(3, 0, 0));
    // Normals without colour: the colour's slots are untouched.
    assert_eq!((c.resident(), c.normals_resident()), (0, 2));
    assert!(!c.has_coarsest());
    assert_eq!(c.normals_queued(), 2);
    assert_eq!(c.normal_texels_held(), 64 + 64);
    let u = c.drain(1);
    assert!(u.uploads.is_empty());
    assert_eq!(u.normals.len(), 1);
    let first = &u.normals[0];
    // Slot (5 mod 2)·2 + (3 mod 2) = 3, at ((3·8) mod 16, (5·8) mod 16) of layer 0.
    assert_eq!(
        (first.layer, first.slot, first.x, first.y, first.size),
        (0, 3, 8, 8, 8)
    );
    assert_eq!(first.texels, normal_payload(8, 40).1);
    assert_eq!(count(&u.levels[0].normals), 1);
    assert_eq!(u.levels[0].normals[0], 1 << 3);
    assert_eq!(
        count(&u.levels[3].normals),
        0,
        "not drawn before its upload"
    );
    let rest = c.drain(usize::MAX);
    assert_eq!(rest.normals.len(), 1);
    assert_eq!(rest.levels[3].normals[0], 1);
    assert_eq!(c.normal_texels_held(), 0, "uploaded codes are freed");
    assert_eq!(c.normals_received(), 2);
    assert_eq!(
        c.normal_bytes(),
        (normal_payload(8, 40).0.len() + normal_payload(8, 90).0.len()) as u64
    );
    assert_eq!(c.bytes(), 0, "colour bytes are counted apart");
}

#[test]
fn a_window_move_drops_normals_with_their_colour() {
    let mut c = cache(Keep::Texels);
    let colour = |seed: u8| {
        let rgb: Vec<u8> = (0..8 * 8 * 3)
            .map(|i| (i as u8).wrapping_mul(seed))
            .collect();
        let mut out = Vec::new();
        colormap::encode(8, &rgb, &mut out).expect("a tile");
        out
    };
    for (x, z) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
        c.apply_tile(0, x, z, &colour(3)).expect("in the window");
        c.apply(&tile(0, x, z, 7)).expect("in the window");
    }
    c.drain(1); // (0, 0)'s colour and normals uploaded and drawn
    assert_eq!(c.normals_queued(), 3);
    c.apply_window(0, 1, 1).expect("inside");
    assert!(c.has_normals(0, 1, 1) && c.is_resident(0, 1, 1));
    assert!(!c.has_normals(0, 0, 0) && !c.has_normals(0, 1, 0) && !c.has_normals(0, 0, 1));
    assert_eq!((c.resident(), c.normals_resident()), (1, 1));
    assert_eq!(
        c.normals_queued(),
        1,
        "the dropped tiles' uploads are dropped"
    );
    let u = c.drain(usize::MAX);
    assert_eq!(count(&u.levels[0].normals), 1);
    assert_eq!((u.normals[0].x, u.normals[0].y), (8, 8));
    // Normals of a tile the window left are refused, as its colour is.
    let e = c.apply(&tile(0, 0, 0, 7)).expect_err("left the window");
    assert_eq!(e.field, "NormalTile.x/z");
}

#[test]
fn hostile_normal_tiles_are_refused_naming_the_field_and_change_nothing() {
    let mut c = cache(Keep::Texels);
    let colour_payload = {
        let mut out = Vec::new();
        colormap::encode(8, &[5; 8 * 8 * 3], &mut out).expect("a tile");
        out
    };
    let long = vec![0; layout().max_tile_bytes(0) + 1];
    for (msg, field) in [
        (tile(4, 0, 0, 1), "NormalTile.level"),
        (tile(0, 8, 0, 1), "NormalTile.x/z"),
        (tile(0, 2, 0, 1), "NormalTile.x/z"),
        (
            ServerMessage::NormalTile {
                level: 0,
                x: 0,
                z: 0,
                data: long,
            },
            "NormalTile.data",
        ),
        (
            ServerMessage::NormalTile {
                level: 0,
                x: 0,
                z: 0,
                data: colour_payload,
            },
            "NormalTile.data",
        ),
        (
            ServerMessage::NormalTile {
                level: 1,
                x: 0,
                z: 0,
                data: normal_payload(4, 1).0,
            },
            "NormalTile.data",
        ),
    ] {
        let e = c.apply(&msg).expect_err("refused");
        assert_eq!(e.field, field, "{e}");
    }
    assert_eq!(
        (c.normals_resident(), c.normals_queued(), c.normal_bytes()),
        (0, 0, 0)
    );
    assert!(c.put_normals(0, 0, 0, &[0; 7]).is_err());
}

#[test]
fn without_texels_only_their_residency_is_kept() {
    let mut c = cache(Keep::Masks);
    c.apply(&tile(0, 1, 1, 4)).expect("in the window");
    assert!(c.has_normals(0, 1, 1));
    assert_eq!((c.normal_texels_held(), c.normals_queued()), (0, 0));
    assert!(c.drain(usize::MAX).normals.is_empty());
}

/// Whatever the server sends within the protocol, and however rarely the renderer drains,
/// the normals stay within the colour's bound: one tile a slot, `levels × S²` texels.
#[test]
fn normals_never_exceed_the_bound() {
    let l = layout();
    let mut c = cache(Keep::Texels);
    let bound_texels = usize::from(l.levels) * (c.layer_side() as usize).pow(2);
    let slots = c.capacity() as usize;
    let mut state = 0x0ddb_a11c_afe0_1234u64;
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
            c.apply(&tile(level, x0 + next(w), z0 + next(w), level))
                .expect("in the window");
        }
        if step % 89 == 0 {
            c.drain(3);
        }
        assert!(c.normal_texels_held() <= bound_texels);
        assert!(c.normals_queued() <= slots);
        assert!(c.normals_resident() as usize <= slots);
        most = most.max(c.normal_texels_held());
    }
    assert!(most > bound_texels / 2, "the walk filled the cache: {most}");
    assert_eq!(
        c.normals_resident(),
        (0..l.levels)
            .map(|v| count(&c.normals_mask(v)))
            .sum::<u32>()
    );
}
