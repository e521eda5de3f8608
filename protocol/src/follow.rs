//! [`Follower`]: the viewer's decoder, which follows the cut frame to frame at the cost of
//! what each frame changed, in memory proportional to the cut (issue 22).
//!
//! It keeps the current cut (its split diamonds with their heights, in a [`DiamondMap`])
//! and, for each recent frame, the diamonds that frame toggled (split or merged) with their
//! heights and the cut's triangles, splits and [`CutHash`]: the **log**. A base `B` is not
//! a copy: its cut is the current cut with every change since `B` undone, by parity, as
//! the server keeps its own logs (`roam_server::viewer`). Decoding a change frame
//! (format 2) against `B` composes the logs since `B` into a small map (`undo`), reads the
//! frame's changes into another (`fresh`), and asks "in B?" as `current ⊕ undo` and "in the
//! frame's cut?" as `B ⊕ fresh`: O(changes since B + changes in the frame), nothing by the
//! cut or the grid. A format-1 frame (a key frame, or a delta walking the whole cut) is
//! O(cut), as its coding is. Heights live with the diamonds: the current cut's in its map,
//! a merged diamond's in the log entry that merged it, so nothing is sized by the grid.
//!
//! A frame that fails changes nothing (it is decoded into the scratch maps, and applied to
//! the current cut only once every check passed), so a bad frame spoils no base. It is
//! the library's one decoder of change frames (their bits read by
//! [`crate::changes::ChangeReader`]). Its result is the reference decoder's, a test
//! oracle that keeps a bitset over the grid and a copy per base (format 1 through
//! [`crate::MeshDecoder`]; `protocol/tests/it/common/reference.rs`): the tests compare the
//! two on random cuts and damaged payloads, and the fuzzing on every frame of its inputs.
//!
//! **Measured** (issue 22, one headless viewer driving at 65,536 triangles, 60 frames/s
//! sent): the reference decoder took 8.6 frames/s at 32769² and 52 at 16385² on an idle
//! machine (it copied, counted and walked a bitset of one bit per grid vertex each frame,
//! and kept up to 32 of them). At 16385², the same server and drive, on a 2-core machine
//! shared with three builds (load 10–12; server and viewer at nice −10): before,
//! 11.0–16.4 frames/s taken of 47–59 sent, 39–41 ms of CPU a frame taken, 1.11 GB peak
//! RSS; with this decoder, its `LiveMesh` and the vertex build slot by slot (and the
//! headless viewer's every-60th full check off its frame loop), 55.5–57.1 frames/s taken,
//! every frame the loaded server sent (55.3–56.8), 6.1–6.6 ms of CPU a frame (the colour
//! tiles and the check included: the decoding, mesh and vertices are under 5 % of the
//! viewer's profile), 33.5–33.8 MB peak RSS (the colour tiles, the cut and 32 bases).

use std::collections::VecDeque;

use crate::bintree::{BitSet, Grid};
use crate::changes::{CHANGES_FORMAT, ChangeReader};
use crate::codec::{self, Check, Decoded, Models};
use crate::cut::CutHash;
use crate::diamonds::DiamondMap;
use crate::format::DecodeError;
use crate::range;

/// One decoded frame's record: the diamonds it toggled (from the cut of the frame decoded
/// before it), each with its height, and its cut's figures.
#[derive(Debug, Default)]
struct Log {
    frame: u64,
    triangles: u32,
    splits: u32,
    hash: u64,
    toggles: Vec<(u32, u16)>,
}

/// The viewer's decoder: the current cut, the logs of recent frames (the bases), and the
/// scratch of decoding.
pub struct Follower {
    grid: Grid,
    /// The current cut's split diamonds and their heights.
    split: DiamondMap<u16>,
    /// The map corners' heights (row-major), from the newest key frame.
    corners: [u16; 4],
    /// Row-major indices of the map corners.
    corner_index: [u32; 4],
    /// Recent frames, oldest first; the newest is the current cut.
    logs: VecDeque<Log>,
    /// Frames kept as bases.
    bases: usize,
    /// Scratch: the changes since the base, composed by parity, with heights.
    undo: DiamondMap<u16>,
    /// Whether `undo` is in use (false: the base is the empty cut of a key frame).
    against: bool,
    /// Scratch: the frame's cut (format 1) or its changes (format 2), with heights.
    fresh: DiamondMap<u16>,
    changes: Vec<u32>,
    order: Vec<u64>,
    list: Vec<u32>,
    next: Vec<u32>,
    models: Box<Models>,
    reader: ChangeReader,
    /// Toggle lists of logs let go, reused.
    spare: Vec<Vec<(u32, u16)>>,
}

impl Follower {
    /// A decoder of `grid`'s frames keeping `bases` frames (at least 1) as bases.
    pub fn new(grid: Grid, bases: usize) -> Follower {
        Follower {
            grid,
            split: DiamondMap::new(),
            corners: [0; 4],
            corner_index: grid.corners().map(|(x, z)| grid.index(x, z)),
            logs: VecDeque::new(),
            bases: bases.max(1),
            undo: DiamondMap::new(),
            against: false,
            fresh: DiamondMap::new(),
            changes: Vec::new(),
            order: Vec::new(),
            list: Vec::new(),
            next: Vec::new(),
            models: Box::new(Models::fresh()),
            reader: ChangeReader::new(grid),
            spare: Vec::new(),
        }
    }

    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// The current cut's frame (`None` before the first frame decoded).
    pub fn frame(&self) -> Option<u64> {
        self.logs.back().map(|l| l.frame)
    }

    /// Whether frames coded against `frame` can be decoded.
    pub fn has_base(&self, frame: u64) -> bool {
        self.logs.iter().any(|l| l.frame == frame)
    }

    /// The current cut's triangles (2 before any frame: the two roots).
    pub fn triangles(&self) -> u32 {
        self.logs.back().map_or(2, |l| l.triangles)
    }

    /// The current cut's split diamonds.
    pub fn splits(&self) -> u32 {
        self.logs.back().map_or(0, |l| l.splits)
    }

    /// The current cut's [`CutHash`] value.
    pub fn hash(&self) -> u64 {
        self.logs.back().map_or(0, |l| l.hash)
    }

    /// Whether diamond `i` is split in the current cut.
    #[inline]
    pub fn contains(&self, i: u32) -> bool {
        self.split.contains(i)
    }

    /// The height of a vertex of the current cut (a split diamond or a map corner); `None`
    /// for any other grid index.
    #[inline]
    pub fn height(&self, i: u32) -> Option<u16> {
        self.split.get(i).or_else(|| self.corner(i))
    }

    #[inline]
    fn corner(&self, i: u32) -> Option<u16> {
        let k = self.corner_index.iter().position(|&c| c == i)?;
        Some(self.corners[k])
    }

    /// The current cut's split diamonds with their heights, in no particular order.
    pub fn split(&self) -> impl Iterator<Item = (u32, u16)> + '_ {
        self.split.iter()
    }

    /// The diamonds the newest frame toggled, each with its height (split or merged, from
    /// the cut before it): a merged diamond's height is no longer in the cut.
    pub fn toggled_heights(&self) -> &[(u32, u16)] {
        self.logs.back().map_or(&[][..], |l| &l.toggles[..])
    }

    /// The diamonds the newest frame toggled (split or merged, from the cut before it).
    pub fn toggled(&self) -> impl ExactSizeIterator<Item = u32> + '_ {
        self.logs
            .back()
            .map_or(&[][..], |l| &l.toggles[..])
            .iter()
            .map(|t| t.0)
    }

    /// Applies the newest frame's toggles to `split` (a bitset over the grid) and
    /// `heights` (row-major, over the grid), and writes the corners' heights: kept so frame
    /// after frame, they are the current cut as [`crate::mesh::emit`] takes it, at
    /// O(changes) a frame. For checks and benchmarks that hold the grid-sized arrays the
    /// decoder does without.
    pub fn mirror(&self, split: &mut BitSet, heights: &mut [u16]) {
        for &(i, h) in self.toggled_heights() {
            if split.contains(i) {
                split.remove(i);
            } else {
                split.insert(i);
                heights[i as usize] = h;
            }
        }
        for (k, &i) in self.corner_index.iter().enumerate() {
            heights[i as usize] = self.corners[k];
        }
    }

    /// Bytes held: the cut, the logs and the scratch (the measure of "proportional to the
    /// cut").
    pub fn bytes(&self) -> usize {
        let logs: usize = self.logs.iter().map(|l| l.toggles.capacity() * 8).sum();
        let spare: usize = self.spare.iter().map(|s| s.capacity() * 8).sum();
        self.split.bytes()
            + self.undo.bytes()
            + self.fresh.bytes()
            + logs
            + spare
            + 4 * (self.changes.capacity() + self.list.capacity() + self.next.capacity())
            + 8 * self.order.capacity()
    }

    /// Decodes frame `frame` (newer than every frame decoded) from `payload`, of either
    /// format, against the frame `base` (`None`: a key frame); on success it is the
    /// current cut and a base for later frames. Refuses meshes of more than
    /// `max_triangles`. On error nothing changes.
    pub fn decode(
        &mut self,
        frame: u64,
        payload: &[u8],
        base: Option<u64>,
        max_triangles: u32,
    ) -> Result<Decoded, DecodeError> {
        if self.frame().is_some_and(|f| frame <= f) {
            return Err(DecodeError::Base);
        }
        let figures = match base {
            Some(b) => {
                let log = self.logs.iter().position(|l| l.frame == b);
                let Some(at) = log else {
                    return Err(DecodeError::Base);
                };
                self.undo.clear();
                for log in self.logs.iter().skip(at + 1) {
                    for &(i, h) in &log.toggles {
                        self.undo.toggle(i, h);
                    }
                }
                self.against = true;
                let l = &self.logs[at];
                (l.triangles, l.splits, l.hash)
            }
            None => {
                self.against = false;
                (2, 0, 0)
            }
        };
        let mut toggles = self.spare.pop().unwrap_or_default();
        toggles.clear();
        let decoded = if payload.first() == Some(&CHANGES_FORMAT) {
            self.decode_changes(payload, figures, max_triangles, &mut toggles)
        } else {
            self.decode_tree(payload, max_triangles, &mut toggles)
        };
        let (decoded, hash, corners) = match decoded {
            Ok(d) => d,
            Err(e) => {
                self.spare.push(toggles);
                return Err(e);
            }
        };
        for &(i, h) in &toggles {
            if self.split.remove(i).is_none() {
                self.split.insert(i, h);
            }
        }
        if let Some(c) = corners {
            self.corners = c;
        }
        self.logs.push_back(Log {
            frame,
            triangles: decoded.triangles,
            splits: decoded.splits,
            hash,
            toggles,
        });
        if self.logs.len() > self.bases
            && let Some(old) = self.logs.pop_front()
        {
            self.spare.push(old.toggles);
        }
        Ok(decoded)
    }

    /// Diamond `i`'s height if it is split in the base (the current cut with `undo`
    /// toggled).
    #[inline]
    fn base(&self, i: u32) -> Option<u16> {
        if !self.against {
            return None;
        }
        match (self.split.get(i), self.undo.get(i)) {
            (Some(h), None) | (None, Some(h)) => Some(h),
            _ => None,
        }
    }

    fn check_grid(&self, payload: &[u8]) -> Result<(), DecodeError> {
        if u32::from(payload[1]) != self.grid.levels() {
            return Err(DecodeError::Grid {
                got: payload[1],
                expected: self.grid.levels(),
            });
        }
        Ok(())
    }

    /// Format 1 (see [`crate::codec`]): the whole cut into `fresh`, then the toggles from
    /// the current cut. O(cut).
    fn decode_tree(
        &mut self,
        payload: &[u8],
        max_triangles: u32,
        toggles: &mut Vec<(u32, u16)>,
    ) -> Result<(Decoded, u64, Option<[u16; 4]>), DecodeError> {
        let grid = self.grid;
        if payload.len() < codec::HEADER {
            return Err(DecodeError::Short(payload.len()));
        }
        if payload[0] != codec::FORMAT {
            return Err(DecodeError::Format(payload[0]));
        }
        self.check_grid(payload)?;
        let delta = payload[2] & 1 != 0;
        if payload[2] > 1 || payload[3] != 0 {
            return Err(DecodeError::Corrupt("unknown flags"));
        }
        if delta != self.against {
            return Err(DecodeError::Base);
        }
        let head = codec::head(payload, max_triangles)?;
        let mut body = &payload[codec::HEADER..];
        let corners = if delta {
            self.corners
        } else {
            let Some((c, rest)) = body.split_at_checked(8) else {
                return Err(DecodeError::Short(payload.len()));
            };
            body = rest;
            [0, 1, 2, 3].map(|k| u16::from_le_bytes([c[2 * k], c[2 * k + 1]]))
        };
        let mut check = Check::of_corners(corners);
        let mut hash = CutHash::new();
        self.models.reset();
        self.fresh.clear();
        let mut rc = range::Decoder::new(body);
        let (mut splits, mut triangles) = (0u32, 2u32);
        codec::start_at_root(&grid, &mut self.list);
        for depth in 0..grid.depths() as usize {
            for &i in &self.list {
                let in_base = self.base(i);
                if !rc.bit(&mut self.models.split[depth][usize::from(in_base.is_some())]) {
                    continue;
                }
                let (x, z) = grid.coords(i);
                splits += 1;
                triangles += grid.added(x, z);
                if splits > head.splits || triangles > head.triangles {
                    return Err(DecodeError::Corrupt("more splits than declared"));
                }
                let h = match in_base {
                    Some(h) => h,
                    None => {
                        let r = codec::decode_residual(&mut rc, &mut self.models, depth)
                            .ok_or(DecodeError::Corrupt("a residual out of range"))?;
                        let (fresh, index) = (&self.fresh, &self.corner_index);
                        let p = codec::predict_by(&grid, x, z, head.step, |j| {
                            fresh
                                .get(j)
                                .or_else(|| index.iter().position(|&c| c == j).map(|k| corners[k]))
                        })
                        .ok_or(DecodeError::Corrupt("a vertex before its hypotenuse"))?;
                        // In i64: a hostile step times a large residual overflows i32.
                        let h = i64::from(p) + i64::from(r) * i64::from(head.step);
                        u16::try_from(h)
                            .map_err(|_| DecodeError::Corrupt("a height out of range"))?
                    }
                };
                self.fresh.insert(i, h);
                check.add(u64::from(i) << 16 | u64::from(h));
                hash.add(i, h);
            }
            if rc.failed() {
                return Err(DecodeError::Corrupt(
                    "the coded bits end early or are not ours",
                ));
            }
            let fresh = &self.fresh;
            codec::next_candidates_by(&grid, &self.list, |j| fresh.contains(j), &mut self.next);
            std::mem::swap(&mut self.list, &mut self.next);
        }
        if splits != head.splits || triangles != head.triangles {
            return Err(DecodeError::Corrupt("fewer splits than declared"));
        }
        if check.value() != head.check {
            return Err(DecodeError::Check);
        }
        // The toggles from the current cut: O(cut), as the decoding was.
        toggles.extend(self.split.iter().filter(|e| !self.fresh.contains(e.0)));
        toggles.extend(self.fresh.iter().filter(|e| !self.split.contains(e.0)));
        let decoded = Decoded {
            triangles,
            splits,
            key: !delta,
        };
        Ok((decoded, hash.value(), (!delta).then_some(corners)))
    }

    /// Whether diamond `i` is split in the change frame's cut (the base with `fresh`
    /// toggled).
    #[inline]
    fn in_frame(&self, i: u32) -> bool {
        self.base(i).is_some() != self.fresh.contains(i)
    }

    /// A vertex's height in the change frame's cut.
    #[inline]
    fn frame_height(&self, i: u32) -> Option<u16> {
        match (self.base(i), self.fresh.get(i)) {
            (Some(h), None) | (None, Some(h)) => Some(h),
            (Some(_), Some(_)) => None,
            (None, None) => self.corner(i),
        }
    }

    /// Format 2 (see [`crate::changes`]) against the base whose figures are `base`
    /// (triangles, splits, hash). O(changes since the base + changes in the frame).
    fn decode_changes(
        &mut self,
        payload: &[u8],
        base: (u32, u32, u64),
        max_triangles: u32,
        toggles: &mut Vec<(u32, u16)>,
    ) -> Result<(Decoded, u64, Option<[u16; 4]>), DecodeError> {
        let grid = self.grid;
        let (head, mut body) = self.reader.read(payload, base.1, max_triangles)?;
        if !self.against {
            return Err(DecodeError::Base);
        }
        self.order.clear();
        self.fresh.clear();
        self.reader.changes(&mut body, &mut self.changes)?;
        let (mut triangles, mut splits) = (i64::from(base.0), i64::from(base.1));
        let mut hash = CutHash(base.2);
        for &i in &self.changes {
            let (x, z) = grid.coords(i);
            let added = i64::from(grid.added(x, z));
            match self.base(i) {
                Some(h) => {
                    triangles -= added;
                    splits -= 1;
                    hash.remove(i, h);
                    self.fresh.insert(i, h);
                }
                None => {
                    triangles += added;
                    splits += 1;
                    self.fresh.insert(i, 0); // its height comes below
                    self.order
                        .push(u64::from(grid.depth(x, z)) << 32 | u64::from(i));
                }
            }
        }
        if triangles != i64::from(head.triangles) || splits != i64::from(head.splits) {
            return Err(DecodeError::Check);
        }
        // New vertices, coarser first: a split's hypotenuse ends are known before it.
        self.order.sort_unstable();
        for k in 0..self.order.len() {
            let o = self.order[k];
            let (i, depth) = (o as u32, (o >> 32) as usize);
            let (x, z) = grid.coords(i);
            let r = self.reader.residual(&mut body, depth)?;
            // An end not in the frame's cut: the cut is not closed.
            let step = i32::from(head.step);
            let p = codec::predict_by(&grid, x, z, step, |j| self.frame_height(j))
                .ok_or(DecodeError::Check)?;
            let h = head.height(p, r)?;
            self.fresh.insert(i, h);
            hash.add(i, h);
        }
        body.finish()?;
        // Closed under parent, given a closed base: every split's parents are split, and
        // no merged diamond keeps a split child.
        for &i in &self.changes {
            let (x, z) = grid.coords(i);
            let closed = if self.in_frame(i) {
                grid.parents(x, z)
                    .into_iter()
                    .flatten()
                    .all(|(px, pz)| self.in_frame(grid.index(px, pz)))
            } else {
                !grid
                    .children(x, z)
                    .into_iter()
                    .flatten()
                    .any(|(cx, cz)| self.in_frame(grid.index(cx, cz)))
            };
            if !closed {
                return Err(DecodeError::Check);
            }
        }
        if hash.value() != head.check {
            return Err(DecodeError::Check);
        }
        // The toggles from the current cut: the changes since the base, and the frame's.
        let toggle = |i: u32| {
            let now = self.in_frame(i);
            match self.split.get(i) {
                Some(h) if !now => Some((i, h)),
                None if now => Some((i, self.frame_height(i).unwrap_or(0))),
                _ => None,
            }
        };
        toggles.extend(self.undo.iter().filter_map(|(i, _)| toggle(i)));
        toggles.extend(
            self.fresh
                .iter()
                .filter(|(i, _)| !self.undo.contains(*i))
                .filter_map(|(i, _)| toggle(i)),
        );
        let decoded = Decoded {
            triangles: head.triangles,
            splits: head.splits,
            key: false,
        };
        Ok((decoded, hash.value(), None))
    }
}
