//! Which colour tiles a viewer gets, and when: a pure per-viewer scheduler
//! ([`ColorScheduler`]) over the pyramid's layout ([`ColorLayout`]). No clock and no
//! socket: the net shell feeds it the camera's position and a byte allowance from its
//! token bucket, and sends what it returns, in order, on the control stream.
//!
//! State: per level, the window origin the viewer was last told, and which tiles of the
//! window were sent. Messages are ordered and reliable, so that is exactly what the viewer
//! holds (a test replays the messages as a viewer would and compares). Which were sent is
//! a bitmap of the window, not of the level: `W²` flags a level, shifted when the window
//! moves, so a viewer's state is sized by its windows whatever the map (a bitmap of the
//! level was 4 MB a viewer at 32769² in tiles of 16; [`ColorScheduler::bytes`], a test
//! compares two map sizes).
//!
//! Decisions:
//!
//! - **Coarse first, then ring by ring**: the coarsest level's single tile before
//!   anything (the shell sends it before the first frame, whatever the budget:
//!   [`ColorScheduler::first`]), then every level's window tiles in one order: by the
//!   distance from the camera to the tile, in tiles of the tile's own level (0 for the
//!   tile under the camera), ties to the coarser level, then by row and column (so the
//!   order is deterministic). A tile's size on screen goes as one over that distance
//!   whatever its level, so this sends what the viewer sees largest first: the tiles
//!   under the vehicle at every level, coarsest first, before the far tiles of any
//!   level. Sending whole levels coarse to fine instead left the ground near the vehicle
//!   blurred for about 11 s at 16385² (the six coarser windows, 22 MB at 2 MB/s, before
//!   level 0's first tile).
//! - **Windows follow the camera with hysteresis**: a level's window is recentred on the
//!   camera (clamped inside the level) only when the camera is more than
//!   `max(0.75, W / 4)` tiles from the window's centre on an axis — 2 tiles at W = 8,
//!   so a camera wandering around a tile edge never makes the window flap, and the
//!   camera is always at least 2 tiles from the window's edge where that level is
//!   drawn. Origins of levels that fit a window never move (and are never sent).
//! - **Budget**: [`ColorScheduler::step`] returns tiles while their payloads fit the
//!   allowance and stops at the first that does not (it never skips ahead to a smaller
//!   tile: priority order is kept). Window messages cost nothing here (a few bytes).
//! - **Normals travel with their colour tile** ([`ColorScheduler::with_normals`]): a
//!   tile's [`ColorSend::Normals`] right after its [`ColorSend::Tile`], the two charged
//!   together against the allowance (both fit or neither goes), held and dropped by the
//!   same windows. So normals arrive in the colour's order, never outpace it (tiles a
//!   second: one normal tile per colour tile, a test counts them), and need no window
//!   messages or state of their own. The coarsest tile's normals are the exception in
//!   time only: its colour goes before the first frame ([`ColorScheduler::first`]), its
//!   normals first thing after (the next [`ColorScheduler::step`]) — lighting per vertex
//!   until they come costs nothing, and a first frame waiting for them would.
//! - "In front of the camera first" is not done: the heading is not known here and the
//!   window is small (2048 texels at W = 8, T = 256); nearest first already gives the
//!   ground under and around the vehicle first.

use roam_protocol::ColorLayout;

/// A colour message to send, without its payload (the shell takes it from the pyramid).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ColorSend {
    /// The viewer now keeps level `level`'s tiles `x0 .. x0 + W` × `z0 .. z0 + W`.
    Window { level: u8, x0: u32, z0: u32 },
    /// Tile `(x, z)` of `level`.
    Tile { level: u8, x: u32, z: u32 },
    /// The normals of tile `(x, z)` of `level` (after its colour).
    Normals { level: u8, x: u32, z: u32 },
}

/// One viewer's colour streaming state.
#[derive(Clone, Debug)]
pub struct ColorScheduler {
    layout: ColorLayout,
    /// Per level: the window origin, in tiles.
    origins: Vec<(u32, u32)>,
    /// Per level: which tiles of the window were sent (row-major over the window, from
    /// its origin), so held.
    sent: Vec<Vec<bool>>,
    /// Whether each tile's normals follow it.
    normals: bool,
    /// The coarsest tile's normals, owed since [`Self::first`].
    owed: Option<(u8, u32, u32)>,
}

impl ColorScheduler {
    /// A viewer that holds nothing yet; every window at `(0, 0)`.
    pub fn new(layout: ColorLayout) -> ColorScheduler {
        let levels = usize::from(layout.levels);
        ColorScheduler {
            layout,
            origins: vec![(0, 0); levels],
            sent: (0..layout.levels)
                .map(|l| vec![false; (layout.window_tiles(l) as usize).pow(2)])
                .collect(),
            normals: false,
            owed: None,
        }
    }

    /// [`Self::new`], each tile's normals sent with it (see the module's header).
    pub fn with_normals(layout: ColorLayout) -> ColorScheduler {
        ColorScheduler {
            normals: true,
            ..ColorScheduler::new(layout)
        }
    }

    /// The layout scheduled for.
    pub fn layout(&self) -> &ColorLayout {
        &self.layout
    }

    /// The coarsest level's single tile (what the viewer gets before its first frame);
    /// marked sent.
    pub fn first(&mut self) -> ColorSend {
        let level = self.layout.levels - 1;
        self.sent[usize::from(level)][0] = true;
        if self.normals {
            self.owed = Some((level, 0, 0));
        }
        ColorSend::Tile { level, x: 0, z: 0 }
    }

    /// The messages for a camera at level-0 texel `(cx, cz)` with `allowance` bytes to
    /// spend, `cost(m)` being a tile message's payload bytes: windows moved, the coarsest
    /// tile's normals if owed, then tiles (each with its normals) in priority order while
    /// they fit. Returns them and the bytes spent.
    pub fn step(
        &mut self,
        (cx, cz): (f64, f64),
        allowance: u64,
        cost: &dyn Fn(ColorSend) -> u64,
    ) -> (Vec<ColorSend>, u64) {
        let mut out = Vec::new();
        for level in 0..self.layout.levels {
            if let Some((x0, z0)) = self.recentre(level, (cx, cz)) {
                out.push(ColorSend::Window { level, x0, z0 });
            }
        }
        let mut spent = 0;
        if let Some((level, x, z)) = self.owed {
            let m = ColorSend::Normals { level, x, z };
            spent = cost(m);
            if spent > allowance {
                return (out, 0);
            }
            self.owed = None;
            out.push(m);
        }
        for (level, x, z) in self.unsent((cx, cz)) {
            let tile = ColorSend::Tile { level, x, z };
            let normals = self.normals.then_some(ColorSend::Normals { level, x, z });
            let c = cost(tile) + normals.map_or(0, cost);
            if spent + c > allowance {
                return (out, spent);
            }
            spent += c;
            let at = self.slot(level, x, z);
            self.sent[usize::from(level)][at] = true;
            out.push(tile);
            out.extend(normals);
        }
        (out, spent)
    }

    /// Whether every tile of every window has been sent (with its normals).
    pub fn complete(&self) -> bool {
        self.owed.is_none()
            && (0..self.layout.levels).all(|l| self.held_in(l).count() == self.window_count(l))
    }

    /// The tiles the viewer holds, as `(level, x, z)`: level by level, rows then columns.
    pub fn held(&self) -> Vec<(u8, u32, u32)> {
        (0..self.layout.levels)
            .flat_map(|l| self.held_in(l).map(move |(x, z)| (l, x, z)))
            .collect()
    }

    /// Level `level`'s window origin.
    pub fn origin(&self, level: u8) -> (u32, u32) {
        self.origins[usize::from(level)]
    }

    /// Bytes this state holds (capacities): a few per level and a flag per window tile,
    /// nothing by the size of the map.
    pub fn bytes(&self) -> usize {
        size_of::<ColorScheduler>()
            + self.origins.capacity() * size_of::<(u32, u32)>()
            + self.sent.capacity() * size_of::<Vec<bool>>()
            + self.sent.iter().map(Vec::capacity).sum::<usize>()
    }

    /// Where tile `(x, z)` of `level`, inside its window, is in `sent`.
    fn slot(&self, level: u8, x: u32, z: u32) -> usize {
        let (x0, z0) = self.origins[usize::from(level)];
        ((z - z0) * self.layout.window_tiles(level) + (x - x0)) as usize
    }

    fn window_count(&self, level: u8) -> usize {
        (self.layout.window_tiles(level) as usize).pow(2)
    }

    fn held_in(&self, level: u8) -> impl Iterator<Item = (u32, u32)> + '_ {
        let w = self.layout.window_tiles(level);
        let (x0, z0) = self.origins[usize::from(level)];
        self.sent[usize::from(level)]
            .iter()
            .enumerate()
            .filter(|(_, s)| **s)
            .map(move |(i, _)| (x0 + i as u32 % w, z0 + i as u32 / w))
    }

    /// The camera's position in tiles of `level`.
    fn camera_tiles(&self, level: u8, (cx, cz): (f64, f64)) -> (f64, f64) {
        let per = f64::from(self.layout.tile_side(level)) * f64::from(1u32 << level);
        (cx / per, cz / per)
    }

    /// Moves `level`'s window when the camera has left its centre by more than the
    /// hysteresis; the new origin, and the tiles outside it forgotten.
    fn recentre(&mut self, level: u8, cam: (f64, f64)) -> Option<(u32, u32)> {
        if !self.layout.windowed(level) {
            return None;
        }
        let w = self.layout.window_tiles(level);
        let room = self.layout.tiles(level) - w;
        let (tx, tz) = self.camera_tiles(level, cam);
        let (x0, z0) = self.origins[usize::from(level)];
        let half = f64::from(w) / 2.0;
        let slack = (f64::from(w) / 4.0).max(0.75);
        // Recentre where the window can still move towards the camera.
        let off = |t: f64, o: u32| {
            let d = t - (f64::from(o) + half);
            (d > slack && o < room) || (d < -slack && o > 0)
        };
        if !off(tx, x0) && !off(tz, z0) {
            return None;
        }
        let place = |t: f64| ((t - half).round().max(0.0) as u32).min(room);
        let origin = (place(tx), place(tz));
        if origin == (x0, z0) {
            return None;
        }
        // The tiles held in both windows keep their flags, shifted; the rest are forgotten.
        let held: Vec<(u32, u32)> = self.held_in(level).collect();
        self.origins[usize::from(level)] = origin;
        self.sent[usize::from(level)].fill(false);
        for (x, z) in held {
            if self.layout.in_window(level, origin, x, z) {
                let at = self.slot(level, x, z);
                self.sent[usize::from(level)][at] = true;
            }
        }
        Some(origin)
    }

    /// Every window's tiles not sent yet, in priority order (see the module's header).
    fn unsent(&self, cam: (f64, f64)) -> Vec<(u8, u32, u32)> {
        let mut tiles: Vec<(f64, u8, u32, u32)> = Vec::new();
        for level in 0..self.layout.levels {
            let (x0, z0) = self.origins[usize::from(level)];
            let w = self.layout.window_tiles(level);
            let (tx, tz) = self.camera_tiles(level, cam);
            let sent = &self.sent[usize::from(level)];
            for z in z0..z0 + w {
                for x in x0..x0 + w {
                    if !sent[self.slot(level, x, z)] {
                        tiles.push((tile_distance((tx, tz), x, z), level, x, z));
                    }
                }
            }
        }
        tiles.sort_by(|a, b| {
            (a.0.total_cmp(&b.0))
                .then(b.1.cmp(&a.1))
                .then((a.3, a.2).cmp(&(b.3, b.2)))
        });
        tiles.into_iter().map(|(_, l, x, z)| (l, x, z)).collect()
    }
}

/// Distance from `(tx, tz)` (in tiles) to the nearest point of tile `(x, z)`: 0 inside it.
pub fn tile_distance((tx, tz): (f64, f64), x: u32, z: u32) -> f64 {
    let gap = |t: f64, lo: u32| (f64::from(lo) - t).max(t - f64::from(lo + 1)).max(0.0);
    gap(tx, x).hypot(gap(tz, z))
}

#[cfg(test)]
#[path = "color_tests.rs"]
mod tests;
