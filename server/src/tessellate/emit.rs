//! Writing a frame's mesh: vertices by rank in the active bitset, triangles diamond by
//! diamond.
//!
//! Every triangle of a split-only mesh is one of the four children of a split diamond (the
//! roots' children included: the root diamond is split first), and such a child is in the
//! mesh exactly when the diamond on its hypotenuse is not split. So one row-major scan of
//! the active bitset writes both lists: each set bit is a vertex (its rank is the running
//! count), and each split diamond writes those of its children that are leaves. No tree
//! walk, no stack.

use super::{Mesh, Tessellator};

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
        let corners = [(0, 0), (s, 0), (0, s), (s, s)].map(|(x, z)| (z * self.side + x) as usize);
        // The corners are vertices but not split diamonds: set for the ranks and the vertex
        // pass, cleared for the triangle pass.
        for c in corners {
            self.active[c >> 6] |= 1 << (c & 63);
        }
        let mut total = 0u64;
        for (slot, &word) in self.ranked.iter_mut().zip(&self.active) {
            *slot = [word, total];
            total += u64::from(word.count_ones());
        }
        let side = self.side as usize;
        // Every slot is overwritten, so only growth since the last frame is initialised.
        out.vertices.resize(total as usize, [0; 2]);
        for (v, (_, x, z)) in out
            .vertices
            .iter_mut()
            .zip(SetBits::new(&self.active, side))
        {
            *v = [x as u16, z as u16];
        }
        for c in corners {
            self.active[c >> 6] &= !(1 << (c & 63));
        }
        let ranked = Ranked {
            last: self.ranked.len() - 1,
            words: &self.ranked,
        };
        // Room for the speculative writes of one diamond past the last triangle.
        let n = 3 * self.triangles as usize;
        out.indices.resize(n + 12, 0);
        let mut k = 0usize;
        // A split diamond's own rank is the count of split diamonds before it, plus the
        // corners before it: (0, 0) always, (s, 0) after row 0, (0, s) in row s.
        let (row_end, last_row) = (s as usize, s as usize * side);
        for (r, (i, x, z)) in SetBits::new(&self.active, side).enumerate() {
            let rc = (r + 1 + usize::from(i > row_end) + usize::from(i > last_row)) as u32;
            let window: &mut [u32; 12] = (&mut out.indices[k..k + 12])
                .try_into()
                .expect("a slice of 12 is an array of 12");
            k += diamond(
                &ranked, window, s, self.side, x as u32, z as u32, i as u32, rc,
            );
        }
        if self.triangles == 2 {
            // Nothing split: the two roots, whose corners are ranks 0 to 3 (row-major).
            let (nw, ne, sw, se) = (0, 1, 2, 3);
            out.indices[..6].copy_from_slice(&[ne, nw, se, sw, se, nw]);
            k = 6;
        }
        debug_assert_eq!(k, n, "every triangle counted is emitted");
        out.indices.truncate(k);
    }
}

/// The set bits of a row-major bitset over rows of `side`, as `(i, x, z)`.
struct SetBits<'a> {
    words: &'a [u64],
    side: usize,
    /// Index of the current word; its bits not yet visited.
    w: usize,
    bits: u64,
    z: usize,
    row_start: usize,
}

impl<'a> SetBits<'a> {
    fn new(words: &'a [u64], side: usize) -> Self {
        SetBits {
            words,
            side,
            w: 0,
            bits: words.first().copied().unwrap_or(0),
            z: 0,
            row_start: 0,
        }
    }
}

impl Iterator for SetBits<'_> {
    type Item = (usize, usize, usize);

    #[inline(always)]
    fn next(&mut self) -> Option<(usize, usize, usize)> {
        while self.bits == 0 {
            self.w += 1;
            self.bits = *self.words.get(self.w)?;
        }
        let i = self.w * 64 + self.bits.trailing_zeros() as usize;
        self.bits &= self.bits - 1;
        while i >= self.row_start + self.side {
            self.z += 1;
            self.row_start += self.side;
        }
        Some((i, i - self.row_start, self.z))
    }
}

/// The active bitset beside each word's rank, read without bounds checks: every index
/// looked up is on the map (debug builds check).
struct Ranked<'a> {
    last: usize,
    words: &'a [[u64; 2]],
}

impl Ranked<'_> {
    #[inline(always)]
    fn word(&self, i: u32) -> [u64; 2] {
        debug_assert!(i as usize >> 6 <= self.last);
        // SAFETY: every index looked up is a grid vertex on the map (a split diamond's
        // centre, corner or child centre; off-map ones are never looked up), below
        // `side²`, and the words cover `side²` bits.
        unsafe { *self.words.get_unchecked(i as usize >> 6) }
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
/// vertex index `rc`) into `out`, counter-clockwise seen from above, and returns how many slots they took.
/// Each child is written in place; the cursor moves only past leaves.
///
/// Both shapes are one computation: a diamond's children fan around its centre between
/// consecutive corners `c0..c3` (square: NE, NW, SW, SE at distance `h` diagonally; rotated:
/// E, N, W, S at distance `h`), and child `k` is a leaf when the diamond at the midpoint of
/// `c_k c_(k+1)` is not split (at the finest level a rotated diamond's children are always
/// leaves). Only rotated diamonds on the map's edge, which lack corners, take another path.
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
    let (tx, tz) = (x.trailing_zeros(), z.trailing_zeros());
    let square = tx == tz;
    if !square && (x == 0 || x == size || z == 0 || z == size) {
        return edge(ranked, out, size, side, x, z, i, rc);
    }
    let m = tx.min(tz);
    let h = 1u32 << m;
    let dz = h * side;
    let (k, kz) = (h / 2, (h / 2) * side);
    // Corners: i + h - u, i - dz - v, i - h + u, i + dz + v.
    let (u, v) = if square { (dz, h) } else { (0, 0) };
    let c = [i + h - u, i - dz - v, i - h + u, i + dz + v];
    // Midpoints: i + a - b, i - c - d, i - a + b, i + c + d.
    let (ma, mb, mc, md) = if square {
        (0, dz, h, 0)
    } else {
        (k, kz, k, kz)
    };
    let mid = [i + ma - mb, i - mc - md, i - ma + mb, i + mc + md];
    let finest_rotated = !square && m == 0;
    let rank = [
        ranked.rank(c[0]),
        ranked.rank(c[1]),
        ranked.rank(c[2]),
        ranked.rank(c[3]),
    ];
    let mut n = 0;
    for j in 0..4 {
        out[n..n + 3].copy_from_slice(&[rc, rank[j], rank[(j + 1) & 3]]);
        let leaf = finest_rotated || !ranked.active(mid[j]);
        n += 3 * usize::from(leaf);
    }
    n
}

/// [`diamond`] for a rotated diamond centred on the map's edge: the corner off the map
/// stands in for itself, and the two children off the map are never leaves.
#[cold]
#[allow(clippy::too_many_arguments)]
fn edge(
    ranked: &Ranked,
    out: &mut [u32; 12],
    size: u32,
    side: u32,
    x: u32,
    z: u32,
    i: u32,
    rc: u32,
) -> usize {
    let m = x.trailing_zeros().min(z.trailing_zeros());
    let h = 1u32 << m;
    let dz = h * side;
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
    // Children's hypotenuse midpoints: squares of half-size h / 2 (none at the finest
    // level, where every child is a leaf).
    let (kx, kz) = (h / 2, (h / 2) * side);
    let leaf = |on: bool, mid: u32| on && (m == 0 || !ranked.active(mid));
    let t = [[re, rn], [rn, rw], [rw, rs], [rs, re]];
    let leaves = [
        leaf(he && hn, (i + kx).wrapping_sub(kz)),
        leaf(hn && hw, i.wrapping_sub(kx + kz)),
        leaf(hw && hs, (i + kz).wrapping_sub(kx)),
        leaf(hs && he, i + kx + kz),
    ];
    let mut k = 0;
    for (&[a, b], &is_leaf) in t.iter().zip(&leaves) {
        out[k..k + 3].copy_from_slice(&[rc, a, b]);
        k += 3 * usize::from(is_leaf);
    }
    k
}
