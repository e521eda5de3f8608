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
//!   memory-mapped (memmap2): a restart serves without coding anything, and the payloads
//!   stay in the page cache, not the heap. The file: a header (magic, format version,
//!   cells, tile, levels, `color.ppm`'s length and a digest of its length, mtime, ctime,
//!   inode and device (`cache::FileStamp`), the tile count), a
//!   blake3 hash of the header and the index, the index ((offset, length) per tile,
//!   levels finest first, rows then columns) and the payloads, back to back. It is
//!   written to a temporary file and renamed (a torn write is never seen), and checked
//!   before it is used: the hash, every entry inside the file, contiguous and within
//!   `colormap::max_len` of its tile. A stale (another `color.ppm`, another tile size) or
//!   damaged cache is rebuilt with a warning; a directory that cannot be written keeps
//!   the pyramid in memory. The payloads are not hashed at open (hundreds of
//!   megabytes at 16385², which would also make them all resident): each index entry
//!   carries its payload's check, verified the first time the tile is served
//!   ([`ColorPyramid::served_tile`]); a damaged tile is never sent (the viewer keeps
//!   drawing a coarser level there) and is reported once. The coarsest tile, which every
//!   viewer gets before its first frame, is verified at open.
//! - Measured (`measure` profile, 2 shared cores, T = 256, `roam-server color-bench`):
//!   kossou (1024², 3 levels) 1.9 MB coded (1.39 MB whole: per-tile tables and the
//!   coarser levels cost the rest) in 0.06 s; 4096² (5 levels) 28.6 MB in 0.68 s;
//!   16384² (7 levels) 454 MB in 15.4 s. A mapped cache opens in under a millisecond.

use std::borrow::Cow;
use std::fs;
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicU8, AtomicUsize, Ordering};

use roam_protocol::colormap;
use roam_protocol::tiles::{self, ColorLayout};

use crate::terrain::cache::FileStamp;
use crate::terrain::dataset::{COLOR_FILE, ColorMap};

/// The cache's file name inside the data set's `.cache` folder.
pub const CACHE_FILE: &str = "color-tiles.bin";
/// The data set's cache folder.
pub const CACHE_DIR: &str = ".cache";
const MAGIC: &[u8; 8] = b"roamCT\0\0";
/// The cache's format version. 2: the source's stamp is a digest of its length, mtime,
/// ctime, inode and device (1 kept its mtime only). 3: each index entry carries its
/// payload's check.
const CACHE_VERSION: u32 = 3;
/// Header bytes: magic, version, cells, tile, levels, source length, source mtime, tiles.
const HEADER: usize = 8 + 4 * 4 + 8 * 3;
const HASH: usize = 32;
/// An index entry: offset (u64), length (u32), check (u64: the payload's blake3, cut).
const ENTRY: usize = 20;

/// Why a tile is not served.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum TileError {
    #[error("no such tile")]
    Outside,
    /// Its payload does not match its check (a damaged cache file); `first`: the first
    /// time this tile was found so.
    #[error("its payload does not match its check: the cache file is damaged")]
    Damaged { first: bool },
}

/// Why a pyramid could not be made.
#[derive(Debug, thiserror::Error)]
pub enum PyramidError {
    #[error("colour map: {0}")]
    Layout(#[from] tiles::LayoutError),
    #[error("colour map tile: {0}")]
    Encode(#[from] colormap::SizeError),
    #[error("{0}")]
    Source(#[from] crate::terrain::dataset::DataError),
}

/// Where a pyramid's payloads live.
enum Payloads {
    Memory(Vec<u8>),
    Mapped(memmap2::Mmap),
}

/// Every tile of a colour map's pyramid, coded.
pub struct ColorPyramid {
    cells: u32,
    tile: u32,
    levels: u8,
    /// Per tile (levels finest first, then rows, then columns): offset and length in
    /// `payloads`, and the payload's check ([`check_of`]).
    index: Vec<(u64, u32, u64)>,
    /// Per tile: 0 not verified against its check yet, 1 verified, 2 damaged.
    verified: Vec<AtomicU8>,
    /// Where each level's tiles start in `index`.
    first: Vec<usize>,
    payloads: Payloads,
    /// Where the payloads start in `payloads` (after the cache's header and index).
    base: usize,
}

/// What [`ColorPyramid::open_or_build`] did with the cache.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum CacheOutcome {
    /// A valid cache was mapped.
    Mapped,
    /// No cache: built and written.
    Built,
    /// The cache was stale or damaged (why): rebuilt and written.
    Rebuilt(String),
    /// Built, but the cache could not be written (why): served from memory.
    InMemory(String),
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
        let first = firsts(&layout);
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
        let mut index = Vec::with_capacity(total);
        let mut blob = Vec::with_capacity(coded.iter().map(Vec::len).sum());
        for c in coded {
            index.push((blob.len() as u64, c.len() as u32, check_of(&c)));
            blob.extend_from_slice(&c);
        }
        Ok(ColorPyramid {
            cells: layout.cells,
            tile,
            levels: layout.levels,
            verified: (0..index.len()).map(|_| AtomicU8::new(1)).collect(),
            index,
            first,
            payloads: Payloads::Memory(blob),
            base: 0,
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
        load: impl FnOnce() -> Result<Cow<'c, ColorMap>, crate::terrain::dataset::DataError>,
        progress: &mut dyn FnMut(u64, u64),
    ) -> Result<(ColorPyramid, CacheOutcome), PyramidError> {
        let source = source_stamp(&dir.join(COLOR_FILE));
        let path = cache_path(dir);
        let stale = match (&source, fs::File::open(&path)) {
            (None, _) => None,
            (Some(_), Err(e)) if e.kind() == io::ErrorKind::NotFound => None,
            (Some(_), Err(e)) => Some(format!("{}: {e}", path.display())),
            (Some(stamp), Ok(file)) => match Self::open(&file, cells, tile, *stamp) {
                Ok(p) => return Ok((p, CacheOutcome::Mapped)),
                Err(why) => Some(format!("{}: {why}", path.display())),
            },
        };
        let color = load()?;
        let pyramid = Self::build(&color, tile, threads, progress)?;
        drop(color);
        let Some(stamp) = source else {
            let why = format!(
                "{}: cannot be read for its date",
                dir.join(COLOR_FILE).display()
            );
            return Ok((pyramid, CacheOutcome::InMemory(why)));
        };
        let outcome = match pyramid.write_cache(&path, stamp) {
            Ok(()) => match stale {
                Some(why) => CacheOutcome::Rebuilt(why),
                None => CacheOutcome::Built,
            },
            Err(e) => CacheOutcome::InMemory(format!("{}: {e}", path.display())),
        };
        Ok((pyramid, outcome))
    }

    /// Maps `file` if it is a valid cache of a `cells` map in `tile` tiles coded from the
    /// source with `stamp`; why not otherwise.
    fn open(
        file: &fs::File,
        cells: u32,
        tile: u32,
        stamp: (u64, u64),
    ) -> Result<ColorPyramid, String> {
        let layout = ColorLayout::new(cells, tile, 1).map_err(|e| e.to_string())?;
        // SAFETY: the map is read only, and the file is ours: written once by
        // `write_cache` and replaced by renaming, never changed in place. Another process
        // truncating it under us is outside what this server guards against.
        let map = unsafe { memmap2::Mmap::map(file) }.map_err(|e| format!("mapping: {e}"))?;
        let head = map.get(..HEADER).ok_or("shorter than its header")?;
        if &head[..8] != MAGIC {
            return Err("not a colour tile cache".into());
        }
        let u32_at = |at: usize| u32::from_le_bytes(head[at..at + 4].try_into().expect("4"));
        let u64_at = |at: usize| u64::from_le_bytes(head[at..at + 8].try_into().expect("8"));
        let version = u32_at(8);
        if version != CACHE_VERSION {
            return Err(format!("format {version}, expected {CACHE_VERSION}"));
        }
        let got = (u32_at(12), u32_at(16), u32_at(20));
        let want = (cells, tile, u32::from(layout.levels));
        if got != want {
            return Err(format!(
                "for {} cells in tiles of {} ({} levels), expected {} in tiles of {}",
                got.0, got.1, got.2, cells, tile
            ));
        }
        if (u64_at(24), u64_at(32)) != stamp {
            return Err(format!("stale: {COLOR_FILE} changed since it was built"));
        }
        let first = firsts(&layout);
        let total = *first.last().expect("one entry past the last level");
        if u64_at(40) != total as u64 {
            return Err(format!("{} tiles, expected {total}", u64_at(40)));
        }
        let base = HEADER + HASH + total * ENTRY;
        let index_bytes = map.get(HEADER + HASH..base).ok_or("index cut short")?;
        let mut hasher = blake3::Hasher::new();
        hasher.update(head);
        hasher.update(index_bytes);
        if hasher.finalize().as_bytes() != &map[HEADER..HEADER + HASH] {
            return Err("header or index damaged (hash mismatch)".into());
        }
        let payload_len = (map.len() - base) as u64;
        let mut index = Vec::with_capacity(total);
        let mut end = 0u64;
        for l in 0..layout.levels {
            let limit = colormap::max_len(layout.tile_side(l));
            for e in index_bytes
                .chunks_exact(ENTRY)
                .take(first[usize::from(l) + 1])
                .skip(first[usize::from(l)])
            {
                let offset = u64::from_le_bytes(e[..8].try_into().expect("8"));
                let len = u32::from_le_bytes(e[8..12].try_into().expect("4"));
                let check = u64::from_le_bytes(e[12..].try_into().expect("8"));
                if offset != end || len as usize > limit || len < 16 {
                    return Err(format!("index entry {} out of order or size", index.len()));
                }
                end += u64::from(len);
                index.push((offset, len, check));
            }
        }
        if end != payload_len {
            return Err(format!("{payload_len} payload bytes, the index says {end}"));
        }
        let pyramid = ColorPyramid {
            cells,
            tile,
            levels: layout.levels,
            verified: (0..index.len()).map(|_| AtomicU8::new(0)).collect(),
            index,
            first,
            payloads: Payloads::Mapped(map),
            base,
        };
        // The coarsest tile goes to every viewer before its first frame: checked now, so a
        // damaged one is rebuilt rather than served. Others are checked when first served.
        let coarsest = layout.levels - 1;
        if let Err(e) = pyramid.served_tile(coarsest, 0, 0) {
            return Err(format!("the coarsest tile: {e}"));
        }
        Ok(pyramid)
    }

    /// Writes the cache to `path` (a temporary file, then renamed).
    fn write_cache(&self, path: &Path, stamp: (u64, u64)) -> io::Result<()> {
        let dir = path.parent().expect("the cache path has a folder");
        fs::create_dir_all(dir)?;
        let mut head = Vec::with_capacity(HEADER + HASH + self.index.len() * ENTRY);
        head.extend_from_slice(MAGIC);
        for v in [CACHE_VERSION, self.cells, self.tile, u32::from(self.levels)] {
            head.extend_from_slice(&v.to_le_bytes());
        }
        for v in [stamp.0, stamp.1, self.index.len() as u64] {
            head.extend_from_slice(&v.to_le_bytes());
        }
        let mut index = Vec::with_capacity(self.index.len() * ENTRY);
        for &(offset, len, check) in &self.index {
            index.extend_from_slice(&offset.to_le_bytes());
            index.extend_from_slice(&len.to_le_bytes());
            index.extend_from_slice(&check.to_le_bytes());
        }
        let mut hasher = blake3::Hasher::new();
        hasher.update(&head);
        hasher.update(&index);
        head.extend_from_slice(hasher.finalize().as_bytes());
        head.extend_from_slice(&index);
        // Unique per process and per write: two builds of one data set in one process (or
        // in two) never write into the same temporary file.
        static WRITES: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let n = WRITES.fetch_add(1, Ordering::Relaxed);
        let tmp = dir.join(format!("{CACHE_FILE}.{}.{n}.tmp", std::process::id()));
        let written = (|| {
            let mut f = io::BufWriter::new(fs::File::create(&tmp)?);
            f.write_all(&head)?;
            f.write_all(self.payload_bytes())?;
            f.into_inner().map_err(|e| e.into_error())?.sync_all()?;
            fs::rename(&tmp, path)
        })();
        if written.is_err() {
            let _ = fs::remove_file(&tmp);
        }
        written
    }

    fn payload_bytes(&self) -> &[u8] {
        match &self.payloads {
            Payloads::Memory(v) => v,
            Payloads::Mapped(m) => &m[self.base..],
        }
    }

    /// The layout viewers are told, with windows of `window` tiles.
    pub fn layout(&self, window: u8) -> Result<ColorLayout, tiles::LayoutError> {
        ColorLayout::new(self.cells, self.tile, window)
    }

    /// Levels in the pyramid.
    pub fn levels(&self) -> u8 {
        self.levels
    }

    /// Tile `(x, z)` of `level`, coded; `None` outside the pyramid.
    pub fn tile(&self, level: u8, x: u32, z: u32) -> Option<&[u8]> {
        let layout = ColorLayout::new(self.cells, self.tile, 1).ok()?;
        let n = layout.tiles(level);
        if level >= self.levels || x >= n || z >= n {
            return None;
        }
        let i = self.first[usize::from(level)] + (z * n + x) as usize;
        let (offset, len, _) = self.index[i];
        let start = offset as usize;
        self.payload_bytes().get(start..start + len as usize)
    }

    /// [`Self::tile`] for a viewer: its payload checked against the index the first time
    /// (hundreds of megabytes at 16385² are not hashed at open; a tile is 20–40 µs).
    pub fn served_tile(&self, level: u8, x: u32, z: u32) -> Result<&[u8], TileError> {
        let data = self.tile(level, x, z).ok_or(TileError::Outside)?;
        let layout = ColorLayout::new(self.cells, self.tile, 1).map_err(|_| TileError::Outside)?;
        let i = self.first[usize::from(level)] + (z * layout.tiles(level) + x) as usize;
        match self.verified[i].load(Ordering::Relaxed) {
            1 => Ok(data),
            2 => Err(TileError::Damaged { first: false }),
            _ if check_of(data) == self.index[i].2 => {
                self.verified[i].store(1, Ordering::Relaxed);
                Ok(data)
            }
            _ => {
                let first = self.verified[i].swap(2, Ordering::Relaxed) != 2;
                Err(TileError::Damaged { first })
            }
        }
    }

    /// Coded bytes of all tiles.
    pub fn coded_bytes(&self) -> u64 {
        self.payload_bytes().len() as u64
    }

    /// Whether the payloads are memory-mapped from the cache.
    pub fn is_mapped(&self) -> bool {
        matches!(self.payloads, Payloads::Mapped(_))
    }
}

/// A payload's check: its blake3 hash, cut to 64 bits.
fn check_of(payload: &[u8]) -> u64 {
    let h = blake3::hash(payload);
    u64::from_le_bytes(
        h.as_bytes()[..8]
            .try_into()
            .expect("a blake3 hash is 32 bytes"),
    )
}

/// The cache's path for the data set in `dir`.
pub fn cache_path(dir: &Path) -> PathBuf {
    dir.join(CACHE_DIR).join(CACHE_FILE)
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

/// Where each level's tiles start in the index, and the count after the last.
fn firsts(layout: &ColorLayout) -> Vec<usize> {
    let mut first = vec![0];
    for l in 0..layout.levels {
        let n = layout.tiles(l) as usize;
        first.push(first[usize::from(l)] + n * n);
    }
    first
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
                            Ok(()) => **slot.lock().unwrap_or_else(|e| e.into_inner()) = coded,
                            Err(e) => {
                                *failed.lock().unwrap_or_else(|e| e.into_inner()) = Some(e.into())
                            }
                        }
                    }
                });
            }
        });
        if let Some(e) = failed.into_inner().unwrap_or_else(|e| e.into_inner()) {
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
