//! Helpers shared by the change-frame tests: a seeded generator, terrain, random closed
//! split sets and the toggles that keep them closed, the round trip every test checks,
//! and the reference decoder they are checked with ([`reference`]).
#![allow(dead_code)] // each test file uses its own subset

pub mod reference;

use roam_protocol::mesh::{self, Mesh};
use roam_protocol::{BitSet, CHANGES_FORMAT, ChangeEncoder, Grid, MeshEncoder};

pub use reference::{Cut, Reference};

/// SplitMix64: a seeded, portable generator.
pub struct Rng(pub u64);

impl Rng {
    pub fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    pub fn below(&mut self, n: u32) -> u32 {
        (self.next() % u64::from(n.max(1))) as u32
    }
}

/// Smooth terrain plus noise, every height a multiple of `step`.
pub fn heights(grid: &Grid, seed: u32, step: u16) -> Vec<u16> {
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
pub fn closed_set(grid: &Grid, rng: &mut Rng, n: u32) -> BitSet {
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
pub fn toggle(grid: &Grid, set: &mut BitSet, rng: &mut Rng, (x0, z0, w): (u32, u32, u32)) -> u32 {
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
pub fn closed(grid: &Grid, set: &BitSet) -> bool {
    set.iter().all(|i| {
        let (x, z) = grid.coords(i);
        grid.parents(x, z)
            .into_iter()
            .flatten()
            .all(|(px, pz)| set.contains(grid.index(px, pz)))
    })
}

/// The diamonds split in one of `a` and `b` only, shuffled (the encoder takes any order).
pub fn changes(a: &BitSet, b: &BitSet, rng: &mut Rng) -> Vec<u32> {
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

/// A key frame of `set`, coded.
pub fn key_bytes(grid: &Grid, h: &[u16], step: u16, set: &BitSet) -> Vec<u8> {
    let mut bytes = Vec::new();
    MeshEncoder::with_step(*grid, step)
        .encode(set, h, None, &mut bytes)
        .expect("a conforming set");
    bytes
}

/// A key frame of `set`, decoded: the viewer's first base.
pub fn key_frame(grid: &Grid, h: &[u16], step: u16, set: &BitSet, dec: &mut Reference) -> Cut {
    let bytes = key_bytes(grid, h, step, set);
    let mut cut = Cut::default();
    let info = dec
        .decode_cut(&bytes, None, u32::MAX, &mut cut)
        .expect("decodes");
    assert!(info.key);
    assert_eq!(cut, Cut::of(grid, set.clone(), h), "the key frame's cut");
    cut
}

/// The change frame from `base` (decoded earlier) to `now`, as the server would code it.
pub fn encode(
    grid: &Grid,
    h: &[u16],
    step: u16,
    base: &BitSet,
    now: &BitSet,
    seed: u64,
) -> Vec<u8> {
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

/// Codes `now` against `base` (a cut `dec`, the reference decoder, decoded), decodes it,
/// and checks the split set,
/// the triangle count, the hash, every vertex's height and the emitted mesh. Returns the
/// payload and the decoded cut.
pub fn check(
    grid: &Grid,
    h: &[u16],
    step: u16,
    base: &Cut,
    now: &BitSet,
    dec: &mut Reference,
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
