//! The per-viewer core: what one viewer's frame loop decides, with no socket, task or
//! clock (as `quinn-proto` is to `quinn`). The `net` shell paces frames, feeds it the
//! viewer's control messages as [`Event`]s and the world's newest vehicle state, and sends
//! the bytes it returns.
//!
//! Each frame: the camera at the followed vehicle (the viewer's [`ViewChange`] applied),
//! the cut carried from the last frame by the split/merge tessellator ([`Coherent`]: it
//! rebuilds from scratch on a jump), its priority weighing each error by the map's fog
//! while the viewer draws it ([`ViewerCore::fog_density`]: a toggle rebuilds the cut),
//! and the frame's mesh payload:
//!
//! - a **change frame** (protocol format 2) against its base: the newer of the newest
//!   frame the viewer acknowledged and the pending key frame (below). It is coded from
//!   the change logs of the frames since the base: their composition (a diamond toggled
//!   an even number of times has not changed) is exactly the difference between the
//!   viewer's base and the cut now, so coding it costs what changed, not the cut;
//! - a **key frame** (format 1, the whole cut) for the first frame, when the viewer asks
//!   for one, when the base is older than the logs kept ([`LOGS`] frames), or when the
//!   change list would cost more than twice the whole cut (changes past a third of the
//!   triangles: see `encode_changes`). No other frame is a key frame: not
//!   the frames made while a key frame is on its way and not yet acknowledged.
//!
//! A key frame is the viewer's next base whatever happens to the frames around it: the
//! shell sends it reliably, never abandoned while it is pending, so until the viewer
//! acknowledges it (or a newer frame) the frames after it are coded against it
//! ([`ViewerCore::pending_key`]) rather than made as key frames again (each as large as
//! the first, on a path that may not carry one a frame interval). It stops being pending
//! when an acknowledgement reaches it, when the viewer asks for a key frame, or when a
//! newer key frame supersedes it (the shell then abandons it). Any other lost or abandoned
//! frame is never a base (only acknowledged frames and the pending key frame are), so it
//! cannot corrupt a later one; the viewer checks every frame against the cut's hash.
//!
//! **Memory** follows the cut and the frames in flight: the cut, its frontiers and queues
//! (all sized by the cut), and the logs of the last [`LOGS`] frames; no split set of any
//! base is stored, and nothing is sized by the map. What needs a bitset over the map (a
//! rebuild from scratch, a key frame's coding) borrows a tessellator from the server's
//! [`Scratch`], one per blocking frame maker, shared by every viewer.
//!
//! **Two steps**: [`ViewerCore::begin_frame`] makes a frame when it is cheap (an update
//! of at most [`INLINE_CHANGES`] changes coded as a change frame) and otherwise stops
//! before the heavy part (more changes, a rebuild, a key frame's coding), which
//! [`ViewerCore::finish_frame`] does: the shell makes the first on its async workers and
//! the second on a blocking thread, so nothing heavy runs on the workers whatever the
//! budget.

use std::collections::VecDeque;

use roam_protocol::messages::{self, Hello, ViewChange};
use roam_protocol::{ChangeEncoder, CutHash, Grid, MeshEncoder};

use crate::Terrain;
use crate::sim::physics::{VehicleState, altitude};
use crate::terrain::heightfield::Heightfield;
use crate::terrain::variance::VarianceTree;
use crate::tessellate::camera::Camera;
use crate::tessellate::{Coherent, Limits, Mode, Scales, Scratch, Step};

pub mod admission;
mod allowance;
mod camera;
pub mod color;
pub mod conversation;
mod cut_args;

pub use allowance::Allowance;
pub use camera::apply_view;
pub use cut_args::{CutArgs, FogPriority};

/// The most changes (splits and merges, forced ones included) [`ViewerCore::begin_frame`]
/// makes before it leaves the rest to [`ViewerCore::finish_frame`]: a driving frame makes
/// 1 to 50, a degree of turning a few hundred; a thousand cost about 0.2 ms.
pub const INLINE_CHANGES: u32 = 1024;

/// Frames whose change logs are kept: a base older than this (the acknowledged frame, or a
/// key frame still pending) gets a key frame. Half a second at 60 Hz, so that a key frame
/// that lost a packet on a long round trip (a retransmission, then its acknowledgement) or
/// an acknowledgement held up behind a lost packet on the control stream still finds its
/// logs: with 16 (267 ms), 80 ms each way at 5 % loss made 17 to 28 key frames in 10 s,
/// each superseding the last; 32 make one (the simulated network, seeds 1 to 3). No more
/// than the decoded frames a viewer keeps as bases (`roam_client::core::BASES`, 32):
/// frames are decoded in order, so a base this close is never one the viewer has dropped.
pub const LOGS: usize = 32;

/// What the viewer's control messages tell the core.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Event {
    /// The triangle budget the viewer asks for (clamped by [`messages::clamp_budget`]).
    Budget(u32),
    /// The viewer decoded this frame: it may be a base.
    Acked(u64),
    /// The viewer lost its bases: the next frame is a key frame.
    KeyFrame,
    /// How the viewer's camera differs from the default one.
    View(ViewChange),
}

/// What the core needs of the world: the terrain it tessellates and the from-scratch
/// tessellators it borrows, shared by every viewer.
#[derive(Clone, Copy)]
pub struct Scene<'a> {
    pub terrain: &'a Terrain,
    pub variance: &'a VarianceTree,
    pub scratch: &'a Scratch,
}

impl Scene<'_> {
    fn heights(&self) -> &Heightfield {
        &self.terrain.heights
    }

    fn scales(&self) -> Scales {
        Scales {
            h: self.terrain.map.h_scale,
            v: self.terrain.map.v_scale,
        }
    }
}

/// What [`ViewerCore::begin_frame`] left to [`ViewerCore::finish_frame`].
#[derive(Clone, Copy, Debug)]
enum Left {
    /// The cut (more changes, or a rebuild), then the payload.
    Cut,
    /// The key frame's coding; the frame is logged.
    Key {
        frame: u64,
        mode: Mode,
        changes: u32,
        cause: KeyCause,
    },
}

/// One frame to send.
#[derive(Clone, Debug, PartialEq)]
pub struct Made {
    /// Rises by one per frame made.
    pub frame: u64,
    /// The frame the payload is coded against (acknowledged, or the pending key frame);
    /// `None` for a key frame.
    pub base: Option<u64>,
    /// The mesh payload (format 1 or 2 of `roam_protocol`).
    pub payload: Vec<u8>,
    /// How the cut was made, and what changed in it this frame.
    pub mode: Mode,
    pub changes: u32,
    pub triangles: u32,
    /// Why a key frame is one (`None` for a change frame).
    pub key: Option<KeyCause>,
}

/// Why a frame is a key frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum KeyCause {
    /// The viewer's first frame (nothing acknowledged, no key frame pending).
    First,
    /// The viewer asked for one (it lost its bases).
    Asked,
    /// The base (the acknowledged frame, or the pending key frame) is older than the
    /// [`LOGS`] frames whose changes are kept: acknowledgements fell behind.
    Behind,
    /// The changes since the base would cost more than twice the whole cut.
    Larger,
}

/// What the server serves one viewer at most, whatever it asks (`serve --max-budget`,
/// `--max-fps`), and how (`--fog-priority`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ViewerLimits {
    /// Triangles per frame, within [`messages::MIN_BUDGET`]`..=`[`messages::MAX_BUDGET`].
    pub max_budget: u32,
    /// Frames per second, within 1 ..= [`MAX_FPS`].
    pub max_fps: u16,
    /// The priority weighs each diamond's error by what the map's fog lets through of it
    /// (while the viewer draws its fog); off, the fog-unaware priority (for comparisons).
    pub fog_priority: bool,
    /// The guard band, degrees each side ([`Limits::guard_deg`]: what a turning viewer is
    /// about to see refined before it is seen; 0 for none), at most [`MAX_GUARD_DEG`].
    pub guard_deg: u8,
    /// Once a cut is at its budget, a merge makes room for a split only when the split's
    /// priority beats the merge's by more than this many percent
    /// ([`Coherent::set_swap_margin`]; 0: ROAM's rule), at most [`MAX_SWAP_MARGIN_PCT`].
    pub swap_margin_pct: u16,
}

pub use crate::tessellate::camera::MAX_GUARD_DEG;

/// The swap margin served unless told otherwise, percent. Along the bench drive on a rough
/// map it took the changes a frame by a fifth and the level of detail's changes the driver
/// sees (`lod_luma_diff_p99`) by a third, for 11 % more fogged error in view; 50 % and 100 %
/// took off little more for 20–30 % more error (README: what the driver sees).
pub const DEFAULT_SWAP_MARGIN_PCT: u16 = 30;

/// The largest swap margin a server takes, percent (a cut up to 5 times worse than its
/// budget allows: past that the margin is not a margin).
pub const MAX_SWAP_MARGIN_PCT: u16 = 400;

/// The guard band served unless told otherwise, degrees each side. Along the bench drive
/// on a rough map, 10° took the level of detail's changes that the driver sees
/// (`lod_luma_diff_p99`) to about a third, for 10 % more fogged error in view at the same
/// budget; 6° left the drive's turn to be refined in sight (2.5 times the changes), 15°
/// changed no more than 10° for a little more error (README: what the driver sees).
pub const DEFAULT_GUARD_DEG: u8 = 10;

/// The most frames a second any viewer gets.
pub const MAX_FPS: u16 = 240;

impl Default for ViewerLimits {
    fn default() -> ViewerLimits {
        ViewerLimits {
            max_budget: messages::MAX_BUDGET,
            max_fps: MAX_FPS,
            fog_priority: true,
            guard_deg: DEFAULT_GUARD_DEG,
            swap_margin_pct: DEFAULT_SWAP_MARGIN_PCT,
        }
    }
}

impl ViewerLimits {
    /// These limits, each kept within what any server serves.
    pub fn clamped(self) -> ViewerLimits {
        ViewerLimits {
            max_budget: messages::clamp_budget(self.max_budget),
            max_fps: self.max_fps.clamp(1, MAX_FPS),
            fog_priority: self.fog_priority,
            guard_deg: self.guard_deg.min(MAX_GUARD_DEG),
            swap_margin_pct: self.swap_margin_pct.min(MAX_SWAP_MARGIN_PCT),
        }
    }

    /// A budget a viewer asked for, as this server serves it.
    pub fn budget(&self, asked: u32) -> u32 {
        messages::clamp_budget(asked).min(self.max_budget)
    }
}

/// One viewer's state: its camera settings, budget, acknowledgements and cut.
pub struct ViewerCore {
    grid: Grid,
    coherent: Coherent,
    key_encoder: MeshEncoder,
    change_encoder: ChangeEncoder,
    /// `(frame, the diamonds it toggled, row-major, each once)`, oldest first.
    logs: VecDeque<(u64, Vec<u32>)>,
    /// The [`CutHash`] of the cut now.
    hash: CutHash,
    /// The default camera (field of view, viewport), before the viewer's view change.
    camera: Camera,
    view: Option<ViewChange>,
    budget: u32,
    caps: ViewerLimits,
    acked: Option<u64>,
    /// The newest key frame made, until the viewer acknowledges it (or a newer frame), asks
    /// for another, or a newer key frame supersedes it.
    pending_key: Option<u64>,
    key_requested: bool,
    /// The first frame made after the newest key-frame request: an acknowledgement of an
    /// older one is not taken (a key datagram's, unordered with the control stream, may
    /// arrive after the request it preceded; the viewer's cut is not that frame's).
    ack_floor: u64,
    /// What [`Self::begin_frame`] left to [`Self::finish_frame`].
    left: Option<Left>,
    next: u64,
    /// Scratch: the composed change list.
    changes: Vec<u32>,
}

impl ViewerCore {
    /// The core for a viewer that said `hello`, on `terrain` whose heights are multiples of
    /// `height_step`, served within `caps`.
    pub fn for_hello(
        terrain: &Terrain,
        height_step: u16,
        hello: &Hello,
        caps: ViewerLimits,
    ) -> ViewerCore {
        ViewerCore::new(
            terrain.heights.levels(),
            height_step,
            hello.fov_y_deg,
            hello.viewport,
            hello.budget,
        )
        .with_caps(caps)
    }

    /// This core served within `caps` (its budget clamped by them).
    pub fn with_caps(mut self, caps: ViewerLimits) -> ViewerCore {
        self.caps = caps.clamped();
        self.budget = self.caps.budget(self.budget);
        self.coherent.set_swap_margin(self.caps.swap_margin_pct);
        self
    }

    /// The frames a second a viewer gets: what its hello asked for, within 1 ..=
    /// `caps.max_fps`.
    pub fn frame_rate(hello: &Hello, caps: ViewerLimits) -> u16 {
        hello.frame_rate.clamp(1, caps.clamped().max_fps)
    }

    /// A core for a map of `levels` (side `2^levels + 1`) whose heights are multiples of
    /// `height_step` ([`roam_protocol::height_step`]), for a viewer that said hello with
    /// this field of view (degrees, vertical), viewport and budget.
    pub fn new(
        levels: u32,
        height_step: u16,
        fov_y_deg: f32,
        viewport: [u32; 2],
        budget: u32,
    ) -> ViewerCore {
        let grid = Grid::new(levels).expect("data sets have 1 ..= 15 levels");
        ViewerCore {
            grid,
            coherent: {
                let mut c = Coherent::new(grid.side());
                c.set_swap_margin(DEFAULT_SWAP_MARGIN_PCT);
                c
            },
            key_encoder: MeshEncoder::with_step(grid, height_step),
            change_encoder: ChangeEncoder::new(grid, height_step),
            logs: VecDeque::new(),
            hash: CutHash::new(),
            camera: camera::default_camera(fov_y_deg, viewport),
            view: None,
            budget: messages::clamp_budget(budget),
            caps: ViewerLimits::default(),
            acked: None,
            pending_key: None,
            key_requested: false,
            ack_floor: 0,
            left: None,
            next: 0,
            changes: Vec::new(),
        }
    }

    pub fn handle(&mut self, event: Event) {
        match event {
            Event::Budget(b) => self.budget = self.caps.budget(b),
            // Only frames made can be acknowledged, none made before the newest key-frame
            // request; a later ack wins. An ack of the pending key frame, or of a frame
            // after it (decoded against it), ends its wait.
            Event::Acked(f) if (self.ack_floor..self.next).contains(&f) => {
                self.acked = Some(self.acked.map_or(f, |a| a.max(f)));
                self.pending_key = self.pending_key.filter(|&k| k > f);
            }
            Event::Acked(_) => {}
            Event::KeyFrame => {
                self.key_requested = true;
                self.ack_floor = self.next;
                self.acked = None;
                self.pending_key = None;
            }
            Event::View(v) => self.view = Some(v),
        }
    }

    pub fn budget(&self) -> u32 {
        self.budget
    }

    /// The newest frame the viewer acknowledged (since its last key-frame request).
    pub fn acked(&self) -> Option<u64> {
        self.acked
    }

    /// The newest key frame, while it is pending: made, not yet acknowledged (nor a frame
    /// after it), not superseded by a newer key frame, and no key frame asked for since.
    /// The frames after it may be coded against it, so the shell must deliver it: reliably,
    /// never abandoned while this names it.
    pub fn pending_key(&self) -> Option<u64> {
        self.pending_key
    }

    /// The camera of a frame at `vehicle`.
    pub fn camera_at(&self, scene: &Scene, vehicle: &VehicleState) -> Camera {
        let mut cam = self.camera;
        cam.eye = [
            vehicle.x,
            altitude(scene.terrain, vehicle.x, vehicle.z),
            vehicle.z,
        ];
        cam.yaw_deg = vehicle.heading;
        if let Some(v) = &self.view {
            apply_view(&mut cam, v);
        }
        cam
    }

    /// The fog density the priority weighs errors by (per world unit): the map's while the
    /// viewer draws its fog (until its first [`ViewChange`] says, it does), 0 when it does
    /// not or the server's `fog_priority` is off.
    pub fn fog_density(&self, scene: &Scene) -> f32 {
        let fog = self.caps.fog_priority && self.view.is_none_or(|v| v.fog);
        if fog {
            scene.terrain.map.fog_density as f32
        } else {
            0.0
        }
    }

    /// The most changes a frame's cut makes once within its budget
    /// ([`Coherent::set_allowance`]; `u32::MAX`: none), and the lag that goes with it
    /// ([`allowance::lag_scale`]).
    pub fn set_allowance(&mut self, changes: u32) {
        self.coherent.set_allowance(changes);
        self.coherent.set_lag_scale(allowance::lag_scale(changes));
    }

    /// The cut carried from the last frame (for tests and benchmarks).
    pub fn cut(&self) -> &Coherent {
        &self.coherent
    }

    /// The mesh of the cut now, as the viewer rebuilds it from the frames.
    pub fn mesh(&self, scratch: &Scratch, out: &mut crate::tessellate::Mesh) {
        self.coherent.mesh(scratch, out);
    }

    /// Bytes of per-viewer state currently reserved.
    pub fn heap_bytes(&self) -> usize {
        self.coherent.heap_bytes()
            + self
                .logs
                .iter()
                .map(|(_, l)| l.capacity() * 4)
                .sum::<usize>()
            + self.changes.capacity() * 4
    }

    /// Makes the next frame for a camera at `vehicle`, whatever it costs.
    pub fn make_frame(&mut self, scene: &Scene, vehicle: &VehicleState) -> Made {
        let camera = self.camera_at(scene, vehicle);
        self.make_frame_at(scene, &camera)
    }

    /// Makes the next frame for `camera` (the view change is the caller's to apply).
    pub fn make_frame_at(&mut self, scene: &Scene, camera: &Camera) -> Made {
        match self.begin_at(scene, camera, u32::MAX, false) {
            Some(made) => made,
            None => self.finish_frame(scene),
        }
    }

    /// Makes the next frame for a camera at `vehicle` if it is cheap: `None` when heavy
    /// work is left (more than [`INLINE_CHANGES`] changes, a rebuild, a key frame), which
    /// [`Self::finish_frame`] must then do before anything else.
    pub fn begin_frame(&mut self, scene: &Scene, vehicle: &VehicleState) -> Option<Made> {
        let camera = self.camera_at(scene, vehicle);
        self.begin_at(scene, &camera, INLINE_CHANGES, true)
    }

    /// Whether [`Self::begin_frame`] left work for [`Self::finish_frame`].
    pub fn unfinished(&self) -> bool {
        self.left.is_some()
    }

    /// Finishes the frame [`Self::begin_frame`] left.
    pub fn finish_frame(&mut self, scene: &Scene) -> Made {
        match self.left.take() {
            Some(Left::Cut) => {
                let mode = self.coherent.finish(
                    scene.heights(),
                    scene.variance,
                    scene.scales(),
                    scene.scratch,
                );
                self.coded(scene, mode, false)
                    .expect("a frame not made in line is always made")
            }
            Some(Left::Key {
                frame,
                mode,
                changes,
                cause,
            }) => self.key_frame(scene, frame, mode, changes, cause),
            None => panic!("finish_frame without an unfinished frame: a caller bug"),
        }
    }

    /// The cut for `camera` within `most` changes, then its payload; `None` (with
    /// `left` set) when heavy work is left and `inline` says not to do it.
    fn begin_at(
        &mut self,
        scene: &Scene,
        camera: &Camera,
        most: u32,
        inline: bool,
    ) -> Option<Made> {
        let limits = Limits {
            budget: self.budget,
            threshold_px: 0.0,
            fog_density: self.fog_density(scene),
            guard_deg: f32::from(self.caps.guard_deg),
        };
        let step = self.coherent.begin(
            scene.heights(),
            scene.variance,
            scene.scales(),
            camera,
            limits,
            false,
            most,
        );
        match step {
            Step::Done(mode) => self.coded(scene, mode, inline),
            Step::Unfinished => {
                self.left = Some(Left::Cut);
                None
            }
        }
    }

    /// Logs the cut's changes as a new frame and codes it: a change frame against the
    /// base, or a key frame (left for later when `inline`).
    fn coded(&mut self, scene: &Scene, mode: Mode, inline: bool) -> Option<Made> {
        let frame = self.next;
        self.next += 1;
        let log = self.log_changes(scene.heights());
        let changes = log.len() as u32;
        self.logs.push_back((frame, log));
        while self.logs.len() > LOGS {
            self.logs.pop_front();
        }
        let mut payload = Vec::new();
        let base = self.delta_base().filter(|_| !self.key_requested);
        if let Some(base) = base
            && self.encode_changes(scene, base, &mut payload)
        {
            return Some(Made {
                frame,
                base: Some(base),
                payload,
                mode,
                changes,
                triangles: self.coherent.triangles(),
                key: None,
            });
        }
        let cause = if self.key_requested {
            KeyCause::Asked
        } else if base.is_some() {
            KeyCause::Larger
        } else if self.acked.max(self.pending_key).is_some() {
            KeyCause::Behind
        } else {
            KeyCause::First
        };
        if inline {
            self.left = Some(Left::Key {
                frame,
                mode,
                changes,
                cause,
            });
            return None;
        }
        Some(self.key_frame(scene, frame, mode, changes, cause))
    }

    /// Codes the cut as frame `frame`'s key frame.
    fn key_frame(
        &mut self,
        scene: &Scene,
        frame: u64,
        mode: Mode,
        changes: u32,
        cause: KeyCause,
    ) -> Made {
        let mut payload = Vec::new();
        self.encode_key(scene, &mut payload);
        self.key_requested = false;
        // Supersedes any older pending key frame.
        self.pending_key = Some(frame);
        Made {
            frame,
            base: None,
            payload,
            mode,
            changes,
            triangles: self.coherent.triangles(),
            key: Some(cause),
        }
    }

    /// This frame's toggles, each once (a diamond split and merged again in one frame has
    /// not changed), as row-major indices; the cut's hash follows them.
    fn log_changes(&mut self, heights: &Heightfield) -> Vec<u32> {
        let side = self.grid.side();
        let mut log: Vec<u32> = self
            .coherent
            .changes()
            .iter()
            .map(|&p| (p >> 16) * side + (p & 0xffff))
            .collect();
        odd_ones(&mut log);
        let samples = heights.samples();
        for &i in &log {
            let (x, z) = self.grid.coords(i);
            let h = samples[i as usize];
            if self.coherent.is_split(x, z) {
                self.hash.add(i, h);
            } else {
                self.hash.remove(i, h);
            }
        }
        log
    }

    /// The base of the next change frame: the newer of the acknowledged frame and the
    /// pending key frame, if the changes since are all logged.
    fn delta_base(&self) -> Option<u64> {
        let base = self.acked.max(self.pending_key)?;
        let oldest = self.logs.front()?.0;
        // The logs of every frame after the base are needed.
        (base + 1 >= oldest).then_some(base)
    }

    /// Codes the difference from `base` as a change frame; false when a key frame would be
    /// smaller (or the change list is not to be had).
    fn encode_changes(&mut self, scene: &Scene, base: u64, out: &mut Vec<u8>) -> bool {
        self.changes.clear();
        for (f, log) in &self.logs {
            if *f > base {
                self.changes.extend_from_slice(log);
            }
        }
        odd_ones(&mut self.changes);
        // About 2–3 bytes a change against a third of a byte a triangle for the key frame:
        // changes up to a third of the triangles (twice a key frame's bytes) still go as a
        // change frame. At an eighth (as small as a key frame), a server overloaded by 40
        // joins at once made frames late, so each carried more changes, so more of them
        // became key frames (107 of 147 key frames in that storm, `key_larger`), which
        // made it later still; a change frame costs what changed to make, a key frame the
        // whole cut.
        if self.changes.len() as u64 * 3 > u64::from(self.coherent.triangles()) {
            return false;
        }
        let grid = self.grid;
        let coherent = &self.coherent;
        self.change_encoder
            .encode(
                &self.changes,
                |i| {
                    let (x, z) = grid.coords(i);
                    coherent.is_split(x, z)
                },
                scene.heights().samples(),
                coherent.triangles(),
                coherent.split_count(),
                self.hash.value(),
                out,
            )
            .is_ok()
    }

    /// Codes the whole cut as a key frame (from a borrowed tessellator's bitset).
    fn encode_key(&mut self, scene: &Scene, out: &mut Vec<u8>) {
        let encoder = &mut self.key_encoder;
        self.coherent
            .with_split_set(scene.scratch, |split| {
                encoder.encode(split, scene.heights().samples(), None, out)
            })
            .expect("the tessellator's cuts are closed under parent");
    }
}

/// Sorts `v` and keeps the values that occur an odd number of times, once each.
fn odd_ones(v: &mut Vec<u32>) {
    v.sort_unstable();
    let mut out = 0;
    let mut i = 0;
    while i < v.len() {
        let mut j = i + 1;
        while j < v.len() && v[j] == v[i] {
            j += 1;
        }
        if (j - i) % 2 == 1 {
            v[out] = v[i];
            out += 1;
        }
        i = j;
    }
    v.truncate(out);
}

#[cfg(test)]
mod tests {
    use super::odd_ones;

    #[test]
    fn odd_ones_cancel_pairs() {
        let check = |input: &[u32], want: &[u32]| {
            let mut v = input.to_vec();
            odd_ones(&mut v);
            assert_eq!(v, want, "{input:?}");
        };
        check(&[], &[]);
        check(&[5], &[5]);
        check(&[5, 5], &[]);
        check(&[3, 5, 3, 5, 5], &[5]);
        check(&[9, 1, 1, 1, 2, 9, 7], &[1, 2, 7]);
    }
}
