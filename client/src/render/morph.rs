//! Geomorphs (issue 24): the cut as drawn, which follows the decoded cut without popping.
//! A vertex a split adds is drawn first where the surface already was (its diamond's
//! hypotenuse midpoint, as drawn) and moves to its height over [`MORPH_TICKS`] world ticks;
//! a vertex a merge removes goes back to that midpoint first, and only then do its
//! triangles go; a split or merge that arrives mid-morph turns the vertex round where it
//! is. The decoded cut (the server's, exactly: [`crate::core`]) is never changed: this is
//! drawing only.
//!
//! **Conforming at every frame.** The drawn cut is the decoded cut plus the diamonds still
//! morphing out, a union of two cuts closed under parent, so it is one too, and its mesh
//! ([`LiveMesh`]) conforms (no crack, no T-junction) whatever the heights drawn. A vertex
//! leaves the drawn cut only when back at its midpoint and no child of it is drawn
//! (children reach their midpoints first: a child enters with or after its parents and
//! all move at one speed, so a child's progress never exceeds a parent's; the check keeps
//! the cut closed even if that ever failed).
//!
//! **How fast a vertex moves: a fixed speed on screen, within a deadline.** Each step a
//! vertex moves towards its target (its height; its midpoint as drawn while morphing
//! out) by at most [`MORPH_PX_PER_TICK`] pixels a tick seen from the frame's camera
//! ([`MorphView`]), unless that would miss its deadline ([`MORPH_TICKS`] after it
//! set out: then by what it needs to arrive exactly then). A first version moved every
//! vertex linearly over a quarter of a second, whatever its size on screen: measured on
//! a rough 4097² map along the bench drive, a frame moved the surface by 1.3 px (p99),
//! against 2.9 px of pops without morphs — while the driver turns, a region is refined a
//! level a frame, and the morphs of a vertex and of its ancestors (the edge it rises from
//! is itself rising) add up. Bounding each vertex's motion on screen bounds the sum, since
//! a vertex's position is absolute. At 0.09 px a tick (0.15 px a 60 Hz frame, under
//! what the eye can tell from the surface's own motion as the vehicle moves), a pop of
//! more than 5.9 px takes longer than 0.65 s; nothing takes more than a second. A
//! reversal keeps the speed: its deadline is the time spent so far on the way out, and
//! it takes no less than that (nor than 0.65 s, if that is less).
//!
//! **Nothing takes less than 0.65 s** ([`MORPH_MIN_TICKS`], or the deadline if shorter:
//! `--morph-ticks`): a change smaller on screen than that speed covers in 0.65 s (a 1–3 px
//! pop, the most the budget leaves on rough terrain) moves linearly over it. Along the bench drive the
//! server changes up to a hundred diamonds in a frame, most of them far and small on
//! screen, and while the vehicle is fast it does so frame after frame: each change alone
//! is invisible, but at the screen speed alone they all finished within the tick, and the
//! picture changed most in those frames. Spreading each over a longer time spreads the
//! bursts (`lod_luma_diff_p99` on a rough map, 10° guard band, one run each, `roam-client
//! --headless --bench`): 0.0013 with none, 0.0012 at 25 ticks, 0.00098 at 50, 0.00083 at
//! 65, 0.0012 at 80 and 0.0025 at 100 (where the screen speed no longer applies: longer
//! morphs overlap their ancestors' and descendants' more, and the surface goes up and down
//! more on the way; the mean over frames grew from 0.00026 to 0.00038).
//!
//! **Time is the frames' ticks**, never the wall clock: the morph advances by the tick
//! difference between consecutive frames taken, and the camera is the frame's, so a slow
//! machine draws the same sequence as a fast one (the `--bench` measures rely on it).
//! Without a camera (tests), every vertex moves linearly to its deadline.

use roam_protocol::{DiamondMap, Grid, LiveMesh};

use super::{Scene, TerrainVertices};

/// The most world ticks a vertex takes to morph from its midpoint to its height: a second
/// at 100 Hz (see the module docs).
pub const MORPH_TICKS: u16 = 100;

/// How far a morphing vertex moves on screen a tick, pixels (see the module docs).
pub const MORPH_PX_PER_TICK: f32 = 0.09;

/// The fewest world ticks a morph takes (0.65 s at 100 Hz), however small its change on
/// screen (see the module docs).
pub const MORPH_MIN_TICKS: u16 = 65;

/// The camera a step's speeds are measured from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MorphView {
    /// World units.
    pub eye: [f32; 3],
    /// Pixels a world unit covers at a distance of one: the viewport's height over
    /// `2 tan(fov_y / 2)`.
    pub px_per_unit: f32,
    /// The map's scales: world units a grid step and a height sample.
    pub h_scale: f32,
    pub v_scale: f32,
}

impl MorphView {
    /// The camera a viewer looks from at the frame that shows `vehicles`: `me`'s, its eye
    /// [`crate::camera::EYE_ABOVE_VEHICLE`] above it (`None` when `me` is not in the
    /// frame: a spectator's vehicle left, or not seated yet).
    pub fn of_vehicle(
        scene: &Scene,
        vehicles: &[roam_protocol::messages::VehicleView],
        me: u16,
        fov_y_deg: f32,
        height: u32,
    ) -> Option<MorphView> {
        let v = vehicles.iter().find(|v| v.id == me)?;
        let eye = [
            v.x as f32,
            (v.y + crate::camera::EYE_ABOVE_VEHICLE) as f32,
            v.z as f32,
        ];
        Some(MorphView::new(scene, eye, fov_y_deg, height))
    }

    /// The camera of `scene` at `eye` with a vertical field of view of `fov_y_deg` on a
    /// viewport `height` pixels high.
    pub fn new(scene: &Scene, eye: [f32; 3], fov_y_deg: f32, height: u32) -> MorphView {
        let half = (fov_y_deg.clamp(1.0, 179.0).to_radians() / 2.0).tan();
        MorphView {
            eye,
            px_per_unit: height as f32 / (2.0 * half),
            h_scale: scene.h_scale as f32,
            v_scale: scene.v_scale as f32,
        }
    }

    /// Height samples vertex `(x, z)` at height `y` (samples) may move in `ticks` ticks.
    fn reach(&self, x: u32, z: u32, y: f32, ticks: f32) -> f32 {
        let d = [
            x as f32 * self.h_scale - self.eye[0],
            y * self.v_scale - self.eye[1],
            z as f32 * self.h_scale - self.eye[2],
        ];
        let dist = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(0.5);
        MORPH_PX_PER_TICK * ticks * dist / self.px_per_unit / self.v_scale.max(1e-9)
    }
}

/// A diamond of the drawn cut.
#[derive(Clone, Copy, Debug, Default)]
struct Drawn {
    /// Its height, samples.
    h: u16,
    /// Where it is drawn, samples (`h` exactly once there).
    y: f32,
    /// Ticks left before it must be at its target (0: there, or to be put there).
    left: u16,
    /// Ticks left before it may be at its target ([`MORPH_MIN_TICKS`], or on a way back
    /// the time spent on the way out if less).
    least: u16,
    /// Just added: drawn this step where the surface is.
    fresh: bool,
    /// Morphing out (merged in the decoded cut, still drawn).
    out: bool,
    /// Listed in [`Morph::moving`].
    listed: bool,
}

/// The drawn cut: the decoded cut's diamonds and the ones morphing out, each with its
/// progress, and the drawn mesh's triangles.
#[derive(Clone, Debug)]
pub struct Morph {
    grid: Grid,
    ticks: u16,
    drawn: DiamondMap<Drawn>,
    /// The drawn cut's triangles, slot by diamond.
    live: LiveMesh,
    /// Diamonds morphing (in or out), each once.
    moving: Vec<u32>,
    /// Scratch.
    toggled: Vec<u32>,
    touched: Vec<u32>,
    /// The camera of the next steps (`None`: linear to each deadline).
    view: Option<MorphView>,
}

impl Morph {
    /// A drawn cut of `grid` (empty: the two root triangles) whose morphs take `ticks`
    /// world ticks (0: none, the drawn cut is the decoded one).
    pub fn new(grid: Grid, ticks: u16) -> Morph {
        Morph {
            grid,
            ticks,
            drawn: DiamondMap::new(),
            live: LiveMesh::new(&grid),
            moving: Vec::new(),
            toggled: Vec::new(),
            touched: Vec::new(),
            view: None,
        }
    }

    /// The camera the next steps measure speeds from.
    pub fn set_view(&mut self, view: Option<MorphView>) {
        self.view = view;
    }

    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// The morphs' length, ticks.
    pub fn ticks(&self) -> u16 {
        self.ticks
    }

    /// Brings `terrain` up to date with the drawn mesh: the slots rewritten or moved since
    /// the last call, each vertex at its drawn height (normals from the heights; a map
    /// corner's height from `corner`).
    pub fn draw(
        &mut self,
        scene: &Scene,
        terrain: &mut TerrainVertices,
        corner: impl Fn(u32) -> Option<u16>,
    ) {
        let drawn = &self.drawn;
        terrain.update(
            scene,
            &mut self.live,
            |i| drawn.get(i).map(|v| v.h).or_else(|| corner(i)),
            |i| drawn.get(i).map_or(0.0, |v| v.y - f32::from(v.h)),
        );
    }

    /// The drawn mesh.
    pub fn live(&self) -> &LiveMesh {
        &self.live
    }

    pub fn live_mut(&mut self) -> &mut LiveMesh {
        &mut self.live
    }

    /// Whether diamond `d` is drawn split.
    pub fn contains(&self, d: u32) -> bool {
        self.drawn.contains(d)
    }

    /// Diamonds drawn split.
    pub fn len(&self) -> usize {
        self.drawn.len()
    }

    pub fn is_empty(&self) -> bool {
        self.drawn.is_empty()
    }

    /// Vertices morphing now.
    pub fn morphing(&self) -> usize {
        self.moving.len()
    }

    /// The diamonds morphing now (in or out).
    pub fn moving(&self) -> &[u32] {
        &self.moving
    }

    /// The diamonds drawn split, in no particular order.
    pub fn diamonds(&self) -> impl Iterator<Item = u32> + '_ {
        self.drawn.iter().map(|(d, _)| d)
    }

    /// The height of a drawn diamond's centre, samples (`None` for a diamond not drawn:
    /// the map's corners are the caller's).
    pub fn height(&self, d: u32) -> Option<u16> {
        self.drawn.get(d).map(|v| v.h)
    }

    /// How far vertex `i` is drawn above its height, samples (0 at its height).
    pub fn lift(&self, i: u32) -> f32 {
        self.drawn.get(i).map_or(0.0, |v| v.y - f32::from(v.h))
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.drawn.bytes()
            + self.live.bytes()
            + 4 * (self.moving.capacity() + self.toggled.capacity() + self.touched.capacity())
    }

    /// Follows the decoded cut: `changes` are the diamonds toggled since the last step
    /// (each once, with its height), `split(d)` whether `d` is split in the decoded cut
    /// now, `corner(i)` a map corner's height, and `ticks` the world ticks since the last
    /// step (`None`: a new cut, shown at once, as a first frame is). Marks in the drawn
    /// mesh the slots whose triangles changed or moved.
    pub fn step(
        &mut self,
        changes: &[(u32, u16)],
        split: impl Fn(u32) -> bool,
        corner: impl Fn(u32) -> Option<u16>,
        ticks: Option<u64>,
    ) {
        let snap = ticks.is_none() || self.ticks == 0;
        let advance = ticks.unwrap_or(0).min(u64::from(u16::MAX)) as u16;
        let full = self.ticks;
        self.toggled.clear();
        // Every vertex that was moving may be drawn elsewhere now.
        self.touched.clear();
        self.touched.extend_from_slice(&self.moving);
        for &(d, h) in changes {
            let now = split(d);
            match self.drawn.get(d) {
                Some(mut v) => {
                    // Split again while morphing out: back up from where it is, as fast.
                    // Merged: back to its midpoint first (at once for a new cut); it
                    // leaves the drawn cut there, after its children.
                    v.out = !now;
                    v.h = h;
                    v.left = if snap { 0 } else { full.saturating_sub(v.left) };
                    v.least = MORPH_MIN_TICKS.min(v.left);
                    self.drawn.insert(d, v);
                    self.list(d);
                    self.touched.push(d);
                }
                None if now => {
                    self.drawn.insert(
                        d,
                        Drawn {
                            h,
                            y: f32::from(h),
                            left: if snap { 0 } else { full },
                            least: if snap { 0 } else { MORPH_MIN_TICKS.min(full) },
                            fresh: !snap,
                            out: false,
                            listed: false,
                        },
                    );
                    self.toggled.push(d);
                    if !snap {
                        self.list(d);
                    }
                }
                None => {}
            }
        }
        self.place(&corner, if snap { None } else { Some(advance) });
        self.remove_finished();
        let drawn = &self.drawn;
        self.live
            .update(&self.grid, self.toggled.iter().copied(), |i| {
                drawn.contains(i)
            });
        // Slots whose vertices moved (the slots the topology changed are marked already).
        let mut touched = std::mem::take(&mut self.touched);
        touched.sort_unstable();
        touched.dedup();
        for &v in &touched {
            if self.drawn.contains(v) {
                self.touch_around(v);
            }
        }
        self.touched = touched;
    }

    fn list(&mut self, d: u32) {
        if let Some(mut v) = self.drawn.get(d)
            && !v.listed
        {
            v.listed = true;
            self.drawn.insert(d, v);
            self.moving.push(d);
        }
    }

    /// Drops from the drawn cut the diamonds back at their midpoints whose children are
    /// gone (finest first, so a parent can follow its children in the same step), and
    /// from the moving list the ones at their heights.
    fn remove_finished(&mut self) {
        let grid = self.grid;
        let depth = |d: u32| depth_of(&grid, d);
        let mut moving = std::mem::take(&mut self.moving);
        moving.sort_unstable_by_key(|&d| (std::cmp::Reverse(depth(d)), d));
        moving.retain(|&d| {
            let Some(mut v) = self.drawn.get(d) else {
                return false;
            };
            let (x, z) = grid.coords(d);
            if v.out {
                let children_gone = !grid
                    .children(x, z)
                    .into_iter()
                    .flatten()
                    .any(|(cx, cz)| self.drawn.contains(grid.index(cx, cz)));
                if v.left == 0 && children_gone {
                    self.drawn.remove(d);
                    self.toggled.push(d);
                    return false;
                }
                true
            } else if v.left == 0 && v.y == f32::from(v.h) {
                v.listed = false;
                self.drawn.insert(d, v);
                false
            } else {
                true
            }
        });
        self.moving = moving;
    }

    /// Moves each moving vertex towards its target by `ticks` ticks (`None`: there at
    /// once), coarse to fine (its hypotenuse ends first); a vertex just added is put on
    /// its edge as drawn. A vertex is at its target exactly when its deadline comes.
    fn place(&mut self, corner: &impl Fn(u32) -> Option<u16>, ticks: Option<u16>) {
        let grid = self.grid;
        let depth = |d: u32| depth_of(&grid, d);
        self.moving.sort_unstable_by_key(|&d| (depth(d), d));
        for k in 0..self.moving.len() {
            let d = self.moving[k];
            let Some(mut v) = self.drawn.get(d) else {
                continue;
            };
            let (x, z) = grid.coords(d);
            let end = |(ex, ez): (u32, u32)| {
                let i = grid.index(ex, ez);
                match self.drawn.get(i) {
                    Some(e) => e.y,
                    None => f32::from(corner(i).unwrap_or(v.h)),
                }
            };
            let [a, b] = grid.hypotenuse(x, z);
            let mid = 0.5 * (end(a) + end(b));
            let h = f32::from(v.h);
            let target = if v.out { mid } else { h };
            if v.fresh {
                v.fresh = false;
                v.y = mid;
            } else {
                match ticks {
                    Some(t) if t < v.left => {
                        let gap = target - v.y;
                        let due = gap * f32::from(t) / f32::from(v.left);
                        let fast = self
                            .view
                            .map_or(0.0, |view| view.reach(x, z, v.y, f32::from(t)));
                        // Not there before its least length: what is left of the gap
                        // over what is left of that, linearly.
                        let gentle = if t < v.least {
                            gap.abs() * f32::from(t) / f32::from(v.least)
                        } else {
                            gap.abs()
                        };
                        v.least = v.least.saturating_sub(t);
                        let step = due.abs().max(fast.min(gentle)).min(gap.abs());
                        v.y = if step >= gap.abs() {
                            target
                        } else {
                            v.y + step.copysign(gap)
                        };
                        v.left -= t;
                        if v.y == target {
                            v.left = 0;
                        }
                    }
                    _ => {
                        v.y = target;
                        v.left = 0;
                    }
                }
            }
            self.drawn.insert(d, v);
        }
    }

    /// Marks the slots of the triangles around vertex `v`: its own diamond's, and those
    /// of the diamonds it is a corner of (a square's at half-size `s` lie `(±s, ±s)` from
    /// it, a rotated diamond's `(±s, 0)` and `(0, ±s)`, at the sizes its coordinates allow).
    fn touch_around(&mut self, v: u32) {
        let grid = self.grid;
        if let Some(slot) = self.live.slot_of(v) {
            self.live.touch(slot);
        }
        let (x, z) = grid.coords(v);
        let size = i64::from(grid.size());
        let top = x
            .trailing_zeros()
            .min(z.trailing_zeros())
            .min(grid.levels());
        for m in 0..=top {
            let s = 1i64 << m;
            let (xi, zi) = (i64::from(x), i64::from(z));
            let around = [
                ((xi + s, zi + s), true),
                ((xi - s, zi + s), true),
                ((xi + s, zi - s), true),
                ((xi - s, zi - s), true),
                ((xi + s, zi), false),
                ((xi - s, zi), false),
                ((xi, zi + s), false),
                ((xi, zi - s), false),
            ];
            for ((cx, cz), square) in around {
                if cx < 0 || cz < 0 || cx > size || cz > size {
                    continue;
                }
                let (cx, cz) = (cx as u32, cz as u32);
                if (cx.is_multiple_of(grid.size()) && cz.is_multiple_of(grid.size()))
                    || grid.classify(cx, cz) != (m, square)
                {
                    continue;
                }
                if let Some(slot) = self.live.slot_of(grid.index(cx, cz)) {
                    self.live.touch(slot);
                }
            }
        }
    }
}

/// Diamond `d`'s depth (coarse first: 0 for the root).
fn depth_of(grid: &Grid, d: u32) -> u32 {
    let (x, z) = grid.coords(d);
    grid.depth(x, z)
}

#[cfg(test)]
#[path = "morph_tests.rs"]
mod tests;
