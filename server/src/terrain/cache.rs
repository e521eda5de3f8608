//! The cache beside a data set: `DIR/.cache/` holds the heights as little-endian `u16`
//! (`heights.bin`), what `hf.pgm` they were converted from (`heights.stamp`) and the
//! variance tree's codes (`variance.bin`), each memory-mapped read-only when served, so a
//! start skips the `hf.pgm` parse and the variance build and several servers on one data
//! set share one copy in the page cache.
//!
//! **Files** (little-endian; each header 128 bytes, a multiple of 8, so the mapped values
//! after it stay aligned in the page-aligned map):
//!
//! - `heights.bin`: magic `ROAMHGT\0`, [`VERSION`], side, the hash of the samples, the hash
//!   of the `hf.pgm` bytes they came from, the sample count; then `side²` samples.
//! - `heights.stamp`: magic `ROAMSTP\0`, [`VERSION`], the `hf.pgm` hash it vouches for, and
//!   that file's length, mtime, ctime, inode and device when it was hashed (the stamp's
//!   own mtime says when it was written). A stamp is its own small file so `heights.bin` is
//!   never written after its rename (other processes map it).
//! - `verified.stamp`: magic `ROAMVFY\0`, [`VERSION`], the stamps of the `heights.bin` and
//!   the `variance.bin` last re-hashed whole (see **Trust**).
//! - `content.hash`: the data set's hash for the recordings, with what it was computed
//!   from (`dataset::content_hash_cached`, which reads and writes it).
//! - `variance.bin`: magic `ROAMVAR\0`, [`VERSION`], `side − 1`, the hash of the code table
//!   (so a change of the table is a different cache), the hash of the heights it was built
//!   from, the hash of the codes, their count; then the codes.
//!
//! **Trust.** Nothing in a cache file is used before it is checked:
//!
//! - header fields and the file's exact length come first, read with `read`, before any
//!   map, so a truncated or foreign file is rebuilt, never indexed past its end;
//! - `hf.pgm` is not re-read when the stamp matches its length, mtime, ctime, inode and
//!   device. Any write to a file sets its ctime, which no program can set back, so a
//!   changed `hf.pgm` never matches; a copied data set (new inode) or a touched file is
//!   re-hashed and, if its content is the same, only re-stamped. A stamp written (its own
//!   mtime) less than 2 s after the file's ctime is "racy" (a write in the same clock tick
//!   would not show) and is not trusted: the next start re-hashes and re-stamps it. No
//!   clock is read: both times are the file system's;
//! - the samples and the codes are re-hashed whole (blake3 over 16 MiB pieces hashed on
//!   every core, then hashed together) by every open with [`Verify::Full`] (`check`, the
//!   tests), so a corrupt file (bit rot, a torn write after a crash) is rebuilt. `serve`
//!   opens with [`Verify::Stamps`]: a file re-hashed whole since it last changed is trusted
//!   by its stamp (`verified.stamp`: the [`FileStamp`] of each file then, written 2 s or
//!   more after the file's ctime, the file `fsync`ed first so a crash cannot leave a
//!   stamped file half on disk). Any write, copy or rename-over makes a new stamp, so what
//!   goes unseen until the next `check` is only damage under the file system (bit rot).
//!   The trade-off, measured at 16385² (671 MB of values, 2 cores shared with three
//!   builds, files in the page cache): the open re-hashing everything 517–683 ms,
//!   trusting the stamps under 1 ms (and from disk, when not cached, the whole files
//!   read against only the pages viewers reach); 32769² holds four times as much. Files just built are not stamped (the next open re-hashes
//!   them from the page cache, syncs and stamps them);
//! - `variance.bin` must name the heights hash of the `heights.bin` actually mapped.
//!
//! A rejected file is rebuilt and the reason is returned in [`CacheReport::notes`] (the CLI
//! logs them as warnings); a missing one is simply built. Files are written to a temporary
//! name in `.cache/` and renamed over the old one, so a reader sees the old file or the new
//! one, never half of one, and several processes can build and read at once. A directory
//! where `.cache/` cannot be written is served from memory, with one note.
//!
//! **Measured** (16385², 268 M samples, measure profile, 2 cores shared with other builds,
//! AVX-512): `check` building the cache 21.5 s wall (31.1 s CPU; the variance build is
//! most of it; `hf.pgm` hashed, converted, both files written), peak RSS 662 MB;
//! `check` on the cache 0.23 s wall, the open itself 52–58 ms (both files' values
//! re-hashed: 671 MB), RSS 662 MB, all of it the shared map (2.50 bytes/sample: heights
//! 2, variance 0.5); after `touch hf.pgm` 0.38 s (open 209 ms, `hf.pgm` re-hashed, then
//! re-stamped). `serve` from start to the data set opened and checked (`check_servable`,
//! at the time still refusing 16385²; it serves up to 32769² now): 0.05 s wall, RSS 662 MB.

use std::fs::{self, File};
use std::io::{self, BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use memmap2::Mmap;

use crate::terrain::backing::Backing;
use crate::terrain::cache_error::{CacheError, MapError};
use crate::terrain::data_error::DataError;
use crate::terrain::heightfield::Heightfield;
pub(crate) use crate::terrain::stamp::{Fields, FileStamp};
use crate::terrain::variance::{self, VarianceTree};

/// The cache's directory inside a data set.
pub const CACHE_DIR: &str = ".cache";
/// The heights, little-endian `u16`.
pub const HEIGHTS_FILE: &str = "heights.bin";
/// Which `hf.pgm` the heights came from.
pub const STAMP_FILE: &str = "heights.stamp";
/// The variance tree's codes.
pub const VARIANCE_FILE: &str = "variance.bin";
/// The stamps of the `heights.bin` and `variance.bin` last re-hashed whole ([`Verify`]).
pub const VERIFIED_FILE: &str = "verified.stamp";
/// Format version of all three files: raise it whenever their layout or the variance build
/// changes what it writes (a changed code table is caught by its hash anyway).
pub const VERSION: u32 = 1;
/// Bytes before the values in `heights.bin` and `variance.bin`; the whole stamp file.
const HEADER: usize = 128;
/// Pieces hashed in parallel.
const PIECE: usize = 16 << 20;
/// A stamp written closer than this to the file's ctime is not trusted (seconds).
pub(crate) const RACY_SECONDS: i64 = 2;

const HEIGHTS_MAGIC: &[u8; 8] = b"ROAMHGT\0";
const STAMP_MAGIC: &[u8; 8] = b"ROAMSTP\0";
const VARIANCE_MAGIC: &[u8; 8] = b"ROAMVAR\0";
const VERIFIED_MAGIC: &[u8; 8] = b"ROAMVFY\0";

/// How much of the cache files' values an open re-hashes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Verify {
    /// All of them, on every open (`check`, the tests): a damaged file is always found.
    Full,
    /// Only a file not re-hashed whole since it last changed: `verified.stamp` holds the
    /// stamps ([`FileStamp`]) of the `heights.bin` and `variance.bin` last re-hashed whole
    /// and synced to disk, and a file with that stamp is trusted (`serve`: 2.7 GB not read
    /// at 32769²). A stamp written less than 2 s after the file's ctime is not trusted.
    /// What it no longer finds: a file damaged without any write to it (bit rot under
    /// the file system); `check` (always [`Verify::Full`]) finds that.
    Stamps,
}

/// Where a part of an opened data set came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Source {
    /// Mapped from a valid cache file.
    Cached,
    /// Built now, written to the cache and mapped from it.
    Built,
    /// Built now and kept in memory: the cache could not be written.
    Memory,
}

/// What [`crate::terrain::dataset::open_cached`] did with the cache.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CacheReport {
    pub heights: Source,
    pub variance: Source,
    /// The hash of the heights served (`hash_values` of their little-endian bytes, as
    /// `heights.bin` records it): what `dataset::content_hash_cached` keys on.
    pub heights_hash: [u8; 32],
    /// Why a cache file was rebuilt or not written, one line each, naming the file.
    pub notes: Vec<String>,
}

/// A step that can take a while, for progress bars.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stage {
    /// Hashing `hf.pgm`.
    Hashing,
    /// Reading `hf.pgm` into samples.
    Converting,
    /// Re-hashing the cache files' values.
    Verifying,
    /// Building the variance tree.
    Variance,
}

impl Stage {
    /// A short label.
    pub fn label(self) -> &'static str {
        match self {
            Stage::Hashing => "hashing",
            Stage::Converting => "converting",
            Stage::Verifying => "verifying",
            Stage::Variance => "variance",
        }
    }
}

/// Progress of a stage: `(stage, done, total)`.
pub type Progress<'a> = &'a mut dyn FnMut(Stage, u64, u64);

/// The strict `hf.pgm` reader, given a `(done, total)` progress callback.
pub(crate) type Convert<'a> =
    &'a mut dyn FnMut(&mut dyn FnMut(u64, u64)) -> Result<Heightfield, DataError>;

/// The cache of one data set while it is opened.
pub(crate) struct Cache {
    dir: PathBuf,
    threads: usize,
    verify: Verify,
    /// The stamps of `heights.bin` and `variance.bin` as opened and checked (re-hashed
    /// now, or trusted), for `verified.stamp`; `changed`: one was re-hashed now.
    checked: [Option<FileStamp>; 2],
    changed: bool,
    /// False once `.cache/` could not be written: everything stays in memory.
    writable: bool,
    pub(crate) notes: Vec<String>,
}

/// A `heights.bin` whose header and length are right, opened, not yet mapped.
struct HeightsHeader {
    file: File,
    samples_hash: [u8; 32],
    source_hash: [u8; 32],
}

/// A `variance.bin` whose header and length are right, opened, not yet mapped.
struct VarianceHeader {
    file: File,
    heights_hash: [u8; 32],
    codes_hash: [u8; 32],
}

/// The hash of the cache's values: blake3 of each 16 MiB piece (on up to `threads` threads),
/// then blake3 of the length and the pieces' hashes. `progress(done, total)` in bytes.
pub fn hash_values(bytes: &[u8], threads: usize, progress: &mut dyn FnMut(u64, u64)) -> [u8; 32] {
    let mut outer = blake3::Hasher::new();
    outer.update(b"roam cache values v1");
    outer.update(&(bytes.len() as u64).to_le_bytes());
    let pieces: Vec<&[u8]> = bytes.chunks(PIECE).collect();
    let total = bytes.len() as u64;
    let mut done = 0;
    for batch in pieces.chunks(threads.max(1)) {
        let hashes: Vec<blake3::Hash> = if batch.len() == 1 {
            vec![blake3::hash(batch[0])]
        } else {
            std::thread::scope(|s| {
                let running: Vec<_> = batch
                    .iter()
                    .map(|piece| s.spawn(move || blake3::hash(piece)))
                    .collect();
                running
                    .into_iter()
                    .map(|h| h.join().expect("hashing a slice does not panic"))
                    .collect()
            })
        };
        for h in &hashes {
            outer.update(h.as_bytes());
        }
        done += batch.iter().map(|p| p.len() as u64).sum::<u64>();
        progress(done, total);
    }
    *outer.finalize().as_bytes()
}

/// The samples as little-endian bytes (a view on little-endian machines).
fn le_bytes(samples: &[u16]) -> std::borrow::Cow<'_, [u8]> {
    if cfg!(target_endian = "little") {
        std::borrow::Cow::Borrowed(bytemuck::cast_slice(samples))
    } else {
        std::borrow::Cow::Owned(samples.iter().flat_map(|s| s.to_le_bytes()).collect())
    }
}

/// The hash of a heightfield's samples, as `heights.bin` records it.
pub fn heights_hash(hf: &Heightfield, threads: usize) -> [u8; 32] {
    hash_values(&le_bytes(hf.samples()), threads, &mut |_, _| {})
}

/// The hash of the code table, as `variance.bin` records it.
fn table_hash() -> [u8; 32] {
    let table = variance::log_table();
    let mut h = blake3::Hasher::new();
    for v in table {
        h.update(&v.to_le_bytes());
    }
    *h.finalize().as_bytes()
}

/// blake3 of a whole file, read in pieces; `progress(done, total)` in bytes.
fn hash_file(path: &Path, progress: &mut dyn FnMut(u64, u64)) -> io::Result<[u8; 32]> {
    let mut file = File::open(path)?;
    let total = file.metadata()?.len();
    let mut h = blake3::Hasher::new();
    let mut buf = vec![0u8; 4 << 20];
    let mut done = 0;
    loop {
        let n = file.read(&mut buf)?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
        done += n as u64;
        progress(done.min(total), total);
    }
    Ok(*h.finalize().as_bytes())
}

/// Reads a cache file's header: the file must be at least `HEADER` bytes and start with
/// `magic` and [`VERSION`]. Returns the file, its length and the header's remaining bytes.
pub(crate) fn read_header(
    path: &Path,
    magic: &[u8; 8],
) -> Result<Option<(File, u64, Vec<u8>)>, CacheError> {
    let io = |action| move |error| CacheError::Io { action, error };
    let mut file = match File::open(path) {
        Ok(f) => f,
        // No file, or no `.cache` directory (missing, or something else by that name: the
        // write will say so).
        Err(e)
            if matches!(
                e.kind(),
                io::ErrorKind::NotFound | io::ErrorKind::NotADirectory
            ) =>
        {
            return Ok(None);
        }
        Err(error) => return Err(io("open")(error)),
    };
    let len = file.metadata().map_err(io("stat"))?.len();
    if len < HEADER as u64 {
        return Err(CacheError::ShortHeader {
            expected: HEADER,
            got: len,
        });
    }
    let mut header = vec![0u8; HEADER];
    file.read_exact(&mut header)
        .map_err(io("read the header"))?;
    let mut f = Fields(&header);
    let got: [u8; 8] = f.bytes();
    if &got != magic {
        return Err(CacheError::Magic {
            expected: *magic,
            got,
        });
    }
    let version = f.u32();
    if version != VERSION {
        return Err(CacheError::Version {
            expected: VERSION,
            got: version,
        });
    }
    let rest = f.0.to_vec();
    Ok(Some((file, len, rest)))
}

/// Maps a file read-only.
fn map(file: &File) -> io::Result<Arc<Mmap>> {
    // SAFETY: cache files are only ever replaced by a rename, never written in place, by
    // roam; a process mapping the old file keeps its inode. Another program writing them
    // in place is outside what this cache supports (as with any mapped file).
    Ok(Arc::new(unsafe { Mmap::map(file) }?))
}

/// Writes `parts` to `dir/name` through a temporary file and a rename.
pub(crate) fn write_atomically(dir: &Path, name: &str, parts: &[&[u8]]) -> io::Result<()> {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let tmp = dir.join(format!(
        ".{name}.tmp-{}-{}",
        std::process::id(),
        COUNTER.fetch_add(1, Ordering::Relaxed)
    ));
    let result = (|| {
        let mut w = BufWriter::with_capacity(1 << 20, File::create(&tmp)?);
        for part in parts {
            w.write_all(part)?;
        }
        w.into_inner().map_err(|e| e.into_error())?;
        fs::rename(&tmp, dir.join(name))
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result
}

impl Cache {
    /// The cache of the data set in `dir` (`.cache/` is created when first written).
    pub(crate) fn new(dir: &Path, threads: usize, verify: Verify) -> Cache {
        Cache {
            dir: dir.join(CACHE_DIR),
            threads: threads.max(1),
            verify,
            checked: [None; 2],
            changed: false,
            writable: true,
            notes: Vec::new(),
        }
    }

    fn path(&self, name: &str) -> PathBuf {
        self.dir.join(name)
    }

    fn note(&mut self, name: &str, reason: impl std::fmt::Display) {
        let line = format!("{}: {reason}; rebuilding it", self.path(name).display());
        self.notes.push(line);
    }

    /// Notes that the file `name`, just written, cannot be mapped (`why`): it is served
    /// from memory.
    fn unmapped(&mut self, name: &str, why: &CacheError) {
        let why: &dyn std::fmt::Display = match why {
            CacheError::Map(e) => e,
            other => other,
        };
        self.notes.push(format!(
            "{}: cannot map the file just written: {why}; serving from memory",
            self.path(name).display()
        ));
    }

    /// Writes a cache file, or notes once that the cache cannot be written.
    fn write(&mut self, name: &str, parts: &[&[u8]]) -> bool {
        if !self.writable {
            return false;
        }
        let result =
            fs::create_dir_all(&self.dir).and_then(|()| write_atomically(&self.dir, name, parts));
        if let Err(e) = result {
            self.writable = false;
            self.notes.push(format!(
                "cannot write the cache in {}: {e}; serving from memory (built again on every \
                 start)",
                self.dir.display()
            ));
        }
        self.writable
    }

    /// The heights of `hf_path` (whose header said `side`), from the cache when it is
    /// valid, else converted (and cached). Returns them, where they came from and their
    /// hash. `convert` reads `hf.pgm` (the caller's strict reader).
    pub(crate) fn heights(
        &mut self,
        hf_path: &Path,
        side: u32,
        progress: Progress,
        convert: Convert,
    ) -> Result<(Heightfield, Source, [u8; 32]), DataError> {
        let io_err = |action| {
            move |error| DataError::Io {
                file: hf_path.to_path_buf(),
                action,
                error,
            }
        };
        let before = FileStamp::of(&fs::metadata(hf_path).map_err(io_err("stat"))?);
        let mut source_hash = None;
        match self.open_heights(hf_path, side, before, progress) {
            Ok(Some((hf, hash))) => return Ok((hf, Source::Cached, hash)),
            Ok(None) => {}
            Err((reason, hashed)) => {
                self.note(HEIGHTS_FILE, reason);
                source_hash = hashed;
            }
        }
        let source_hash = match source_hash {
            Some(h) => h,
            None => hash_file(hf_path, &mut |d, t| progress(Stage::Hashing, d, t))
                .map_err(io_err("read"))?,
        };
        let hf = convert(&mut |d, t| progress(Stage::Converting, d, t))?;
        let after = FileStamp::of(&fs::metadata(hf_path).map_err(io_err("stat"))?);
        if after != before {
            return Err(DataError::Invalid {
                file: hf_path.to_path_buf(),
                line: None,
                field: "data".into(),
                message: "expected the file to stay as it was, got a change while loading".into(),
            });
        }
        let samples_hash = hash_values(&le_bytes(hf.samples()), self.threads, &mut |d, t| {
            progress(Stage::Verifying, d, t)
        });
        let mut header = Vec::with_capacity(HEADER);
        header.extend_from_slice(HEIGHTS_MAGIC);
        header.extend_from_slice(&VERSION.to_le_bytes());
        header.extend_from_slice(&side.to_le_bytes());
        header.extend_from_slice(&samples_hash);
        header.extend_from_slice(&source_hash);
        header.extend_from_slice(&(hf.samples().len() as u64).to_le_bytes());
        header.resize(HEADER, 0);
        if !self.write(HEIGHTS_FILE, &[&header, &le_bytes(hf.samples())]) {
            return Ok((hf, Source::Memory, samples_hash));
        }
        self.write_stamp(&source_hash, before);
        // Serve from the map (shared with other processes), not from this copy. Another
        // process may have renamed its own file over ours since: the same content has the
        // same hash.
        let mapped = match self.heights_header(side) {
            Ok(Some(h)) if h.samples_hash == samples_hash => {
                Self::map_heights(&h.file, side).map_err(CacheError::Map)
            }
            Ok(_) => Err(CacheError::Replaced("other heights")),
            Err(e) => Err(e),
        };
        match mapped {
            Ok(mapped) => Ok((mapped, Source::Built, samples_hash)),
            Err(e) => {
                self.unmapped(HEIGHTS_FILE, &e);
                Ok((hf, Source::Memory, samples_hash))
            }
        }
    }

    /// A valid `heights.bin` for `hf.pgm`, `None` when there is none, or why it was
    /// rejected (with `hf.pgm`'s hash when it was computed on the way).
    #[allow(clippy::type_complexity)]
    fn open_heights(
        &mut self,
        hf_path: &Path,
        side: u32,
        now: FileStamp,
        progress: Progress,
    ) -> Result<Option<(Heightfield, [u8; 32])>, (CacheError, Option<[u8; 32]>)> {
        let Some(header) = self.heights_header(side).map_err(|e| (e, None))? else {
            return Ok(None);
        };
        if !self.stamp_vouches(&header.source_hash, now) {
            let hash = hash_file(hf_path, &mut |d, t| progress(Stage::Hashing, d, t)).map_err(
                |error| {
                    let file = hf_path.to_path_buf();
                    (CacheError::Hash { file, error }, None)
                },
            )?;
            if hash != header.source_hash {
                let file = hf_path.to_path_buf();
                return Err((CacheError::SourceChanged { file }, Some(hash)));
            }
            // Same content (copied or touched): only the stamp is renewed.
            self.write_stamp(&hash, now);
        }
        let hf = Self::map_heights(&header.file, side).map_err(|e| (CacheError::Map(e), None))?;
        let stamp = self.trusted(0, &header.file);
        if let Err(stamp) = stamp {
            let got = hash_values(&le_bytes(hf.samples()), self.threads, &mut |d, t| {
                progress(Stage::Verifying, d, t)
            });
            if got != header.samples_hash {
                return Err((CacheError::Corrupt("the samples"), None));
            }
            self.verified(0, &header.file, stamp);
        }
        Ok(Some((hf, header.samples_hash)))
    }

    /// The header of `heights.bin`, checked against `side` and the file's length.
    fn heights_header(&self, side: u32) -> Result<Option<HeightsHeader>, CacheError> {
        let Some((file, len, rest)) = read_header(&self.path(HEIGHTS_FILE), HEIGHTS_MAGIC)? else {
            return Ok(None);
        };
        let mut f = Fields(&rest);
        let got_side = f.u32();
        let samples_hash = f.bytes();
        let source_hash = f.bytes();
        let count = f.u64();
        let want_count = u64::from(side) * u64::from(side);
        if got_side != side || count != want_count {
            return Err(CacheError::HeightsSide {
                expected: side,
                got: got_side,
                samples: count,
            });
        }
        let want_len = HEADER as u64 + 2 * want_count;
        if len != want_len {
            return Err(CacheError::Length {
                expected: want_len,
                codes: None,
                got: len,
            });
        }
        Ok(Some(HeightsHeader {
            file,
            samples_hash,
            source_hash,
        }))
    }

    /// Maps an opened `heights.bin` (whose header was checked) as a heightfield.
    fn map_heights(file: &File, side: u32) -> Result<Heightfield, MapError> {
        let map = map(file).map_err(MapError::Mmap)?;
        let count = side as usize * side as usize;
        let samples = if cfg!(target_endian = "little") {
            Backing::mapped(map, HEADER, count)?
        } else {
            let bytes = map
                .get(HEADER..HEADER + 2 * count)
                .ok_or(MapError::Truncated)?;
            Backing::Owned(
                bytes
                    .chunks_exact(2)
                    .map(|p| u16::from_le_bytes([p[0], p[1]]))
                    .collect(),
            )
        };
        Ok(Heightfield::with_backing(side, samples)?)
    }

    /// Whether `heights.stamp` says `hf.pgm`, as it is now, has the content hashed
    /// `source_hash`.
    fn stamp_vouches(&self, source_hash: &[u8; 32], now: FileStamp) -> bool {
        let Ok(Some((file, len, rest))) = read_header(&self.path(STAMP_FILE), STAMP_MAGIC) else {
            return false;
        };
        // When the stamp was written, by the file system's clock (no clock read here).
        let Some(written) = file
            .metadata()
            .and_then(|m| m.modified())
            .ok()
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
            .map(|d| d.as_secs() as i64)
        else {
            return false;
        };
        if len != HEADER as u64 {
            return false;
        }
        let mut f = Fields(&rest);
        let hash: [u8; 32] = f.bytes();
        let stamp = FileStamp::from_bytes(&f.bytes());
        &hash == source_hash && stamp == now && written >= stamp.ctime.0 + RACY_SECONDS
    }

    fn write_stamp(&mut self, source_hash: &[u8; 32], s: FileStamp) {
        let mut b = Vec::with_capacity(HEADER);
        b.extend_from_slice(STAMP_MAGIC);
        b.extend_from_slice(&VERSION.to_le_bytes());
        b.extend_from_slice(source_hash);
        b.extend_from_slice(&s.to_bytes());
        b.resize(HEADER, 0);
        self.write(STAMP_FILE, &[&b]);
    }

    /// The variance tree of `hf` (whose samples hash `heights_hash`), from the cache when it
    /// is valid, else built (and cached).
    pub(crate) fn variance(
        &mut self,
        hf: &Heightfield,
        heights_hash: &[u8; 32],
        progress: Progress,
    ) -> (VarianceTree, Source) {
        match self.open_variance(hf.size(), heights_hash, progress) {
            Ok(Some(vt)) => return (vt, Source::Cached),
            Ok(None) => {}
            Err(reason) => self.note(VARIANCE_FILE, reason),
        }
        let vt = VarianceTree::build(hf, self.threads, &mut |d, t| {
            progress(Stage::Variance, d, t)
        });
        let codes = vt.codes();
        let codes_hash = hash_values(codes, self.threads, &mut |_, _| {});
        let mut header = Vec::with_capacity(HEADER);
        header.extend_from_slice(VARIANCE_MAGIC);
        header.extend_from_slice(&VERSION.to_le_bytes());
        header.extend_from_slice(&hf.size().to_le_bytes());
        header.extend_from_slice(&table_hash());
        header.extend_from_slice(heights_hash);
        header.extend_from_slice(&codes_hash);
        header.extend_from_slice(&(codes.len() as u64).to_le_bytes());
        header.resize(HEADER, 0);
        if !self.write(VARIANCE_FILE, &[&header, codes]) {
            return (vt, Source::Memory);
        }
        let mapped = match self.variance_header(hf.size()) {
            Ok(Some(h)) if h.codes_hash == codes_hash => {
                Self::map_variance(&h.file, hf.size()).map_err(CacheError::Map)
            }
            Ok(_) => Err(CacheError::Replaced("another tree")),
            Err(e) => Err(e),
        };
        match mapped {
            Ok(mapped) => (mapped, Source::Built),
            Err(e) => {
                self.unmapped(VARIANCE_FILE, &e);
                (vt, Source::Memory)
            }
        }
    }

    fn open_variance(
        &mut self,
        size: u32,
        heights_hash: &[u8; 32],
        progress: Progress,
    ) -> Result<Option<VarianceTree>, CacheError> {
        let Some(header) = self.variance_header(size)? else {
            return Ok(None);
        };
        if &header.heights_hash != heights_hash {
            return Err(CacheError::OtherHeights);
        }
        let vt = Self::map_variance(&header.file, size).map_err(CacheError::Map)?;
        if let Err(stamp) = self.trusted(1, &header.file) {
            let got = hash_values(vt.codes(), self.threads, &mut |d, t| {
                progress(Stage::Verifying, d, t)
            });
            if got != header.codes_hash {
                return Err(CacheError::Corrupt("the codes"));
            }
            self.verified(1, &header.file, stamp);
        }
        Ok(Some(vt))
    }

    /// The header of `variance.bin`, checked against `size`, the code table and the
    /// file's length.
    fn variance_header(&self, size: u32) -> Result<Option<VarianceHeader>, CacheError> {
        let Some((file, len, rest)) = read_header(&self.path(VARIANCE_FILE), VARIANCE_MAGIC)?
        else {
            return Ok(None);
        };
        let mut f = Fields(&rest);
        let got_size = f.u32();
        let table: [u8; 32] = f.bytes();
        let heights_hash: [u8; 32] = f.bytes();
        let codes_hash: [u8; 32] = f.bytes();
        let count = f.u64();
        if got_size != size {
            return Err(CacheError::VarianceSide {
                expected: u64::from(size) + 1,
                got: u64::from(got_size) + 1,
            });
        }
        if table != table_hash() {
            return Err(CacheError::CodeTable);
        }
        let want = VarianceTree::codes_len(size) as u64;
        if count != want || len != HEADER as u64 + want {
            return Err(CacheError::Length {
                expected: HEADER as u64 + want,
                codes: Some(want),
                got: len,
            });
        }
        Ok(Some(VarianceHeader {
            file,
            heights_hash,
            codes_hash,
        }))
    }

    /// `Ok` when `verified.stamp` vouches for the opened cache file `file` (`slot` 0:
    /// `heights.bin`, 1: `variance.bin`) as it is now, with [`Verify::Stamps`]; else its
    /// stamp now (`None` if it cannot be read), for [`Cache::verified`].
    fn trusted(&mut self, slot: usize, file: &File) -> Result<(), Option<FileStamp>> {
        let now = file.metadata().ok().map(|m| FileStamp::of(&m));
        let Some(stamp) = now else {
            return Err(None);
        };
        if self.verify == Verify::Full {
            return Err(Some(stamp));
        }
        let Ok(Some((f, len, rest))) = read_header(&self.path(VERIFIED_FILE), VERIFIED_MAGIC)
        else {
            return Err(Some(stamp));
        };
        let written = f
            .metadata()
            .and_then(|m| m.modified())
            .ok()
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
            .map_or(0, |d| d.as_secs() as i64);
        let mut fields = Fields(&rest);
        let _pad: [u8; 4] = fields.bytes();
        let stamps = [
            FileStamp::from_bytes(&fields.bytes()),
            FileStamp::from_bytes(&fields.bytes()),
        ];
        if len == HEADER as u64 && stamps[slot] == stamp && written >= stamp.ctime.0 + RACY_SECONDS
        {
            self.checked[slot] = Some(stamp);
            Ok(())
        } else {
            Err(Some(stamp))
        }
    }

    /// The cache file `file` (`slot` as in [`Cache::trusted`]) was re-hashed whole and
    /// found right: synced to disk (so a crash cannot leave a stamped file unwritten), its
    /// stamp is kept for `verified.stamp`.
    fn verified(&mut self, slot: usize, file: &File, stamp: Option<FileStamp>) {
        if let Some(stamp) = stamp
            && file.sync_all().is_ok()
        {
            self.checked[slot] = Some(stamp);
            self.changed = true;
        }
    }

    /// Writes `verified.stamp` when a file was re-hashed whole by this open and both
    /// files were checked; nothing otherwise (a note only if it cannot be written).
    pub(crate) fn finish(&mut self) {
        let [Some(heights), Some(variance)] = self.checked else {
            return;
        };
        if !self.changed {
            return;
        }
        let mut b = Vec::with_capacity(HEADER);
        b.extend_from_slice(VERIFIED_MAGIC);
        b.extend_from_slice(&VERSION.to_le_bytes());
        b.extend_from_slice(&[0; 4]);
        b.extend_from_slice(&heights.to_bytes());
        b.extend_from_slice(&variance.to_bytes());
        b.resize(HEADER, 0);
        self.write(VERIFIED_FILE, &[&b]);
    }

    fn map_variance(file: &File, size: u32) -> Result<VarianceTree, MapError> {
        let map = map(file).map_err(MapError::Mmap)?;
        let codes = Backing::mapped(map, HEADER, VarianceTree::codes_len(size))?;
        Ok(VarianceTree::from_codes(size, codes)?)
    }
}
