//! The triangle bintree of a `2^N + 1` grid, diamond by diamond, without allocating: where
//! its geometry is defined, for the codec, the variance tree and the tessellators alike
//! (a few hot paths, such as the tessellator's branchless parents and its output pass,
//! work parts of it out inline).
//!
//! Grid coordinates run `0..=size` (`size = 2^N`); `x` is the column (east), `z` the row
//! (south). Splitting a bintree triangle bisects its hypotenuse; the two triangles sharing
//! a hypotenuse form a diamond, named by its centre (the hypotenuse's midpoint); every
//! grid vertex but the four corners is the centre of exactly one diamond, so a split-only
//! mesh is a set of split diamonds, closed under "parent". With half-size `h = 2^m`, a
//! diamond is a *square* (`x ≡ z ≡ h mod 2h`: its triangles halve a `2h` cell, cut along
//! one diagonal, which alternates cell by cell) or *rotated* (its hypotenuse is an
//! axis-aligned cell edge; on the map's boundary it has one triangle). A diamond's parents
//! are its triangles' apices; its hypotenuse ends are its other two corners. The root is
//! the square at the map's centre: its two triangles share the NW–SE diagonal and have no
//! parents.
//!
//! **Depth**: the root square (`m = N − 1`) is depth 0; the rotated diamonds of level `m`
//! come right after the squares of level `m`, and the squares of level `m − 1` after them.
//! A diamond's parents are all one depth up, which is what the codec's level-by-level
//! traversal rests on.
//!
//! By coordinates: [`shape_of`], [`parents`], [`children`], [`hypotenuse`] and [`added`]
//! (what the tessellators' hot loops call), and [`Grid`]'s methods over them (indices,
//! depths, forced splits). By name: a [`Diamond`] and its [`Triangle`]s (the variance tree
//! and the tests).

/// Grid vertex `(x, z)`.
pub type Vertex = (u32, u32);

/// The two diamond shapes; see the module docs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Shape {
    Square,
    /// Hypotenuse along `x` (`horizontal`) or along `z`.
    Rotated {
        horizontal: bool,
    },
}

/// Level `m` (`h = 2^m`) and shape of the diamond centred at `(x, z)` (not a corner).
#[inline(always)]
pub fn shape_of(x: u32, z: u32) -> (u32, Shape) {
    let (tx, tz) = (x.trailing_zeros(), z.trailing_zeros());
    if tx == tz {
        (tx, Shape::Square)
    } else {
        (
            tx.min(tz),
            Shape::Rotated {
                horizontal: tx < tz,
            },
        )
    }
}

/// The parents of the diamond centred at `(x, z)` on a map of side `size + 1`: none for
/// the root, one for a rotated diamond on the map's edge.
#[inline]
pub fn parents(size: u32, x: u32, z: u32) -> [Option<Vertex>; 2] {
    let (m, shape) = shape_of(x, z);
    let h = 1 << m;
    match shape {
        Shape::Square if 2 * h == size => [None, None],
        Shape::Square => {
            if (((x + h) >> (m + 1)) + ((z + h) >> (m + 1))) & 1 == 1 {
                [Some((x + h, z + h)), Some((x - h, z - h))]
            } else {
                [Some((x + h, z - h)), Some((x - h, z + h))]
            }
        }
        // Hypotenuse along x: apices north and south.
        Shape::Rotated { horizontal: true } => [
            (z >= h).then(|| (x, z - h)),
            (z + h <= size).then(|| (x, z + h)),
        ],
        Shape::Rotated { horizontal: false } => [
            (x >= h).then(|| (x - h, z)),
            (x + h <= size).then(|| (x + h, z)),
        ],
    }
}

/// Triangles splitting the diamond centred at `(x, z)` adds to a mesh: two (its two
/// triangles become four), or one for a rotated diamond on the map's edge (one triangle,
/// one parent).
#[inline]
pub fn added(size: u32, x: u32, z: u32) -> u32 {
    match shape_of(x, z).1 {
        Shape::Square => 2,
        Shape::Rotated { .. } => parents(size, x, z).iter().flatten().count() as u32,
    }
}

/// The parent of `child` other than `parent` (one of its [`parents`]) on a map of side
/// `size + 1`: `parent` mirrored through the child (a diamond's two parents lie on either
/// side of it at the same distance), or none where that falls off the map (a rotated
/// diamond on the map's edge). No look-up of the parents' shapes: the codec and the
/// frontiers ask it for every child of a cut.
#[inline]
pub fn other_parent(size: u32, parent: Vertex, child: Vertex) -> Option<Vertex> {
    let x = 2 * i64::from(child.0) - i64::from(parent.0);
    let z = 2 * i64::from(child.1) - i64::from(parent.1);
    let on = |v: i64| (0..=i64::from(size)).contains(&v);
    (on(x) && on(z)).then_some((x as u32, z as u32))
}

/// The hypotenuse ends of the diamond centred at `(x, z)`: the corners that are not its
/// parents.
#[inline]
pub fn hypotenuse(x: u32, z: u32) -> [Vertex; 2] {
    let (m, shape) = shape_of(x, z);
    let h = 1 << m;
    match shape {
        Shape::Square => {
            if (((x + h) >> (m + 1)) + ((z + h) >> (m + 1))) & 1 == 1 {
                [(x + h, z - h), (x - h, z + h)]
            } else {
                [(x - h, z - h), (x + h, z + h)]
            }
        }
        Shape::Rotated { horizontal: true } => [(x - h, z), (x + h, z)],
        Shape::Rotated { horizontal: false } => [(x, z - h), (x, z + h)],
    }
}

/// The children on the map of the diamond centred at `(x, z)` (a square's four rotated
/// ones, a rotated diamond's squares below; none at the finest rotated level).
#[inline]
pub fn children(size: u32, x: u32, z: u32) -> [Option<Vertex>; 4] {
    let (m, shape) = shape_of(x, z);
    let h = 1 << m;
    match shape {
        Shape::Square => [
            Some((x + h, z)),
            Some((x - h, z)),
            Some((x, z + h)),
            Some((x, z - h)),
        ],
        Shape::Rotated { .. } if m == 0 => [None; 4],
        Shape::Rotated { .. } => {
            let k = i64::from(h / 2);
            let ok = |cx: i64, cz: i64| {
                (cx >= 0 && cz >= 0 && cx <= i64::from(size) && cz <= i64::from(size))
                    .then_some((cx as u32, cz as u32))
            };
            let (x, z) = (i64::from(x), i64::from(z));
            [
                ok(x + k, z - k),
                ok(x - k, z - k),
                ok(x - k, z + k),
                ok(x + k, z + k),
            ]
        }
    }
}

/// Twice the signed area of `a, b, c` seen from above: positive when counter-clockwise with
/// `x` east and `z` south (the y component of `(b - a) × (c - a)`).
pub fn ccw(a: Vertex, b: Vertex, c: Vertex) -> i64 {
    let (ax, az) = (a.0 as i64, a.1 as i64);
    let (bx, bz) = (b.0 as i64 - ax, b.1 as i64 - az);
    let (cx, cz) = (c.0 as i64 - ax, c.1 as i64 - az);
    bz * cx - bx * cz
}

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
        let (m, shape) = shape_of(x, z);
        (m.min(self.levels), shape == Shape::Square)
    }

    /// Depth of the diamond centred at `(x, z)`: 0 for the root.
    pub fn depth(&self, x: u32, z: u32) -> u32 {
        let (m, square) = self.classify(x, z);
        2 * (self.levels - 1 - m) + u32::from(!square)
    }

    /// The diamond's parents (none for the root; one for a rotated diamond on the map's
    /// edge): [`parents`].
    #[inline]
    pub fn parents(&self, x: u32, z: u32) -> [Option<(u32, u32)>; 2] {
        parents(self.size, x, z)
    }

    /// Triangles splitting the diamond centred at `(x, z)` adds to a mesh: [`added`].
    #[inline]
    pub fn added(&self, x: u32, z: u32) -> u32 {
        added(self.size, x, z)
    }

    /// The diamond's hypotenuse ends: [`hypotenuse`].
    #[inline]
    pub fn hypotenuse(&self, x: u32, z: u32) -> [(u32, u32); 2] {
        hypotenuse(x, z)
    }

    /// The diamond's children on the map: [`children`].
    #[inline]
    pub fn children(&self, x: u32, z: u32) -> [Option<(u32, u32)>; 4] {
        children(self.size, x, z)
    }

    /// The parent of `child` other than `parent`: [`other_parent`].
    #[inline]
    pub fn other_parent(&self, parent: (u32, u32), child: (u32, u32)) -> Option<(u32, u32)> {
        other_parent(self.size, parent, child)
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

/// A bintree triangle: right angle at `apex`, hypotenuse from `left` to `right`, and
/// `apex → left → right` counter-clockwise seen from above (+Y), so face normals point up.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Triangle {
    pub apex: Vertex,
    pub left: Vertex,
    pub right: Vertex,
}

impl Triangle {
    /// The two root triangles of a `size × size` map.
    pub fn roots(size: u32) -> [Triangle; 2] {
        [
            Triangle {
                apex: (size, 0),
                left: (0, 0),
                right: (size, size),
            },
            Triangle {
                apex: (0, size),
                left: (size, size),
                right: (0, 0),
            },
        ]
    }

    /// Midpoint of the hypotenuse, if it is a grid vertex (else the triangle is a leaf of the
    /// full-resolution bintree).
    pub fn split_vertex(&self) -> Option<Vertex> {
        let (sx, sz) = (self.left.0 + self.right.0, self.left.1 + self.right.1);
        (sx % 2 == 0 && sz % 2 == 0).then_some((sx / 2, sz / 2))
    }

    /// The two halves, in bintree order (left child first). `None` at full resolution.
    pub fn children(&self) -> Option<[Triangle; 2]> {
        let m = self.split_vertex()?;
        Some([
            Triangle {
                apex: m,
                left: self.apex,
                right: self.left,
            },
            Triangle {
                apex: m,
                left: self.right,
                right: self.apex,
            },
        ])
    }

    /// The triangle's vertices in counter-clockwise order.
    pub fn vertices(&self) -> [Vertex; 3] {
        [self.apex, self.left, self.right]
    }
}

/// A diamond, named by its centre: the geometry above, by name.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Diamond {
    pub x: u32,
    pub z: u32,
    /// `h = 2^m`.
    pub m: u32,
    pub shape: Shape,
}

impl Diamond {
    /// The diamond centred at `(x, z)` on a `size × size` map; `None` for corners and
    /// points outside the map.
    pub fn at(x: u32, z: u32, size: u32) -> Option<Diamond> {
        if x > size || z > size || (x.is_multiple_of(size) && z.is_multiple_of(size)) {
            return None;
        }
        let (m, shape) = shape_of(x, z);
        Some(Diamond { x, z, m, shape })
    }

    pub fn h(&self) -> u32 {
        1 << self.m
    }

    /// Depth in the bintree of the diamond's triangles (the root diamond is 0, the finest
    /// diamonds `2N - 1`): [`Grid::depth`].
    pub fn depth(&self, size: u32) -> u32 {
        let grid = Grid {
            levels: size.trailing_zeros(),
            size,
        };
        grid.depth(self.x, self.z)
    }

    /// Whether this is the map's root diamond.
    pub fn is_root(&self, size: u32) -> bool {
        self.shape == Shape::Square && self.h() * 2 == size
    }

    /// Centres of the parent diamonds (the apices of its triangles), those that exist.
    pub fn parents(&self, size: u32) -> [Option<Vertex>; 2] {
        parents(size, self.x, self.z)
    }

    /// Ends of the shared hypotenuse.
    pub fn hypotenuse(&self) -> [Vertex; 2] {
        hypotenuse(self.x, self.z)
    }

    /// The diamond's triangles (one on the map's boundary, else two), counter-clockwise.
    pub fn triangles(&self, size: u32) -> [Option<Triangle>; 2] {
        let [p, q] = self.hypotenuse();
        let apices = if self.is_root(size) {
            [Some((size, 0)), Some((0, size))]
        } else {
            self.parents(size)
        };
        apices.map(|apex| {
            let apex = apex?;
            Some(if ccw(apex, p, q) > 0 {
                Triangle {
                    apex,
                    left: p,
                    right: q,
                }
            } else {
                Triangle {
                    apex,
                    left: q,
                    right: p,
                }
            })
        })
    }

    /// Centres of the child diamonds that exist (four inside the map, fewer on its edge,
    /// none at full resolution).
    pub fn children(&self, size: u32) -> [Option<Vertex>; 4] {
        children(size, self.x, self.z)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_non_corner_vertex_is_one_diamond() {
        let size = 16;
        let mut count = 0;
        for z in 0..=size {
            for x in 0..=size {
                match Diamond::at(x, z, size) {
                    None => assert!(x.is_multiple_of(size) && z.is_multiple_of(size)),
                    Some(d) => {
                        count += 1;
                        // Its triangles are children of its parents' triangles and split at
                        // its centre.
                        for t in d.triangles(size).into_iter().flatten() {
                            assert_eq!(t.split_vertex(), Some((x, z)), "{d:?}");
                            assert!(ccw(t.apex, t.left, t.right) > 0);
                        }
                        for p in d.parents(size).into_iter().flatten() {
                            let pd = Diamond::at(p.0, p.1, size).expect("parents are diamonds");
                            assert!(pd.children(size).contains(&Some((x, z))), "{pd:?} -> {d:?}");
                            assert_eq!(pd.depth(size) + 1, d.depth(size));
                        }
                        for c in d.children(size).into_iter().flatten() {
                            let cd = Diamond::at(c.0, c.1, size).expect("children are diamonds");
                            assert!(cd.parents(size).contains(&Some((x, z))));
                        }
                    }
                }
            }
        }
        assert_eq!(count, 17 * 17 - 4);
    }

    #[test]
    fn triangles_of_a_diamond_are_children_of_its_parents_triangles() {
        let size = 16;
        // Walk the bintree from the roots; every triangle must be one of its diamond's.
        let mut stack = Triangle::roots(size).to_vec();
        let mut seen = 0;
        while let Some(t) = stack.pop() {
            if let Some(m) = t.split_vertex() {
                let d = Diamond::at(m.0, m.1, size).expect("split vertices are diamonds");
                assert!(d.triangles(size).contains(&Some(t)), "{t:?} not in {d:?}");
                seen += 1;
                stack.extend(t.children().expect("split vertex exists"));
            }
        }
        // Interior triangles of a full bintree of depth 2N: 2 * (4^N - 1).
        assert_eq!(seen, 2 * (256 - 1));
    }
}
