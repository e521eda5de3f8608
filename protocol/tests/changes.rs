//! Change frames (format 2) on random conforming cuts: exact round trips of random closed
//! split sets and toggle sequences, chains of frames each coded against a random earlier
//! one, wrong bases, damage, truncation, hostile headers, no allocation once warm; and
//! (printed, not asserted) the bytes a change costs.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

use proptest::prelude::*;
use roam_protocol::mesh::{self, Mesh};
use roam_protocol::{
    BitSet, CHANGES_FORMAT, ChangeEncoder, Cut, CutHash, DecodeError, EncodeError, Grid,
    MeshDecoder, MeshEncoder,
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

/// SplitMix64: a seeded, portable generator.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    fn below(&mut self, n: u32) -> u32 {
        (self.next() % u64::from(n.max(1))) as u32
    }
}

/// Smooth terrain plus noise, every height a multiple of `step`.
fn heights(grid: &Grid, seed: u32, step: u16) -> Vec<u16> {
    (0..grid.vertices() as u32)
        .map(|i| {
            let (x, z) = grid.coords(i);
            let smooth = 30_000.0 + 20_000.0 * ((x as f64 * 0.05).sin() * (z as f64 * 0.07).cos());
            let noise = (i.wrapping_mul(2_654_435_761).wrapping_add(seed) >> 24) as f64;
            (smooth + noise) as u16 / step * step
        })
        .collect()
}

/// A closed split set: the ancestors of `n` random vertices.
fn closed_set(grid: &Grid, rng: &mut Rng, n: u32) -> BitSet {
    let mut set = BitSet::new(grid.vertices());
    for _ in 0..n {
        grid.split_closed(&mut set, rng.below(grid.side()), rng.below(grid.side()));
    }
    set
}

/// One toggle that keeps `set` closed, near a random vertex of the `w`-wide window at
/// `(x0, z0)`: from there, up through unsplit parents to one whose parents are all split
/// (a split), or down through split children to one with none split (a merge). Returns the
/// diamond toggled.
fn toggle(grid: &Grid, set: &mut BitSet, rng: &mut Rng, (x0, z0, w): (u32, u32, u32)) -> u32 {
    let s = grid.size();
    let (mut x, mut z) = loop {
        let (x, z) = ((x0 + rng.below(w)).min(s), (z0 + rng.below(w)).min(s));
        if !(x.is_multiple_of(s) && z.is_multiple_of(s)) {
            break (x, z);
        }
    };
    loop {
        let i = grid.index(x, z);
        if set.contains(i) {
            let child = grid
                .children(x, z)
                .into_iter()
                .flatten()
                .find(|&(cx, cz)| set.contains(grid.index(cx, cz)));
            match child {
                Some(c) => (x, z) = c,
                None => {
                    set.remove(i);
                    return i;
                }
            }
        } else {
            let parent = grid
                .parents(x, z)
                .into_iter()
                .flatten()
                .find(|&(px, pz)| !set.contains(grid.index(px, pz)));
            match parent {
                Some(p) => (x, z) = p,
                None => {
                    set.insert(i);
                    return i;
                }
            }
        }
    }
}

/// Whether `set` is closed under parent.
fn closed(grid: &Grid, set: &BitSet) -> bool {
    set.iter().all(|i| {
        let (x, z) = grid.coords(i);
        grid.parents(x, z)
            .into_iter()
            .flatten()
            .all(|(px, pz)| set.contains(grid.index(px, pz)))
    })
}

/// The diamonds split in one of `a` and `b` only, shuffled (the encoder takes any order).
fn changes(a: &BitSet, b: &BitSet, rng: &mut Rng) -> Vec<u32> {
    let mut out: Vec<u32> = a
        .words()
        .iter()
        .zip(b.words())
        .enumerate()
        .flat_map(|(w, (&x, &y))| {
            let mut bits = x ^ y;
            std::iter::from_fn(move || {
                (bits != 0).then(|| {
                    let i = w as u32 * 64 + bits.trailing_zeros();
                    bits &= bits - 1;
                    i
                })
            })
        })
        .collect();
    for k in (1..out.len()).rev() {
        out.swap(k, rng.below(k as u32 + 1) as usize);
    }
    out
}

/// A key frame of `set`, decoded: the viewer's first base.
fn key_frame(grid: &Grid, h: &[u16], step: u16, set: &BitSet, dec: &mut MeshDecoder) -> Cut {
    let mut bytes = Vec::new();
    MeshEncoder::with_step(*grid, step)
        .encode(set, h, None, &mut bytes)
        .expect("a conforming set");
    let mut cut = Cut::default();
    let info = dec
        .decode_cut(&bytes, None, u32::MAX, &mut cut)
        .expect("decodes");
    assert!(info.key);
    assert_eq!(cut, Cut::of(grid, set.clone(), h), "the key frame's cut");
    cut
}

/// The change frame from `base` (decoded earlier) to `now`, as the server would code it.
fn encode(grid: &Grid, h: &[u16], step: u16, base: &BitSet, now: &BitSet, seed: u64) -> Vec<u8> {
    let list = changes(base, now, &mut Rng(seed));
    let want = Cut::of(grid, now.clone(), h);
    let mut bytes = vec![0xAA; 3]; // encode appends
    ChangeEncoder::new(*grid, step)
        .encode(
            &list,
            |i| now.contains(i),
            h,
            want.triangles,
            now.len() as u32,
            want.hash,
            &mut bytes,
        )
        .expect("encodes");
    assert_eq!(&bytes[..3], &[0xAA; 3]);
    bytes.split_off(3)
}

/// Codes `now` against `base` (a cut `dec` decoded), decodes it, and checks the split set,
/// the triangle count, the hash, every vertex's height and the emitted mesh. Returns the
/// payload and the decoded cut.
fn check(
    grid: &Grid,
    h: &[u16],
    step: u16,
    base: &Cut,
    now: &BitSet,
    dec: &mut MeshDecoder,
) -> (Vec<u8>, Cut) {
    assert!(closed(grid, now));
    let bytes = encode(grid, h, step, &base.split, now, u64::from(base.triangles));
    assert_eq!(bytes[0], CHANGES_FORMAT);
    let mut got = Cut::default();
    let info = dec
        .decode_cut(&bytes, Some(base), u32::MAX, &mut got)
        .expect("decodes");
    let want = Cut::of(grid, now.clone(), h);
    assert_eq!(got, want);
    assert_eq!(info.splits as usize, now.len());
    assert_eq!(info.triangles, want.triangles);
    assert!(!info.key);
    for i in now.iter() {
        assert_eq!(dec.heights()[i as usize], h[i as usize], "height of {i}");
    }
    let (mut server, mut viewer) = (Mesh::default(), Mesh::default());
    mesh::emit(grid, now, h, &mut server);
    mesh::emit(grid, &got.split, dec.heights(), &mut viewer);
    assert_eq!(viewer, server, "the viewer's mesh is the server's");
    assert_eq!(server.triangle_count(), want.triangles as usize);
    (bytes, got)
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
        let mut dec = MeshDecoder::new(grid);
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
        let mut dec = MeshDecoder::new(grid);
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
    let mut dec = MeshDecoder::new(grid);
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
    let mut dec = MeshDecoder::new(grid);
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
        let mut try_one = |input: &[u8], dec: &mut MeshDecoder| {
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

/// A header that claims too much is refused before anything is allocated.
#[test]
fn hostile_headers_are_refused_before_allocating() {
    let grid = Grid::new(8).expect("valid");
    let h = heights(&grid, 5, 1);
    let mut rng = Rng(5);
    let a = closed_set(&grid, &mut rng, 50);
    let mut dec = MeshDecoder::new(grid);
    let base = key_frame(&grid, &h, 1, &a, &mut dec);
    let mut now = a.clone();
    for _ in 0..8 {
        toggle(&grid, &mut now, &mut rng, (0, 0, grid.side()));
    }
    let bytes = encode(&grid, &h, 1, &a, &now, 3);
    let mut got = Cut::default();
    check(&grid, &h, 1, &base, &now, &mut dec); // warm: `got` and the decoder sized
    dec.decode_cut(&bytes, Some(&base), u32::MAX, &mut got)
        .expect("decodes");
    let patch = |at: usize, v: &[u8]| {
        let mut b = bytes.clone();
        b[at..at + v.len()].copy_from_slice(v);
        b
    };
    let huge_count = patch(22, &u32::MAX.to_le_bytes());
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
        let (n, result) = allocations(|| dec.decode_cut(input, Some(&base), limit, &mut got));
        assert_eq!(result, Err(want));
        assert_eq!(n, 0, "allocations");
    }
    // A count within the bound but no bits for it: an error soon, allocating little.
    let mut starved = bytes[..26].to_vec();
    starved[22..26].copy_from_slice(&(a.len() as u32).to_le_bytes());
    let (n, result) = allocations(|| dec.decode_cut(&starved, Some(&base), u32::MAX, &mut got));
    assert!(result.is_err());
    assert!(n <= 2, "{n} allocations");
}

#[test]
fn nothing_is_allocated_once_warm() {
    let grid = Grid::new(10).expect("valid");
    let h = heights(&grid, 6, 1);
    let mut rng = Rng(6);
    let a = closed_set(&grid, &mut rng, 300);
    let mut dec = MeshDecoder::new(grid);
    let base = key_frame(&grid, &h, 1, &a, &mut dec);
    let mut enc = ChangeEncoder::new(grid, 1);
    let (mut out, mut got) = (Vec::with_capacity(4096), Cut::default());
    for round in 0..3 {
        let mut now = a.clone();
        for _ in 0..100 {
            toggle(&grid, &mut now, &mut rng, (100, 200, 300));
        }
        let list = changes(&a, &now, &mut rng);
        let want = Cut::of(&grid, now.clone(), &h);
        let (n, ()) = allocations(|| {
            out.clear();
            enc.encode(
                &list,
                |i| now.contains(i),
                &h,
                want.triangles,
                now.len() as u32,
                want.hash,
                &mut out,
            )
            .expect("encodes");
            dec.decode_cut(&out, Some(&base), u32::MAX, &mut got)
                .expect("decodes");
        });
        assert_eq!(got, want);
        if round > 0 {
            assert!(list.len() < 400);
            assert_eq!(n, 0, "allocations in round {round}");
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
        let mut dec = MeshDecoder::new(grid);
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

    /// Any bytes at all, behind a change frame's first byte or not: a value or an error.
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
        let mut dec = MeshDecoder::new(grid);
        let base = key_frame(&grid, &h, 1, &closed_set(&grid, &mut Rng(seed), 20), &mut dec);
        let mut got = Cut::default();
        let _ = dec.decode_cut(&bytes, Some(&base), 10_000, &mut got);
        let _ = dec.decode_cut(&bytes, None, 10_000, &mut got);
    }
}

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

/// Prints what change frames cost (run with `--nocapture`); asserts only round trips.
#[test]
fn sizes() {
    // ~20 random toggles clustered in a 64-wide window of a 2^12 + 1 grid, against a
    // viewpoint-dependent cut.
    let grid = Grid::new(12).expect("valid");
    let h = heights(&grid, 8, 1);
    let mut rng = Rng(8);
    let mut dec = MeshDecoder::new(grid);
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
        "2^12+1 synthetic, clustered toggles against a cut of {} triangles: {:.1} changes \
         ({:.1} splits) a frame, {:.2} bytes a change ({:.2} of it the position), plus the \
         26-byte header",
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
            let mut dec = MeshDecoder::new(*grid);
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
                    "{name}, eye moving {speed} cells a frame, k {k}, against frame t-{back}: \
                     {} triangles, {} changes, change frame {} bytes ({:.2} a change, {:.2} \
                     of it the position, header included), format 1 delta {} bytes",
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
