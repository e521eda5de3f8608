//! A decoded mesh: the triangles of a split set, in the order the server's tessellator
//! writes them, so the viewer's mesh equals the server's index for index.
//!
//! Vertices are the four corners and the split diamonds' centres, row-major; a vertex's
//! index is its rank. Every triangle is one of the four children of a split diamond, and is
//! in the mesh when the diamond on its hypotenuse is not split. Diamonds write their leaf
//! children in row-major order, each fanning around its centre between consecutive corners
//! (a square's NE, NW, SW, SE; a rotated diamond's E, N, W, S), counter-clockwise seen from
//! above.

use crate::bintree::{BitSet, Grid};
use crate::diamonds::DiamondMap;

/// Triangles over grid vertices, with heights.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Mesh {
    /// `[x, z]` grid coordinates, row-major.
    pub vertices: Vec<[u16; 2]>,
    /// Each vertex's height sample.
    pub heights: Vec<u16>,
    /// Three indices per triangle, counter-clockwise seen from above.
    pub indices: Vec<u32>,
}

impl Mesh {
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }
}

/// Words of the split set per rank block: a block's count is kept, the words within it are
/// counted at each lookup (at most 7 popcounts).
const BLOCK: usize = 8;

/// Ranks in the vertex set (split ∪ corners) without copying it: the split set's bits
/// before each block of [`BLOCK`] words, and the corners (never diamond centres, so never
/// split) counted apart. A frame used to clone the split set and keep a rank beside every
/// word: about 100 MB written a frame at 16385², most of the viewer's decode time there
/// (page faults); this keeps 4 bytes per 512 vertices.
struct Ranks<'s> {
    words: &'s [u64],
    blocks: Vec<u32>,
    corners: [u32; 4],
}

impl<'s> Ranks<'s> {
    fn new(split: &'s BitSet, corners: [u32; 4]) -> Ranks<'s> {
        let words = split.words();
        let mut before = 0u32;
        let blocks = words
            .chunks(BLOCK)
            .map(|chunk| {
                let r = before;
                before += chunk.iter().map(|w| w.count_ones()).sum::<u32>();
                r
            })
            .collect();
        Ranks {
            words,
            blocks,
            corners,
        }
    }

    fn rank(&self, i: u32) -> u32 {
        let w = i as usize >> 6;
        let b = w / BLOCK;
        let mut r = self.blocks[b];
        for bits in &self.words[b * BLOCK..w] {
            r += bits.count_ones();
        }
        r += (self.words[w] & ((1u64 << (i & 63)) - 1)).count_ones();
        r + self.corners.iter().filter(|&&c| c < i).count() as u32
    }
}

/// Writes the mesh of `split` (closed under parent) on `grid` into `out`, with heights from
/// the row-major `heights`.
pub fn emit(grid: &Grid, split: &BitSet, heights: &[u16], out: &mut Mesh) {
    out.vertices.clear();
    out.heights.clear();
    out.indices.clear();
    let mut corners = grid.corners().map(|(x, z)| grid.index(x, z));
    corners.sort_unstable();
    let ranks = Ranks::new(split, corners);
    // The vertices in index order: the split set's, with the corners merged in.
    let mut push = |i: u32| {
        let (x, z) = grid.coords(i);
        out.vertices.push([x as u16, z as u16]);
        out.heights
            .push(heights.get(i as usize).copied().unwrap_or(0));
    };
    let mut next_corner = 0;
    for i in split.iter() {
        while next_corner < 4 && corners[next_corner] < i {
            push(corners[next_corner]);
            next_corner += 1;
        }
        push(i);
    }
    for &c in &corners[next_corner..] {
        push(c);
    }
    if split.is_empty() {
        // The two roots; corners are ranks 0 to 3 (NW, NE, SW, SE).
        out.indices.extend_from_slice(&[1, 0, 3, 2, 3, 0]);
        return;
    }
    let s = grid.size();
    for i in split.iter() {
        let (x, z) = grid.coords(i);
        let (m, square) = grid.classify(x, z);
        let on =
            |(cx, cz): (i64, i64)| cx >= 0 && cz >= 0 && cx <= i64::from(s) && cz <= i64::from(s);
        let idx = |(cx, cz): (i64, i64)| grid.index(cx as u32, cz as u32);
        let (corner, mid) = layout(x, z, m, square);
        let rc = ranks.rank(i);
        // A corner off the map (a rotated diamond on the edge) stands in for itself; the
        // children next to it are off the map too and are skipped.
        let rank = corner.map(|c| if on(c) { ranks.rank(idx(c)) } else { rc });
        for j in 0..4 {
            let both_on = on(corner[j]) && on(corner[(j + 1) & 3]);
            let leaf = both_on && ((!square && m == 0) || !split.contains(idx(mid[j])));
            if leaf {
                out.indices
                    .extend_from_slice(&[rc, rank[j], rank[(j + 1) & 3]]);
            }
        }
    }
}

/// No triangle in this place of a [`LiveMesh`] slot.
pub const NO_TRIANGLE: [u32; 3] = [u32::MAX; 3];

/// Triangle places per slot: a split diamond's four children.
pub const SLOT_TRIANGLES: usize = 4;

/// The triangles of a cut kept up to date change by change: each split diamond owns a
/// *slot* of four triangle places (its children that are leaves; [`NO_TRIANGLE`] in the
/// others), slots freed by merged diamonds are reused, and the slots rewritten since the
/// last [`LiveMesh::take_dirty`] are listed, so a vertex buffer laid out by slot is
/// rewritten where the frame changed it and nowhere else. The root diamond is always slot
/// 0 (the two root triangles while it is not split).
///
/// Toggling diamond `d` changes the triangles of `d` and of its parents (whose children
/// are leaves or not by `d`'s state), nothing else: [`LiveMesh::update`] costs
/// O(toggles). The triangles are those [`emit`] writes, as grid indices, in slot order
/// rather than row-major.
#[derive(Clone, Debug, Default)]
pub struct LiveMesh {
    slot_of: DiamondMap<u32>,
    /// Each slot's diamond (`u32::MAX`: free).
    owner: Vec<u32>,
    free: Vec<u32>,
    /// [`SLOT_TRIANGLES`] per slot, grid indices, counter-clockwise seen from above.
    triangles: Vec<[u32; 3]>,
    count: usize,
    dirty: Vec<u32>,
    is_dirty: Vec<bool>,
    /// Scratch: the diamonds to rewrite.
    affected: DiamondMap<()>,
}

impl LiveMesh {
    /// The mesh of the empty cut of `grid`: the two root triangles.
    pub fn new(grid: &Grid) -> LiveMesh {
        let mut live = LiveMesh::default();
        let (x, z) = grid.root();
        live.owner.push(grid.index(x, z));
        live.triangles.resize(SLOT_TRIANGLES, NO_TRIANGLE);
        live.is_dirty.push(false);
        live.write(grid, 0, |_| false);
        live
    }

    /// Triangles in the mesh.
    pub fn triangle_count(&self) -> usize {
        self.count
    }

    /// Slots in use or free: the vertex buffer's extent is this many slots.
    pub fn slots(&self) -> usize {
        self.owner.len()
    }

    /// A slot's triangle places.
    pub fn slot(&self, slot: u32) -> &[[u32; 3]] {
        let at = slot as usize * SLOT_TRIANGLES;
        &self.triangles[at..at + SLOT_TRIANGLES]
    }

    /// The slot of diamond `d`'s triangles: split (or the root, always slot 0), `None`
    /// for a diamond not split.
    pub fn slot_of(&self, d: u32) -> Option<u32> {
        if self.owner.first() == Some(&d) {
            return Some(0);
        }
        self.slot_of.get(d)
    }

    /// Marks `slot` rewritten without changing it (its triangles' vertices moved: a
    /// drawing that places vertices by more than their heights, as a geomorph does).
    pub fn touch(&mut self, slot: u32) {
        let s = slot as usize;
        if s < self.is_dirty.len() && !self.is_dirty[s] {
            self.is_dirty[s] = true;
            self.dirty.push(slot);
        }
    }

    /// The triangles, in slot order.
    pub fn triangles(&self) -> impl Iterator<Item = [u32; 3]> + '_ {
        self.triangles.iter().copied().filter(|t| *t != NO_TRIANGLE)
    }

    /// Appends to `out` the slots rewritten since the last call, each once, and forgets
    /// them.
    pub fn take_dirty(&mut self, out: &mut Vec<u32>) {
        for &s in &self.dirty {
            self.is_dirty[s as usize] = false;
        }
        out.append(&mut self.dirty);
    }

    /// The protocol's [`Mesh`] of these triangles (vertices row-major, as [`emit`] lays
    /// them out; triangles in slot order), with heights from `height` (0 for a vertex it
    /// does not hold): O(cut), for checks and screenshots.
    pub fn to_mesh(&self, grid: &Grid, height: impl Fn(u32) -> Option<u16>) -> Mesh {
        let mut used: Vec<u32> = self.triangles().flatten().collect();
        used.sort_unstable();
        used.dedup();
        let rank = |i: u32| used.binary_search(&i).unwrap_or(0) as u32;
        Mesh {
            vertices: used
                .iter()
                .map(|&i| {
                    let (x, z) = grid.coords(i);
                    [x as u16, z as u16]
                })
                .collect(),
            heights: used.iter().map(|&i| height(i).unwrap_or(0)).collect(),
            indices: self.triangles().flatten().map(rank).collect(),
        }
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.slot_of.bytes()
            + self.affected.bytes()
            + 4 * (self.owner.capacity() + self.free.capacity() + self.dirty.capacity())
            + 12 * self.triangles.capacity()
            + self.is_dirty.capacity()
    }

    /// Follows a cut whose diamonds `toggled` changed state (each listed once): `split(i)`
    /// says whether diamond `i` is split now.
    pub fn update(
        &mut self,
        grid: &Grid,
        toggled: impl Iterator<Item = u32>,
        split: impl Fn(u32) -> bool,
    ) {
        let mut affected = std::mem::take(&mut self.affected);
        affected.clear();
        for d in toggled {
            affected.insert(d, ());
            let (x, z) = grid.coords(d);
            for (px, pz) in grid.parents(x, z).into_iter().flatten() {
                affected.insert(grid.index(px, pz), ());
            }
        }
        let root = self.owner[0];
        for (d, ()) in affected.iter() {
            if d == root {
                self.write(grid, 0, &split);
            } else if split(d) {
                let slot = match self.slot_of.get(d) {
                    Some(s) => s,
                    None => {
                        let s = self.free.pop().unwrap_or_else(|| {
                            self.owner.push(u32::MAX);
                            self.is_dirty.push(false);
                            self.triangles
                                .resize(self.owner.len() * SLOT_TRIANGLES, NO_TRIANGLE);
                            self.owner.len() as u32 - 1
                        });
                        self.owner[s as usize] = d;
                        self.slot_of.insert(d, s);
                        s
                    }
                };
                self.write(grid, slot, &split);
            } else if let Some(slot) = self.slot_of.remove(d) {
                self.owner[slot as usize] = u32::MAX;
                self.set(slot, [NO_TRIANGLE; SLOT_TRIANGLES]);
                self.free.push(slot);
            }
        }
        self.affected = affected;
    }

    /// Writes `slot`'s places, marking it dirty.
    fn set(&mut self, slot: u32, places: [[u32; 3]; SLOT_TRIANGLES]) {
        let at = slot as usize * SLOT_TRIANGLES;
        for (old, new) in self.triangles[at..at + SLOT_TRIANGLES]
            .iter_mut()
            .zip(places)
        {
            self.count -= usize::from(*old != NO_TRIANGLE);
            self.count += usize::from(new != NO_TRIANGLE);
            *old = new;
        }
        if !self.is_dirty[slot as usize] {
            self.is_dirty[slot as usize] = true;
            self.dirty.push(slot);
        }
    }

    /// Writes the leaf children of `slot`'s diamond (split, or the unsplit root).
    fn write(&mut self, grid: &Grid, slot: u32, split: impl Fn(u32) -> bool) {
        let i = self.owner[slot as usize];
        if slot == 0 && !split(i) {
            let [nw, ne, sw, se] = grid.corners().map(|(x, z)| grid.index(x, z));
            self.set(0, [[ne, nw, se], [sw, se, nw], NO_TRIANGLE, NO_TRIANGLE]);
            return;
        }
        let (corner, leaf) = children(grid, i, &split);
        let mut places = [NO_TRIANGLE; SLOT_TRIANGLES];
        for j in 0..4 {
            if let (Some(a), Some(b), true) = (corner[j], corner[(j + 1) & 3], leaf[j]) {
                places[j] = [i, a, b];
            }
        }
        self.set(slot, places);
    }
}

/// A grid position that may lie off the map.
type Point = (i64, i64);

/// The diamond centred at `(x, z)` (level `m`, square or not): its four corners in
/// [`emit`]'s order, and the midpoint of each edge between corner `j` and `j + 1` (the
/// centre of the child there), in grid coordinates that may lie off the map.
fn layout(x: u32, z: u32, m: u32, square: bool) -> ([Point; 4], [Point; 4]) {
    let (h, k) = (1i64 << m, (1i64 << m) / 2);
    let (xi, zi) = (i64::from(x), i64::from(z));
    if square {
        (
            [
                (xi + h, zi - h),
                (xi - h, zi - h),
                (xi - h, zi + h),
                (xi + h, zi + h),
            ],
            [(xi, zi - h), (xi - h, zi), (xi, zi + h), (xi + h, zi)],
        )
    } else {
        (
            [(xi + h, zi), (xi, zi - h), (xi - h, zi), (xi, zi + h)],
            [
                (xi + k, zi - k),
                (xi - k, zi - k),
                (xi - k, zi + k),
                (xi + k, zi + k),
            ],
        )
    }
}

/// A split diamond's four corners (`None` off the map) in [`emit`]'s order, and whether
/// each child (between corner `j` and `j + 1`) is a leaf.
fn children(grid: &Grid, i: u32, split: impl Fn(u32) -> bool) -> ([Option<u32>; 4], [bool; 4]) {
    let s = i64::from(grid.size());
    let (x, z) = grid.coords(i);
    let (m, square) = grid.classify(x, z);
    let at = |(cx, cz): (i64, i64)| {
        (cx >= 0 && cz >= 0 && cx <= s && cz <= s).then(|| grid.index(cx as u32, cz as u32))
    };
    let (corner, mid) = layout(x, z, m, square);
    let leaf = mid.map(|c| (!square && m == 0) || at(c).is_none_or(|c| !split(c)));
    (corner.map(at), leaf)
}
