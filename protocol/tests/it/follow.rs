//! The viewer's decoder ([`Follower`]) and its mesh ([`LiveMesh`]) against the reference
//! decoder ([`Reference`], the tests' oracle: a bitset and a copy per base) and
//! [`mesh::emit`]:
//! random drives of change frames, format-1 deltas and key frames against random recent
//! bases, damaged payloads, and the memory held.

use crate::common;

use std::collections::{BTreeSet, VecDeque};

use common::{Cut, Reference, Rng, closed_set, encode, heights, toggle};
use roam_protocol::mesh::{self, LiveMesh, Mesh};
use roam_protocol::{BitSet, DecodeError, Follower, Grid, MeshEncoder};

/// A mesh's triangles as sets of grid indices, each rotated to start at its least index
/// (orientation kept).
fn triangle_set(tris: impl Iterator<Item = [u32; 3]>) -> BTreeSet<[u32; 3]> {
    tris.map(|t| {
        let k = (0..3).min_by_key(|&k| t[k]).unwrap_or(0);
        [t[k], t[(k + 1) % 3], t[(k + 2) % 3]]
    })
    .collect()
}

/// [`mesh::emit`]'s triangles as grid indices.
fn emitted(grid: &Grid, split: &BitSet, h: &[u16]) -> BTreeSet<[u32; 3]> {
    let mut m = Mesh::default();
    mesh::emit(grid, split, h, &mut m);
    let index = |r: u32| {
        let [x, z] = m.vertices[r as usize];
        grid.index(u32::from(x), u32::from(z))
    };
    triangle_set(
        m.indices
            .chunks_exact(3)
            .map(|t| [index(t[0]), index(t[1]), index(t[2])]),
    )
}

/// The follower's cut as a bitset, each height checked against the terrain's.
fn follower_cut(grid: &Grid, f: &Follower, h: &[u16]) -> BitSet {
    let mut set = BitSet::new(grid.vertices());
    for (i, height) in f.split() {
        assert_eq!(height, h[i as usize], "height of {i}");
        set.insert(i);
    }
    set
}

/// A viewer decoding with both decoders: the reference keeps a [`Cut`] per base.
struct Both {
    grid: Grid,
    reference: Reference,
    bases: VecDeque<(u64, Cut)>,
    follower: Follower,
    live: LiveMesh,
    kept: usize,
}

impl Both {
    fn new(grid: Grid, kept: usize) -> Both {
        Both {
            grid,
            reference: Reference::new(grid),
            bases: VecDeque::new(),
            follower: Follower::new(grid, kept),
            live: LiveMesh::new(&grid),
            kept,
        }
    }

    /// Decodes `payload` (frame `frame` against `base`) with both; they must agree, and
    /// the live mesh must be `emit`'s. The reference's result.
    fn decode(
        &mut self,
        frame: u64,
        payload: &[u8],
        base: Option<u64>,
        h: &[u16],
    ) -> Result<(), DecodeError> {
        let grid = self.grid;
        let (before_frame, before_hash) = (self.follower.frame(), self.follower.hash());
        let base_cut = base.map(|b| {
            &self
                .bases
                .iter()
                .find(|(f, _)| *f == b)
                .expect("the test codes against bases both hold")
                .1
        });
        let mut cut = Cut::default();
        let want = self
            .reference
            .decode_cut(payload, base_cut, 10_000_000, &mut cut);
        let got = self.follower.decode(frame, payload, base, 10_000_000);
        assert_eq!(got.is_ok(), want.is_ok(), "{got:?} / {want:?}");
        if want.is_err() {
            assert_eq!(
                (self.follower.frame(), self.follower.hash()),
                (before_frame, before_hash),
                "a failed frame changes nothing"
            );
            return want.map(|_| ());
        }
        assert_eq!(got, want);
        assert_eq!(follower_cut(&grid, &self.follower, h), cut.split);
        assert_eq!(self.follower.triangles(), cut.triangles);
        assert_eq!(self.follower.hash(), cut.hash);
        let follower = &self.follower;
        self.live
            .update(&grid, follower.toggled(), |i| follower.contains(i));
        assert_eq!(
            triangle_set(self.live.triangles()),
            emitted(&grid, &cut.split, h),
            "the live mesh is emit's"
        );
        assert_eq!(self.live.triangle_count(), cut.triangles as usize);
        let m = self.live.to_mesh(&grid, |i| self.follower.height(i));
        roam_protocol::validate::check_mesh(&m.vertices, &m.indices, grid.size())
            .expect("the live mesh is a conforming tessellation");
        self.bases.push_back((frame, cut));
        if self.bases.len() > self.kept {
            self.bases.pop_front();
        }
        Ok(())
    }
}

/// A drive: each frame toggles a few diamonds near a wandering window, and is coded as a
/// change frame, a format-1 delta or a key frame against a random base still held.
fn drive(levels: u32, seed: u64, frames: u64, kept: usize) {
    let grid = Grid::new(levels).expect("a grid of the protocol");
    let step = 1 + (seed % 3) as u16;
    let h = heights(&grid, seed as u32, step);
    let mut rng = Rng(seed);
    let mut both = Both::new(grid, kept);
    let mut sets: VecDeque<(u64, BitSet)> = VecDeque::new();
    let mut now = closed_set(&grid, &mut rng, 20);
    let mut key = Vec::new();
    MeshEncoder::with_step(grid, step)
        .encode(&now, &h, None, &mut key)
        .expect("a conforming set");
    both.decode(0, &key, None, &h).expect("the key frame");
    sets.push_back((0, now.clone()));
    let w = (grid.side() / 4).max(2);
    let (mut x0, mut z0) = (0, 0);
    for frame in 1..frames {
        x0 = (x0 + rng.below(5)).min(grid.size() - w / 2);
        z0 = (z0 + rng.below(3)).min(grid.size() - w / 2);
        for _ in 0..rng.below(12) {
            toggle(&grid, &mut now, &mut rng, (x0, z0, w));
        }
        let (base, base_set) = &sets[rng.below(sets.len() as u32) as usize];
        let (base, payload) = match rng.below(8) {
            0 => {
                let mut out = Vec::new();
                MeshEncoder::with_step(grid, step)
                    .encode(&now, &h, None, &mut out)
                    .expect("a conforming set");
                (None, out)
            }
            1 => {
                let mut out = Vec::new();
                MeshEncoder::with_step(grid, step)
                    .encode(&now, &h, Some(base_set), &mut out)
                    .expect("a conforming set");
                (Some(*base), out)
            }
            _ => (Some(*base), encode(&grid, &h, step, base_set, &now, frame)),
        };
        both.decode(frame, &payload, base, &h).expect("decodes");
        sets.push_back((frame, now.clone()));
        if sets.len() > kept {
            sets.pop_front();
        }
    }
}

#[test]
fn drives_decode_as_the_reference_does() {
    for (levels, seed, frames, kept) in [
        (3, 1, 40, 4),
        (6, 2, 120, 8),
        (8, 3, 150, 32),
        (9, 4, 100, 3),
        (10, 5, 60, 16),
    ] {
        drive(levels, seed, frames, kept);
    }
}

/// Truncations and byte flips of a change frame against an older base: both decoders
/// agree on each, and a failure changes nothing of the follower's.
#[test]
fn damaged_frames_decode_as_the_reference_does() {
    let grid = Grid::new(6).expect("valid");
    let h = heights(&grid, 7, 1);
    let mut rng = Rng(7);
    let mut both = Both::new(grid, 1 << 12);
    let a = closed_set(&grid, &mut rng, 15);
    let mut key = Vec::new();
    MeshEncoder::new(grid)
        .encode(&a, &h, None, &mut key)
        .expect("a conforming set");
    both.decode(0, &key, None, &h).expect("the key frame");
    // Frame 1 moves on; the damaged frames are coded against frame 0.
    let mut b = a.clone();
    for _ in 0..5 {
        toggle(&grid, &mut b, &mut rng, (0, 0, grid.side()));
    }
    both.decode(1, &encode(&grid, &h, 1, &a, &b, 1), Some(0), &h)
        .expect("decodes");
    let mut now = b.clone();
    for _ in 0..6 {
        toggle(&grid, &mut now, &mut rng, (0, 0, grid.side()));
    }
    let bytes = encode(&grid, &h, 1, &a, &now, 2);
    let mut frame = 2;
    let mut decoded = 0;
    let mut inputs: Vec<Vec<u8>> = (0..bytes.len()).map(|n| bytes[..n].to_vec()).collect();
    for at in 0..bytes.len() {
        for x in [1u8, 2, 4, 8, 16, 32, 64, 128, 255] {
            let mut bad = bytes.clone();
            bad[at] ^= x;
            inputs.push(bad);
        }
    }
    for input in &inputs {
        if both.decode(frame, input, Some(0), &h).is_ok() {
            decoded += 1;
            frame += 1;
        }
    }
    assert!(decoded < inputs.len() / 2, "{decoded} of {}", inputs.len());
    both.decode(frame, &bytes, Some(0), &h)
        .expect("the payload itself");
}

/// What the follower refuses: a base it does not hold, a frame not after the newest, a
/// delta before any key frame.
#[test]
fn bases_not_held_and_old_frames_are_refused() {
    let grid = Grid::new(5).expect("valid");
    let h = heights(&grid, 9, 1);
    let mut rng = Rng(9);
    let a = closed_set(&grid, &mut rng, 6);
    let mut key = Vec::new();
    MeshEncoder::new(grid)
        .encode(&a, &h, None, &mut key)
        .expect("a conforming set");
    let mut f = Follower::new(grid, 2);
    let change = encode(&grid, &h, 1, &a, &a, 1);
    let check = |f: &mut Follower, frame: u64, payload: &[u8], base: Option<u64>, ok: bool| {
        let got = f.decode(frame, payload, base, u32::MAX);
        assert_eq!(got.is_ok(), ok, "frame {frame} against {base:?}: {got:?}");
        if !ok {
            assert_eq!(got, Err(DecodeError::Base));
        }
    };
    check(&mut f, 3, &change, Some(2), false);
    check(&mut f, 3, &key, None, true);
    check(&mut f, 3, &key, None, false);
    check(&mut f, 2, &change, Some(3), false);
    check(&mut f, 4, &change, Some(3), true);
    check(&mut f, 5, &change, Some(4), true);
    // Two bases kept: frame 3 is gone.
    assert!(!f.has_base(3) && f.has_base(4) && f.has_base(5));
    check(&mut f, 6, &change, Some(3), false);
    check(&mut f, 6, &key, Some(5), false);
    assert_eq!(f.frame(), Some(5));
}

/// Memory follows the cut, not the grid: on 4097² (a bitset of the grid is 2 MiB, and the
/// reference kept one per base) a drive through a cut of 4,700 diamonds holds a quarter of
/// one such bitset, its 32 bases included.
#[test]
fn memory_is_proportional_to_the_cut() {
    let grid = Grid::new(12).expect("valid");
    let h = heights(&grid, 11, 1);
    let mut rng = Rng(11);
    let mut now = closed_set(&grid, &mut rng, 40);
    let mut key = Vec::new();
    MeshEncoder::new(grid)
        .encode(&now, &h, None, &mut key)
        .expect("a conforming set");
    let mut f = Follower::new(grid, 32);
    let mut live = LiveMesh::new(&grid);
    f.decode(0, &key, None, u32::MAX).expect("the key frame");
    let mut base = now.clone();
    for frame in 1..200u64 {
        for _ in 0..8 {
            toggle(&grid, &mut now, &mut rng, (1000, 1000, 512));
        }
        let payload = encode(&grid, &h, 1, &base, &now, frame);
        f.decode(frame, &payload, Some(frame - 1), u32::MAX)
            .expect("decodes");
        live.update(&grid, f.toggled(), |i| f.contains(i));
        base = now.clone();
    }
    let splits = now.len();
    let bytes = f.bytes() + live.bytes();
    println!(
        "{splits} splits: follower {} B, live mesh {} B",
        f.bytes(),
        live.bytes()
    );
    assert!(
        bytes < 200 * splits + 64 * 1024,
        "{bytes} B for {splits} splits"
    );
    assert!(bytes < grid.vertices() / 8 / 4, "{bytes} B");
}
