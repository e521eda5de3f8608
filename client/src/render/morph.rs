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
//! **Where a vertex is drawn**: `mid + p/T · (h − mid)`, where `p` is its progress in
//! ticks (integers: a replay of the same frames draws the same mesh, bit for bit), `T`
//! the morph's length, `h` its height and `mid` the mean of its hypotenuse ends *as
//! drawn* (an end still morphing moves the midpoint with it, so a vertex appearing on a
//! moving edge appears on it). At `p = T` it is at `h` exactly. Computed coarse to fine,
//! so the ends are placed before the vertices between them.
//!
//! **Time is the frames' ticks**, never the wall clock: the morph advances by the tick
//! difference between consecutive frames taken, so a slow machine draws the same
//! sequence as a fast one (the `--bench` measures rely on it).
//!
//! **Why a quarter of a second** (25 ticks of 100 Hz): the morph has to be slow enough
//! that a frame's step is well under a pixel (at 60 frames a second a vertex covers a
//! fifteenth of its pop per frame: a 5 px pop, the largest screen error the budget leaves
//! on rough terrain, moves a third of a pixel a frame), and fast enough that the detail
//! a split reveals is there while the driver still looks at it (at the bench drive's
//! speed a quarter of a second is a few metres; half a second left visibly flat terrain
//! in front of a fast vehicle). Linear in time: an eased curve is steeper in its middle
//! (smoothstep's peak rate is 1.5×), which is what the per-frame displacement measures.

use roam_protocol::{DiamondMap, Grid, LiveMesh};

use super::{Scene, TerrainVertices};

/// World ticks a vertex takes to morph from its midpoint to its height: a quarter of a
/// second at 100 Hz (see the module docs).
pub const MORPH_TICKS: u16 = 25;

/// A diamond of the drawn cut.
#[derive(Clone, Copy, Debug, Default)]
struct Drawn {
    /// Its height, samples.
    h: u16,
    /// Progress from its midpoint (0) to its height ([`Morph::ticks`]).
    p: u16,
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
    /// Drawn height less height, samples, of each vertex not at its height.
    lift: DiamondMap<f32>,
    /// Scratch.
    toggled: Vec<u32>,
    touched: Vec<u32>,
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
            lift: DiamondMap::new(),
            toggled: Vec::new(),
            touched: Vec::new(),
        }
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
        let (drawn, lift) = (&self.drawn, &self.lift);
        terrain.update(
            scene,
            &mut self.live,
            |i| drawn.get(i).map(|v| v.h).or_else(|| corner(i)),
            |i| lift.get(i).unwrap_or(0.0),
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
        self.lift.get(i).unwrap_or(0.0)
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.drawn.bytes()
            + self.lift.bytes()
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
        for &d in &self.moving {
            if let Some(mut v) = self.drawn.get(d) {
                v.p = match (v.out, snap) {
                    (true, true) => 0,
                    (false, true) => full,
                    (true, false) => v.p.saturating_sub(advance),
                    (false, false) => v.p.saturating_add(advance).min(full),
                };
                self.drawn.insert(d, v);
            }
        }
        for &(d, h) in changes {
            let now = split(d);
            match self.drawn.get(d) {
                Some(mut v) if now => {
                    // Split again while morphing out: back up from where it is.
                    v.out = false;
                    v.h = h;
                    if snap {
                        v.p = full;
                    }
                    self.drawn.insert(d, v);
                    self.list(d);
                    self.touched.push(d);
                }
                Some(mut v) => {
                    // Merged: back to its midpoint first (at once for a new cut); it
                    // leaves the drawn cut there, after its children.
                    v.out = true;
                    if snap {
                        v.p = 0;
                    }
                    self.drawn.insert(d, v);
                    self.list(d);
                    self.touched.push(d);
                }
                None if now => {
                    let p = if snap { full } else { 0 };
                    self.drawn.insert(
                        d,
                        Drawn {
                            h,
                            p,
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
        self.remove_finished();
        let drawn = &self.drawn;
        self.live
            .update(&self.grid, self.toggled.iter().copied(), |i| {
                drawn.contains(i)
            });
        self.place(&corner);
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
        let depth = |d: u32| {
            let (x, z) = grid.coords(d);
            grid.depth(x, z)
        };
        let mut moving = std::mem::take(&mut self.moving);
        moving.sort_unstable_by_key(|&d| (std::cmp::Reverse(depth(d)), d));
        let full = self.ticks;
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
                if v.p == 0 && children_gone {
                    self.drawn.remove(d);
                    self.toggled.push(d);
                    return false;
                }
                true
            } else if v.p >= full {
                v.listed = false;
                self.drawn.insert(d, v);
                false
            } else {
                true
            }
        });
        self.moving = moving;
    }

    /// Where each moving vertex is drawn, coarse to fine (its hypotenuse ends first).
    fn place(&mut self, corner: &impl Fn(u32) -> Option<u16>) {
        let grid = self.grid;
        let depth = |d: u32| {
            let (x, z) = grid.coords(d);
            grid.depth(x, z)
        };
        self.moving.sort_unstable_by_key(|&d| (depth(d), d));
        self.lift.clear();
        let full = f32::from(self.ticks.max(1));
        for &d in &self.moving {
            let Some(v) = self.drawn.get(d) else {
                continue;
            };
            if !v.out && v.p >= self.ticks {
                continue;
            }
            let (x, z) = grid.coords(d);
            let end = |(ex, ez): (u32, u32)| {
                let i = grid.index(ex, ez);
                let h = self.drawn.get(i).map(|e| e.h).or_else(|| corner(i));
                f32::from(h.unwrap_or(v.h)) + self.lift.get(i).unwrap_or(0.0)
            };
            let [a, b] = grid.hypotenuse(x, z);
            let mid = 0.5 * (end(a) + end(b));
            let h = f32::from(v.h);
            let y = mid + (h - mid) * (f32::from(v.p) / full);
            if y != h {
                self.lift.insert(d, y - h);
            }
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
        let top = x.trailing_zeros().min(z.trailing_zeros()).min(grid.levels());
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

#[cfg(test)]
#[path = "morph_tests.rs"]
mod tests;
