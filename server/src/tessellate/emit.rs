//! Writing a frame's mesh: vertices by rank in the active bitset, triangles diamond by
//! diamond.
//!
//! Every triangle of a split-only mesh is one of the four children of a split diamond (the
//! roots' children included: the root diamond is split first), and such a child is in the
//! mesh exactly when the diamond on its hypotenuse is not split. So one row-major scan of
//! the active bitset writes both lists: each set bit is a vertex (its rank is the running
//! count), and each split diamond writes those of its children that are leaves. No tree
//! walk, no stack.

use super::{Mesh, Tessellator, classify};
use crate::diamond::Shape;

impl Tessellator {
    /// Writes the mesh: vertices are the corners and the split diamonds' centres, indexed by
    /// rank in the active bitset (row-major); triangles by their diamond, row-major.
    pub(super) fn emit(&mut self, out: &mut Mesh) {
        #[cfg(target_arch = "x86_64")]
        if self.v3 {
            // SAFETY: `v3` is set only when the CPU supports these features.
            unsafe { self.emit_v3(out) };
            return;
        }
        self.emit_body(out);
    }

    /// [`Self::emit_body`] compiled for x86-64-v3 (`popcnt` for the ranks, BMI shifts).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,bmi1,bmi2,fma,lzcnt,popcnt")]
    fn emit_v3(&mut self, out: &mut Mesh) {
        self.emit_body(out);
    }

    #[inline(always)]
    fn emit_body(&mut self, out: &mut Mesh) {
        let s = self.size;
        for (x, z) in [(0, 0), (s, 0), (0, s), (s, s)] {
            self.set_active(x, z);
        }
        let mut total = 0u64;
        for (slot, &word) in self.ranked.iter_mut().zip(&self.active) {
            *slot = [word, total];
            total += u64::from(word.count_ones());
        }
        let ranked = Ranked {
            last: self.ranked.len() - 1,
            words: &self.ranked,
        };
        // Every slot is overwritten, so only growth since the last frame is initialised.
        out.vertices.resize(total as usize, [0; 2]);
        // Room for the speculative writes of one diamond past the last triangle.
        let n = 3 * self.triangles as usize;
        out.indices.resize(n + 12, 0);
        let side = self.side as usize;
        let (mut z, mut row_start) = (0usize, 0usize);
        let mut k = 0usize;
        let mut r = 0usize;
        for (w, &word) in self.active.iter().enumerate() {
            let mut bits = word;
            while bits != 0 {
                let i = w * 64 + bits.trailing_zeros() as usize;
                bits &= bits - 1;
                while i >= row_start + side {
                    z += 1;
                    row_start += side;
                }
                let x = i - row_start;
                out.vertices[r] = [x as u16, z as u16];
                let corner = (x == 0 || x == s as usize) && (z == 0 || z == s as usize);
                if !corner {
                    let window: &mut [u32; 12] = (&mut out.indices[k..k + 12])
                        .try_into()
                        .expect("a slice of 12 is an array of 12");
                    let rc = r as u32;
                    k += diamond(
                        &ranked, window, s, self.side, x as u32, z as u32, i as u32, rc,
                    );
                }
                r += 1;
            }
        }
        if !self.is_active(s / 2, s / 2) {
            // Nothing split: the two roots, whose corners are ranks 0 to 3 (row-major).
            let (nw, ne, sw, se) = (0, 1, 2, 3);
            out.indices[..6].copy_from_slice(&[ne, nw, se, sw, se, nw]);
            k = 6;
        }
        debug_assert_eq!(k, n, "every triangle counted is emitted");
        out.indices.truncate(k);
    }
}

/// The active bitset beside each word's rank. Indices are clamped to the last word (a
/// conditional move the compiler can see is in bounds): no bounds-check branches.
struct Ranked<'a> {
    last: usize,
    words: &'a [[u64; 2]],
}

impl Ranked<'_> {
    #[inline(always)]
    fn word(&self, i: u32) -> [u64; 2] {
        self.words[(i as usize >> 6).min(self.last)]
    }

    /// Vertex index of grid vertex `i` (set in the bitset): set bits before it.
    #[inline(always)]
    fn rank(&self, i: u32) -> u32 {
        let [bits, rank] = self.word(i);
        rank as u32 + (bits & ((1u64 << (i & 63)) - 1)).count_ones()
    }

    #[inline(always)]
    fn active(&self, i: u32) -> bool {
        self.word(i)[0] >> (i & 63) & 1 != 0
    }
}

/// Writes the leaf children of the split diamond centred at `(x, z)` (row-major index `i`,
/// rank `rc`) into `out`, counter-clockwise seen from above, and returns how many slots they
/// took. Each child is written in place; the cursor moves only past leaves.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn diamond(
    ranked: &Ranked,
    out: &mut [u32; 12],
    size: u32,
    side: u32,
    x: u32,
    z: u32,
    i: u32,
    rc: u32,
) -> usize {
    let (m, shape) = classify(x, z);
    let h = 1u32 << m;
    let dz = h * side;
    // The four children in turn, each given its hypotenuse ends' ranks and whether it is a
    // leaf. (Computed for off-map children too, hence wrapping; those are never leaves.)
    let (t, leaf) = match shape {
        Shape::Square => {
            let (nw, ne) = (i.wrapping_sub(dz + h), i - dz + h);
            let (sw, se) = (i + dz - h, i + dz + h);
            let (rnw, rne, rsw, rse) = (
                ranked.rank(nw),
                ranked.rank(ne),
                ranked.rank(sw),
                ranked.rank(se),
            );
            (
                [[rne, rnw], [rnw, rsw], [rsw, rse], [rse, rne]],
                [
                    !ranked.active(i - dz),
                    !ranked.active(i - h),
                    !ranked.active(i + dz),
                    !ranked.active(i + h),
                ],
            )
        }
        Shape::Rotated { .. } => {
            // Off the map (a diamond on the map's edge) a corner stands in for itself.
            let (hn, hs, hw, he) = (z >= h, z + h <= size, x >= h, x + h <= size);
            let n = if hn { i - dz } else { i };
            let so = if hs { i + dz } else { i };
            let w = if hw { i - h } else { i };
            let e = if he { i + h } else { i };
            let (rn, rs, rw, re) = (
                ranked.rank(n),
                ranked.rank(so),
                ranked.rank(w),
                ranked.rank(e),
            );
            // Children's hypotenuse midpoints: squares of half-size h / 2 (none at the
            // finest level, where every child is a leaf).
            let (kx, kz) = (h / 2, (h / 2) * side);
            let leaf = |on: bool, mid: u32| on && (m == 0 || !ranked.active(mid));
            (
                [[re, rn], [rn, rw], [rw, rs], [rs, re]],
                [
                    leaf(he && hn, (i + kx).wrapping_sub(kz)),
                    leaf(hn && hw, i.wrapping_sub(kx + kz)),
                    leaf(hw && hs, (i + kz).wrapping_sub(kx)),
                    leaf(hs && he, i + kx + kz),
                ],
            )
        }
    };
    let mut k = 0;
    for (&[a, b], &is_leaf) in t.iter().zip(&leaf) {
        out[k..k + 3].copy_from_slice(&[rc, a, b]);
        k += 3 * usize::from(is_leaf);
    }
    k
}
