//! Change frames (format 2) on random conforming cuts: exact round trips of random closed
//! split sets and toggle sequences, chains of frames each coded against a random earlier
//! one, wrong bases, damage and truncation, through the reference decoder (the tests'
//! oracle, `common/reference.rs`); hostile headers, random bytes and no allocation once
//! warm through the viewer's decoder ([`Follower`], the library's one decoder of change
//! frames; `follow.rs` holds it to the reference frame by frame).
//! What a change costs is measured by `benches/change_sizes.rs`.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

use crate::common;

use common::Rng;
use common::*;
use proptest::prelude::*;
use roam_protocol::mesh::{self, Mesh};
use roam_protocol::{
    BitSet, CHANGES_FORMAT, ChangeEncoder, CutHash, DecodeError, EncodeError, Follower, Grid,
};

/// Counts this thread's allocations (tests run on several threads).
struct Counting;

thread_local! {
    static ALLOCATIONS: Cell<u64> = const { Cell::new(0) };
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.with(|a| a.set(a.get() + 1));
        unsafe { System.alloc(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        ALLOCATIONS.with(|a| a.set(a.get() + 1));
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static COUNTING: Counting = Counting;

/// Allocations `f` makes on this thread.
fn allocations<T>(f: impl FnOnce() -> T) -> (u64, T) {
    let before = ALLOCATIONS.with(Cell::get);
    let value = f();
    (ALLOCATIONS.with(Cell::get) - before, value)
}

#[test]
fn the_cut_hash_is_order_independent_and_incremental() {
    let grid = Grid::new(6).expect("valid");
    let h = heights(&grid, 1, 1);
    let mut rng = Rng(5);
    let set = closed_set(&grid, &mut rng, 30);
    let mut forward = CutHash::new();
    assert_eq!(forward.value(), 0, "the empty set");
    for i in set.iter() {
        forward.add(i, h[i as usize]);
    }
    let mut backward = CutHash::new();
    let all: Vec<u32> = set.iter().collect();
    for &i in all.iter().rev() {
        backward.add(i, h[i as usize]);
    }
    assert_eq!(forward, backward);
    assert_eq!(forward, CutHash::of(&grid, &set, &h));
    for &i in &all[..all.len() / 2] {
        forward.remove(i, h[i as usize]);
    }
    let mut rest = BitSet::new(grid.vertices());
    for &i in &all[all.len() / 2..] {
        rest.insert(i);
    }
    assert_eq!(forward, CutHash::of(&grid, &rest, &h));
    // A height counts.
    let mut other = CutHash::new();
    other.add(all[0], h[all[0] as usize] ^ 1);
    let mut same = CutHash::new();
    same.add(all[0], h[all[0] as usize]);
    assert_ne!(other, same);
}

#[test]
fn triangles_of_a_cut_are_those_emitted() {
    for levels in 1..=6 {
        let grid = Grid::new(levels).expect("valid");
        let h = heights(&grid, 2, 1);
        let mut rng = Rng(u64::from(levels));
        for n in [0, 1, 5, 40] {
            let set = closed_set(&grid, &mut rng, n);
            let mut m = Mesh::default();
            mesh::emit(&grid, &set, &h, &mut m);
            assert_eq!(
                Cut::of(&grid, set, &h).triangles as usize,
                m.triangle_count()
            );
        }
    }
}

/// Round trips: (levels, seed, vertices picked for the base, toggles, window width,
/// height step).
#[test]
fn round_trips() {
    let cases: &[(u32, u64, u32, u32, u32, u16)] = &[
        (1, 1, 0, 1, 2, 1),
        (1, 2, 3, 4, 2, 1),
        (2, 3, 0, 10, 4, 1),
        (3, 4, 5, 20, 8, 1),
        (4, 5, 10, 40, 16, 7),
        (5, 6, 0, 1, 32, 1),
        (6, 7, 30, 60, 16, 1),
        (7, 8, 80, 200, 128, 100),
        (8, 9, 200, 20, 24, 1),
        (10, 10, 500, 150, 64, 1),
        (12, 11, 300, 20, 64, 1),
    ];
    for &(levels, seed, picks, toggles, window, step) in cases {
        let grid = Grid::new(levels).expect("valid");
        let h = heights(&grid, seed as u32, step);
        let mut rng = Rng(seed);
        let set = closed_set(&grid, &mut rng, picks);
        let mut dec = Reference::new(grid);
        let base = key_frame(&grid, &h, step, &set, &mut dec);
        let mut now = set.clone();
        let w = window.min(grid.side());
        let at = (
            rng.below(grid.side() - w + 1),
            rng.below(grid.side() - w + 1),
            w,
        );
        for _ in 0..toggles {
            toggle(&grid, &mut now, &mut rng, at);
        }
        check(&grid, &h, step, &base, &now, &mut dec);
        // No change at all; and back again.
        check(&grid, &h, step, &base, &set, &mut dec);
        let (_, later) = check(&grid, &h, step, &base, &now, &mut dec);
        check(&grid, &h, step, &later, &set, &mut dec);
    }
}

/// A chain of frames, each coded against a random one of the last 32 decoded.
#[test]
fn chains_of_frames_against_random_earlier_bases() {
    for (levels, seed, frames) in [(5, 1, 200), (7, 2, 200), (9, 3, 100)] {
        let grid = Grid::new(levels).expect("valid");
        let h = heights(&grid, seed, 1);
        let mut rng = Rng(u64::from(seed));
        let first = closed_set(&grid, &mut rng, 20);
        let mut dec = Reference::new(grid);
        let mut decoded = vec![(first.clone(), key_frame(&grid, &h, 1, &first, &mut dec))];
        let mut now = first;
        for _ in 0..frames {
            let w = 1 + rng.below(grid.side());
            let at = (
                rng.below(grid.side() - w + 1),
                rng.below(grid.side() - w + 1),
                w,
            );
            for _ in 0..rng.below(12) {
                toggle(&grid, &mut now, &mut rng, at);
            }
            let from = decoded.len().saturating_sub(32);
            let b = from + rng.below((decoded.len() - from) as u32) as usize;
            let (_, cut) = check(&grid, &h, 1, &decoded[b].1, &now, &mut dec);
            assert_eq!(cut.split, now);
            decoded.push((now.clone(), cut));
        }
    }
}

#[test]
fn a_frame_against_the_wrong_base_is_refused_and_changes_nothing() {
    let grid = Grid::new(7).expect("valid");
    let h = heights(&grid, 3, 1);
    let mut rng = Rng(3);
    let a = closed_set(&grid, &mut rng, 40);
    let mut dec = Reference::new(grid);
    let base = key_frame(&grid, &h, 1, &a, &mut dec);
    let mut others = Vec::new();
    for toggles in [1, 2, 5, 30] {
        let mut other = a.clone();
        for _ in 0..toggles {
            toggle(&grid, &mut other, &mut rng, (0, 0, grid.side()));
        }
        let (_, cut) = check(&grid, &h, 1, &base, &other, &mut dec);
        others.push(cut);
    }
    let mut now = a.clone();
    for _ in 0..10 {
        toggle(&grid, &mut now, &mut rng, (40, 40, 30));
    }
    let bytes = encode(&grid, &h, 1, &a, &now, 1);
    let held = dec.heights().to_vec();
    for other in &others {
        let mut got = Cut::default();
        let err = dec
            .decode_cut(&bytes, Some(other), u32::MAX, &mut got)
            .expect_err("the wrong base");
        assert!(
            matches!(err, DecodeError::Check | DecodeError::Corrupt(_)),
            "{err}"
        );
        assert_eq!(dec.heights(), &held[..], "heights put back");
    }
    let mut got = Cut::default();
    assert_eq!(
        dec.decode_cut(&bytes, None, u32::MAX, &mut got),
        Err(DecodeError::Base)
    );
    let (_, got) = check(&grid, &h, 1, &base, &now, &mut dec);
    assert_eq!(got.split, now);
}

/// Every truncation and every single-byte change of a few payloads: an error (with the
/// heights held put back) or the right cut, never a panic.
#[test]
fn every_truncation_and_byte_flip_is_an_error_or_the_right_cut() {
    let grid = Grid::new(6).expect("valid");
    let h = heights(&grid, 4, 1);
    let mut rng = Rng(4);
    let a = closed_set(&grid, &mut rng, 15);
    let mut dec = Reference::new(grid);
    let base = key_frame(&grid, &h, 1, &a, &mut dec);
    let mut values = 0;
    for toggles in [1, 6, 25] {
        let mut now = a.clone();
        for _ in 0..toggles {
            toggle(&grid, &mut now, &mut rng, (0, 0, grid.side()));
        }
        let want = Cut::of(&grid, now.clone(), &h);
        let bytes = encode(&grid, &h, 1, &a, &now, 2);
        let mut got = Cut::default();
        let mut before = Vec::new();
        let mut try_one = |input: &[u8], dec: &mut Reference| {
            before.clear();
            before.extend_from_slice(dec.heights());
            match dec.decode_cut(input, Some(&base), u32::MAX, &mut got) {
                Ok(_) => {
                    assert_eq!(got, want);
                    for i in now.iter() {
                        assert_eq!(dec.heights()[i as usize], h[i as usize]);
                    }
                    values += 1;
                }
                Err(_) => assert!(dec.heights() == before, "a failed frame changes no height"),
            }
        };
        for len in 0..bytes.len() {
            try_one(&bytes[..len], &mut dec);
        }
        for at in 0..bytes.len() {
            for x in 1..=255u8 {
                let mut bad = bytes.clone();
                bad[at] ^= x;
                try_one(&bad, &mut dec);
            }
        }
        // The payload itself still decodes.
        check(&grid, &h, 1, &base, &now, &mut dec);
    }
    println!("{values} damaged payloads decoded to the right cut (flips in the slack bytes)");
}

/// A header that claims too much is refused by the viewer's decoder before anything is
/// allocated.
#[test]
fn hostile_headers_are_refused_before_allocating() {
    let grid = Grid::new(8).expect("valid");
    let h = heights(&grid, 5, 1);
    let mut rng = Rng(5);
    let a = closed_set(&grid, &mut rng, 50);
    let mut now = a.clone();
    for _ in 0..8 {
        toggle(&grid, &mut now, &mut rng, (0, 0, grid.side()));
    }
    let bytes = encode(&grid, &h, 1, &a, &now, 3);
    let mut f = Follower::new(grid, 4);
    f.decode(0, &key_bytes(&grid, &h, 1, &a), None, u32::MAX)
        .expect("the key frame");
    // Warm: the maps sized by a frame against frame 0, and a refusal.
    f.decode(1, &bytes, Some(0), u32::MAX).expect("decodes");
    let patch = |at: usize, v: &[u8]| {
        let mut b = bytes.clone();
        b[at..at + v.len()].copy_from_slice(v);
        b
    };
    let huge_count = patch(22, &u32::MAX.to_le_bytes());
    assert!(f.decode(2, &huge_count, Some(0), u32::MAX).is_err());
    let huge_triangles = patch(4, &u32::MAX.to_le_bytes());
    let huge_splits = patch(8, &(u32::MAX - 10).to_le_bytes());
    let zero_step = patch(20, &[0, 0]);
    let flags = patch(2, &[1]);
    let levels = patch(1, &[9]);
    let cases: [(&[u8], u32, DecodeError); 7] = [
        (
            &huge_count,
            u32::MAX,
            DecodeError::Corrupt("more changes than the base and the frame have splits"),
        ),
        (
            &huge_triangles,
            1_000_000,
            DecodeError::TooBig {
                declared: u32::MAX,
                limit: 1_000_000,
            },
        ),
        (
            &huge_splits,
            u32::MAX,
            DecodeError::Corrupt("more splits than triangles"),
        ),
        (
            &zero_step,
            u32::MAX,
            DecodeError::Corrupt("a height step of 0"),
        ),
        (&flags, u32::MAX, DecodeError::Corrupt("unknown flags")),
        (
            &levels,
            u32::MAX,
            DecodeError::Grid {
                got: 9,
                expected: 8,
            },
        ),
        (&bytes[..25], u32::MAX, DecodeError::Short(25)),
    ];
    for (input, limit, want) in cases {
        let (n, result) = allocations(|| f.decode(2, input, Some(0), limit));
        assert_eq!(result, Err(want));
        assert_eq!(n, 0, "allocations");
    }
    // A count within the bound but no bits for it: an error soon, allocating little.
    let mut starved = bytes[..26].to_vec();
    starved[22..26].copy_from_slice(&(a.len() as u32).to_le_bytes());
    let (n, result) = allocations(|| f.decode(2, &starved, Some(0), u32::MAX));
    assert!(result.is_err());
    assert!(n <= 2, "{n} allocations");
    assert_eq!(f.frame(), Some(1), "nothing refused was taken");
}

/// The encoder and the viewer's decoder, frame after frame between two cuts (each frame
/// against the one before): once warm, neither allocates.
#[test]
fn nothing_is_allocated_once_warm() {
    let grid = Grid::new(10).expect("valid");
    let h = heights(&grid, 6, 1);
    let mut rng = Rng(6);
    let a = closed_set(&grid, &mut rng, 300);
    let mut b = a.clone();
    for _ in 0..100 {
        toggle(&grid, &mut b, &mut rng, (100, 200, 300));
    }
    let sets = [a, b];
    let mut f = Follower::new(grid, 2);
    f.decode(0, &key_bytes(&grid, &h, 1, &sets[0]), None, u32::MAX)
        .expect("the key frame");
    let mut enc = ChangeEncoder::new(grid, 1);
    let mut out = Vec::with_capacity(4096);
    for frame in 1..8u64 {
        let (from, to) = (&sets[(frame as usize - 1) % 2], &sets[frame as usize % 2]);
        let list = changes(from, to, &mut rng);
        let want = Cut::of(&grid, to.clone(), &h);
        let (n, ()) = allocations(|| {
            out.clear();
            enc.encode(
                &list,
                |i| to.contains(i),
                &h,
                want.triangles,
                to.len() as u32,
                want.hash,
                &mut out,
            )
            .expect("encodes");
            f.decode(frame, &out, Some(frame - 1), u32::MAX)
                .expect("decodes");
        });
        assert_eq!((f.triangles(), f.hash()), (want.triangles, want.hash));
        assert!(list.len() < 400);
        if frame > 3 {
            assert_eq!(n, 0, "allocations in frame {frame}");
        }
    }
}

#[test]
fn the_encoder_refuses_what_is_not_a_change_list() {
    let grid = Grid::new(4).expect("valid");
    let h = heights(&grid, 7, 1);
    let mut enc = ChangeEncoder::new(grid, 1);
    let mut out = vec![1, 2, 3];
    let corner = grid.index(grid.size(), 0);
    let inside = grid.index(3, 5);
    for (list, want) in [
        (vec![inside, corner], "a map corner"),
        (vec![grid.vertices() as u32], "off the grid"),
        (vec![inside, 7, inside], "listed twice"),
    ] {
        let err = enc
            .encode(&list, |_| true, &h, 10, 4, 0, &mut out)
            .expect_err("not a change list");
        assert!(
            matches!(err, EncodeError::Change { why, .. } if why.contains(want)),
            "{err}"
        );
        assert_eq!(out, [1, 2, 3], "nothing written");
    }
    let err = enc
        .encode(&[inside], |_| true, &h[1..], 4, 1, 0, &mut out)
        .expect_err("short heights");
    assert!(matches!(err, EncodeError::Heights { .. }));
    let stepped = ChangeEncoder::new(grid, 7)
        .encode(&[grid.index(8, 8)], |_| true, &h, 4, 1, 0, &mut out)
        .expect_err("off the step");
    assert!(
        matches!(stepped, EncodeError::Step { step: 7, .. }),
        "{stepped}"
    );
    assert_eq!(out, [1, 2, 3], "nothing written");
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Random closed sets and random closure-keeping toggles, any grid size.
    #[test]
    fn random_toggles_round_trip(
        levels in 1u32..=9,
        seed in any::<u64>(),
        picks in 0u32..80,
        toggles in 0u32..80,
        window in 1u32..600,
    ) {
        let grid = Grid::new(levels).expect("valid");
        let h = heights(&grid, seed as u32, 1);
        let mut rng = Rng(seed);
        let a = closed_set(&grid, &mut rng, picks);
        let mut dec = Reference::new(grid);
        let base = key_frame(&grid, &h, 1, &a, &mut dec);
        let w = window.min(grid.side());
        let at = (rng.below(grid.side() - w + 1), rng.below(grid.side() - w + 1), w);
        let mut now = a.clone();
        for _ in 0..toggles {
            toggle(&grid, &mut now, &mut rng, at);
        }
        let (_, cut) = check(&grid, &h, 1, &base, &now, &mut dec);
        // And a fresh random set, against the same base.
        let b = closed_set(&grid, &mut rng, picks / 2);
        check(&grid, &h, 1, &base, &b, &mut dec);
        check(&grid, &h, 1, &cut, &b, &mut dec);
    }

    /// Any bytes at all, behind a change frame's first byte or not: a value or an error,
    /// the same from both decoders.
    #[test]
    fn random_bytes_never_panic(
        mut bytes in prop::collection::vec(any::<u8>(), 0..200),
        format2 in any::<bool>(),
        seed in any::<u64>(),
    ) {
        let grid = Grid::new(6).expect("valid");
        if format2 && bytes.len() >= 4 {
            bytes[..4].copy_from_slice(&[CHANGES_FORMAT, 6, 0, 0]);
        }
        let h = heights(&grid, 1, 1);
        let set = closed_set(&grid, &mut Rng(seed), 20);
        let mut dec = Reference::new(grid);
        let base = key_frame(&grid, &h, 1, &set, &mut dec);
        let mut got = Cut::default();
        let want = dec.decode_cut(&bytes, Some(&base), 10_000, &mut got);
        let _ = dec.decode_cut(&bytes, None, 10_000, &mut got);
        // The viewer's decoder, as the reference.
        let mut f = Follower::new(grid, 2);
        f.decode(0, &key_bytes(&grid, &h, 1, &set), None, u32::MAX).expect("the key frame");
        let decoded = f.decode(1, &bytes, Some(0), 10_000);
        prop_assert_eq!(decoded.is_ok(), want.is_ok());
        if decoded.is_ok() {
            prop_assert_eq!((f.triangles(), f.hash()), (got.triangles, got.hash));
        }
        let _ = f.decode(2, &bytes, None, 10_000);
    }
}
