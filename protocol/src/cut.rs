//! A decoded cut and its hash, shared by both mesh formats' decoders and the server's
//! per-viewer core: [`Cut`] (a split set, its triangles and its hash) and [`CutHash`] (an
//! order-independent hash kept change by change at both ends).

use crate::bintree::{BitSet, Grid};

/// An order-independent 64-bit hash of a split set with heights: the wrapping sum over the
/// split diamonds `i` of a 64-bit mix of `i << 16 | h_i`. Adding or removing one diamond is
/// O(1), so the server and the viewer keep it change by change; [`CutHash::of`] computes it
/// over a whole set.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct CutHash(pub(crate) u64);

impl CutHash {
    /// The hash of the empty set: 0.
    pub fn new() -> CutHash {
        CutHash(0)
    }

    /// Diamond `i`'s term: the SplitMix64 output function of `i << 16 | h`.
    #[inline]
    fn term(i: u32, h: u16) -> u64 {
        let mut z = (u64::from(i) << 16 | u64::from(h)).wrapping_add(0x9e37_79b9_7f4a_7c15);
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Diamond `i`, of height `h`, is split.
    #[inline]
    pub fn add(&mut self, i: u32, h: u16) {
        self.0 = self.0.wrapping_add(CutHash::term(i, h));
    }

    /// Diamond `i`, of height `h`, is merged (it was added with that height).
    #[inline]
    pub fn remove(&mut self, i: u32, h: u16) {
        self.0 = self.0.wrapping_sub(CutHash::term(i, h));
    }

    pub fn value(&self) -> u64 {
        self.0
    }

    /// The hash of the split set `split` of `grid` with the row-major `heights`, over the
    /// whole set (O(grid)).
    pub fn of(grid: &Grid, split: &BitSet, heights: &[u16]) -> CutHash {
        let mut hash = CutHash::new();
        for i in split.iter() {
            if (i as usize) < grid.vertices() {
                hash.add(i, heights.get(i as usize).copied().unwrap_or(0));
            }
        }
        hash
    }
}

/// A decoded cut, as a viewer keeps it per frame (a base later frames may be coded
/// against): its split diamonds, its triangle count and its [`CutHash`] value.
#[derive(Debug, Default, PartialEq, Eq)]
pub struct Cut {
    pub split: BitSet,
    pub triangles: u32,
    pub hash: u64,
}

impl Clone for Cut {
    fn clone(&self) -> Cut {
        Cut {
            split: self.split.clone(),
            triangles: self.triangles,
            hash: self.hash,
        }
    }

    /// Copies into this cut's memory.
    fn clone_from(&mut self, source: &Cut) {
        self.split.clone_from(&source.split);
        self.triangles = source.triangles;
        self.hash = source.hash;
    }
}

impl Cut {
    /// The cut of `split` (closed under parent) with the row-major `heights`, computed over
    /// the whole set (O(grid)).
    pub fn of(grid: &Grid, split: BitSet, heights: &[u16]) -> Cut {
        let triangles = split.iter().fold(2u32, |t, i| {
            let (x, z) = grid.coords(i);
            t.wrapping_add(grid.added(x, z))
        });
        let hash = CutHash::of(grid, &split, heights).value();
        Cut {
            split,
            triangles,
            hash,
        }
    }
}
