//! A cut's hash, [`CutHash`]: order-independent, kept change by change at both ends (the
//! server's per-viewer core and the viewer's decoder), and carried by every change frame.

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
