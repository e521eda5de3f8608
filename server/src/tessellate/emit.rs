//! Writing a frame's mesh: vertices by rank in the active bitset, triangles by a walk of
//! the bintree.

use super::{Mesh, Tessellator};

impl Tessellator {
    /// Writes the mesh: vertices are the corners and the split diamonds' centres, indexed by
    /// rank in the active bitset; triangles in depth-first order of the bintree.
    pub(super) fn emit(&mut self, out: &mut Mesh) {
        let s = self.size;
        for (x, z) in [(0, 0), (s, 0), (0, s), (s, s)] {
            self.set_active(x, z);
        }
        out.vertices.clear();
        let mut total = 0u32;
        let side = self.side as usize;
        let (mut z, mut row_start) = (0usize, 0usize);
        for (w, (&word, rank)) in self.active.iter().zip(self.rank.iter_mut()).enumerate() {
            *rank = total;
            total += word.count_ones();
            let mut bits = word;
            while bits != 0 {
                let i = w * 64 + bits.trailing_zeros() as usize;
                bits &= bits - 1;
                while i >= row_start + side {
                    z += 1;
                    row_start += side;
                }
                out.vertices.push([(i - row_start) as u16, z as u16]);
            }
        }
        // Depth-first over the bintree with an explicit stack. Vertices are row-major
        // indices: a split triangle's hypotenuse has even coordinate sums, so its midpoint
        // is the mean of the ends' indices. Each child is written both to the stack and to
        // the output, and the one that applies advances: no unpredictable branch.
        let n = 3 * self.triangles as usize;
        // Room for one speculative write past the last triangle. Every slot up to `n` is
        // overwritten, so only growth since the last frame needs initialising.
        if out.indices.len() < n + 3 {
            out.indices.resize(n + 3, 0);
        } else {
            out.indices.truncate(n + 3);
        }
        let leaf_depth = 2 * s.trailing_zeros();
        let mut stack = [[0u32; 7]; 2 * 16 + 4];
        let (mut sp, mut k) = (0usize, 0usize);
        let sd = self.side;
        let (nw, ne, sw, se) = (0, s, s * sd, s * sd + s);
        let (rnw, rne, rsw, rse) = (
            self.rank_at(nw),
            self.rank_at(ne),
            self.rank_at(sw),
            self.rank_at(se),
        );
        for t in [
            [ne, nw, se, rne, rnw, rse, 0],
            [sw, se, nw, rsw, rse, rnw, 0],
        ] {
            self.visit(&mut stack, &mut sp, &mut out.indices, &mut k, t, leaf_depth);
        }
        while sp > 0 {
            sp -= 1;
            let [a, l, r, ra, rl, rr, d] = stack[sp];
            let m = (l + r) / 2;
            let rm = self.rank_at(m);
            self.visit(
                &mut stack,
                &mut sp,
                &mut out.indices,
                &mut k,
                [m, r, a, rm, rr, ra, d + 1],
                leaf_depth,
            );
            self.visit(
                &mut stack,
                &mut sp,
                &mut out.indices,
                &mut k,
                [m, a, l, rm, ra, rl, d + 1],
                leaf_depth,
            );
        }
        debug_assert_eq!(k, n, "every triangle counted is emitted");
        out.indices.truncate(k);
    }

    /// Pushes triangle `t = [apex, left, right, ranks…, depth]` if it is split, else emits
    /// it; both slots are written, only one cursor moves.
    #[inline(always)]
    fn visit(
        &self,
        stack: &mut [[u32; 7]],
        sp: &mut usize,
        out: &mut [u32],
        k: &mut usize,
        t: [u32; 7],
        leaf_depth: u32,
    ) {
        let m = ((t[1] + t[2]) / 2) as usize;
        let split = (t[6] < leaf_depth) & (self.active[m >> 6] >> (m & 63) & 1 != 0);
        stack[*sp] = t;
        *sp += usize::from(split);
        out[*k..*k + 3].copy_from_slice(&t[3..6]);
        *k += 3 * usize::from(!split);
    }

    #[inline(always)]
    fn rank_at(&self, i: u32) -> u32 {
        let i = i as usize;
        self.rank[i >> 6] + (self.active[i >> 6] & ((1u64 << (i & 63)) - 1)).count_ones()
    }
}
