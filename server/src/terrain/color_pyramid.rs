//! The colour map as a pyramid of coded tiles ([`ColorPyramid`]), streamed to viewers by
//! view ([`crate::viewer::color`]): level 0 is the map, each next level the 2×2 box
//! average of the one before (sRGB bytes, rounded half up), down to a single tile; every
//! tile is coded once with [`roam_protocol::colormap`] (the layout is
//! [`roam_protocol::tiles`]'s). Serving then only copies bytes.
//!
//! Decisions:
//!
//! - Tiles are coded on `threads` threads taking tiles from one counter; each result goes
//!   to its tile's slot, so the bytes do not depend on the thread count (a test checks).
//!   Levels are averaged on the same threads, a band of rows each.
//! - The coded tiles of a data set are cached in `DIR/.cache/color-tiles.bin` and
//!   memory-mapped (memmap2) through [`super::tile_store`] (shared with the normal
//!   pyramid, which documents the file; both pyramids dereference to their
//!   [`TileStore`] for serving): a restart serves without coding anything, and the
//!   payloads stay in the page cache, not the heap. Its key is `color.ppm`'s length and a
//!   digest of its length, mtime, ctime, inode and device (`cache::FileStamp`). A stale
//!   (another `color.ppm`, another tile size) or damaged cache is rebuilt with a warning;
//!   a directory that cannot be written keeps the pyramid in memory. Each tile's payload
//!   is checked the first time it is served ([`TileStore::served_tile`]); a damaged
//!   tile is never sent (the viewer keeps drawing a coarser level there) and is reported
//!   once. The coarsest tile, which every viewer gets before its first frame, is verified
//!   at open.
//! - Measured (`measure` profile, 2 shared cores, T = 256, `roam-server color-bench`):
//!   kossou (1024², 3 levels) 1.9 MB coded (1.39 MB whole: per-tile tables and the
//!   coarser levels cost the rest) in 0.06 s; 4096² (5 levels) 28.6 MB in 0.68 s;
//!   16384² (7 levels) 454 MB in 15.4 s. A mapped cache opens in under a millisecond.

use std::borrow::Cow;
use std::fs;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use roam_protocol::colormap;
use roam_protocol::sync::lock;
use roam_protocol::tiles::{self, ColorLayout};

use crate::terrain::cache::FileStamp;
use crate::terrain::dataset::{COLOR_FILE, ColorMap};
use crate::terrain::tile_store::{self as store, Kind, TileStore};
pub use crate::terrain::tile_store::{CACHE_DIR, CacheOutcome, TileError};
#[cfg(test)]
use crate::terrain::tile_store::{ENTRY, HASH};

/// The cache's file name inside the data set's `.cache` folder.
pub const CACHE_FILE: &str = "color-tiles.bin";
/// The colour cache: format 2: the source's stamp is a digest of its length, mtime,
/// ctime, inode and device (1 kept its mtime only). 3: each index entry carries its
/// payload's check. Its key: `color.ppm`'s length and stamp digest (two `u64`s).
const KIND: Kind = Kind {
    magic: b"roamCT\0\0",
    version: 3,
    file: CACHE_FILE,
    what: "colour tile cache",
    source: COLOR_FILE,
    key_len: 16,
    max_len: colormap::max_len,
};
/// Header bytes: magic, version, cells, tile, levels, source length, source stamp, tiles.
#[cfg(test)]
const HEADER: usize = 8 + 4 * 4 + 8 * 3;

/// Why a pyramid could not be made.
#[derive(Debug, thiserror::Error)]
pub enum PyramidError {
    #[error("colour map: {0}")]
    Layout(#[from] tiles::LayoutError),
    #[error("colour map tile: {0}")]
    Encode(#[from] colormap::SizeError),
    #[error("{0}")]
    Source(#[from] crate::terrain::data_error::DataError),
}

/// Every tile of a colour map's pyramid, coded.
pub struct ColorPyramid {
    store: TileStore,
}

impl ColorPyramid {
    /// The pyramid of `color` in `tile × tile` tiles, coded on `threads` threads,
    /// reporting `(tiles done, tiles)`.
    pub fn build(
        color: &ColorMap,
        tile: u32,
        threads: usize,
        progress: &mut dyn FnMut(u64, u64),
    ) -> Result<ColorPyramid, PyramidError> {
        let layout = ColorLayout::new(color.cells(), tile, 1)?;
        let threads = threads.max(1);
        let first = store::firsts(&layout);
        let total = *first.last().expect("one entry past the last level");
        let mut coded: Vec<Vec<u8>> = vec![Vec::new(); total];
        let mut level: Vec<[u8; 3]> = Vec::new();
        for l in 0..layout.levels {
            if l > 0 {
                let from = if l == 1 { color.rgb() } else { &level };
                level = halve(from, layout.side(l - 1), threads);
            }
            let texels = if l == 0 { color.rgb() } else { &level };
            let slots = &mut coded[first[usize::from(l)]..first[usize::from(l) + 1]];
            encode_level(&layout, l, texels, slots, threads, &mut |done| {
                progress((first[usize::from(l)] + done) as u64, total as u64)
            })?;
        }
        Ok(ColorPyramid {
            store: TileStore::from_coded(layout, coded),
        })
    }

    /// The pyramid of the data set in `dir`, whose colour map is `color`: mapped from its
    /// cache when that is valid for `color.ppm` and `tile`, else built (and cached).
    pub fn open_or_build(
        dir: &Path,
        color: &ColorMap,
        tile: u32,
        threads: usize,
        progress: &mut dyn FnMut(u64, u64),
    ) -> Result<(ColorPyramid, CacheOutcome), PyramidError> {
        Self::open_or_load(
            dir,
            color.cells(),
            tile,
            threads,
            || Ok(Cow::Borrowed(color)),
            progress,
        )
    }

    /// [`Self::open_or_build`] for a `cells × cells` colour map that `load` reads only when
    /// the cache cannot be used: a server with a valid cache never reads `color.ppm`'s
    /// pixels (805 MB at 16385²).
    pub fn open_or_load<'c>(
        dir: &Path,
        cells: u32,
        tile: u32,
        threads: usize,
        load: impl FnOnce() -> Result<Cow<'c, ColorMap>, crate::terrain::data_error::DataError>,
        progress: &mut dyn FnMut(u64, u64),
    ) -> Result<(ColorPyramid, CacheOutcome), PyramidError> {
        let key = source_stamp(&dir.join(COLOR_FILE))
            .map(|(len, digest)| [len.to_le_bytes(), digest.to_le_bytes()].concat())
            .ok_or_else(|| store::Unkeyed {
                file: dir.join(COLOR_FILE),
            });
        let (store, outcome) = store::open_or_make(
            dir,
            &KIND,
            (cells, tile, threads),
            key.as_deref().map_err(Clone::clone),
            || {
                let color = load()?;
                Self::build(&color, tile, threads, progress).map(|p| p.store)
            },
        )?;
        Ok((ColorPyramid { store }, outcome))
    }
}

/// Served as its [`TileStore`]: layout, levels, tiles, checks and bytes.
impl std::ops::Deref for ColorPyramid {
    type Target = TileStore;

    fn deref(&self) -> &TileStore {
        &self.store
    }
}

/// The cache's path for the data set in `dir`.
pub fn cache_path(dir: &Path) -> PathBuf {
    store::cache_path(dir, &KIND)
}

/// A file's length and modification time (ns since the epoch), or `None`.
/// `color.ppm`'s length and the digest of its stamp (length, mtime, ctime, inode, device:
/// any write changes the ctime, which no program can set back, so a copy made with its
/// times kept, `touch -r` or a restore is a new stamp). What is left is a rewrite within
/// one tick of the file system's ctime after the tiles were coded (nanoseconds on ext4,
/// XFS and btrfs); `heights.bin`'s stamp also closes that, at the cost of re-hashing.
fn source_stamp(path: &Path) -> Option<(u64, u64)> {
    let stamp = FileStamp::of(&fs::metadata(path).ok()?);
    Some((stamp.len(), stamp.digest()))
}

/// The 2×2 box average of a `side × side` level (side ≥ 2), rounded half up.
fn halve(from: &[[u8; 3]], side: u32, threads: usize) -> Vec<[u8; 3]> {
    let (s, h) = (side as usize, (side / 2) as usize);
    let mut out = vec![[0u8; 3]; h * h];
    let rows_per = h.div_ceil(threads).max(1);
    std::thread::scope(|scope| {
        for (band, rows) in out.chunks_mut(rows_per * h).enumerate() {
            scope.spawn(move || {
                for (r, row) in rows.chunks_exact_mut(h).enumerate() {
                    let z = (band * rows_per + r) * 2;
                    let (a, b) = (&from[z * s..(z + 1) * s], &from[(z + 1) * s..(z + 2) * s]);
                    for (x, px) in row.iter_mut().enumerate() {
                        *px = std::array::from_fn(|c| {
                            let sum = u16::from(a[2 * x][c])
                                + u16::from(a[2 * x + 1][c])
                                + u16::from(b[2 * x][c])
                                + u16::from(b[2 * x + 1][c]);
                            ((sum + 2) / 4) as u8
                        });
                    }
                }
            });
        }
    });
    out
}

/// Codes every tile of level `l` (texels `texels`) into `slots`, on `threads` threads,
/// in batches: `progress(tiles done)` after each.
fn encode_level(
    layout: &ColorLayout,
    l: u8,
    texels: &[[u8; 3]],
    slots: &mut [Vec<u8>],
    threads: usize,
    progress: &mut dyn FnMut(usize),
) -> Result<(), PyramidError> {
    let (side, t, n) = (
        layout.side(l) as usize,
        layout.tile_side(l) as usize,
        layout.tiles(l) as usize,
    );
    let batch = (threads * 8).max(n * n / 64);
    let mut start = 0;
    for chunk in slots.chunks_mut(batch) {
        let next = AtomicUsize::new(0);
        let failed = Mutex::new(None::<PyramidError>);
        let out: Vec<Mutex<&mut Vec<u8>>> = chunk.iter_mut().map(Mutex::new).collect();
        std::thread::scope(|scope| {
            for _ in 0..threads.min(out.len()) {
                scope.spawn(|| {
                    let mut rgb = Vec::with_capacity(t * t * 3);
                    loop {
                        let k = next.fetch_add(1, Ordering::Relaxed);
                        let Some(slot) = out.get(k) else { return };
                        let (x, z) = ((start + k) % n, (start + k) / n);
                        rgb.clear();
                        for row in z * t..(z + 1) * t {
                            let at = row * side + x * t;
                            rgb.extend(texels[at..at + t].iter().flatten());
                        }
                        let mut coded = Vec::new();
                        match colormap::encode(t as u32, &rgb, &mut coded) {
                            Ok(()) => **lock(slot) = coded,
                            Err(e) => *lock(&failed) = Some(e.into()),
                        }
                    }
                });
            }
        });
        if let Some(e) = lock(&failed).take() {
            return Err(e);
        }
        start += out.len();
        progress(start);
    }
    Ok(())
}

#[cfg(test)]
#[path = "color_pyramid_tests.rs"]
mod tests;
