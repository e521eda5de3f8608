//! Change frames (payload format 2): a delta coded from the list of diamonds whose split
//! state changed since a base the viewer holds, so coding it costs O(changes), not O(cut).
//!
//! A frame-coherent tessellator knows which diamonds it split or merged since any recent
//! frame; the change list between the viewer's base `B` and the cut now `R` is the
//! symmetric difference `B △ R`. The viewer toggles each listed diamond in a copy of `B`: a
//! diamond in `B` is merged, any other is split and is a new vertex, whose height comes with
//! the frame. Key frames stay format 1 ([`crate::codec`]), as do deltas from a coder that
//! has no change list.
//!
//! **Positions.** The changes are sorted by their Morton (Z-order) key, `x` and `z`
//! interleaved with `x` in bit 0, so changes close together on the map are close in the
//! order; each key is coded as its gap from the previous one (the first from −1), always
//! ≥ 1: the gap's bit length minus one through an adaptive 5-bit tree, the bit below the
//! leading one adaptively, then the rest with probability ½. Nothing says whether a change
//! is a split or a merge: the base says.
//!
//! **Heights.** Then, for every split (a change not in the base), in (depth, index) order
//! ([`Grid::depth`]): its height residual in steps, predicted exactly as format 1 does (the
//! mean of the hypotenuse ends, rounded to the step) and coded as format 1 codes residuals,
//! one context per depth. A split diamond's hypotenuse ends are vertices of the cut (split
//! diamonds or map corners) one or more depths coarser, so the viewer holds their heights:
//! from the base, from earlier in this frame (hence the order), or the corners from the key
//! frame.
//!
//! **Checks.** The frame declares the cut's triangles, splits and
//! [`CutHash`](crate::CutHash), a hash of the split set with heights that both ends keep
//! up to date change by change; the viewer checks all three, and that the result is closed under parent (every split's parents
//! split, no merged diamond's child split), so a frame decoded against the wrong base is
//! refused ([`DecodeError::Check`]) rather than shown. A frame that fails changes nothing
//! the viewer holds, so a bad frame spoils no base.
//!
//! **One reading.** [`ChangeReader`] reads the bits (the header and its checks, the
//! positions, the residuals) for the one decoder of change frames, the viewer's
//! ([`crate::Follower`]), which knows the base and so what each change means; the tests'
//! reference decoder (a bitset over the grid and a copy per base, their oracle) reads
//! through it too.
//!
//! **Cost.** The encoder sorts and codes the changes: O(n log n) for n changes, nothing
//! proportional to the cut or the grid, no allocation once warm. The viewer's decoder is
//! O(changes since the base + n log n) ([`crate::follow`]).
//!
//! # Payload
//!
//! ```text
//! format    u8   2
//! levels    u8   N (side 2^N + 1)
//! flags     u8   0
//! reserved  u8   0
//! triangles u32  of the cut now
//! splits    u32  of the cut now
//! check     u64  the cut now's CutHash value
//! step      u16  every height is a multiple of it; residuals are coded in steps
//! changes   u32  how many diamonds changed
//! body      range-coded: the gaps between the changes' Morton keys, then the new
//!                vertices' height residuals in (depth, index) order
//! ```
//!
//! # Size
//!
//! Measured by `cargo bench -p roam-protocol --bench change_sizes` (one JSON line a
//! case), on viewpoint-dependent cuts of 44k to 200k triangles with the eye moving
//! between frames: at 60 to 130 changes a frame, 2.2 to 3.0 bytes a change, header
//! included (1.5 to 1.75 of it the position), 30 to 55 % smaller than format 1's delta;
//! at 250 to 500 changes, 1.7 to 2.3 bytes a change, about format 1's size; past 1,000
//! changes 1 to 1.9 bytes a change, up to 70 % larger than format 1's delta (which codes
//! one well-predicted bit per diamond of the cut's frontier, and so gets cheaper per change
//! as changes crowd it). Twenty toggles in a 64-cell window of a 2^12 + 1 grid: 3.45 bytes
//! a change (1.87 of it the position; heights of noisy synthetic terrain). A key frame is
//! format 1 at 0.33 bytes a triangle.

use crate::bintree::Grid;
use crate::codec::u32_le;
use crate::codec::{self, ChangeModels, EncodeError};
use crate::format::{self, DecodeError};
use crate::range;

/// The payload format of a change frame.
pub const CHANGES_FORMAT: u8 = format::CHANGES;
const HEADER: usize = 26;

/// Spreads the low 16 bits of `v` to the even bits.
#[inline]
fn spread(v: u32) -> u32 {
    let mut v = v & 0xffff;
    v = (v | v << 8) & 0x00ff_00ff;
    v = (v | v << 4) & 0x0f0f_0f0f;
    v = (v | v << 2) & 0x3333_3333;
    (v | v << 1) & 0x5555_5555
}

/// The even bits of `v`, packed.
#[inline]
fn compact(v: u32) -> u32 {
    let mut v = v & 0x5555_5555;
    v = (v | v >> 1) & 0x3333_3333;
    v = (v | v >> 2) & 0x0f0f_0f0f;
    v = (v | v >> 4) & 0x00ff_00ff;
    (v | v >> 8) & 0xffff
}

/// The Morton key of `(x, z)` (each < 2^16): x in the even bits, z in the odd ones.
#[inline]
fn morton(x: u32, z: u32) -> u32 {
    spread(x) | spread(z) << 1
}

#[inline]
fn unmorton(key: u32) -> (u32, u32) {
    (compact(key), compact(key >> 1))
}

/// Codes a gap `≥ 1` between Morton keys: its bit length minus one through the 5-bit
/// tree, the bit below the leading one, then the rest with probability ½.
fn encode_gap(rc: &mut range::Encoder, m: &mut ChangeModels, gap: u32) {
    debug_assert!(gap >= 1);
    let class = 31 - gap.leading_zeros(); // bit length − 1, 0 ..= 31
    rc.tree(&mut m.class, class, 5);
    if class >= 1 {
        rc.bit(&mut m.second[class as usize], gap >> (class - 1) & 1 != 0);
        rc.direct(gap, class - 1);
    }
}

fn decode_gap(rc: &mut range::Decoder, m: &mut ChangeModels) -> u32 {
    let class = rc.tree(&mut m.class, 5);
    let mut gap = 1u32 << class;
    if class >= 1 {
        gap |= u32::from(rc.bit(&mut m.second[class as usize])) << (class - 1);
        gap |= rc.direct(class - 1) & ((1 << (class - 1)) - 1);
    }
    gap
}

/// Encodes change frames of one grid, reusing its buffers: once warm it allocates nothing
/// but growth of the output.
pub struct ChangeEncoder {
    grid: Grid,
    step: u16,
    models: Box<ChangeModels>,
    /// Morton keys of the changes, sorted.
    keys: Vec<u32>,
    /// The splits, `depth << 32 | index`, sorted.
    order: Vec<u64>,
}

impl ChangeEncoder {
    /// An encoder for heights that are all multiples of `step` (see
    /// [`crate::height_step`]; 1 for any heights).
    pub fn new(grid: Grid, step: u16) -> ChangeEncoder {
        ChangeEncoder {
            grid,
            step: step.max(1),
            models: Box::new(ChangeModels::fresh()),
            keys: Vec::new(),
            order: Vec::new(),
        }
    }

    /// Appends a change frame to `out`.
    ///
    /// `changes`: the row-major indices of diamonds whose split state differs between the
    /// base the viewer holds and the cut now (any order, no duplicates). `now_split(i)`
    /// says whether `i` (one of `changes`) is split now (true = a split relative to the
    /// base, false = a merge). `heights`: the full row-major heightfield. `triangles`,
    /// `splits`, `hash`: of the cut now (`hash` is its [`CutHash`](crate::CutHash) value). Costs
    /// O(changes · log changes): nothing here looks at the cut or the grid as a whole, so
    /// nothing checks that the result is closed under parent (the viewer does).
    #[allow(clippy::too_many_arguments)]
    pub fn encode(
        &mut self,
        changes: &[u32],
        now_split: impl Fn(u32) -> bool,
        heights: &[u16],
        triangles: u32,
        splits: u32,
        hash: u64,
        out: &mut Vec<u8>,
    ) -> Result<(), EncodeError> {
        let grid = self.grid;
        if heights.len() != grid.vertices() {
            return Err(EncodeError::Heights {
                got: heights.len(),
                expected: grid.vertices(),
            });
        }
        self.keys.clear();
        self.order.clear();
        for &i in changes {
            if i as usize >= grid.vertices() {
                return Err(EncodeError::Change {
                    index: i,
                    why: "off the grid",
                });
            }
            let (x, z) = grid.coords(i);
            if x.is_multiple_of(grid.size()) && z.is_multiple_of(grid.size()) {
                return Err(EncodeError::Change {
                    index: i,
                    why: "a map corner, not a diamond",
                });
            }
            self.keys.push(morton(x, z));
            if now_split(i) {
                self.order
                    .push(u64::from(grid.depth(x, z)) << 32 | u64::from(i));
            }
        }
        self.keys.sort_unstable();
        if let Some(w) = self.keys.windows(2).find(|w| w[0] == w[1]) {
            let (x, z) = unmorton(w[0]);
            return Err(EncodeError::Change {
                index: grid.index(x, z),
                why: "listed twice",
            });
        }
        self.order.sort_unstable();
        let count = self.keys.len() as u32; // distinct grid vertices: < 2^31
        let m = &mut *self.models;
        m.reset();
        let start = out.len();
        out.resize(start + HEADER, 0);
        let mut rc = range::Encoder::new(std::mem::take(out));
        // Gaps between keys, the first from −1: every gap is ≥ 1, and keys are < 2^32 − 1
        // (coordinates ≤ 2^15), so every gap fits in 32 bits.
        let mut next = 0u32;
        for &key in &self.keys {
            encode_gap(&mut rc, m, key - next + 1);
            next = key + 1;
        }
        let step = i32::from(self.step);
        for &o in &self.order {
            let (i, depth) = (o as u32, (o >> 32) as usize);
            let (x, z) = grid.coords(i);
            let h = heights[i as usize];
            let r = i32::from(h) - codec::predict(&grid, heights, x, z, step);
            if r % step != 0 {
                *out = rc.finish();
                out.truncate(start);
                return Err(EncodeError::Step {
                    height: h,
                    step: self.step,
                });
            }
            codec::encode_residual(&mut rc, &mut m.residuals, depth, r / step);
        }
        *out = rc.finish();
        let head = &mut out[start..start + HEADER];
        head[0] = CHANGES_FORMAT;
        head[1] = grid.levels() as u8;
        head[4..8].copy_from_slice(&triangles.to_le_bytes());
        head[8..12].copy_from_slice(&splits.to_le_bytes());
        head[12..20].copy_from_slice(&hash.to_le_bytes());
        head[20..22].copy_from_slice(&self.step.to_le_bytes());
        head[22..26].copy_from_slice(&count.to_le_bytes());
        Ok(())
    }
}

/// A change frame's figures, read from its header and checked alone
/// ([`ChangeReader::read`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ChangeHead {
    /// The cut's triangles.
    pub triangles: u32,
    /// The cut's split diamonds.
    pub splits: u32,
    /// The cut's [`CutHash`](crate::CutHash) value.
    pub check: u64,
    /// Every height is a multiple of it (not 0).
    pub step: u16,
    /// Diamonds changed since the base.
    pub count: u32,
}

impl ChangeHead {
    /// A new vertex's height: `predicted` (the mean of its hypotenuse ends, rounded to the
    /// step, as the encoder predicts it) plus `residual` steps; refused outside `u16`.
    pub fn height(&self, predicted: i32, residual: i32) -> Result<u16, DecodeError> {
        // In i64: a hostile step times a large residual overflows i32.
        let h = i64::from(predicted) + i64::from(residual) * i64::from(self.step);
        u16::try_from(h).map_err(|_| DecodeError::Corrupt("a height out of range"))
    }
}

/// Where a change frame's reading is: the range decoder over its body.
pub struct ChangeBody<'p> {
    rc: range::Decoder<'p>,
    count: u32,
}

impl ChangeBody<'_> {
    /// After the last residual: refused when the bits ended early or are not ours.
    pub fn finish(&self) -> Result<(), DecodeError> {
        if self.rc.failed() {
            return Err(DecodeError::Corrupt(
                "the coded bits end early or are not ours",
            ));
        }
        Ok(())
    }
}

/// Reads change frames of one grid, bit by bit: the header, the changes' positions, then
/// the new vertices' height residuals. What each change means (a split or a merge) and
/// the heights it predicts from are the caller's, who holds the base: the viewer's
/// decoder ([`crate::Follower`]), and the tests' reference decoder. Its models are reused:
/// reading allocates nothing.
pub struct ChangeReader {
    grid: Grid,
    models: Box<ChangeModels>,
}

impl ChangeReader {
    pub fn new(grid: Grid) -> ChangeReader {
        ChangeReader {
            grid,
            models: Box::new(ChangeModels::fresh()),
        }
    }

    /// Reads a change frame's header, against a base of `base_splits` split diamonds:
    /// refuses a payload too short, of another format or grid, with unknown flags, a step
    /// of 0, more than `max_triangles`, more splits than its triangles allow, or more
    /// changes than the base and the frame have splits (checked before anything is sized
    /// by the count). Then the body, to read with [`Self::changes`] and [`Self::residual`]
    /// and end with [`ChangeBody::finish`].
    pub fn read<'p>(
        &mut self,
        payload: &'p [u8],
        base_splits: u32,
        max_triangles: u32,
    ) -> Result<(ChangeHead, ChangeBody<'p>), DecodeError> {
        let grid = self.grid;
        if payload.len() < HEADER {
            return Err(DecodeError::Short(payload.len()));
        }
        if payload[0] != CHANGES_FORMAT {
            return Err(DecodeError::Format(payload[0]));
        }
        if u32::from(payload[1]) != grid.levels() {
            return Err(DecodeError::Grid {
                got: payload[1],
                expected: grid.levels(),
            });
        }
        if payload[2] != 0 || payload[3] != 0 {
            return Err(DecodeError::Corrupt("unknown flags"));
        }
        let figures = codec::head(payload, max_triangles)?;
        let head = ChangeHead {
            triangles: figures.triangles,
            splits: figures.splits,
            check: figures.check,
            step: figures.step as u16, // read from a u16
            count: u32_le(payload, 22),
        };
        // Each split adds at least one triangle to the two of the empty cut.
        if head.splits > head.triangles.saturating_sub(2) {
            return Err(DecodeError::Corrupt("more splits than triangles"));
        }
        // Every change is a split of the base or of the cut now.
        if u64::from(head.count) > u64::from(base_splits) + u64::from(head.splits) {
            return Err(DecodeError::Corrupt(
                "more changes than the base and the frame have splits",
            ));
        }
        self.models.reset();
        let body = ChangeBody {
            rc: range::Decoder::new(&payload[HEADER..]),
            count: head.count,
        };
        Ok((head, body))
    }

    /// The changes' row-major grid indices, in the coded (Morton) order, into `out`
    /// (cleared first); refused when the bits end early or a change is off the grid or at
    /// a map corner.
    pub fn changes(
        &mut self,
        body: &mut ChangeBody,
        out: &mut Vec<u32>,
    ) -> Result<(), DecodeError> {
        let grid = self.grid;
        let size = grid.size();
        out.clear();
        let mut next = 0u64;
        for _ in 0..body.count {
            let gap = decode_gap(&mut body.rc, &mut self.models);
            if body.rc.failed() {
                return Err(DecodeError::Corrupt(
                    "the coded bits end early or are not ours",
                ));
            }
            // ≤ 2^32 + 2^32: no overflow in u64.
            let key = next + u64::from(gap) - 1;
            next = key + 1;
            let Ok(key) = u32::try_from(key) else {
                return Err(DecodeError::Corrupt("a change off the grid"));
            };
            let (x, z) = unmorton(key);
            if x > size || z > size || (x.is_multiple_of(size) && z.is_multiple_of(size)) {
                return Err(DecodeError::Corrupt("a change off the grid or at a corner"));
            }
            out.push(grid.index(x, z));
        }
        Ok(())
    }

    /// The next new vertex's height residual, in steps: the new vertices come in (depth,
    /// index) order ([`Grid::depth`]), each read with its depth.
    pub fn residual(&mut self, body: &mut ChangeBody, depth: usize) -> Result<i32, DecodeError> {
        codec::decode_residual(&mut body.rc, &mut self.models.residuals, depth)
            .ok_or(DecodeError::Corrupt("a residual out of range"))
    }
}
