//! The colour map's tile pyramid, as both ends see it ([`ColorLayout`], sent in the
//! welcome): level 0 is the map, `cells` texels a side; level `l` has `max(1, cells >> l)`
//! (a 2×2 box average of level `l − 1`). Each level is cut into `tile × tile` tiles (the
//! whole level when it is smaller), each coded alone with [`crate::colormap`]. The pyramid
//! stops at the first level that is one tile. A viewer keeps, per level, a window of
//! `window × window` tiles whose origin the server moves ([`crate::messages::ServerMessage::ColorWindow`]);
//! a level of at most `window` tiles a side is held whole.
//!
//! Decisions:
//!
//! - All sides are powers of two: `cells` (the grid is `2^N + 1` samples), `tile` (at
//!   most [`MAX_TILE`], so a tile's payload is at most [`MAX_TILE_BYTES`], the bound a
//!   [`crate::messages::ServerMessage::ColorTile`] is decoded against before anything is
//!   allocated) — so tiles never straddle a level's edge and every level's tiles are whole.
//! - The window is at most [`MAX_WINDOW`] tiles: 16 × 256 = 4096 texels a layer, within
//!   every GPU's 2D texture limit (8192 in wgpu's defaults).
//! - [`ColorLayout::check`] is what a viewer runs on a welcome's layout: a server's layout
//!   that does not add up is refused there, so later code can index by it without checks.

use serde::{Deserialize, Serialize};

/// The largest tile side.
pub const MAX_TILE: u32 = 256;
/// The largest tile payload, bytes: [`crate::colormap::max_len`] of [`MAX_TILE`].
pub const MAX_TILE_BYTES: usize = (MAX_TILE as usize) * (MAX_TILE as usize) * 3 + (64 << 10);
/// The largest map side: the largest grid is `2^15 + 1` samples.
pub const MAX_COLOR_CELLS: u32 = 1 << 15;
/// The most tiles a side of a viewer's window per level.
pub const MAX_WINDOW: u8 = 16;
/// The tile side servers use.
pub const DEFAULT_TILE: u32 = 256;
/// The window side (tiles) viewers ask for and servers offer by default.
pub const DEFAULT_WINDOW: u8 = 8;

/// The shape of a colour map's tile pyramid ([`crate::messages::Welcome::color`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ColorLayout {
    /// Texels a side of level 0 (a power of two).
    pub cells: u32,
    /// Texels a side of a tile (a power of two, at most [`MAX_TILE`]).
    pub tile: u32,
    /// Levels in the pyramid: the last is a single tile.
    pub levels: u8,
    /// Tiles a side of the window kept per level (1 ..= [`MAX_WINDOW`]).
    pub window: u8,
}

/// A layout that does not add up.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum LayoutError {
    #[error("colour map of {0} cells a side: expected a power of two in 1 ..= {MAX_COLOR_CELLS}")]
    Cells(u32),
    #[error("colour tile of {0} texels a side: expected a power of two in 1 ..= {MAX_TILE}")]
    Tile(u32),
    #[error("colour window of {0} tiles a side: expected 1 ..= {MAX_WINDOW}")]
    Window(u8),
    #[error("{got} colour levels for {cells} cells in tiles of {tile}: expected {expected}")]
    Levels {
        got: u8,
        expected: u8,
        cells: u32,
        tile: u32,
    },
}

/// Levels of the pyramid of a `cells` map in `tile` tiles (both powers of two).
pub fn levels_for(cells: u32, tile: u32) -> u8 {
    let (n, k) = (cells.max(1).ilog2(), tile.max(1).ilog2());
    (n.saturating_sub(k) + 1) as u8
}

impl ColorLayout {
    /// The layout of a `cells` map in `tile` tiles, windows of `window` tiles.
    pub fn new(cells: u32, tile: u32, window: u8) -> Result<ColorLayout, LayoutError> {
        let layout = ColorLayout {
            cells,
            tile,
            levels: levels_for(cells, tile),
            window,
        };
        layout.check()?;
        Ok(layout)
    }

    /// Whether the fields agree (see [`LayoutError`]).
    pub fn check(&self) -> Result<(), LayoutError> {
        if !self.cells.is_power_of_two() || self.cells > MAX_COLOR_CELLS {
            return Err(LayoutError::Cells(self.cells));
        }
        if !self.tile.is_power_of_two() || self.tile > MAX_TILE {
            return Err(LayoutError::Tile(self.tile));
        }
        if !(1..=MAX_WINDOW).contains(&self.window) {
            return Err(LayoutError::Window(self.window));
        }
        let expected = levels_for(self.cells, self.tile);
        if self.levels != expected {
            return Err(LayoutError::Levels {
                got: self.levels,
                expected,
                cells: self.cells,
                tile: self.tile,
            });
        }
        Ok(())
    }

    /// Texels a side of `level`.
    pub fn side(&self, level: u8) -> u32 {
        (self.cells >> level.min(31)).max(1)
    }

    /// Texels a side of a tile of `level` (the whole level when it is smaller than a tile).
    pub fn tile_side(&self, level: u8) -> u32 {
        self.side(level).min(self.tile)
    }

    /// Tiles a side of `level`.
    pub fn tiles(&self, level: u8) -> u32 {
        self.side(level) / self.tile_side(level)
    }

    /// Tiles a side of `level`'s window: the whole level when it fits.
    pub fn window_tiles(&self, level: u8) -> u32 {
        self.tiles(level).min(u32::from(self.window))
    }

    /// Whether `level`'s window moves (the level is larger than a window).
    pub fn windowed(&self, level: u8) -> bool {
        self.tiles(level) > u32::from(self.window)
    }

    /// Whether a window origin `(x0, z0)` keeps the window inside `level`.
    pub fn origin_valid(&self, level: u8, x0: u32, z0: u32) -> bool {
        let room = self.tiles(level) - self.window_tiles(level);
        level < self.levels && x0 <= room && z0 <= room
    }

    /// Whether tile `(x, z)` of `level` is in the window at `origin`.
    pub fn in_window(&self, level: u8, origin: (u32, u32), x: u32, z: u32) -> bool {
        let w = self.window_tiles(level);
        level < self.levels
            && (origin.0..origin.0 + w).contains(&x)
            && (origin.1..origin.1 + w).contains(&z)
    }

    /// The most bytes a tile of `level` may take ([`crate::colormap::max_len`]).
    pub fn max_tile_bytes(&self, level: u8) -> usize {
        crate::colormap::max_len(self.tile_side(level))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn levels_stop_at_one_tile() {
        assert_eq!(levels_for(4, 256), 1);
        assert_eq!(levels_for(256, 256), 1);
        assert_eq!(levels_for(512, 256), 2);
        assert_eq!(levels_for(16384, 256), 7);
        assert_eq!(levels_for(256, 16), 5);
        let l = ColorLayout::new(256, 16, 4).expect("a valid layout");
        assert_eq!(
            (0..l.levels).map(|v| l.tiles(v)).collect::<Vec<_>>(),
            [16, 8, 4, 2, 1]
        );
        assert_eq!(l.tile_side(4), 16);
        assert!(l.windowed(0) && l.windowed(1) && !l.windowed(2));
        assert_eq!(l.window_tiles(0), 4);
        assert_eq!(l.window_tiles(3), 2);
        let small = ColorLayout::new(8, 256, 8).expect("a valid layout");
        assert_eq!(
            (small.levels, small.tile_side(0), small.tiles(0)),
            (1, 8, 1)
        );
        assert_eq!(MAX_TILE_BYTES, crate::colormap::max_len(MAX_TILE));
    }

    #[test]
    fn bad_layouts_are_refused() {
        let good = ColorLayout::new(1024, 256, 8).expect("a valid layout");
        for (bad, want) in [
            (
                ColorLayout {
                    cells: 1000,
                    ..good
                },
                LayoutError::Cells(1000),
            ),
            (
                ColorLayout {
                    cells: 1 << 16,
                    ..good
                },
                LayoutError::Cells(1 << 16),
            ),
            (ColorLayout { tile: 512, ..good }, LayoutError::Tile(512)),
            (ColorLayout { tile: 0, ..good }, LayoutError::Tile(0)),
            (ColorLayout { window: 0, ..good }, LayoutError::Window(0)),
            (ColorLayout { window: 17, ..good }, LayoutError::Window(17)),
            (
                ColorLayout { levels: 4, ..good },
                LayoutError::Levels {
                    got: 4,
                    expected: 3,
                    cells: 1024,
                    tile: 256,
                },
            ),
        ] {
            assert_eq!(bad.check(), Err(want));
        }
    }

    #[test]
    fn windows_stay_inside_their_level() {
        let l = ColorLayout::new(256, 16, 4).expect("a valid layout");
        assert!(l.origin_valid(0, 12, 12));
        assert!(!l.origin_valid(0, 13, 0));
        assert!(l.origin_valid(3, 0, 0));
        assert!(!l.origin_valid(3, 1, 0));
        assert!(!l.origin_valid(5, 0, 0));
        assert!(l.in_window(0, (12, 0), 15, 3));
        assert!(!l.in_window(0, (12, 0), 11, 3));
        assert!(!l.in_window(0, (12, 0), 12, 4));
        assert!(!l.in_window(9, (0, 0), 0, 0));
    }
}
