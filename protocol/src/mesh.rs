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
        let (h, k) = (1i64 << m, (1i64 << m) / 2);
        let (xi, zi) = (i64::from(x), i64::from(z));
        let on =
            |(cx, cz): (i64, i64)| cx >= 0 && cz >= 0 && cx <= i64::from(s) && cz <= i64::from(s);
        let idx = |(cx, cz): (i64, i64)| grid.index(cx as u32, cz as u32);
        let (corner, mid) = if square {
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
        };
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
