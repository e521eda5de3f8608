//! The reference decoder: the oracle the tests hold the viewer's decoder
//! ([`roam_protocol::Follower`], the library's one decoder of change frames) to. It keeps
//! what the viewer's decoder does not, a cut per base as a bitset over the grid ([`Cut`])
//! and every height decoded in one array over the grid, and reads a frame the plain way:
//! format 1 through [`MeshDecoder`] (a bitset over the grid), format 2 by toggling a copy
//! of its base's bitset change by change, then checking the triangles and splits counted,
//! the whole result closed under parent and its hash computed over the whole set. Only
//! the bits are read as the viewer's decoder reads them ([`ChangeReader`]: the format's one
//! reading); what they mean is worked out here independently, at O(grid) a frame.
//!
//! Test code only: the protocol's tests and its `change_sizes` bench take it through
//! `common`, and roam-tests' fuzzing (`tests/src/fuzz.rs`) includes this file by path.
//! A frame that fails puts back the heights it wrote, so it spoils no other base.

#![allow(dead_code)] // each includer uses its own subset

use roam_protocol::changes::{ChangeBody, ChangeHead, ChangeReader};
use roam_protocol::{BitSet, CHANGES_FORMAT, CutHash, DecodeError, Decoded, Grid, MeshDecoder};

/// A decoded cut, as the reference keeps one per base: its split diamonds, its triangle
/// count and its [`CutHash`] value.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Cut {
    pub split: BitSet,
    pub triangles: u32,
    pub hash: u64,
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

/// Decodes frames of one grid against any [`Cut`] given as their base.
pub struct Reference {
    grid: Grid,
    /// Format 1, and the heights of every vertex decoded (format 2's written there too).
    format1: MeshDecoder,
    reader: ChangeReader,
    changes: Vec<u32>,
    /// The splits of a change frame, `depth << 32 | index`.
    splits: Vec<u64>,
    /// Heights a change frame overwrote, put back if it fails.
    saved: Vec<(u32, u16)>,
}

impl Reference {
    pub fn new(grid: Grid) -> Reference {
        Reference {
            grid,
            format1: MeshDecoder::new(grid),
            reader: ChangeReader::new(grid),
            changes: Vec::new(),
            splits: Vec::new(),
            saved: Vec::new(),
        }
    }

    /// Heights of every vertex decoded so far (row-major; others are 0).
    pub fn heights(&self) -> &[u16] {
        self.format1.heights()
    }

    /// Decodes either format (by `payload[0]`): a format-1 key frame (`base` `None`) or
    /// delta, or a change frame against `base`, into `out`. On error `out` holds nothing
    /// usable.
    pub fn decode_cut(
        &mut self,
        payload: &[u8],
        base: Option<&Cut>,
        max_triangles: u32,
        out: &mut Cut,
    ) -> Result<Decoded, DecodeError> {
        if payload.first() != Some(&CHANGES_FORMAT) {
            let base = base.map(|b| &b.split);
            let info = self
                .format1
                .decode(payload, base, max_triangles, &mut out.split)?;
            out.triangles = info.triangles;
            out.hash = CutHash::of(&self.grid, &out.split, self.heights()).value();
            return Ok(info);
        }
        let base = base.ok_or(DecodeError::Base)?;
        if base.split.words().len() != self.grid.vertices().div_ceil(64) {
            return Err(DecodeError::Base);
        }
        let (head, mut body) = self
            .reader
            .read(payload, base.split.len() as u32, max_triangles)?;
        self.saved.clear();
        let result = self.toggle(&head, &mut body, base, out);
        if result.is_err() {
            let heights = self.format1.heights_mut();
            for &(i, h) in self.saved.iter().rev() {
                heights[i as usize] = h;
            }
        }
        result.map(|()| Decoded {
            triangles: head.triangles,
            splits: head.splits,
            key: false,
        })
    }

    /// A change frame's body: its changes toggled in a copy of `base`, the new vertices'
    /// heights, and the checks.
    fn toggle(
        &mut self,
        head: &ChangeHead,
        body: &mut ChangeBody,
        base: &Cut,
        out: &mut Cut,
    ) -> Result<(), DecodeError> {
        let grid = self.grid;
        self.reader.changes(body, &mut self.changes)?;
        out.split.clone_from(&base.split);
        let (mut triangles, mut splits) = (i64::from(base.triangles), base.split.len() as i64);
        self.splits.clear();
        for &i in &self.changes {
            let (x, z) = grid.coords(i);
            let added = i64::from(grid.added(x, z));
            if base.split.contains(i) {
                out.split.remove(i);
                (triangles, splits) = (triangles - added, splits - 1);
            } else {
                out.split.insert(i);
                (triangles, splits) = (triangles + added, splits + 1);
                self.splits
                    .push(u64::from(grid.depth(x, z)) << 32 | u64::from(i));
            }
        }
        if (triangles, splits) != (i64::from(head.triangles), i64::from(head.splits)) {
            return Err(DecodeError::Check);
        }
        // Coarser first: a split's hypotenuse ends are held before it.
        self.splits.sort_unstable();
        for &s in &self.splits {
            let (i, depth) = (s as u32, (s >> 32) as usize);
            let r = self.reader.residual(body, depth)?;
            let heights = self.format1.heights_mut();
            let h = head.height(predict(&grid, heights, i, head.step), r)?;
            self.saved.push((i, heights[i as usize]));
            heights[i as usize] = h;
        }
        body.finish()?;
        let closed = out.split.iter().all(|i| {
            let (x, z) = grid.coords(i);
            grid.parents(x, z)
                .into_iter()
                .flatten()
                .all(|(px, pz)| out.split.contains(grid.index(px, pz)))
        });
        out.triangles = head.triangles;
        out.hash = CutHash::of(&grid, &out.split, self.heights()).value();
        if !closed || out.hash != head.check {
            return Err(DecodeError::Check);
        }
        Ok(())
    }
}

/// The mean of diamond `i`'s hypotenuse ends, rounded to the nearest multiple of `step`.
fn predict(grid: &Grid, heights: &[u16], i: u32, step: u16) -> i32 {
    let (x, z) = grid.coords(i);
    let [(ax, az), (bx, bz)] = grid.hypotenuse(x, z);
    let end = |x, z| i32::from(heights[grid.index(x, z) as usize]);
    let (sum, step) = (end(ax, az) + end(bx, bz), i32::from(step));
    (sum + step) / (2 * step) * step
}
