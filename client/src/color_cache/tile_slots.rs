//! One kind of resident tile (colour, or normals) of the viewer's tile cache
//! ([`super::ColorCache`]): per level, a slot per window position
//! (`(z mod W)·W + (x mod W)`), the texels a tile brought until the renderer takes them,
//! and the upload queue in arrival order. No checks here (the cache checks every message
//! before it gets this far) and no window of its own: the cache tells it which tiles a
//! moved window drops ([`TileSlots::keep_window`]), the same for both kinds.
//!
//! Bounded as the cache is: at most one tile per slot, and the queue at most one entry per
//! slot (an entry leaves with its tile when a window moves).

use std::collections::VecDeque;

use roam_protocol::tiles::ColorLayout;

use super::{MASK_WORDS, Upload};

#[derive(Clone, Debug)]
struct Slot {
    x: u32,
    z: u32,
    /// Texels not yet taken by the renderer.
    texels: Option<Vec<u8>>,
    /// Handed to the renderer.
    drawn: bool,
}

/// The resident tiles of one kind, `texel` bytes a texel as uploaded.
#[derive(Clone, Debug)]
pub(crate) struct TileSlots {
    texel: usize,
    /// Per level, its slots.
    levels: Vec<Vec<Option<Slot>>>,
    /// (level, slot) of tiles whose texels wait for the renderer, in arrival order.
    queue: VecDeque<(u8, u16)>,
    resident: u32,
    received: u64,
    /// Payload bytes of the tiles received.
    bytes: u64,
}

impl TileSlots {
    /// Empty slots for `layout`'s levels, `texel` bytes a texel.
    pub(crate) fn new(layout: &ColorLayout, texel: usize) -> TileSlots {
        let w = usize::from(layout.window);
        TileSlots {
            texel,
            levels: (0..layout.levels)
                .map(|_| (0..w * w).map(|_| None).collect())
                .collect(),
            queue: VecDeque::new(),
            resident: 0,
            received: 0,
            bytes: 0,
        }
    }

    /// Makes tile `(x, z)` of `level` resident in `slot` (its texels queued for the
    /// renderer when given), counting `payload` bytes.
    pub(crate) fn put(
        &mut self,
        level: u8,
        slot: usize,
        (x, z): (u32, u32),
        texels: Option<Vec<u8>>,
        payload: u64,
    ) {
        self.received += 1;
        self.bytes += payload;
        let queue = texels.is_some();
        let was = self.levels[usize::from(level)][slot].replace(Slot {
            x,
            z,
            texels,
            drawn: false,
        });
        let queued = was.as_ref().is_some_and(|s| s.texels.is_some());
        if was.is_none() {
            self.resident += 1;
        }
        if queue && !queued {
            self.queue.push_back((level, slot as u16));
        }
    }

    /// Drops `level`'s tiles that `keep(x, z)` refuses (a window moved), with their
    /// queued uploads.
    pub(crate) fn keep_window(&mut self, level: u8, keep: impl Fn(u32, u32) -> bool) {
        let mut dropped = 0;
        for (i, slot) in self.levels[usize::from(level)].iter_mut().enumerate() {
            if slot.as_ref().is_some_and(|s| !keep(s.x, s.z)) {
                *slot = None;
                dropped += 1;
                self.queue.retain(|&q| q != (level, i as u16));
            }
        }
        self.resident -= dropped;
    }

    /// Takes at most `most` uploads, oldest first, each at `((x·T) mod S, (z·T) mod S)`
    /// of its level's layer (`S` = `side`): marked drawn.
    pub(crate) fn drain(&mut self, most: usize, layout: &ColorLayout, side: u32) -> Vec<Upload> {
        let mut uploads = Vec::new();
        let t = layout.tile;
        while uploads.len() < most {
            let Some((level, slot)) = self.queue.pop_front() else {
                break;
            };
            let size = layout.tile_side(level);
            let Some(tile) = self.levels[usize::from(level)][usize::from(slot)].as_mut() else {
                continue;
            };
            let Some(texels) = tile.texels.take() else {
                continue;
            };
            tile.drawn = true;
            uploads.push(Upload {
                layer: u32::from(level),
                slot: u32::from(slot),
                x: (tile.x * t) % side,
                y: (tile.z * t) % side,
                size,
                texels,
            });
        }
        uploads
    }

    /// Tiles of `level` resident (`drawn`: only those handed to the renderer), as window
    /// bits.
    pub(crate) fn mask(&self, level: u8, drawn: bool) -> [u32; MASK_WORDS] {
        let mut m = [0; MASK_WORDS];
        if let Some(l) = self.levels.get(usize::from(level)) {
            for (i, s) in l.iter().enumerate() {
                if s.as_ref().is_some_and(|s| s.drawn || !drawn) {
                    m[i / 32] |= 1 << (i % 32);
                }
            }
        }
        m
    }

    /// Whether tile `(x, z)` of `level` is the one resident in `slot`.
    pub(crate) fn is_resident(&self, level: u8, slot: usize, x: u32, z: u32) -> bool {
        self.levels
            .get(usize::from(level))
            .and_then(|l| l[slot].as_ref())
            .is_some_and(|s| (s.x, s.z) == (x, z))
    }

    /// Tiles resident now.
    pub(crate) fn resident(&self) -> u32 {
        self.resident
    }

    /// Tiles received (those dropped since included).
    pub(crate) fn received(&self) -> u64 {
        self.received
    }

    /// Payload bytes received.
    pub(crate) fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Texels held, waiting for the renderer.
    pub(crate) fn texels_held(&self) -> usize {
        self.levels
            .iter()
            .flatten()
            .flatten()
            .filter_map(|s| s.texels.as_ref())
            .map(|t| t.len() / self.texel)
            .sum()
    }

    /// Uploads waiting.
    pub(crate) fn queued(&self) -> usize {
        self.queue.len()
    }
}
