//! The triangle bintree of a `2^N + 1` grid, diamond by diamond, without allocating.
//!
//! Grid coordinates run `0..=size` (`size = 2^N`); `x` is the column, `z` the row. The two
//! triangles sharing a hypotenuse form a diamond, named by its centre (the hypotenuse's
//! midpoint); every grid vertex but the four corners is the centre of exactly one diamond,
//! so a split-only mesh is a set of split diamonds, closed under "parent". With half-size
//! `h = 2^m`, a diamond is a *square* (`x ≡ z ≡ h mod 2h`: its triangles halve a `2h` cell)
//! or *rotated* (its hypotenuse is an axis-aligned cell edge). A diamond's parents are the
//! centres of its triangles' apices; its hypotenuse ends are its other two corners.
//!
//! **Depth**: the root square (`m = N − 1`) is depth 0; the rotated diamonds of level `m`
//! come right after the squares of level `m`, and the squares of level `m − 1` after them.
//! A diamond's parents are all one depth up, which is what the codec's level-by-level
//! traversal rests on.

/// A `2^N + 1` grid.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Grid {
    levels: u32,
    size: u32,
}

/// The largest `N`: coordinates stay within `u16`.
pub const MAX_LEVELS: u32 = 15;

impl Grid {
    /// The grid of side `2^levels + 1`, for `1 ≤ levels ≤ MAX_LEVELS`.
    pub fn new(levels: u32) -> Option<Grid> {
        (1..=MAX_LEVELS).contains(&levels).then_some(Grid {
            levels,
            size: 1 << levels,
        })
    }

    pub fn levels(&self) -> u32 {
        self.levels
    }

    /// `side − 1`.
    pub fn size(&self) -> u32 {
        self.size
    }

    pub fn side(&self) -> u32 {
        self.size + 1
    }

    /// Grid vertices.
    pub fn vertices(&self) -> usize {
        self.side() as usize * self.side() as usize
    }

    /// Depths: `2N` (a square and a rotated depth per level).
    pub fn depths(&self) -> u32 {
        2 * self.levels
    }

    /// Row-major index of `(x, z)`.
    #[inline]
    pub fn index(&self, x: u32, z: u32) -> u32 {
        z * self.side() + x
    }

    /// `(x, z)` of a row-major index.
    #[inline]
    pub fn coords(&self, i: u32) -> (u32, u32) {
        (i % self.side(), i / self.side())
    }

    /// The root diamond's centre.
    pub fn root(&self) -> (u32, u32) {
        (self.size / 2, self.size / 2)
    }

    /// The four corners, row-major.
    pub fn corners(&self) -> [(u32, u32); 4] {
        let s = self.size;
        [(0, 0), (s, 0), (0, s), (s, s)]
    }

    /// Level `m` and squareness of the diamond centred at `(x, z)` (not a corner).
    #[inline]
    pub fn classify(&self, x: u32, z: u32) -> (u32, bool) {
        let (tx, tz) = (x.trailing_zeros(), z.trailing_zeros());
        (tx.min(tz).min(self.levels), tx == tz)
    }

    /// Depth of the diamond centred at `(x, z)`: 0 for the root.
    pub fn depth(&self, x: u32, z: u32) -> u32 {
        let (m, square) = self.classify(x, z);
        2 * (self.levels - 1 - m) + u32::from(!square)
    }

    /// The diamond's parents (none for the root; one for a rotated diamond on the map's
    /// edge).
    #[inline]
    pub fn parents(&self, x: u32, z: u32) -> [Option<(u32, u32)>; 2] {
        let (m, square) = self.classify(x, z);
        let h = 1 << m;
        let s = self.size;
        if square {
            if 2 * h == s {
                return [None, None];
            }
            if (((x + h) >> (m + 1)) + ((z + h) >> (m + 1))) & 1 == 1 {
                [Some((x + h, z + h)), Some((x - h, z - h))]
            } else {
                [Some((x + h, z - h)), Some((x - h, z + h))]
            }
        } else if x.trailing_zeros() < z.trailing_zeros() {
            // Hypotenuse along x: apices north and south.
            [
                (z >= h).then(|| (x, z - h)),
                (z + h <= s).then(|| (x, z + h)),
            ]
        } else {
            [
                (x >= h).then(|| (x - h, z)),
                (x + h <= s).then(|| (x + h, z)),
            ]
        }
    }

    /// Triangles splitting the diamond centred at `(x, z)` adds to a mesh: two (its two
    /// triangles become four), or one for a rotated diamond on the map's edge (one
    /// triangle, one parent).
    #[inline]
    pub fn added(&self, x: u32, z: u32) -> u32 {
        if self.classify(x, z).1 {
            2
        } else {
            self.parents(x, z).iter().flatten().count() as u32
        }
    }

    /// The diamond's hypotenuse ends: the corners that are not its parents.
    #[inline]
    pub fn hypotenuse(&self, x: u32, z: u32) -> [(u32, u32); 2] {
        let (m, square) = self.classify(x, z);
        let h = 1 << m;
        if square {
            if (((x + h) >> (m + 1)) + ((z + h) >> (m + 1))) & 1 == 1 {
                [(x + h, z - h), (x - h, z + h)]
            } else {
                [(x - h, z - h), (x + h, z + h)]
            }
        } else if x.trailing_zeros() < z.trailing_zeros() {
            [(x - h, z), (x + h, z)]
        } else {
            [(x, z - h), (x, z + h)]
        }
    }

    /// The diamond's children on the map (a square's four rotated ones, a rotated
    /// diamond's squares below; none at the finest rotated level).
    #[inline]
    pub fn children(&self, x: u32, z: u32) -> [Option<(u32, u32)>; 4] {
        let (m, square) = self.classify(x, z);
        let h = 1 << m;
        let s = self.size;
        if square {
            return [
                Some((x + h, z)),
                Some((x - h, z)),
                Some((x, z + h)),
                Some((x, z - h)),
            ];
        }
        if m == 0 {
            return [None; 4];
        }
        let k = h / 2;
        let ok = |cx: i64, cz: i64| {
            (cx >= 0 && cz >= 0 && cx <= i64::from(s) && cz <= i64::from(s))
                .then_some((cx as u32, cz as u32))
        };
        let (x, z, k) = (i64::from(x), i64::from(z), i64::from(k));
        [
            ok(x + k, z - k),
            ok(x - k, z - k),
            ok(x - k, z + k),
            ok(x + k, z + k),
        ]
    }
}

impl Grid {
    /// Splits the diamond centred at `(x, z)` in `set`, and first every ancestor not yet
    /// split (a forced split), so `set` stays closed under parent. Corners and points off
    /// the grid are ignored. Recursion is as deep as the bintree (`2N`).
    pub fn split_closed(&self, set: &mut BitSet, x: u32, z: u32) {
        let corner = x.is_multiple_of(self.size) && z.is_multiple_of(self.size);
        if corner || x > self.size || z > self.size || set.contains(self.index(x, z)) {
            return;
        }
        for (px, pz) in self.parents(x, z).into_iter().flatten() {
            self.split_closed(set, px, pz);
        }
        set.insert(self.index(x, z));
    }
}

/// A set of grid vertices (split diamonds, or vertices a viewer holds), one bit each.
#[derive(Debug, Default, PartialEq, Eq)]
pub struct BitSet {
    words: Vec<u64>,
}

impl Clone for BitSet {
    fn clone(&self) -> BitSet {
        BitSet {
            words: self.words.clone(),
        }
    }

    /// Copies `source` into this set's memory (no allocation when it is large enough).
    fn clone_from(&mut self, source: &BitSet) {
        self.words.clone_from(&source.words);
    }
}

impl BitSet {
    pub fn new(bits: usize) -> BitSet {
        BitSet {
            words: vec![0; bits.div_ceil(64)],
        }
    }

    /// The set whose members are the set bits of `words` (bit `i % 64` of word `i / 64`),
    /// taking them without a copy.
    pub fn from_words(words: Vec<u64>) -> BitSet {
        BitSet { words }
    }

    /// The words back, without a copy.
    pub fn into_words(self) -> Vec<u64> {
        self.words
    }

    /// Empties the set and sizes it for `bits`, keeping its memory.
    pub fn reset(&mut self, bits: usize) {
        self.words.clear();
        self.words.resize(bits.div_ceil(64), 0);
    }

    #[inline]
    pub fn contains(&self, i: u32) -> bool {
        self.words
            .get(i as usize >> 6)
            .is_some_and(|w| w >> (i & 63) & 1 != 0)
    }

    #[inline]
    pub fn insert(&mut self, i: u32) {
        if let Some(w) = self.words.get_mut(i as usize >> 6) {
            *w |= 1 << (i & 63);
        }
    }

    #[inline]
    pub fn remove(&mut self, i: u32) {
        if let Some(w) = self.words.get_mut(i as usize >> 6) {
            *w &= !(1 << (i & 63));
        }
    }

    pub fn len(&self) -> usize {
        self.words.iter().map(|w| w.count_ones() as usize).sum()
    }

    pub fn is_empty(&self) -> bool {
        self.words.iter().all(|&w| w == 0)
    }

    /// The words, 64 vertices each, row-major.
    pub fn words(&self) -> &[u64] {
        &self.words
    }

    /// Set bits in increasing order.
    pub fn iter(&self) -> impl Iterator<Item = u32> + '_ {
        set_bits(&self.words)
    }
}

/// The set bits of a row of words (bit `i % 64` of word `i / 64`), in increasing order: a
/// [`BitSet`]'s members, or any bitset laid out the same way.
pub fn set_bits(words: &[u64]) -> impl Iterator<Item = u32> + '_ {
    words.iter().enumerate().flat_map(|(w, &word)| {
        let mut bits = word;
        std::iter::from_fn(move || {
            if bits == 0 {
                return None;
            }
            let i = w as u32 * 64 + bits.trailing_zeros();
            bits &= bits - 1;
            Some(i)
        })
    })
}
