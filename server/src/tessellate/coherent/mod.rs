//! Frame-coherent ROAM: a viewer's cut carried from frame to frame with splits and merges
//! (Duchaineau et al. 1997, §5–7), so the work per frame follows what changed.
//!
//! The cut is a set of split diamonds ([`PosSet`], sized by the cut: no per-viewer state
//! is sized by the map). Two frontiers are kept incrementally ([`Frontier`]): **split
//! candidates** (unsplit diamonds with at least one split parent: what from-scratch
//! split-only would have queued) and **merge candidates** (split diamonds none of whose
//! children are split). Each frontier diamond keeps its last evaluation in its record
//! ([`frontier::Member`]) and sits in a priority-bucket queue by it, kept from frame to
//! frame ([`buckets`]). Each frame:
//!
//! 1. The frontier diamonds whose kept evaluation is due are evaluated again, with the
//!    very function the from-scratch tessellator uses ([`super::evaluate::priority`]),
//!    four at a time, and queued again (ROAM's deferred priority recomputation, §7.3):
//!    each evaluation also says how far the eye may travel, and how far it may turn,
//!    before the diamond's priority could drift by 2 % (its distance, and with it the
//!    fog's transmission, changes by at most the eye's travel: `eval.rs`), its frustum
//!    verdict could flip (a plane through the eye moves a point at distance `r` by at
//!    most travel + `r` × turn, and the verdict holds while that stays under the prism's
//!    margin to the plane), or the eye could enter or leave its footprint; two odometers (travel and turn, summed over frames) say when, and
//!    two schedules ([`buckets::Schedule`]) hand out exactly the diamonds due. Diamonds
//!    under the eye are due every frame, exact ones never again. Splits are queued
//!    highest first, merges lowest first. Merge candidates that are exact, wholly outside
//!    the view pyramid or below the threshold are *unwanted*: from scratch would not have
//!    split them, so they are merged first, whatever the budget. The diamonds under the
//!    eye are never merged.
//! 2. While over budget, the lowest merge candidate is merged. Otherwise the highest split
//!    candidate is split (with its forced splits, exactly as from scratch) if it fits the
//!    budget; if it does not, the lowest merge candidate is merged instead when its
//!    priority is below the split's by more than the swap margin
//!    ([`Coherent::set_swap_margin`]; with none, ROAM's rule: strictly below), and the
//!    loop stops when it is not.
//!    Splits and merges update both frontiers and queue the diamonds they uncover.
//! 3. The frame's changes are logged in order (a diamond may appear twice: split, then
//!    merged); the codec composes logs into the difference from any base a viewer holds.
//!
//! A loaded server gives the loop an allowance ([`Coherent::set_allowance`]): past it the
//! frame goes on only with the splits above [`LAG_PX`] (or [`LAG_FACTOR`] times the error
//! the budget gets the cut to, times [`Coherent::set_lag_scale`]) and the merges that make
//! room for them, and the frames after carry on from there; its kept evaluations then lag
//! a turn inside the guard band ([`TURN_LAG_SHARE`]).
//!
//! The loop is bounded (a quarter of the budget plus 256 changes); a frame that reaches
//! the bound, a camera jump (a turn of more than 30°, a move of more than 64 grid cells),
//! a new field of view or viewport, a new threshold, guard band or fog density (the viewer
//! turned its fog on or off), a budget change of more than ×2, or the caller's say
//! rebuilds the cut from scratch with split-only ROAM, the spec's algorithm, on a
//! tessellator borrowed from the server's [`Scratch`], and logs the difference from the
//! old cut.
//!
//! A frame may be made in two steps ([`Coherent::begin`], then [`Coherent::finish`]): the
//! first does at most a given number of changes and stops before anything heavy (a
//! rebuild), so the server makes it on its async workers and hands only what is left to
//! a blocking thread. The queues are kept between the two, so the second goes on where
//! the first stopped.
//!
//! **Cost**: on `kossou` at 32,768 triangles, a frame of driving evaluates 10 to 20 of
//! some 22,000 frontier diamonds; nothing else in a frame walks the frontiers, so a frame
//! costs what it evaluates and changes. (Queuing every frontier diamond each frame, as
//! this did before, cost 150–200 µs a frame whatever changed.)
//!
//! **Memory** (issue 22: a viewer within 4 MB, aim 2, everything counted, at 65,536
//! triangles). `heap_bytes` counts what is reserved (capacities), and the bench reports
//! it at the drive's end and its peak after any frame (`serve_viewer_heap_bytes_peak`).
//! On `kossou` at 65,536 triangles (32,913 split diamonds, 30,781 split and 8,496 merge
//! candidates at the drive's end):
//!
//! | | before | now |
//! |---|---|---|
//! | split set | 1.31 MB (list + `(position, index)` table ≤ ½ full) | 0.20 MB (a table of positions, 40–80 % full) |
//! | split candidates | 5.51 MB (64-byte entries, `Vec` reserve, table) | 1.34 MB (36-byte records in chunks + index) |
//! | split queue, schedules | 4.27 MB (63,687 + 108,874 entries, half stale) | 16 KB (bucket heads; links in the records) |
//! | merge side | 2.97 MB | 0.39 MB |
//! | scratch | 0.39 MB (rebuild lists kept) | 37 KB |
//! | total (peak) | 14.46 MB | 1.99 MB (2.21 MB) |
//!
//! At 32,768: 7.11 MB, now 1.11 MB (peak 1.25 MB). The decisions, each measured in its
//! file: lists threaded through the records, not entries pushed per evaluation and
//! compacted ([`buckets`]); the camera-independent part of an evaluation gathered again
//! rather than kept, links of 24 bits, records in chunks ([`frontier`],
//! [`super::frontier`]); odometer keys in fixed point ([`Odometer`]). The median frame
//! got faster, the heaviest slower ([`buckets`]: `serve_frame_us_median` at 32,768, six
//! runs of each in turn on a busy machine, 17–41 µs before, 13–21 µs after).

mod audit;
mod audit_error;
mod buckets;
mod eval;
mod frontier;
mod odometer;
mod ops;

pub use audit::{fogged_error_px, measured_error};
pub use audit_error::{AuditError, ListError};

use self::frontier::{DROPPED, Frontier};
use self::odometer::{Odometer, TRAVEL_SCALE, TURN_SCALE};
use super::frontier::PosSet;
use super::{Frame, Limits, Mesh, Scales, Scratch, pack, unpack};
use crate::terrain::heightfield::Heightfield;
use crate::terrain::variance::VarianceTree;
use crate::tessellate::camera::Camera;
use crate::tessellate::queue::{TOP, bucket_of};

/// How the last frame's cut was made.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    /// From scratch (split-only ROAM), the difference from the old cut logged.
    Rebuild,
    /// The old cut, split and merged.
    Update,
}

/// How far [`Coherent::begin`] got.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Step {
    /// The frame is made, this way.
    Done(Mode),
    /// Heavier work is left (more changes than allowed, or a rebuild): call
    /// [`Coherent::finish`] before anything else.
    Unfinished,
}

/// Counts from the last frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CoherentStats {
    /// Frontier diamonds whose priority was computed.
    pub evaluated: u32,
    /// Diamonds split and merged (forced splits included).
    pub splits: u32,
    pub merges: u32,
    /// Members taken from the two frontiers' schedules, due.
    pub popped: u32,
    /// The update stopped at its allowance ([`Coherent::set_allowance`]), with changes
    /// perhaps still worth making: the frames after go on from there.
    pub short: bool,
}

/// The camera and limits of the last frame, to tell a jump from a step.
#[derive(Clone, Copy)]
struct Last {
    camera: Camera,
    limits: Limits,
}

/// A frame [`Coherent::begin`] left for [`Coherent::finish`].
#[derive(Clone, Copy)]
enum Left {
    /// The update stopped after this many changes, within its bound.
    Update { changes: u32 },
    /// The cut is to be rebuilt from scratch.
    Rebuild,
}

/// One viewer's cut, carried from frame to frame.
pub struct Coherent {
    size: u32,
    /// The split diamonds (packed positions).
    split: PosSet,
    splits: Frontier,
    merges: Frontier,
    /// Scratch for forced splits: the unsplit parents a split needs, parents first.
    chain: Vec<u32>,
    /// Scratch: the members due this frame.
    due: Vec<u32>,
    /// How far the eye has travelled and turned: the odometers a kept evaluation is due
    /// against.
    odometers: [Odometer; 2],
    /// How far the eye has lately travelled and turned a frame (a moving average): how an
    /// evaluation shares its margin between the two ([`eval`]).
    pace: (f32, f32),
    /// This frame's changes (packed positions), in order.
    log: Vec<u32>,
    triangles: u32,
    split_count: u32,
    error_bound_px: f32,
    dropped: f32,
    last: Option<Last>,
    left: Option<Left>,
    mode: Mode,
    stats: CoherentStats,
    /// A merge makes room for a split only when the split's priority exceeds the merge's
    /// times this (1: ROAM's rule).
    swap_margin: f32,
    /// The most changes an update makes in a frame once the cut is within its budget.
    allowance: u32,
    /// What the lag's bound is multiplied by past the allowance ([`Coherent::set_lag_scale`]).
    lag_scale: f32,
    /// Under an allowance, what a kept evaluation may lag a turn by, radians (see
    /// [`TURN_LAG_SHARE`]; 0 without).
    turn_lag: f32,
}

/// Past its allowance ([`Coherent::set_allowance`]) a frame's update still makes the splits
/// whose priority (the screen-space error they remove, pixels) is above this, or above
/// [`LAG_FACTOR`] times the error the budget gets the cut to (its cheapest merge candidate:
/// [`Coherent::lag_px`]), whichever is more: what a loaded server lets lag is detail under
/// a pixel, or under twice what the budget gets where it cannot get that far. Read from
/// the last whole frame instead, the bound froze under load wherever that frame was: a
/// review measured 42–119 px left where a cut with no allowance left 0–38. With an
/// allowance alone, of 64 changes a frame, the error left along
/// `scripts/capacity-drive.txt` (p99, 32 viewers' cuts) went from 0.14 to 0.68 px on
/// `data/kossou` and from 2.5 to 52 px on the steep map; of 32, to 3.4 and 1,270 px.
const LAG_PX: f32 = 1.0;
const LAG_FACTOR: f32 = 2.0;

/// Under an allowance, a kept evaluation falls due later in a turn than its frustum
/// margin says, by up to this share of the guard band (the side planes only: the band
/// widens them; scaled down near the vertical through the eye, where the band is
/// narrow: `eval.rs`): a diamond entering the view is evaluated again by the time it is
/// that far into the band, still outside the view, and one leaving it stays split a little
/// longer. Most of a turn's evaluations are of diamonds near the frustum's edges, each
/// evaluated several times as its margin shrinks. Along `scripts/capacity-drive.txt`, 32
/// viewers' cuts held to 4 changes a frame (`roam-server bench DIR --budget 32768 --drive
/// ... --allowance 4`, 2026-12-08): on `data/kossou` 112 → 71 evaluations a frame, 44 → 28
/// µs, the error left (p99) 1.0 px either way; on the steep map 415 → 309 evaluations
/// (its held frames are changes: [`crate::viewer::Allowance`]'s lag at the floor). The
/// first version lagged every plane by the whole share: a test turning low over rough
/// ground found 13 million pixels left at the foot of the eye. Without a guard band (the
/// spec's split-only ROAM) there is no lag.
const TURN_LAG_SHARE: f32 = 0.5;

/// A frame's log keeps at most this much reserved into the next frame.
const LOG_KEPT: usize = 1024;

/// Rebuild rather than update past these camera changes.
const JUMP_DEGREES: f64 = 30.0;
const JUMP_CELLS: f64 = 64.0;

impl Coherent {
    /// An empty cut (the two roots) for a map of this `side` (`2^N + 1`): nothing sized by
    /// the map.
    pub fn new(side: u32) -> Coherent {
        Coherent {
            size: side - 1,
            split: PosSet::default(),
            splits: Frontier::new(false),
            merges: Frontier::new(true),
            chain: Vec::new(),
            due: Vec::new(),
            odometers: [Odometer::new(TRAVEL_SCALE), Odometer::new(TURN_SCALE)],
            pace: (0.0, 0.0),
            log: Vec::new(),
            triangles: 2,
            split_count: 0,
            error_bound_px: 0.0,
            dropped: 0.0,
            last: None,
            left: None,
            mode: Mode::Rebuild,
            stats: CoherentStats::default(),
            swap_margin: 1.0,
            allowance: u32::MAX,
            lag_scale: 1.0,
            turn_lag: 0.0,
        }
    }

    /// Past its allowance, a frame makes only the splits above this priority, pixels: a
    /// pixel, or twice the error the budget gets the cut to, read from the cheapest merge
    /// candidate it would trade (the two queues meet there once the cut has caught up); a
    /// pixel while the cut is under its budget (it could then take every split). Read
    /// under the budget too, the lag let 24 px through in a spin on the steep map (p99,
    /// 4 changes a frame), and 158 px against 52 in the test beside a cut with none.
    pub fn lag_px(&self, budget: u32) -> f32 {
        let level = if self.triangles < budget {
            0.0
        } else {
            self.peek_merge().map_or(0.0, |(_, prio)| prio)
        };
        self.lag_scale * LAG_PX.max(LAG_FACTOR * level)
    }

    /// Whether an update stopped now would leave anything it would do: an unwanted split to
    /// merge, or a split candidate that fits the budget or beats the cheapest merge.
    fn work_left(&self, budget: u32) -> bool {
        let merge = self.peek_merge();
        if merge.is_some_and(|(b, _)| b == TOP) {
            return true;
        }
        let Some((b, split)) = self.splits.peek() else {
            return false;
        };
        let gain = if b == TOP { f32::INFINITY } else { split.prio };
        self.triangles < budget || merge.is_some_and(|(_, loss)| loss * self.swap_margin < gain)
    }

    /// A merge makes room for a split, once the cut is at its budget, only when the split's
    /// priority exceeds the merge's by more than `pct` percent (0, the default: ROAM's
    /// rule, any gain). Diamonds of nearly equal priority are then not traded back and
    /// forth as the eye moves: the cut changes less, and what it leaves is at most this
    /// much worse than the budget could have (`serve --swap-margin`, README: what the
    /// driver sees). Rebuilds are the spec's split-only ROAM either way.
    pub fn set_swap_margin(&mut self, pct: u16) {
        self.swap_margin = 1.0 + f32::from(pct) / 100.0;
    }

    /// An update stops after `changes` changes (forced splits counted, a split's chain
    /// finished) once the cut is within its budget, and the frame is made with the cut it
    /// reached; the frames after go on from there, the most important changes first (both
    /// queues are in priority order). ROAM's optimisation may stop at any time with the
    /// best cut so far: this is what lets a loaded server keep its frame rate, the cut
    /// lagging a turn by a few frames instead of every viewer losing frames
    /// (`net/frames.rs` sets it from how late frames start). `u32::MAX` (the default):
    /// no allowance. A rebuild is never stopped.
    ///
    /// Under an allowance the kept evaluations also lag a turn by half the guard band
    /// ([`TURN_LAG_SHARE`]).
    pub fn set_allowance(&mut self, changes: u32) {
        self.allowance = changes.max(1);
    }

    /// Past its allowance, a frame makes only the splits above `scale` (at least 1) times
    /// [`Coherent::lag_px`]'s bound: how much more a server far behind lets lag.
    pub fn set_lag_scale(&mut self, scale: f32) {
        self.lag_scale = scale.max(1.0);
    }

    /// Triangles in the cut.
    pub fn triangles(&self) -> u32 {
        self.triangles
    }

    /// Split diamonds in the cut.
    pub fn split_count(&self) -> u32 {
        self.split_count
    }

    /// The largest screen-space error left unsplit at the last frame's camera, pixels.
    pub fn error_bound_px(&self) -> f32 {
        self.error_bound_px
    }

    pub fn mode(&self) -> Mode {
        self.mode
    }

    pub fn stats(&self) -> CoherentStats {
        self.stats
    }

    /// The last frame's changes, as packed positions (`x | z << 16`) in the order they
    /// happened; a diamond split and merged again appears twice.
    pub fn changes(&self) -> &[u32] {
        &self.log
    }

    /// Whether the diamond centred at `(x, z)` is split.
    pub fn is_split(&self, x: u32, z: u32) -> bool {
        self.split.contains(pack(x, z))
    }

    /// The split diamonds, row-major (sorted: for key frames and tests, not per frame).
    pub fn split_diamonds(&self) -> impl Iterator<Item = (u32, u32)> + use<> {
        let mut list: Vec<u32> = self.split.iter().collect();
        list.sort_unstable();
        list.into_iter().map(unpack)
    }

    /// Calls `f` with the split set as the codec's row-major bitset over the map, on a
    /// tessellator borrowed from `scratch`.
    pub fn with_split_set<R>(
        &self,
        scratch: &Scratch,
        f: impl FnOnce(&roam_protocol::BitSet) -> R,
    ) -> R {
        scratch.with(|t| {
            t.load_cut(self.split.iter(), self.triangles);
            t.with_split_set(f)
        })
    }

    /// Writes the cut's mesh (the from-scratch tessellator's layout and order), on a
    /// tessellator borrowed from `scratch`.
    pub fn mesh(&self, scratch: &Scratch, out: &mut Mesh) {
        scratch.with(|t| {
            t.load_cut(self.split.iter(), self.triangles);
            t.emit(out);
        });
        out.error_bound_px = self.error_bound_px;
    }

    /// Bytes of per-viewer state currently reserved (capacities, not lengths).
    pub fn heap_bytes(&self) -> usize {
        self.heap_parts().iter().map(|&(_, bytes, _)| bytes).sum()
    }

    /// Where the per-viewer bytes go: `(part, bytes reserved, entries)`.
    pub fn heap_parts(&self) -> Vec<(&'static str, usize, usize)> {
        let f = |name, f: &Frontier| {
            let (queued, moved, turned) = f.counts();
            [
                (name, f.members_bytes(), f.len()),
                ("index", f.index_bytes(), f.len()),
                ("queue", f.queue_bytes(), queued),
                ("due_moved", f.schedule_bytes(0), moved),
                ("due_turned", f.schedule_bytes(1), turned),
            ]
        };
        let mut v = vec![("split", self.split.heap_bytes(), self.split.len())];
        v.extend(f("split_cands", &self.splits));
        v.extend(f("merge_cands", &self.merges));
        v.push((
            "scratch",
            (self.chain.capacity() + self.due.capacity() + self.log.capacity()) * 4,
            0,
        ));
        v
    }

    /// Brings the cut up to date for `camera`: split and merge, or rebuild from scratch
    /// (on a tessellator borrowed from `scratch`) on a jump, a bounded update that did not
    /// finish, or when `rebuild` says so.
    #[allow(clippy::too_many_arguments)]
    pub fn frame(
        &mut self,
        hf: &Heightfield,
        variance: &VarianceTree,
        scales: Scales,
        camera: &Camera,
        limits: Limits,
        rebuild: bool,
        scratch: &Scratch,
    ) -> Mode {
        match self.begin(hf, variance, scales, camera, limits, rebuild, u32::MAX) {
            Step::Done(mode) => mode,
            Step::Unfinished => self.finish(hf, variance, scales, scratch),
        }
    }

    /// The first step of a frame: the update, stopping after `most` changes (forced
    /// splits counted) or before a rebuild; `Step::Unfinished` then says that
    /// [`Self::finish`] must come next.
    #[allow(clippy::too_many_arguments)]
    pub fn begin(
        &mut self,
        hf: &Heightfield,
        variance: &VarianceTree,
        scales: Scales,
        camera: &Camera,
        limits: Limits,
        rebuild: bool,
        most: u32,
    ) -> Step {
        assert!(self.left.is_none(), "a frame was begun and not finished");
        self.log.clear();
        // A rebuild's log (the difference of two cuts) is not kept reserved for the small
        // ones that follow.
        if self.log.capacity() > LOG_KEPT {
            self.log = Vec::new();
        }
        self.stats = CoherentStats::default();
        let jump = rebuild || self.jumped(camera, limits, scales);
        if let Some(last) = &self.last {
            let (moved, yaw, pitch) = motion(&last.camera, camera);
            self.odometers[0].reading += moved;
            // A yaw and a pitch change compose into a rotation of at most their sum.
            let turned = (yaw + pitch).to_radians();
            self.odometers[1].reading += turned;
            let ease = |old: f32, new: f64| 0.75 * old + 0.25 * new as f32;
            self.pace = (ease(self.pace.0, moved), ease(self.pace.1, turned));
        }
        self.last = Some(Last {
            camera: *camera,
            limits,
        });
        self.turn_lag = if self.allowance < u32::MAX {
            (limits.guard_deg.max(0.0) * TURN_LAG_SHARE).to_radians()
        } else {
            0.0
        };
        if jump {
            self.left = Some(Left::Rebuild);
            return Step::Unfinished;
        }
        let f = Frame::new(hf, variance, scales, camera, limits);
        self.rebase();
        self.evaluate_due(&f);
        self.run(&f, limits, 0, most)
    }

    /// The rest of a frame [`Self::begin`] left: the update goes on within its bound, and
    /// a rebuild (on a tessellator borrowed from `scratch`) follows if it needs one.
    pub fn finish(
        &mut self,
        hf: &Heightfield,
        variance: &VarianceTree,
        scales: Scales,
        scratch: &Scratch,
    ) -> Mode {
        let last = self.last.expect("a frame was begun");
        let limits = last.limits;
        let f = Frame::new(hf, variance, scales, &last.camera, limits);
        if let Some(Left::Update { changes }) = self.left.take()
            && let Step::Done(mode) = self.run(&f, limits, changes, u32::MAX)
        {
            return mode;
        }
        self.left = None;
        self.rebuild(&f, scratch, hf, variance, scales, &last.camera, limits);
        self.mode = Mode::Rebuild;
        self.mode
    }

    /// Runs the update loop from `changes` done, stopping after `most`; a loop that
    /// reaches its bound leaves a rebuild.
    fn run(&mut self, f: &Frame, limits: Limits, changes: u32, most: u32) -> Step {
        match self.update(f, limits, changes, most) {
            Ok(()) => {
                self.error_bound_px = self.bound(limits);
                self.mode = Mode::Update;
                Step::Done(Mode::Update)
            }
            Err(Some(changes)) => {
                self.left = Some(Left::Update { changes });
                Step::Unfinished
            }
            Err(None) => {
                self.left = Some(Left::Rebuild);
                Step::Unfinished
            }
        }
    }

    /// Whether a frame at `camera` would rebuild the cut rather than update it (a jump).
    pub fn jumped(&self, camera: &Camera, limits: Limits, scales: Scales) -> bool {
        let Some(last) = self.last else {
            return true;
        };
        let (c, l) = (&last.camera, &last.limits);
        let (moved, yaw, pitch) = motion(c, camera);
        yaw > JUMP_DEGREES
            || pitch > JUMP_DEGREES
            || moved > JUMP_CELLS * scales.h
            || camera.fov_y_deg != c.fov_y_deg
            || (camera.width, camera.height) != (c.width, c.height)
            || limits.threshold_px != l.threshold_px
            || limits.fog_density.to_bits() != l.fog_density.to_bits()
            || limits.guard_deg.to_bits() != l.guard_deg.to_bits()
            || limits.budget > 2 * l.budget
            || 2 * limits.budget < l.budget
    }

    /// From scratch: split-only ROAM on a borrowed tessellator, then the difference from
    /// the old cut logged and the frontiers rebuilt.
    #[allow(clippy::too_many_arguments)]
    fn rebuild(
        &mut self,
        f: &Frame,
        scratch: &Scratch,
        hf: &Heightfield,
        variance: &VarianceTree,
        scales: Scales,
        camera: &Camera,
        limits: Limits,
    ) {
        // The log keeps what an unfinished update did before: the difference logged here is
        // from the cut as that update left it.
        let logged = self.log.len();
        // Both lists live as long as the rebuild: a rebuild is rare, and kept they would
        // hold the cut twice over.
        let mut old: Vec<u32> = self.split.iter().collect();
        old.sort_unstable();
        // The frontiers' members are found while the tessellator is still lent (its bitset
        // says what is split: a bit test where the split set's table is a probe); the
        // split set and the evaluations come after it is given back.
        let mut new = Vec::new();
        let mut added = Vec::new();
        scratch.with(|t| {
            t.cut(hf, variance, scales, camera, limits);
            self.triangles = t.triangles;
            new.extend_from_slice(&t.active_list);
            new.sort_unstable();
            // The difference of two row-major lists (packed positions sort row-major),
            // logged; what left the cut is removed on the way, what joined it kept for
            // after (removals first, so none shrinks a table sized for the new cut).
            let (mut i, mut j) = (0, 0);
            while i < old.len() || j < new.len() {
                match (old.get(i), new.get(j)) {
                    (Some(a), Some(b)) if a == b => (i, j) = (i + 1, j + 1),
                    (Some(&a), Some(&b)) if a < b => {
                        self.log.push(a);
                        self.split.remove(a);
                        i += 1;
                    }
                    (Some(&a), None) => {
                        self.log.push(a);
                        self.split.remove(a);
                        i += 1;
                    }
                    (_, Some(&b)) => {
                        self.log.push(b);
                        added.push(b);
                        j += 1;
                    }
                    (None, None) => break,
                }
            }
            self.rebuild_frontiers(&new, |p| {
                let (x, z) = unpack(p);
                t.is_active(x, z)
            });
        });
        self.split_count = new.len() as u32;
        self.split.reserve(new.len());
        for &p in &added {
            self.split.insert(p);
        }
        self.stats.splits += (self.log.len() - logged) as u32;
        self.evaluate_frontiers(f);
        self.error_bound_px = self.bound(limits);
    }

    /// Splits and merges the old cut towards the new camera from `changes` done: `Ok`
    /// when it is done, `Err(Some(changes))` when it stopped after `most`, `Err(None)`
    /// when it reached its bound (or cannot get under budget): a rebuild is needed.
    fn update(
        &mut self,
        f: &Frame,
        limits: Limits,
        mut changes: u32,
        most: u32,
    ) -> Result<(), Option<u32>> {
        let budget = limits.budget.max(2);
        let bound = budget / 4 + 256;
        loop {
            if changes > bound {
                return Err(None);
            }
            // Past the allowance, the splits in the lag's bucket and above go on (with the
            // merges that make room for them): what is left is below the lag.
            if changes >= self.allowance
                && self.triangles <= budget
                && self
                    .splits
                    .peek()
                    .is_none_or(|(b, _)| b < bucket_of(self.lag_px(budget)))
            {
                self.stats.short = self.work_left(budget);
                break;
            }
            if changes >= most {
                return Err(Some(changes));
            }
            // Unwanted splits, and anything while over budget, are merged first.
            if self.triangles > budget || self.peek_merge().is_some_and(|(b, _)| b == TOP) {
                match self.pop_merge() {
                    Some(pos) => {
                        self.merge(f, pos);
                        changes += 1;
                        continue;
                    }
                    None if self.triangles > budget => return Err(None),
                    None => {}
                }
            }
            let Some((bucket, pos, prio)) = self.pop_split() else {
                break;
            };
            let (x, z) = unpack(pos);
            self.chain.clear();
            let cost = self.collect(x, z);
            if self.triangles + cost <= budget {
                for k in 0..self.chain.len() {
                    let c = self.chain[k];
                    self.split(f, c);
                    changes += 1;
                }
                continue;
            }
            // It does not fit: make room if a merge costs less error than the split gains.
            let gain = if bucket == TOP { f32::INFINITY } else { prio };
            match self.peek_merge() {
                Some((_, loss)) if loss * self.swap_margin < gain => {
                    let merged = self.pop_merge().expect("peeked above");
                    self.merge(f, merged);
                    changes += 1;
                    self.splits.requeue(pos);
                }
                _ => {
                    self.splits.requeue(pos);
                    break;
                }
            }
        }
        Ok(())
    }

    /// The error the cut leaves: the highest split candidate still queued, and with a
    /// threshold the highest of those below it (a walk of the frontier, only then).
    fn bound(&mut self, limits: Limits) -> f32 {
        if limits.threshold_px > 0.0 {
            self.dropped = self
                .splits
                .members()
                .filter(|m| m.flags & DROPPED != 0)
                .map(|m| m.prio)
                .fold(0.0, f32::max);
        } else {
            self.dropped = 0.0;
        }
        self.splits.max_queued().max(self.dropped)
    }
}

/// How far the eye moved between two cameras (world units), and how far the view turned
/// in yaw and in pitch (degrees, the short way round).
fn motion(a: &Camera, b: &Camera) -> (f64, f64, f64) {
    let moved = (0..3)
        .map(|i| (b.eye[i] - a.eye[i]).powi(2))
        .sum::<f64>()
        .sqrt();
    // The turn in `[0, 360]`: 360 itself (a tiny negative turn rounded) is the short way 0,
    // as it is once wrapped to 0.
    let yaw = (b.yaw_deg - a.yaw_deg).rem_euclid(360.0);
    (
        moved,
        yaw.min(360.0 - yaw),
        (b.pitch_deg - a.pitch_deg).abs(),
    )
}

#[cfg(test)]
mod tests;
