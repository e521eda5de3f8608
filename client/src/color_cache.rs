//! The viewer's colour cache, with no socket, task or clock: what the server's
//! [`ServerMessage::ColorWindow`], [`ServerMessage::ColorTile`] and
//! [`ServerMessage::NormalTile`] messages leave resident, per level of the colour pyramid
//! ([`ColorLayout`]), and the texture uploads the renderer owes the GPU. The session feeds
//! it from the control stream; the renderer drains it ([`ColorCache::drain`]) into its
//! clipmap texture arrays, one for colour and one for normals.
//!
//! **Normals** ([`roam_protocol::normals`]) are a second kind of tile in the same slots
//! ([`tile_slots`]): the same layout, the same windows (a window move drops both
//! kinds' tiles outside it), the same checks, kept apart so either may come without the
//! other (a damaged tile on the server is not sent). Their texels are the two-byte codes
//! (an `Rg8Unorm` texel), half a colour texel's four.
//!
//! **Addressing.** Every level has a layer of `S × S` texels, `S = min(W·T, cells)` (W the
//! window in tiles, T the tile side); texel `(u, v)` of level `l` lives at `(u mod S,
//! v mod S)` of layer `l`, so tile `(x, z)` lands at `((x·T) mod S, (z·T) mod S)` and
//! occupies *slot* `(z mod W)·W + (x mod W)`: the bit of the level's masks, and the index
//! into its slots here. A level larger than a window keeps the `W × W` tiles from the
//! origin the server last gave ([`ColorCache::apply_window`]; `(0, 0)` until then); a
//! smaller level is held whole.
//!
//! **Checks.** Every message is checked before it changes anything, and a bad one is a
//! [`ColorError`] naming the field: a level past the layout's, a window origin that does
//! not keep the window inside its level (or a window for a level held whole), a tile
//! outside its level or the level's current window, a payload longer than
//! [`ColorLayout::max_tile_bytes`] or one that does not decode to the tile's side (with
//! [`Keep::Counted`] nothing is decoded: the place and the length are checked).
//!
//! **Bounded.** At most one tile of each kind per slot: `Σ_l min(tiles_l, W)²` tiles, so
//! never more than `levels × S²` texels of each (6 bytes a texel in all, RGBA and the
//! normal's code, waiting to be uploaded; plus the coarsest tile's RGB, at most `T² · 3`
//! bytes, or its payload, at most [`ColorLayout::max_tile_bytes`], which a reconnection
//! compares), and each upload queue holds at most one entry
//! per slot (an entry is removed with its tile when a window moves). With
//! [`Keep::Masks`] (a headless viewer that never draws) no texel is kept at all: tiles are
//! decoded to check them, counted, and dropped. Uploaded texels are freed here (the GPU has
//! them); the masks the shader reads ([`LevelState::drawn`]) only name tiles already
//! handed to the renderer, so a tile never shows before its texels do.
//!
//! Decision: the renderer is fed by draining, not by reading a CPU copy of every layer:
//! a window at W = 8 over a 16385² map holds 7 layers of 2048² texels (112 MiB in RGBA,
//! and 56 MiB of normals) — worth keeping on the GPU, not twice. The cost: a renderer made after a drain cannot
//! be filled again (one renderer per session, as the window, the benchmark and the
//! headless screenshot each have).

use roam_protocol::messages::ServerMessage;
use roam_protocol::tiles::{ColorLayout, MAX_WINDOW};
use roam_protocol::{colormap, normals};

mod tile_slots;

use tile_slots::TileSlots;

/// The most window bits a level has: [`MAX_WINDOW`]², as `u32` words.
pub const MASK_WORDS: usize = (MAX_WINDOW as usize * MAX_WINDOW as usize).div_ceil(32);

/// What the cache keeps of a tile's texels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Keep {
    /// Texels until the renderer takes them (a viewer that draws).
    Texels,
    /// Nothing: residency and counts only (a headless viewer that never draws).
    Masks,
    /// As [`Keep::Masks`], and tiles are not even decoded: their level and place are
    /// checked, their bytes counted, the coarsest colour tile's payload kept as received
    /// (a reconnection compares it: the same server sends the same bytes; a server whose
    /// tile encoder changed would read as another map). For a load
    /// generator measuring the server (`roam-client --skip-decode`): decoding the join's
    /// tiles was 56 % of a generator's core while 40 viewers joined at once (`perf`,
    /// `colormap::run`, 2026-12-07), which its viewers' gaps then measured.
    Counted,
}

/// A message the cache refuses: the field, and what was wrong with it.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{field}: {message}")]
pub struct ColorError {
    /// The message and field, e.g. `ColorTile.level`.
    pub field: &'static str,
    pub message: String,
}

fn refuse(field: &'static str, message: String) -> ColorError {
    ColorError { field, message }
}

/// One texture upload: `size × size` texels at `(x, y)` of layer `layer`, the tile of
/// window slot `slot`: RGBA (4 bytes a texel) for colour, the normal's two-byte code for
/// normals.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Upload {
    pub layer: u32,
    pub slot: u32,
    pub x: u32,
    pub y: u32,
    pub size: u32,
    pub texels: Vec<u8>,
}

/// What the shader needs of a level: the window's origin (tiles) and the tiles it may
/// sample (bit `(z mod W)·W + (x mod W)`), of colour and of normals.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LevelState {
    pub origin: [u32; 2],
    pub drawn: [u32; MASK_WORDS],
    pub normals: [u32; MASK_WORDS],
}

/// What [`ColorCache::drain`] hands the renderer: uploads (colour, normals), then every
/// level's state once they are written.
#[derive(Clone, Debug, Default)]
pub struct ColorUpdate {
    pub uploads: Vec<Upload>,
    pub normals: Vec<Upload>,
    pub levels: Vec<LevelState>,
}

/// The resident colour and normal tiles of one connection (a reconnection starts a fresh
/// one).
#[derive(Clone, Debug)]
pub struct ColorCache {
    layout: ColorLayout,
    keep: Keep,
    /// Per level, the window's origin (tiles).
    origins: Vec<(u32, u32)>,
    colors: TileSlots,
    normals: TileSlots,
    scratch: Vec<u8>,
    /// The coarsest level's tile (RGB; its payload with [`Keep::Counted`]): what a
    /// reconnection compares to know the map.
    coarsest: Vec<u8>,
}

impl ColorCache {
    /// An empty cache for `layout` (checked: see [`ColorLayout::check`]) on a grid of
    /// `2^grid_levels + 1` samples, whose window was asked to be at most `asked` tiles.
    pub fn new(
        layout: ColorLayout,
        grid_levels: u8,
        asked: u8,
        keep: Keep,
    ) -> Result<ColorCache, ColorError> {
        layout
            .check()
            .map_err(|e| refuse("Welcome.color", e.to_string()))?;
        let cells = 1u64 << grid_levels.min(32);
        if u64::from(layout.cells) != cells {
            return Err(refuse(
                "Welcome.color.cells",
                format!(
                    "{}, expected {cells} for a grid of 2^{grid_levels} + 1",
                    layout.cells
                ),
            ));
        }
        if layout.window > asked {
            return Err(refuse(
                "Welcome.color.window",
                format!("{} tiles, more than the {asked} asked for", layout.window),
            ));
        }
        Ok(ColorCache::empty(layout, keep))
    }

    fn empty(layout: ColorLayout, keep: Keep) -> ColorCache {
        ColorCache {
            layout,
            keep,
            origins: vec![(0, 0); usize::from(layout.levels)],
            colors: TileSlots::new(&layout, 4),
            normals: TileSlots::new(&layout, 2),
            scratch: Vec::new(),
            coarsest: Vec::new(),
        }
    }

    /// An empty cache of the same layout and keeping, at the same window origins (what a
    /// cache handed away leaves: the server goes on sending for the windows it set, so
    /// its later tiles must still be taken).
    pub fn fresh(&self) -> ColorCache {
        let mut c = ColorCache::empty(self.layout, self.keep);
        c.origins.clone_from(&self.origins);
        c
    }

    /// The coarsest level's tile as received (RGB; its payload with [`Keep::Counted`]),
    /// empty before it.
    pub fn coarsest(&self) -> &[u8] {
        &self.coarsest
    }

    pub fn layout(&self) -> &ColorLayout {
        &self.layout
    }

    /// Texels a side of every layer: `min(W·T, cells)`.
    pub fn layer_side(&self) -> u32 {
        layer_side(&self.layout)
    }

    /// Colour tile payload bytes received.
    pub fn bytes(&self) -> u64 {
        self.colors.bytes()
    }

    /// Colour tiles received (those dropped since included).
    pub fn received(&self) -> u64 {
        self.colors.received()
    }

    /// Colour tiles resident now.
    pub fn resident(&self) -> u32 {
        self.colors.resident()
    }

    /// Normal tile payload bytes received.
    pub fn normal_bytes(&self) -> u64 {
        self.normals.bytes()
    }

    /// Normal tiles received (those dropped since included).
    pub fn normals_received(&self) -> u64 {
        self.normals.received()
    }

    /// Normal tiles resident now.
    pub fn normals_resident(&self) -> u32 {
        self.normals.resident()
    }

    /// The most tiles that can be resident: one per slot.
    pub fn capacity(&self) -> u32 {
        (0..self.layout.levels)
            .map(|l| self.layout.window_tiles(l).pow(2))
            .sum()
    }

    /// RGBA texels held, waiting for the renderer.
    pub fn texels_held(&self) -> usize {
        self.colors.texels_held()
    }

    /// Normal texels held (two bytes each), waiting for the renderer.
    pub fn normal_texels_held(&self) -> usize {
        self.normals.texels_held()
    }

    /// Colour uploads waiting.
    pub fn queued(&self) -> usize {
        self.colors.queued()
    }

    /// Normal uploads waiting.
    pub fn normals_queued(&self) -> usize {
        self.normals.queued()
    }

    /// Whether the coarsest level's single tile is resident (every point has a colour).
    pub fn has_coarsest(&self) -> bool {
        let last = self.layout.levels - 1;
        self.resident_mask(last)[0] & 1 == 1
    }

    fn slot_of(&self, x: u32, z: u32) -> usize {
        let w = u32::from(self.layout.window);
        ((z % w) * w + (x % w)) as usize
    }

    /// Colour tiles of `level` resident (bit `(z mod W)·W + (x mod W)`).
    pub fn resident_mask(&self, level: u8) -> [u32; MASK_WORDS] {
        self.colors.mask(level, false)
    }

    /// Colour tiles of `level` handed to the renderer.
    pub fn drawn_mask(&self, level: u8) -> [u32; MASK_WORDS] {
        self.colors.mask(level, true)
    }

    /// Normal tiles of `level` resident.
    pub fn normals_mask(&self, level: u8) -> [u32; MASK_WORDS] {
        self.normals.mask(level, false)
    }

    /// The window origin of `level`, in tiles.
    pub fn origin(&self, level: u8) -> Option<(u32, u32)> {
        self.origins.get(usize::from(level)).copied()
    }

    /// Whether colour tile `(x, z)` of `level` is resident.
    pub fn is_resident(&self, level: u8, x: u32, z: u32) -> bool {
        self.colors.is_resident(level, self.slot_of(x, z), x, z)
    }

    /// Whether normal tile `(x, z)` of `level` is resident.
    pub fn has_normals(&self, level: u8, x: u32, z: u32) -> bool {
        self.normals.is_resident(level, self.slot_of(x, z), x, z)
    }

    /// A colour or normal message from the server; anything else is not for the cache
    /// (`Ok(false)`).
    pub fn apply(&mut self, msg: &ServerMessage) -> Result<bool, ColorError> {
        match msg {
            ServerMessage::ColorWindow { level, x0, z0 } => self.apply_window(*level, *x0, *z0)?,
            ServerMessage::ColorTile { level, x, z, data } if self.keep == Keep::Counted => {
                check_payload(&self.layout, "ColorTile", *level, *x, *z, data)?;
                self.check_tile("ColorTile", *level, *x, *z)?;
                self.put(*level, *x, *z, data, data.len());
            }
            ServerMessage::NormalTile { level, x, z, data } if self.keep == Keep::Counted => {
                check_payload(&self.layout, "NormalTile", *level, *x, *z, data)?;
                self.check_tile("NormalTile", *level, *x, *z)?;
                self.put_codes(*level, *x, *z, &[], data.len());
            }
            ServerMessage::ColorTile { level, x, z, data } => {
                self.apply_tile(*level, *x, *z, data)?
            }
            ServerMessage::NormalTile { level, x, z, data } => {
                let mut codes = std::mem::take(&mut self.scratch);
                let decoded = decode_normal_tile(&self.layout, *level, *x, *z, data, &mut codes)
                    .and_then(|()| self.put_normals_decoded(*level, *x, *z, &codes, data.len()));
                self.scratch = codes;
                decoded?
            }
            _ => return Ok(false),
        }
        Ok(true)
    }

    fn check_level(&self, field: &'static str, level: u8) -> Result<(), ColorError> {
        if level >= self.layout.levels {
            return Err(refuse(
                field,
                format!(
                    "{level}, but the colour map has {} levels",
                    self.layout.levels
                ),
            ));
        }
        Ok(())
    }

    /// Level `level` keeps the tiles `x0 .. x0 + W` × `z0 .. z0 + W` from now on: the
    /// others are dropped.
    pub fn apply_window(&mut self, level: u8, x0: u32, z0: u32) -> Result<(), ColorError> {
        self.check_level("ColorWindow.level", level)?;
        let l = &self.layout;
        if !l.windowed(level) {
            return Err(refuse(
                "ColorWindow.level",
                format!(
                    "{level}, which is held whole ({} tiles a side, window {})",
                    l.tiles(level),
                    l.window
                ),
            ));
        }
        if !l.origin_valid(level, x0, z0) {
            return Err(refuse(
                "ColorWindow.x0/z0",
                format!(
                    "({x0}, {z0}): the window of {} tiles leaves level {level} ({} tiles a \
                     side)",
                    l.window,
                    l.tiles(level)
                ),
            ));
        }
        let origin = (x0, z0);
        let layout = self.layout;
        self.origins[usize::from(level)] = origin;
        let keep = |x, z| layout.in_window(level, origin, x, z);
        self.colors.keep_window(level, keep);
        self.normals.keep_window(level, keep);
        Ok(())
    }

    /// Tile `(x, z)` of `level`, coded by [`colormap`]: decoded, checked, made resident.
    pub fn apply_tile(&mut self, level: u8, x: u32, z: u32, data: &[u8]) -> Result<(), ColorError> {
        self.check_tile("ColorTile", level, x, z)?;
        let mut rgb = std::mem::take(&mut self.scratch);
        let decoded = decode_tile(&self.layout, level, x, z, data, &mut rgb);
        if decoded.is_ok() {
            self.put(level, x, z, &rgb, data.len());
        }
        self.scratch = rgb;
        decoded
    }

    /// Tile `(x, z)` of `level` decoded by [`decode_tile`] (outside the lock the cache is
    /// shared under) from `payload` bytes: checked against the window now, made resident.
    pub fn put_decoded(
        &mut self,
        level: u8,
        x: u32,
        z: u32,
        rgb: &[u8],
        payload: usize,
    ) -> Result<(), ColorError> {
        self.check_tile("ColorTile", level, x, z)?;
        let side = self.layout.tile_side(level) as usize;
        if rgb.len() != side * side * 3 {
            return Err(refuse(
                "ColorTile.data",
                format!("{} texel bytes, expected {side}² · 3", rgb.len()),
            ));
        }
        self.put(level, x, z, rgb, payload);
        Ok(())
    }

    /// Tile `(x, z)` of `level` from texels decoded elsewhere (`side² · 3` RGB bytes, row 0
    /// north): a local map, a test. The same checks as [`Self::apply_tile`] but the
    /// payload's.
    pub fn put_tile(&mut self, level: u8, x: u32, z: u32, rgb: &[u8]) -> Result<(), ColorError> {
        self.check_tile("put_tile", level, x, z)?;
        let side = self.layout.tile_side(level) as usize;
        if rgb.len() != side * side * 3 {
            return Err(refuse(
                "put_tile.rgb",
                format!("{} bytes, expected {side}² · 3", rgb.len()),
            ));
        }
        self.put(level, x, z, rgb, 0);
        Ok(())
    }

    fn check_tile(&self, what: &'static str, level: u8, x: u32, z: u32) -> Result<(), ColorError> {
        let (level_field, xz_field) = match what {
            "ColorTile" => ("ColorTile.level", "ColorTile.x/z"),
            "NormalTile" => ("NormalTile.level", "NormalTile.x/z"),
            "put_normals" => ("put_normals.level", "put_normals.x/z"),
            _ => ("put_tile.level", "put_tile.x/z"),
        };
        self.check_level(level_field, level)?;
        let tiles = self.layout.tiles(level);
        if x >= tiles || z >= tiles {
            return Err(refuse(
                xz_field,
                format!("({x}, {z}), outside level {level} of {tiles} tiles a side"),
            ));
        }
        let origin = self.origins[usize::from(level)];
        if !self.layout.in_window(level, origin, x, z) {
            return Err(refuse(
                xz_field,
                format!(
                    "({x}, {z}), outside level {level}'s window of {} tiles at ({}, {})",
                    self.layout.window_tiles(level),
                    origin.0,
                    origin.1
                ),
            ));
        }
        Ok(())
    }

    /// Makes tile `(x, z)` of `level` resident with these RGB texels (checked; its payload
    /// with [`Keep::Counted`]), counting `payload` bytes.
    fn put(&mut self, level: u8, x: u32, z: u32, rgb: &[u8], payload: usize) {
        if level + 1 == self.layout.levels {
            self.coarsest.clear();
            self.coarsest.extend_from_slice(rgb);
        }
        let slot = self.slot_of(x, z);
        let texels = (self.keep == Keep::Texels).then(|| {
            rgb.chunks_exact(3)
                .flat_map(|c| [c[0], c[1], c[2], 255])
                .collect::<Vec<u8>>()
        });
        self.colors.put(level, slot, (x, z), texels, payload as u64);
    }

    /// Normal tile `(x, z)` of `level` decoded by [`decode_normal_tile`] from `payload`
    /// bytes (`side² · 2` code bytes): checked against the window now, made resident.
    pub fn put_normals_decoded(
        &mut self,
        level: u8,
        x: u32,
        z: u32,
        codes: &[u8],
        payload: usize,
    ) -> Result<(), ColorError> {
        self.check_tile("NormalTile", level, x, z)?;
        let side = self.layout.tile_side(level) as usize;
        if codes.len() != side * side * 2 {
            return Err(refuse(
                "NormalTile.data",
                format!("{} code bytes, expected {side}² · 2", codes.len()),
            ));
        }
        self.put_codes(level, x, z, codes, payload);
        Ok(())
    }

    /// Normal tile `(x, z)` of `level` from codes made elsewhere (`side² · 2` bytes,
    /// [`normals::encode`] per texel, row 0 north): a local map, a test.
    pub fn put_normals(
        &mut self,
        level: u8,
        x: u32,
        z: u32,
        codes: &[u8],
    ) -> Result<(), ColorError> {
        self.check_tile("put_normals", level, x, z)?;
        let side = self.layout.tile_side(level) as usize;
        if codes.len() != side * side * 2 {
            return Err(refuse(
                "put_normals.codes",
                format!("{} bytes, expected {side}² · 2", codes.len()),
            ));
        }
        self.put_codes(level, x, z, codes, 0);
        Ok(())
    }

    fn put_codes(&mut self, level: u8, x: u32, z: u32, codes: &[u8], payload: usize) {
        let slot = self.slot_of(x, z);
        let texels = (self.keep == Keep::Texels).then(|| codes.to_vec());
        self.normals
            .put(level, slot, (x, z), texels, payload as u64);
    }

    /// Takes at most `most` colour uploads and `most` normal uploads (oldest first: the
    /// server sends coarse levels first), and every level's state once they are written.
    pub fn drain(&mut self, most: usize) -> ColorUpdate {
        let s = self.layer_side();
        let uploads = self.colors.drain(most, &self.layout, s);
        let normals = self.normals.drain(most, &self.layout, s);
        let levels = (0..self.layout.levels)
            .map(|l| {
                let (x0, z0) = self.origins[usize::from(l)];
                LevelState {
                    origin: [x0, z0],
                    drawn: self.colors.mask(l, true),
                    normals: self.normals.mask(l, true),
                }
            })
            .collect();
        ColorUpdate {
            uploads,
            normals,
            levels,
        }
    }
}

/// Decodes tile `(x, z)` of `level`'s payload into `rgb` (`side² · 3` bytes), checking
/// what the layout alone decides (the level, the tile inside it, the payload's length and
/// that it decodes to the tile's side); the window is [`ColorCache::put_decoded`]'s check.
pub fn decode_tile(
    layout: &ColorLayout,
    level: u8,
    x: u32,
    z: u32,
    data: &[u8],
    rgb: &mut Vec<u8>,
) -> Result<(), ColorError> {
    check_payload(layout, "ColorTile", level, x, z, data)?;
    let side = layout.tile_side(level);
    colormap::decode(side, data, rgb).map_err(|e| {
        refuse(
            "ColorTile.data",
            format!("tile ({x}, {z}) of level {level} ({side}² texels): {e}"),
        )
    })
}

/// What the layout alone decides of a tile message (`what`: `ColorTile`, `NormalTile`):
/// the level, the tile inside it and the payload's length.
fn check_payload(
    layout: &ColorLayout,
    what: &'static str,
    level: u8,
    x: u32,
    z: u32,
    data: &[u8],
) -> Result<(), ColorError> {
    let field = |f: &'static str| match (what, f) {
        ("NormalTile", "level") => "NormalTile.level",
        ("NormalTile", "x/z") => "NormalTile.x/z",
        ("NormalTile", _) => "NormalTile.data",
        (_, "level") => "ColorTile.level",
        (_, "x/z") => "ColorTile.x/z",
        _ => "ColorTile.data",
    };
    if level >= layout.levels {
        return Err(refuse(
            field("level"),
            format!("{level}, but the colour map has {} levels", layout.levels),
        ));
    }
    let tiles = layout.tiles(level);
    if x >= tiles || z >= tiles {
        return Err(refuse(
            field("x/z"),
            format!("({x}, {z}), outside level {level} of {tiles} tiles a side"),
        ));
    }
    let side = layout.tile_side(level);
    let most = layout.max_tile_bytes(level);
    if data.len() > most {
        return Err(refuse(
            field("data"),
            format!(
                "{} bytes for a tile of {side}² texels, at most {most}",
                data.len()
            ),
        ));
    }
    Ok(())
}

/// Decodes normal tile `(x, z)` of `level`'s payload into `codes` (`side² · 2` bytes),
/// with [`decode_tile`]'s checks; the window is [`ColorCache::put_normals_decoded`]'s.
pub fn decode_normal_tile(
    layout: &ColorLayout,
    level: u8,
    x: u32,
    z: u32,
    data: &[u8],
    codes: &mut Vec<u8>,
) -> Result<(), ColorError> {
    check_payload(layout, "NormalTile", level, x, z, data)?;
    let side = layout.tile_side(level);
    normals::decode_tile(side, data, codes).map_err(|e| {
        refuse(
            "NormalTile.data",
            format!("normals of tile ({x}, {z}) of level {level} ({side}² texels): {e}"),
        )
    })
}

/// Texels a side of every layer of `layout`: `min(W·T, cells)`.
pub fn layer_side(layout: &ColorLayout) -> u32 {
    (u32::from(layout.window) * layout.tile).min(layout.cells)
}

/// The window this device can hold: `W` tiles of [`roam_protocol::tiles::DEFAULT_TILE`]
/// with `W·T` within `max_texture_side`, at most the default window (memory: a layer is
/// `(W·T)²` texels, 16 MiB at W = 8).
pub fn window_for(max_texture_side: u32) -> u8 {
    let w = max_texture_side / roam_protocol::tiles::DEFAULT_TILE;
    w.clamp(1, u32::from(roam_protocol::tiles::DEFAULT_WINDOW)) as u8
}

/// The colour pyramid of a `cells × cells` RGB map (row 0 north): level `l + 1` is the 2×2
/// box average of level `l` (in sRGB bytes, rounded), down to `levels` levels.
pub fn pyramid(cells: u32, rgb: &[u8], levels: u8) -> Vec<Vec<u8>> {
    let mut out = vec![rgb.to_vec()];
    let mut side = cells as usize;
    for _ in 1..levels {
        let prev = out.last().expect("level 0 is there");
        let half = (side / 2).max(1);
        let mut next = Vec::with_capacity(half * half * 3);
        for z in 0..half {
            for x in 0..half {
                for c in 0..3 {
                    let at = |dx: usize, dz: usize| {
                        let (px, pz) = ((2 * x + dx).min(side - 1), (2 * z + dz).min(side - 1));
                        u32::from(prev[(pz * side + px) * 3 + c])
                    };
                    next.push(((at(0, 0) + at(1, 0) + at(0, 1) + at(1, 1) + 2) / 4) as u8);
                }
            }
        }
        out.push(next);
        side = half;
    }
    out
}

/// The texels of tile `(x, z)` of a level `side` texels a side in tiles of `t`.
pub fn cut_tile(level: &[u8], side: u32, t: u32, x: u32, z: u32) -> Vec<u8> {
    let (side, t) = (side as usize, t.min(side) as usize);
    let mut out = Vec::with_capacity(t * t * 3);
    for row in 0..t {
        let start = ((z as usize * t + row) * side + x as usize * t) * 3;
        out.extend_from_slice(&level[start..start + t * 3]);
    }
    out
}

impl ColorCache {
    /// A cache holding every tile a viewer could hold of a whole `cells × cells` RGB map
    /// (each window at `(0, 0)`): for tests and local rendering. An error if `rgb` is not
    /// the layout's map.
    pub fn whole(layout: ColorLayout, rgb: &[u8]) -> Result<ColorCache, ColorError> {
        let grid = layout.cells.max(1).ilog2() as u8;
        let mut cache = ColorCache::new(layout, grid, layout.window, Keep::Texels)?;
        if rgb.len() as u64 != u64::from(layout.cells).pow(2) * 3 {
            return Err(refuse(
                "whole.rgb",
                format!("{} bytes, expected {}² · 3", rgb.len(), layout.cells),
            ));
        }
        for (l, texels) in pyramid(layout.cells, rgb, layout.levels).iter().enumerate() {
            let l = l as u8;
            let w = layout.window_tiles(l);
            for z in 0..w {
                for x in 0..w {
                    let tile = cut_tile(texels, layout.side(l), layout.tile, x, z);
                    cache.put_tile(l, x, z, &tile)?;
                }
            }
        }
        Ok(cache)
    }
}

#[cfg(test)]
#[path = "color_cache_tests.rs"]
mod tests;

#[cfg(test)]
#[path = "color_cache_normals_tests.rs"]
mod normals_tests;
