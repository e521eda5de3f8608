//! The terrain's normals as a pyramid of coded tiles ([`NormalPyramid`]), laid out as the
//! colour pyramid is ([`roam_protocol::tiles::ColorLayout`]) and streamed with it: each
//! colour tile's normals follow it ([`crate::viewer::color`]), so a viewer lights every
//! pixel at the data's full resolution whatever the cut it draws (issue 24). Level 0 holds
//! one normal per map cell, each next level the average of its four children; what a
//! normal and its two-byte code are exactly is [`roam_protocol::normals`]'s header.
//!
//! Decisions:
//!
//! - **The layout is the heightfield's, not the colour map's**: `cells` is the grid's
//!   `side − 1` (the normals need nothing from the colour map, so a data set without one
//!   would have them all the same; today `color.ppm` is required) and the tile size the
//!   colour's. The two layouts are then one (a colour map has one texel per cell,
//!   `Terrain::validate`; `Server::start` checks it): one scheduler, one set of window
//!   messages and one slot per tile on the viewer for both, no second window protocol.
//! - **Built by quadtree, not by level**: a tile's normals are computed from its four
//!   children's (level 0's from the heights), depth first, so the build holds a tile per
//!   level on the way down instead of whole levels (at 16385², level 0 alone would be
//!   3.2 GB of `f32` normals). The subtrees under one level's tiles (at least 4 per
//!   thread) are built on `threads` threads from one counter, each result in its tile's
//!   slot; the levels above them on the calling thread. The bytes do not depend on the
//!   thread count (a test checks).
//! - **Served as its store**: a [`NormalPyramid`] dereferences to its
//!   [`super::tile_store::TileStore`], as the colour pyramid does, so the two share one
//!   copy of what serving asks (layout, tiles, checks, bytes) and keep only their builds.
//! - **Coded by the colour map codec** ([`roam_protocol::normals::encode_tile`]):
//!   lossless, already on both ends, decoded within the same limits. Measured with
//!   `roam-server color-bench` (T = 256, 2 shared cores, the dev profile, which is
//!   optimised): kossou (1024², 3 levels, 21 tiles) 1.39 MB of normals beside 1.92 MB of
//!   colour, 66 KB a tile against 91 KB (1.01 bytes a texel against 1.39; the raw codes
//!   are 2), built and cached in 0.11 s; a generated 4097² (5 levels, 341 tiles, fBm
//!   down to the sample) 28.9 MB against 28.6 MB (1.29 bytes a texel against 1.28), in
//!   1.9 s; synth-257 (one tile) 88 KB against 104 KB. A mapped cache opens in under a
//!   millisecond.
//! - **What it costs the colour**: the normals come out of the colour's bytes
//!   (`--color-rate`), so where that cap binds, colour tiles come slower: driving on the
//!   4097² set, 121 colour tiles (and 122 normal tiles, the coarsest's included) in 10 s
//!   at 2 MB/s, against 148 colour tiles before. On kossou the whole pyramid still comes
//!   in 8 s (20 colour tiles and 21 normal tiles after the first frame).
//! - **Cached like the colour** ([`super::tile_store`]): `DIR/.cache/normal-tiles.bin`,
//!   memory-mapped, its header keyed by the heights' content hash (the one
//!   `cache::CacheReport::heights_hash` gives, so a warm start reads no heights to check
//!   it) and the map's hScale and vScale (the normals depend on both); stale or damaged is
//!   rebuilt with the reason, each tile checked the first time it is served, the coarsest
//!   at open.

use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use roam_protocol::colormap;
use roam_protocol::normals;
use roam_protocol::sync::lock;
use roam_protocol::tiles::{self, ColorLayout};

use crate::terrain::heightfield::Heightfield;
use crate::terrain::tile_store::{self as store, Kind, TileStore};
pub use crate::terrain::tile_store::{CacheOutcome, TileError};

/// The cache's file name inside the data set's `.cache` folder.
pub const CACHE_FILE: &str = "normal-tiles.bin";
/// The normal cache, format 1. Its key: the heights' hash (32 bytes), then hScale and
/// vScale (`f64` bits, little-endian).
const KIND: Kind = Kind {
    magic: b"roamNT\0\0",
    version: 1,
    file: CACHE_FILE,
    what: "normal tile cache",
    source: "the heights or the map's scales",
    key_len: 48,
    max_len: colormap::max_len,
};

/// Why a normal pyramid could not be made.
#[derive(Debug, thiserror::Error)]
pub enum NormalError {
    #[error("normals: {0}")]
    Layout(#[from] tiles::LayoutError),
    #[error("normal tile: {0}")]
    Encode(#[from] colormap::SizeError),
}

/// Every tile of a heightfield's normal pyramid, coded.
pub struct NormalPyramid {
    store: TileStore,
}

/// What the build's workers share.
struct Build<'a> {
    hf: &'a Heightfield,
    layout: ColorLayout,
    scales: (f64, f64),
    /// Where each level's tiles start in `coded`.
    first: Vec<usize>,
    coded: Vec<Mutex<Vec<u8>>>,
    done: AtomicUsize,
}

impl NormalPyramid {
    /// The normals of `hf` (`h_scale` world units between samples, `v_scale` a sample
    /// step) in `tile × tile` tiles, on `threads` threads, reporting `(tiles done, tiles)`.
    pub fn build(
        hf: &Heightfield,
        (h_scale, v_scale): (f64, f64),
        tile: u32,
        threads: usize,
        progress: &mut dyn FnMut(u64, u64),
    ) -> Result<NormalPyramid, NormalError> {
        let layout = ColorLayout::new(hf.size(), tile, 1)?;
        let threads = threads.max(1);
        let first = store::firsts(&layout);
        let total = *first.last().expect("one entry past the last level");
        let b = Build {
            hf,
            layout,
            scales: (h_scale, v_scale),
            coded: (0..total).map(|_| Mutex::new(Vec::new())).collect(),
            first,
            done: AtomicUsize::new(0),
        };
        // The subtrees' roots: the coarsest level with at least 4 tiles a thread.
        let root = (0..layout.levels)
            .rev()
            .find(|&l| (layout.tiles(l) as usize).pow(2) >= 4 * threads)
            .unwrap_or(0);
        let n = layout.tiles(root);
        let roots: Vec<Mutex<Option<Vec<[f32; 3]>>>> =
            (0..n * n).map(|_| Mutex::new(None)).collect();
        let next = AtomicUsize::new(0);
        let failed = Mutex::new(None::<NormalError>);
        let work = |report: &mut dyn FnMut(usize)| {
            loop {
                let k = next.fetch_add(1, Ordering::Relaxed);
                let Some(slot) = roots.get(k) else { return };
                let (x, z) = (k as u32 % n, k as u32 / n);
                match b.node(root, x, z, None) {
                    Ok(t) => *lock(slot) = Some(t),
                    Err(e) => {
                        *lock(&failed) = Some(e);
                        return;
                    }
                }
                report(b.done.load(Ordering::Relaxed));
            }
        };
        std::thread::scope(|scope| {
            for _ in 1..threads.min(roots.len()) {
                scope.spawn(|| work(&mut |_| {}));
            }
            work(&mut |done| progress(done as u64, total as u64));
        });
        if let Some(e) = lock(&failed).take() {
            return Err(e);
        }
        b.node(layout.levels - 1, 0, 0, Some((root, &roots)))?;
        progress(total as u64, total as u64);
        let coded = b
            .coded
            .into_iter()
            .map(|c| std::mem::take(&mut *lock(&c)))
            .collect();
        Ok(NormalPyramid {
            store: TileStore::from_coded(layout, coded),
        })
    }

    /// The normal pyramid of the data set in `dir`, whose heights are `hf` (their content
    /// hash `heights_hash`): mapped from its cache when that is valid for these heights,
    /// scales and `tile`, else built (and cached).
    pub fn open_or_build(
        dir: &Path,
        hf: &Heightfield,
        scales: (f64, f64),
        heights_hash: &[u8; 32],
        tile: u32,
        threads: usize,
        progress: &mut dyn FnMut(u64, u64),
    ) -> Result<(NormalPyramid, CacheOutcome), NormalError> {
        let key = [
            heights_hash.as_slice(),
            &scales.0.to_bits().to_le_bytes(),
            &scales.1.to_bits().to_le_bytes(),
        ]
        .concat();
        let (store, outcome) =
            store::open_or_make(dir, &KIND, (hf.size(), tile, threads), Ok(&key), || {
                Self::build(hf, scales, tile, threads, progress).map(|p| p.store)
            })?;
        Ok((NormalPyramid { store }, outcome))
    }
}

/// Served as its [`TileStore`]: layout, levels, tiles, checks and bytes.
impl std::ops::Deref for NormalPyramid {
    type Target = TileStore;

    fn deref(&self) -> &TileStore {
        &self.store
    }
}

/// The cache's path for the data set in `dir`.
pub fn cache_path(dir: &Path) -> PathBuf {
    store::cache_path(dir, &KIND)
}

/// The subtrees' roots already built: their level, and their normals by `z · n + x`.
type Roots<'r> = (u8, &'r [Mutex<Option<Vec<[f32; 3]>>>]);

impl Build<'_> {
    /// Tile `(x, z)` of `level`: its unit normals (row-major), coded into its slot on the
    /// way. With `roots`, that level's tiles are taken from there (built and coded).
    fn node(
        &self,
        level: u8,
        x: u32,
        z: u32,
        roots: Option<Roots<'_>>,
    ) -> Result<Vec<[f32; 3]>, NormalError> {
        let l = &self.layout;
        if let Some((at, built)) = roots
            && at == level
        {
            let k = (z * l.tiles(level) + x) as usize;
            let taken = lock(&built[k]).take();
            return Ok(taken.expect("every root is built before the levels above"));
        }
        let t = l.tile_side(level) as usize;
        let normals = if level == 0 {
            self.cells(x, z, t)
        } else {
            let mut out = vec![[0.0f32; 3]; t * t];
            let h = t / 2;
            for (dz, dx) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                let child = self.node(level - 1, 2 * x + dx, 2 * z + dz, roots)?;
                for i in 0..h {
                    for j in 0..h {
                        let at = |a: usize, b: usize| child[(2 * i + a) * t + 2 * j + b];
                        let (p, q, r, s) = (at(0, 0), at(0, 1), at(1, 0), at(1, 1));
                        let sum = std::array::from_fn(|c| p[c] + q[c] + r[c] + s[c]);
                        out[(dz as usize * h + i) * t + dx as usize * h + j] =
                            normals::normalize(sum);
                    }
                }
            }
            out
        };
        let codes: Vec<[u8; 2]> = normals.iter().map(|&n| normals::encode(n)).collect();
        let mut coded = Vec::new();
        normals::encode_tile(t as u32, &codes, &mut coded)?;
        let k = self.first[usize::from(level)] + (z * l.tiles(level) + x) as usize;
        *lock(&self.coded[k]) = coded;
        self.done.fetch_add(1, Ordering::Relaxed);
        Ok(normals)
    }

    /// The normals of level 0's tile `(x, z)`, `t` cells a side, from the heights.
    fn cells(&self, x: u32, z: u32, t: usize) -> Vec<[f32; 3]> {
        let side = self.hf.side() as usize;
        let h = self.hf.samples();
        let (x0, z0) = (x as usize * t, z as usize * t);
        let (hs, vs) = self.scales;
        let mut out = Vec::with_capacity(t * t);
        for cz in z0..z0 + t {
            let (north, south) = (&h[cz * side..(cz + 1) * side], &h[(cz + 1) * side..]);
            for cx in x0..x0 + t {
                out.push(normals::cell_normal(
                    north[cx],
                    north[cx + 1],
                    south[cx],
                    south[cx + 1],
                    hs,
                    vs,
                ));
            }
        }
        out
    }
}

#[cfg(test)]
#[path = "normal_pyramid_tests.rs"]
mod tests;
