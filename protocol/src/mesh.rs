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

/// Ranks of the vertex set (split ∪ corners): each word beside the set bits before it.
struct Ranks {
    words: Vec<(u64, u32)>,
}

impl Ranks {
    fn rank(&self, i: u32) -> u32 {
        let (bits, before) = self.words[i as usize >> 6];
        before + (bits & ((1u64 << (i & 63)) - 1)).count_ones()
    }
}

/// Writes the mesh of `split` (closed under parent) on `grid` into `out`, with heights from
/// the row-major `heights`.
pub fn emit(grid: &Grid, split: &BitSet, heights: &[u16], out: &mut Mesh) {
    out.vertices.clear();
    out.heights.clear();
    out.indices.clear();
    let corners = grid.corners().map(|(x, z)| grid.index(x, z));
    let mut vertex_set = split.clone();
    for c in corners {
        vertex_set.insert(c);
    }
    let mut before = 0u32;
    let ranks = Ranks {
        words: vertex_set
            .words()
            .iter()
            .map(|&w| {
                let r = (w, before);
                before += w.count_ones();
                r
            })
            .collect(),
    };
    for i in vertex_set.iter() {
        let (x, z) = grid.coords(i);
        out.vertices.push([x as u16, z as u16]);
        out.heights
            .push(heights.get(i as usize).copied().unwrap_or(0));
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
