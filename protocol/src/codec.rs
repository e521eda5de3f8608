//! The mesh codec: a split-only mesh as a cut of the bintree, with heights predicted and
//! only residuals sent.
//!
//! A mesh is its set of split diamonds (see [`crate::bintree`]); vertex positions are
//! implicit in the grid. The coder walks the bintree depth by depth from the root. At each
//! depth the *candidates* are the diamonds all of whose parents are split (only they may
//! be split); each costs one adaptively coded bit, split or not, whose context is its depth
//! and whether the base frame had it split. A split diamond's centre is a new vertex: its
//! height is predicted as the mean of its hypotenuse ends (coarser vertices, already
//! known) and the residual is coded, unless the base frame had that diamond split, in which
//! case the viewer already holds the height. The next depth's candidates are the children of
//! this depth's split diamonds, each listed by its first parent (lowest index) once all its
//! parents are split: both ends derive the same order with no sorting and no side
//! information.
//!
//! A **key frame** codes against nothing (and carries the four corner heights); a **delta
//! frame** codes against a base split set the viewer has decoded and acknowledged. Heights
//! are terrain, so they never change: a viewer keeps every height it decoded, and a frame
//! that fails (lost, abandoned, corrupt) is simply not a base for later ones. Every frame
//! carries a check over its split diamonds and heights, so a frame decoded against the wrong
//! base is detected rather than shown.
//!
//! A delta can also come as a **change frame** (format 2, [`crate::changes`]): coded from
//! the list of diamonds that changed since the base, in O(changes) on the server, rather
//! than by walking the cut. Key frames are always format 1.
//! The viewer's decoder, [`crate::Follower`], reads both formats; [`MeshDecoder::decode`]
//! reads format 1 into a bitset over the grid (the tools', the benchmarks' and the tests'
//! reference).
//!
//! # Payload
//!
//! ```text
//! format    u8   1
//! levels    u8   N (side 2^N + 1)
//! flags     u8   bit 0: a delta frame
//! reserved  u8   0
//! triangles u32
//! splits    u32
//! check     u64  (a 64-bit hash over the corners' heights and every split diamond's index
//!                and height, in coding order)
//! step      u16  every height is a multiple of it; residuals are coded in steps
//! corners   4 × u16, key frames only
//! body      range-coded bits (see `range`)
//! ```

use crate::bintree::{BitSet, Grid};
use crate::format::{self, DecodeError};
use crate::range::{self, Prob};

/// The payload format this code writes and reads.
pub const FORMAT: u8 = format::MESH;
pub(crate) const HEADER: usize = 22;
const DEPTHS: usize = 2 * crate::bintree::MAX_LEVELS as usize;
/// Height residual contexts: one per depth.
const CONTEXTS: usize = DEPTHS;

/// Why a mesh could not be encoded (a caller bug: the input is not a mesh of this grid).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum EncodeError {
    #[error("{got} heights for a grid of {expected} vertices")]
    Heights { got: usize, expected: usize },
    #[error(
        "the split set is not closed under parent: {unreached} split diamonds have an unsplit parent"
    )]
    NotConforming { unreached: usize },
    #[error("height {height} is not a multiple of the step {step}")]
    Step { height: u16, step: u16 },
    /// A change frame's change list names something that is not one diamond of the grid.
    #[error("change at index {index}: {why}")]
    Change { index: u32, why: &'static str },
}

/// Adaptive probabilities of one frame.
pub(crate) struct Models {
    pub(crate) split: [[Prob; 2]; DEPTHS],
    zero: [Prob; CONTEXTS],
    sign: [Prob; CONTEXTS],
    /// Bit length of the residual's magnitude, minus one (0 ..= 16): a 5-bit tree.
    class: [[Prob; 32]; CONTEXTS],
    /// The bit below the leading one, per context and class.
    second: [[Prob; 18]; CONTEXTS],
}

impl Models {
    pub(crate) fn fresh() -> Models {
        Models {
            split: [[Prob::default(); 2]; DEPTHS],
            zero: [Prob::default(); CONTEXTS],
            sign: [Prob::default(); CONTEXTS],
            class: [[Prob::default(); 32]; CONTEXTS],
            second: [[Prob::default(); 18]; CONTEXTS],
        }
    }

    fn new() -> Box<Models> {
        Box::new(Models::fresh())
    }

    /// Back to the initial probabilities, in place (no allocation).
    pub(crate) fn reset(&mut self) {
        *self = Models::fresh();
    }
}

/// A frame's figures, read from bytes 4 .. 22 of either format's header, before its checks
/// against what it decodes to.
pub(crate) struct Head {
    pub(crate) triangles: u32,
    pub(crate) splits: u32,
    pub(crate) check: u64,
    /// Every height is a multiple of it (not 0).
    pub(crate) step: i32,
}

/// The figures both formats' headers carry after their first four bytes (`payload` holds
/// at least [`HEADER`] bytes: the caller has checked), checked alone: a step of 0 and more
/// triangles than `max_triangles` are refused.
pub(crate) fn head(payload: &[u8], max_triangles: u32) -> Result<Head, DecodeError> {
    let head = Head {
        triangles: u32_le(payload, 4),
        splits: u32_le(payload, 8),
        check: u64::from_le_bytes(
            payload[12..20]
                .try_into()
                .expect("8 bytes: the caller checked the header's length"),
        ),
        step: i32::from(u16::from_le_bytes([payload[20], payload[21]])),
    };
    if head.step == 0 {
        return Err(DecodeError::Corrupt("a height step of 0"));
    }
    if head.triangles > max_triangles {
        return Err(DecodeError::TooBig {
            declared: head.triangles,
            limit: max_triangles,
        });
    }
    Ok(head)
}

/// The little-endian `u32` at `at` (the caller has checked the length).
pub(crate) fn u32_le(bytes: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]])
}

/// The predicted height of a new vertex: the mean of its hypotenuse ends, rounded to the
/// nearest multiple of the heightfield's `step` (so the residual is a whole number of
/// steps).
#[inline]
pub(crate) fn predict(grid: &Grid, heights: &[u16], x: u32, z: u32, step: i32) -> i32 {
    let [(ax, az), (bx, bz)] = grid.hypotenuse(x, z);
    let h = |x, z| i32::from(heights[grid.index(x, z) as usize]);
    let sum = h(ax, az) + h(bx, bz);
    // round(sum / 2 / step) · step, in integers
    (sum + step) / (2 * step) * step
}

/// [`predict`] with heights looked up by `height` (a grid index's height, `None` when the
/// viewer does not hold it): `None` when a hypotenuse end's height is not held.
#[inline]
pub(crate) fn predict_by(
    grid: &Grid,
    x: u32,
    z: u32,
    step: i32,
    height: impl Fn(u32) -> Option<u16>,
) -> Option<i32> {
    let [(ax, az), (bx, bz)] = grid.hypotenuse(x, z);
    let sum = i32::from(height(grid.index(ax, az))?) + i32::from(height(grid.index(bx, bz))?);
    Some((sum + step) / (2 * step) * step)
}

/// The largest step every height is a multiple of (1 when there is none): the
/// heightfield's quantization, which the coder divides out of every residual. Real data
/// often has one: SRTM heights are whole metres, 100 samples apart in `kossou`.
pub fn height_step(heights: &[u16]) -> u16 {
    let mut gcd = 0u16;
    // Once 1, the divisor stays 1: most real maps get there within a few samples, so a
    // 32769² map is not read whole (a server's start waited seconds on this scan).
    for &h in heights {
        let (mut a, mut b) = (gcd, h);
        while b != 0 {
            (a, b) = (b, a % b);
        }
        gcd = a;
        if gcd == 1 {
            break;
        }
    }
    gcd.max(1)
}

/// The candidates of depth 0: the root alone.
pub(crate) fn start_at_root(grid: &Grid, list: &mut Vec<u32>) {
    let (x, z) = grid.root();
    list.clear();
    list.push(grid.index(x, z));
}

/// The candidates of the next depth: children of this depth's split diamonds, each listed
/// by its lowest-index parent once all its parents are split.
fn next_candidates(grid: &Grid, list: &[u32], split: &BitSet, next: &mut Vec<u32>) {
    next_candidates_by(grid, list, |i| split.contains(i), next);
}

/// [`next_candidates`] over any split set: `split(i)` says whether diamond `i` is split.
///
/// The other parent of a child `c` of `i` is `i` mirrored through `c`
/// ([`Grid::other_parent`]), of index `2c − i`. The child is `i`'s to list when that
/// parent is none, or is split and of a higher index (`c > i`): one look-up a child at
/// most, where asking [`Grid::parents`] for both and looking both up made this a fifth of
/// a first frame's time on the server (`perf`, `data/kossou`, 32,768 triangles,
/// 2026-12-07).
pub(crate) fn next_candidates_by(
    grid: &Grid,
    list: &[u32],
    split: impl Fn(u32) -> bool,
    next: &mut Vec<u32>,
) {
    next.clear();
    let side = grid.side();
    for &i in list {
        if !split(i) {
            continue;
        }
        let (x, z) = (i % side, i / side);
        for (cx, cz) in grid.children(x, z).into_iter().flatten() {
            let c = cz * side + cx;
            let other = grid.other_parent((x, z), (cx, cz));
            if other.is_none() || (c > i && split(2 * c - i)) {
                next.push(c);
            }
        }
    }
}

/// The frame check: a 64-bit multiply-rotate hash over the corners' heights, then each
/// split diamond's index and height in coding order. It is there to catch a frame decoded
/// against the wrong base, or damage the range coder let through, not to resist forgery
/// (QUIC's encryption does that), so it is cheap: a few cycles a vertex.
pub(crate) struct Check(u64);

impl Check {
    fn new(grid: &Grid, heights: &[u16]) -> Check {
        Check::of_corners(
            grid.corners()
                .map(|(x, z)| heights[grid.index(x, z) as usize]),
        )
    }

    /// The check's start: the four corners' heights, row-major.
    pub(crate) fn of_corners(corners: [u16; 4]) -> Check {
        let mut c = Check(0x243f_6a88_85a3_08d3);
        for h in corners {
            c.add(u64::from(h));
        }
        c
    }

    #[inline]
    pub(crate) fn add(&mut self, v: u64) {
        self.0 = (self.0.rotate_left(23) ^ v).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    }

    pub(crate) fn value(&self) -> u64 {
        let mut h = self.0;
        h ^= h >> 33;
        h = h.wrapping_mul(0xff51_afd7_ed55_8ccd);
        h ^ (h >> 33)
    }
}

/// Encodes meshes of one grid.
///
/// A key frame's lists of candidates (a depth's and the next's) are made for each call and
/// given back after it: a server keeps an encoder per viewer and makes key frames rarely
/// (a join, a viewer that fell behind), and keeping the lists' capacity cost each viewer
/// about 130 KB at 65,536 triangles (heaptrack, `data/kossou`, five driving viewers,
/// 2026-12-08), a tenth of issue 41's memory must.
pub struct MeshEncoder {
    grid: Grid,
    models: Box<Models>,
    step: u16,
}

impl MeshEncoder {
    /// An encoder for heights of any value.
    pub fn new(grid: Grid) -> MeshEncoder {
        MeshEncoder::with_step(grid, 1)
    }

    /// An encoder for heights that are all multiples of `step` (see [`height_step`]).
    pub fn with_step(grid: Grid, step: u16) -> MeshEncoder {
        MeshEncoder {
            grid,
            models: Models::new(),
            step: step.max(1),
        }
    }

    /// Appends to `out` the mesh whose split diamonds are `split`, with heights from the
    /// full row-major heightfield `heights`; against `base` (a split set the viewer holds)
    /// when given, else as a key frame.
    pub fn encode(
        &mut self,
        split: &BitSet,
        heights: &[u16],
        base: Option<&BitSet>,
        out: &mut Vec<u8>,
    ) -> Result<(), EncodeError> {
        let grid = self.grid;
        if heights.len() != grid.vertices() {
            return Err(EncodeError::Heights {
                got: heights.len(),
                expected: grid.vertices(),
            });
        }
        self.models.reset();
        let m = &mut *self.models;
        let start = out.len();
        out.resize(start + HEADER, 0);
        if base.is_none() {
            for (x, z) in grid.corners() {
                out.extend_from_slice(&heights[grid.index(x, z) as usize].to_le_bytes());
            }
        }
        let mut check = Check::new(&grid, heights);
        let mut rc = range::Encoder::new(std::mem::take(out));
        let (mut splits, mut triangles) = (0u32, 2u32);
        let (mut list, mut next) = (Vec::new(), Vec::new());
        start_at_root(&grid, &mut list);
        for depth in 0..grid.depths() as usize {
            for &i in &list {
                let is_split = split.contains(i);
                let in_base = base.is_some_and(|b| b.contains(i));
                rc.bit(&mut m.split[depth][usize::from(in_base)], is_split);
                if !is_split {
                    continue;
                }
                let (x, z) = grid.coords(i);
                splits += 1;
                triangles += grid.added(x, z);
                let h = heights[i as usize];
                check.add(u64::from(i) << 16 | u64::from(h));
                if !in_base {
                    let step = i32::from(self.step);
                    let r = i32::from(h) - predict(&grid, heights, x, z, step);
                    if r % step != 0 {
                        return Err(EncodeError::Step {
                            height: h,
                            step: self.step,
                        });
                    }
                    encode_residual(&mut rc, m, depth, r / step);
                }
            }
            next_candidates(&grid, &list, split, &mut next);
            std::mem::swap(&mut list, &mut next);
        }
        let total = split.len();
        if total != splits as usize {
            *out = rc.finish();
            out.truncate(start);
            return Err(EncodeError::NotConforming {
                unreached: total - splits as usize,
            });
        }
        *out = rc.finish();
        let head = &mut out[start..start + HEADER];
        head[0] = FORMAT;
        head[1] = grid.levels() as u8;
        head[2] = u8::from(base.is_some());
        head[4..8].copy_from_slice(&triangles.to_le_bytes());
        head[8..12].copy_from_slice(&splits.to_le_bytes());
        head[12..20].copy_from_slice(&check.value().to_le_bytes());
        head[20..22].copy_from_slice(&self.step.to_le_bytes());
        Ok(())
    }
}

/// A height residual `r` (in steps) in context `ctx` (the diamond's depth): zero or not,
/// sign, bit length through a 5-bit tree, the bit below the leading one, then the rest
/// with probability ½.
pub(crate) fn encode_residual(rc: &mut range::Encoder, m: &mut Models, ctx: usize, r: i32) {
    rc.bit(&mut m.zero[ctx], r == 0);
    if r == 0 {
        return;
    }
    rc.bit(&mut m.sign[ctx], r < 0);
    let mag = r.unsigned_abs();
    let class = 31 - mag.leading_zeros(); // bit length − 1, 0 ..= 16
    rc.tree(&mut m.class[ctx], class, 5);
    if class >= 1 {
        rc.bit(
            &mut m.second[ctx][class as usize],
            mag >> (class - 1) & 1 != 0,
        );
        rc.direct(mag, class - 1);
    }
}

pub(crate) fn decode_residual(rc: &mut range::Decoder, m: &mut Models, ctx: usize) -> Option<i32> {
    if rc.bit(&mut m.zero[ctx]) {
        return Some(0);
    }
    let negative = rc.bit(&mut m.sign[ctx]);
    let class = rc.tree(&mut m.class[ctx], 5);
    if class > 16 {
        return None;
    }
    let mut mag = 1u32 << class;
    if class >= 1 {
        let second = rc.bit(&mut m.second[ctx][class as usize]);
        mag |= u32::from(second) << (class - 1);
        mag |= rc.direct(class - 1) & ((1 << (class - 1)) - 1);
    }
    let r = mag as i32;
    Some(if negative { -r } else { r })
}

/// What a decoded frame holds besides its split set.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Decoded {
    pub triangles: u32,
    pub splits: u32,
    /// A key frame (no base).
    pub key: bool,
}

/// Adaptive probabilities of one change frame.
pub(crate) struct ChangeModels {
    /// Bit length of a gap minus one (0 ..= 31): a 5-bit tree.
    pub(crate) class: [Prob; 32],
    /// The bit below a gap's leading one, by bit length.
    pub(crate) second: [Prob; 32],
    /// Height residuals, as format 1 codes them.
    pub(crate) residuals: Models,
}

impl ChangeModels {
    pub(crate) fn fresh() -> ChangeModels {
        ChangeModels {
            class: [Prob::default(); 32],
            second: [Prob::default(); 32],
            residuals: Models::fresh(),
        }
    }

    /// Back to the initial probabilities, in place.
    pub(crate) fn reset(&mut self) {
        self.class = [Prob::default(); 32];
        self.second = [Prob::default(); 32];
        self.residuals.reset();
    }
}

/// Decodes format-1 meshes of one grid into a bitset over it, keeping every height it has
/// decoded in an array over the grid (O(grid) memory: the viewer's decoder is
/// [`crate::Follower`]).
pub struct MeshDecoder {
    grid: Grid,
    models: Box<Models>,
    list: Vec<u32>,
    next: Vec<u32>,
    heights: Vec<u16>,
}

impl MeshDecoder {
    pub fn new(grid: Grid) -> MeshDecoder {
        MeshDecoder {
            grid,
            models: Models::new(),
            list: Vec::new(),
            next: Vec::new(),
            heights: vec![0; grid.vertices()],
        }
    }

    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// Heights of every vertex decoded so far (row-major; others are 0).
    pub fn heights(&self) -> &[u16] {
        &self.heights
    }

    /// The heights the decoder predicts from, for a caller that decodes other frames of
    /// the same terrain (change frames) and must leave their new vertices' heights here.
    pub fn heights_mut(&mut self) -> &mut [u16] {
        &mut self.heights
    }

    /// Decodes a format-1 `payload` into `split` (a key frame, or a delta against `base`).
    /// Refuses meshes of more than `max_triangles`. On error, `split` holds nothing usable
    /// and the frame is to be dropped. Change frames (format 2) are [`crate::Follower`]'s.
    pub fn decode(
        &mut self,
        payload: &[u8],
        base: Option<&BitSet>,
        max_triangles: u32,
        split: &mut BitSet,
    ) -> Result<Decoded, DecodeError> {
        let grid = self.grid;
        if payload.len() < HEADER {
            return Err(DecodeError::Short(payload.len()));
        }
        if payload[0] != FORMAT {
            return Err(DecodeError::Format(payload[0]));
        }
        if u32::from(payload[1]) != grid.levels() {
            return Err(DecodeError::Grid {
                got: payload[1],
                expected: grid.levels(),
            });
        }
        let delta = payload[2] & 1 != 0;
        if payload[2] > 1 || payload[3] != 0 {
            return Err(DecodeError::Corrupt("unknown flags"));
        }
        if delta != base.is_some() {
            return Err(DecodeError::Base);
        }
        let Head {
            triangles: declared_triangles,
            splits: declared_splits,
            check: declared_check,
            step,
        } = head(payload, max_triangles)?;
        let mut body = &payload[HEADER..];
        if !delta {
            let Some((corners, rest)) = body.split_at_checked(8) else {
                return Err(DecodeError::Short(payload.len()));
            };
            for (k, (x, z)) in grid.corners().into_iter().enumerate() {
                self.heights[grid.index(x, z) as usize] =
                    u16::from_le_bytes([corners[2 * k], corners[2 * k + 1]]);
            }
            body = rest;
        }
        let mut check = Check::new(&grid, &self.heights);
        self.models.reset();
        let m = &mut *self.models;
        let mut rc = range::Decoder::new(body);
        split.reset(grid.vertices());
        let (mut splits, mut triangles) = (0u32, 2u32);
        start_at_root(&grid, &mut self.list);
        for depth in 0..grid.depths() as usize {
            for &i in &self.list {
                let in_base = base.is_some_and(|b| b.contains(i));
                if !rc.bit(&mut m.split[depth][usize::from(in_base)]) {
                    continue;
                }
                let (x, z) = grid.coords(i);
                splits += 1;
                triangles += grid.added(x, z);
                if splits > declared_splits || triangles > declared_triangles {
                    return Err(DecodeError::Corrupt("more splits than declared"));
                }
                split.insert(i);
                if !in_base {
                    let r = decode_residual(&mut rc, m, depth)
                        .ok_or(DecodeError::Corrupt("a residual out of range"))?;
                    // In i64: a hostile step times a large residual overflows i32.
                    let h = i64::from(predict(&grid, &self.heights, x, z, step))
                        + i64::from(r) * i64::from(step);
                    self.heights[i as usize] = u16::try_from(h)
                        .map_err(|_| DecodeError::Corrupt("a height out of range"))?;
                }
                check.add(u64::from(i) << 16 | u64::from(self.heights[i as usize]));
            }
            if rc.failed() {
                return Err(DecodeError::Corrupt(
                    "the coded bits end early or are not ours",
                ));
            }
            next_candidates(&grid, &self.list, split, &mut self.next);
            std::mem::swap(&mut self.list, &mut self.next);
        }
        if splits != declared_splits || triangles != declared_triangles {
            return Err(DecodeError::Corrupt("fewer splits than declared"));
        }
        if check.value() != declared_check {
            return Err(DecodeError::Check);
        }
        Ok(Decoded {
            triangles,
            splits,
            key: !delta,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The candidates by the definition: each child of a split diamond whose parents
    /// ([`Grid::parents`]) are all split, listed by the lowest-index one.
    fn by_definition(grid: &Grid, list: &[u32], split: &BitSet) -> Vec<u32> {
        let mut next = Vec::new();
        for &i in list.iter().filter(|&&i| split.contains(i)) {
            let (x, z) = grid.coords(i);
            for (cx, cz) in grid.children(x, z).into_iter().flatten() {
                let parents: Vec<u32> = grid
                    .parents(cx, cz)
                    .into_iter()
                    .flatten()
                    .map(|(px, pz)| grid.index(px, pz))
                    .collect();
                let owner = parents.iter().copied().min();
                if owner == Some(i) && parents.iter().all(|&p| split.contains(p)) {
                    next.push(grid.index(cx, cz));
                }
            }
        }
        next
    }

    /// The mirrored parent lists exactly what the definition lists, in its order, at every
    /// depth of closed cuts of 1 to 6 levels (sparse, dense, and everything split).
    #[test]
    fn next_candidates_are_the_definitions() {
        let mut seed = 0x9e37_79b9u32;
        for levels in 1..=6 {
            let grid = Grid::new(levels).expect("1 ..= 6 levels are grids");
            let size = grid.side() - 1;
            for density in [1u32, 4, 16, 64] {
                let mut split = BitSet::new(grid.vertices());
                for _ in 0..density * levels {
                    seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                    let (x, z) = ((seed >> 8) % (size + 1), (seed >> 20) % (size + 1));
                    grid.split_closed(&mut split, x, z);
                }
                if density == 64 {
                    for i in 0..grid.vertices() as u32 {
                        let (x, z) = grid.coords(i);
                        grid.split_closed(&mut split, x, z);
                    }
                }
                let (mut list, mut next) = (Vec::new(), Vec::new());
                start_at_root(&grid, &mut list);
                for depth in 0..grid.depths() {
                    let want = by_definition(&grid, &list, &split);
                    next_candidates(&grid, &list, &split, &mut next);
                    assert_eq!(
                        next, want,
                        "{levels} levels, density {density}, depth {depth}"
                    );
                    std::mem::swap(&mut list, &mut next);
                }
            }
        }
    }
}
