//! A pyramid of coded tiles and its cache file, whatever the tiles hold: what the colour
//! pyramid ([`super::color_pyramid`]) and the normal pyramid ([`super::normal_pyramid`])
//! share. Tiles are laid out as [`ColorLayout`] says (levels finest first, then rows, then
//! columns); the store keeps their payloads back to back, in memory or memory-mapped from
//! the cache, each with a check verified the first time it is served.
//!
//! The cache file (one per kind, in `DIR/.cache/`): a header (magic, format version,
//! cells, tile, levels, the kind's key of its source — `color.ppm`'s length and stamp
//! digest; the heights' hash and the scales — and the tile count), a blake3 hash of the
//! header and the index, the index ((offset u64, length u32, check u64) per tile) and the
//! payloads. It is written to a temporary file and renamed (a torn write is never seen),
//! and checked before it is used: the hash, every entry inside the file, contiguous and
//! within the kind's `max_len` of its tile, and **every payload against its check** unless
//! the file was checked so since it last changed. A stale or damaged cache is rebuilt (with
//! the reason, for a warning); a folder that cannot be written keeps the pyramid in memory
//! ([`CacheOutcome`]). The colour cache's bytes are those of its format 3 before this
//! module existed: its key is the 16 bytes it always held.
//!
//! Both pyramids dereference to their [`TileStore`] (`Deref`), so what serving asks of a
//! pyramid (its layout, levels, tiles, checks and bytes) is written once, here; each
//! pyramid keeps only how it is built and keyed.
//!
//! **Checked whole at open, trusted by a stamp after** (as the heights are: `cache.rs`'s
//! **Trust**). Damaged payloads (bytes flipped in the file) were once found only when their
//! tile was first served: the tile was withheld and the log said to restart, but a restart
//! checked only the header, the index and the coarsest tile, so it rebuilt nothing. Now an
//! open hashes every payload (on every core) unless `<file>.verified` beside the cache
//! holds the cache's [`FileStamp`] (length, times, inode, device) as it was when last
//! checked whole and synced, written 2 s or more after the file's ctime (a write in the
//! same clock tick would not show). Any write to the file, in place or by a rename over it,
//! makes a new stamp, so a damaged file is checked whole and rebuilt at the next start.
//! What a stamp cannot show (bit rot under the file system, or damage while the server
//! runs) is still found when a tile is first served ([`TileStore::served_tile`]): the tile
//! is withheld and the stamp removed, so the next start checks the file whole and rebuilds
//! it. Measured by `serve`'s log on `data/kossou` (1025², colour cache 1.9 MB, normals
//! 1.4 MB; the optimised dev profile, 2 cores shared with another build, files in the page
//! cache): the open that checks every tile, syncs the file and writes its stamp 1.7–5.7 ms
//! (colour) and 2.9–7.6 ms (normals); trusted by the stamp, 0.04–0.09 ms. At 1–5 ms a
//! megabyte the whole check would cost 0.4–2 s at 16385² (a 454 MB colour cache), which
//! is why a stamped file is trusted rather than checked on every start.

use std::fs;
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU8, Ordering};

use roam_protocol::tiles::{self, ColorLayout};

use crate::terrain::cache::{RACY_SECONDS, write_atomically};
use crate::terrain::stamp::{Fields, FileStamp};

/// The data set's cache folder.
pub const CACHE_DIR: &str = ".cache";
/// Bytes of the header before the kind's key: magic, version, cells, tile, levels.
pub(crate) const HEAD: usize = 8 + 4 * 4;
/// Bytes of the header's hash.
pub(crate) const HASH: usize = 32;
/// An index entry: offset (u64), length (u32), check (u64: the payload's blake3, cut).
pub(crate) const ENTRY: usize = 20;
/// The magic of a cache's `.verified` stamp (then its [`FileStamp`]).
const VERIFIED_MAGIC: &[u8; 8] = b"ROAMTVF\0";

/// What a kind of tile cache is.
pub(crate) struct Kind {
    pub magic: &'static [u8; 8],
    pub version: u32,
    /// The file's name in the cache folder.
    pub file: &'static str,
    /// What the file is, for "not a …" ("colour tile cache").
    pub what: &'static str,
    /// What it was built from, for "stale: … changed since it was built".
    pub source: &'static str,
    /// Bytes of the key.
    pub key_len: usize,
    /// The most bytes a tile of a side may take.
    pub max_len: fn(u32) -> usize,
}

impl Kind {
    /// Header bytes: [`HEAD`], the key, the tile count.
    pub(crate) fn header(&self) -> usize {
        HEAD + self.key_len + 8
    }
}

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

/// Why a tile cache file is not used (it is rebuilt, with this reason after its path).
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The map and its tiles cannot be laid out.
    #[error(transparent)]
    Layout(#[from] tiles::LayoutError),
    #[error("mapping: {0}")]
    Map(io::Error),
    #[error("shorter than its header")]
    ShortHeader,
    /// Its magic is not the kind's (`what`: the kind, as [`Kind::what`]).
    #[error("not a {what}")]
    Foreign { what: &'static str },
    #[error("format {got}, expected {expected}")]
    Version { got: u32, expected: u32 },
    /// Built for another map: `got` its cells, tile side and levels.
    #[error(
        "for {} cells in tiles of {} ({} levels), expected {cells} in tiles of {tile}",
        got.0, got.1, got.2
    )]
    Shape {
        got: (u32, u32, u32),
        cells: u32,
        tile: u32,
    },
    /// Its key is not the source's now (`from`: what it was built from, [`Kind::source`]).
    #[error("stale: {from} changed since it was built")]
    Stale { from: &'static str },
    #[error("{got} tiles, expected {expected}")]
    Count { got: u64, expected: usize },
    #[error("index cut short")]
    ShortIndex,
    #[error("header or index damaged (hash mismatch)")]
    Hash,
    /// Index entry `at` does not follow the one before it, or its length is not a tile's.
    #[error("index entry {at} out of order or size")]
    Entry { at: usize },
    #[error("{got} payload bytes, the index says {indexed}")]
    Payloads { got: u64, indexed: u64 },
    /// The coarsest tile, checked at open, is not served.
    #[error("the coarsest tile: {0}")]
    Coarsest(TileError),
    /// A payload does not match its check: the first such tile.
    #[error("tile ({x}, {z}) of level {level}: {}", TileError::Damaged { first: true })]
    Damaged { x: u32, z: u32, level: u8 },
}

/// A cache's source whose date cannot be read: it cannot be keyed, so nothing is cached.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{}: cannot be read for its date", file.display())]
pub struct Unkeyed {
    pub file: PathBuf,
}

/// What opening a pyramid did with its cache.
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

/// Where a store's payloads live.
enum Payloads {
    Memory(Vec<u8>),
    Mapped(memmap2::Mmap),
}

/// Every tile of a pyramid, coded. The colour and normal pyramids are this store, each
/// with its own way of building it (they dereference to it for serving).
pub struct TileStore {
    pub(crate) layout: ColorLayout,
    /// Per tile: offset and length in `payloads`, and the payload's check ([`check_of`]).
    pub(crate) index: Vec<(u64, u32, u64)>,
    /// Per tile: 0 not verified against its check yet, 1 verified, 2 damaged.
    verified: Vec<AtomicU8>,
    /// Where each level's tiles start in `index`.
    first: Vec<usize>,
    payloads: Payloads,
    /// Where the payloads start in `payloads` (after the cache's header and index).
    base: usize,
    /// The `.verified` stamp of the cache mapped, removed when a damaged tile is found.
    stamp: Option<PathBuf>,
}

impl TileStore {
    /// The store of `coded` tiles (in index order) of `layout`.
    pub(crate) fn from_coded(layout: ColorLayout, coded: Vec<Vec<u8>>) -> TileStore {
        let mut index = Vec::with_capacity(coded.len());
        let mut blob = Vec::with_capacity(coded.iter().map(Vec::len).sum());
        for c in coded {
            index.push((blob.len() as u64, c.len() as u32, check_of(&c)));
            blob.extend_from_slice(&c);
        }
        TileStore {
            layout,
            verified: (0..index.len()).map(|_| AtomicU8::new(1)).collect(),
            index,
            first: firsts(&layout),
            payloads: Payloads::Memory(blob),
            base: 0,
            stamp: None,
        }
    }

    /// Maps `file` (at `path`) if it is a valid `kind` cache of a `cells` map in `tile`
    /// tiles, built from the source whose key is `key`, every payload checked on `threads`
    /// threads unless its stamp vouches for it (see the module docs); why not otherwise.
    pub(crate) fn open(
        (path, file): (&Path, &fs::File),
        kind: &Kind,
        (cells, tile): (u32, u32),
        key: &[u8],
        threads: usize,
    ) -> Result<TileStore, StoreError> {
        let layout = ColorLayout::new(cells, tile, 1)?;
        let header = kind.header();
        // SAFETY: the map is read only, and the file is ours: written once by `write` and
        // replaced by renaming, never changed in place. Another process truncating it
        // under us is outside what this server guards against.
        let map = unsafe { memmap2::Mmap::map(file) }.map_err(StoreError::Map)?;
        let head = map.get(..header).ok_or(StoreError::ShortHeader)?;
        if &head[..8] != kind.magic {
            return Err(StoreError::Foreign { what: kind.what });
        }
        let u32_at = |at: usize| u32::from_le_bytes(head[at..at + 4].try_into().expect("4"));
        let version = u32_at(8);
        if version != kind.version {
            let expected = kind.version;
            return Err(StoreError::Version {
                got: version,
                expected,
            });
        }
        let got = (u32_at(12), u32_at(16), u32_at(20));
        if got != (cells, tile, u32::from(layout.levels)) {
            return Err(StoreError::Shape { got, cells, tile });
        }
        if &head[HEAD..HEAD + kind.key_len] != key {
            return Err(StoreError::Stale { from: kind.source });
        }
        let first = firsts(&layout);
        let total = *first.last().expect("one entry past the last level");
        let count_at = HEAD + kind.key_len;
        let count = u64::from_le_bytes(head[count_at..count_at + 8].try_into().expect("8"));
        if count != total as u64 {
            return Err(StoreError::Count {
                got: count,
                expected: total,
            });
        }
        let base = header + HASH + total * ENTRY;
        let index_bytes = map.get(header + HASH..base).ok_or(StoreError::ShortIndex)?;
        let mut hasher = blake3::Hasher::new();
        hasher.update(head);
        hasher.update(index_bytes);
        if hasher.finalize().as_bytes() != &map[header..header + HASH] {
            return Err(StoreError::Hash);
        }
        let payload_len = (map.len() - base) as u64;
        let mut index = Vec::with_capacity(total);
        let mut end = 0u64;
        for l in 0..layout.levels {
            let limit = (kind.max_len)(layout.tile_side(l));
            for e in index_bytes
                .chunks_exact(ENTRY)
                .take(first[usize::from(l) + 1])
                .skip(first[usize::from(l)])
            {
                let offset = u64::from_le_bytes(e[..8].try_into().expect("8"));
                let len = u32::from_le_bytes(e[8..12].try_into().expect("4"));
                let check = u64::from_le_bytes(e[12..].try_into().expect("8"));
                if offset != end || len as usize > limit || len < 16 {
                    return Err(StoreError::Entry { at: index.len() });
                }
                end += u64::from(len);
                index.push((offset, len, check));
            }
        }
        if end != payload_len {
            return Err(StoreError::Payloads {
                got: payload_len,
                indexed: end,
            });
        }
        let store = TileStore {
            layout,
            verified: (0..index.len()).map(|_| AtomicU8::new(0)).collect(),
            index,
            first,
            payloads: Payloads::Mapped(map),
            base,
            stamp: Some(stamp_path(path)),
        };
        // The coarsest tile goes to every viewer first: checked now, so a damaged one is
        // rebuilt rather than served.
        let coarsest = layout.levels - 1;
        if let Err(e) = store.served_tile(coarsest, 0, 0) {
            return Err(StoreError::Coarsest(e));
        }
        let now = file.metadata().ok().map(|m| FileStamp::of(&m));
        if now.is_none_or(|now| !vouched(&stamp_path(path), now)) {
            store.check_whole(threads)?;
            // Synced first, so a crash cannot leave a stamped file unwritten; a stamp that
            // cannot be written only means the next open checks the file whole again.
            if let Some(now) = now
                && file.sync_all().is_ok()
            {
                let _ = write_stamp(&stamp_path(path), now);
            }
        }
        Ok(store)
    }

    /// Every payload against its check, on `threads` threads: why not, naming the first
    /// damaged tile. The tiles stay unverified for [`Self::served_tile`], which checks each
    /// again when first served (damage while the server runs).
    fn check_whole(&self, threads: usize) -> Result<(), StoreError> {
        let n = self.index.len();
        let per = n.div_ceil(threads.clamp(1, n.max(1))).max(1);
        let bad = std::thread::scope(|s| {
            let running: Vec<_> = (0..n)
                .step_by(per)
                .map(|from| {
                    s.spawn(move || {
                        (from..(from + per).min(n)).find(|&i| {
                            let (offset, len, check) = self.index[i];
                            let start = offset as usize;
                            let payload = self.payload_bytes().get(start..start + len as usize);
                            payload.is_none_or(|p| check_of(p) != check)
                        })
                    })
                })
                .collect();
            running
                .into_iter()
                .filter_map(|h| h.join().expect("checking payloads does not panic"))
                .min()
        });
        match bad {
            None => Ok(()),
            Some(i) => {
                let level = (0..self.layout.levels)
                    .rev()
                    .find(|&l| self.first[usize::from(l)] <= i)
                    .expect("level 0 starts at 0");
                let (at, side) = (i - self.first[usize::from(level)], self.layout.tiles(level));
                let (x, z) = (at as u32 % side, at as u32 / side);
                Err(StoreError::Damaged { x, z, level })
            }
        }
    }

    /// Writes the cache to `path` (a temporary file, then renamed).
    pub(crate) fn write(&self, path: &Path, kind: &Kind, key: &[u8]) -> io::Result<()> {
        let dir = path.parent().expect("the cache path has a folder");
        fs::create_dir_all(dir)?;
        let l = &self.layout;
        let mut head = Vec::with_capacity(kind.header() + HASH + self.index.len() * ENTRY);
        head.extend_from_slice(kind.magic);
        for v in [kind.version, l.cells, l.tile, u32::from(l.levels)] {
            head.extend_from_slice(&v.to_le_bytes());
        }
        head.extend_from_slice(key);
        head.extend_from_slice(&(self.index.len() as u64).to_le_bytes());
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
        let tmp = dir.join(format!("{}.{}.{n}.tmp", kind.file, std::process::id()));
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

    pub(crate) fn payload_bytes(&self) -> &[u8] {
        match &self.payloads {
            Payloads::Memory(v) => v,
            Payloads::Mapped(m) => &m[self.base..],
        }
    }

    /// The layout viewers are told, with windows of `window` tiles.
    pub fn layout(&self, window: u8) -> Result<ColorLayout, tiles::LayoutError> {
        ColorLayout::new(self.layout.cells, self.layout.tile, window)
    }

    /// Where tile `(x, z)` of `level` is in the index; `None` outside the pyramid.
    fn slot(&self, level: u8, x: u32, z: u32) -> Option<usize> {
        let n = self.layout.tiles(level);
        (level < self.layout.levels && x < n && z < n)
            .then(|| self.first[usize::from(level)] + (z * n + x) as usize)
    }

    /// Levels in the pyramid.
    pub fn levels(&self) -> u8 {
        self.layout.levels
    }

    /// Tile `(x, z)` of `level`, coded; `None` outside the pyramid.
    pub fn tile(&self, level: u8, x: u32, z: u32) -> Option<&[u8]> {
        let (offset, len, _) = self.index[self.slot(level, x, z)?];
        let start = offset as usize;
        self.payload_bytes().get(start..start + len as usize)
    }

    /// [`Self::tile`] for a viewer: its payload checked against the index the first time
    /// (hundreds of megabytes at 16385² are not hashed at open; a tile is 20–40 µs).
    pub fn served_tile(&self, level: u8, x: u32, z: u32) -> Result<&[u8], TileError> {
        let data = self.tile(level, x, z).ok_or(TileError::Outside)?;
        let i = self.slot(level, x, z).ok_or(TileError::Outside)?;
        match self.verified[i].load(Ordering::Relaxed) {
            1 => Ok(data),
            2 => Err(TileError::Damaged { first: false }),
            _ if check_of(data) == self.index[i].2 => {
                self.verified[i].store(1, Ordering::Relaxed);
                Ok(data)
            }
            _ => {
                let first = self.verified[i].swap(2, Ordering::Relaxed) != 2;
                // The next open checks the file whole, and rebuilds it.
                if first && let Some(stamp) = &self.stamp {
                    let _ = fs::remove_file(stamp);
                }
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

/// Opens the `kind` cache in `dir`'s cache folder for a `cells` map in `tile` tiles
/// built from the source keyed `key` (`Err`: the source cannot be keyed, so nothing is
/// cached), or makes the store with `make` (only then) and caches it.
pub(crate) fn open_or_make<E>(
    dir: &Path,
    kind: &Kind,
    (cells, tile, threads): (u32, u32, usize),
    key: Result<&[u8], Unkeyed>,
    make: impl FnOnce() -> Result<TileStore, E>,
) -> Result<(TileStore, CacheOutcome), E> {
    let path = cache_path(dir, kind);
    let stale = match (&key, fs::File::open(&path)) {
        (Err(_), _) => None,
        (Ok(_), Err(e)) if e.kind() == io::ErrorKind::NotFound => None,
        (Ok(_), Err(e)) => Some(format!("{}: {e}", path.display())),
        (Ok(key), Ok(file)) => {
            match TileStore::open((&path, &file), kind, (cells, tile), key, threads) {
                Ok(store) => return Ok((store, CacheOutcome::Mapped)),
                Err(why) => Some(format!("{}: {why}", path.display())),
            }
        }
    };
    let store = make()?;
    let key = match key {
        Ok(key) => key,
        Err(why) => return Ok((store, CacheOutcome::InMemory(why.to_string()))),
    };
    let outcome = match store.write(&path, kind, key) {
        Ok(()) => match stale {
            Some(why) => CacheOutcome::Rebuilt(why),
            None => CacheOutcome::Built,
        },
        Err(e) => CacheOutcome::InMemory(format!("{}: {e}", path.display())),
    };
    Ok((store, outcome))
}

/// The `kind` cache's path for the data set in `dir`.
pub(crate) fn cache_path(dir: &Path, kind: &Kind) -> PathBuf {
    dir.join(CACHE_DIR).join(kind.file)
}

/// The stamp beside the cache file `cache`: `<name>.verified`.
fn stamp_path(cache: &Path) -> PathBuf {
    let mut name = cache.file_name().unwrap_or_default().to_owned();
    name.push(".verified");
    cache.with_file_name(name)
}

/// Whether the stamp at `path` vouches that the cache file, stamped `now`, was checked
/// whole as it is: the same stamp, written [`RACY_SECONDS`] or more after its ctime.
fn vouched(path: &Path, now: FileStamp) -> bool {
    let Ok(bytes) = fs::read(path) else {
        return false;
    };
    let written = fs::metadata(path)
        .and_then(|m| m.modified())
        .ok()
        .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
        .map_or(0, |d| d.as_secs() as i64);
    if bytes.len() != 8 + FileStamp::BYTES || &bytes[..8] != VERIFIED_MAGIC {
        return false;
    }
    let stamp = FileStamp::from_bytes(&Fields(&bytes[8..]).bytes());
    stamp == now && written >= now.ctime_secs() + RACY_SECONDS
}

/// Writes the stamp vouching for a cache file stamped `now`, checked whole.
fn write_stamp(path: &Path, now: FileStamp) -> io::Result<()> {
    let dir = path.parent().expect("a stamp's path has a folder");
    let name = path.file_name().expect("a stamp's path has a name");
    write_atomically(
        dir,
        &name.to_string_lossy(),
        &[VERIFIED_MAGIC, &now.to_bytes()],
    )
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

/// Where each level's tiles start in the index, and the count after the last.
pub(crate) fn firsts(layout: &ColorLayout) -> Vec<usize> {
    let mut first = vec![0];
    for l in 0..layout.levels {
        let n = layout.tiles(l) as usize;
        first.push(first[usize::from(l)] + n * n);
    }
    first
}
