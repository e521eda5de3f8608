//! A terrain data set on disk: a directory holding `map` (TOML parameters, see
//! [`crate::terrain::map`]), `hf.pgm` (16-bit heightfield, side `2^N + 1`) and `color.ppm`
//! (8-bit RGB, one pixel per grid cell, `(side − 1)²`).
//!
//! [`load`] validates everything and reports problems as a [`DataError`] naming the file, the
//! field and what was expected, e.g.
//! `data/x/hf.pgm: width: expected 2^N + 1 (3, 5, 9, …, 32769), got 1000`.
//!
//! Two ways in:
//!
//! - [`load`]: everything in memory, the colour map included (generate, import, replay,
//!   tests);
//! - [`open_cached`]: for serving: the heights and the variance tree mapped from the data
//!   set's cache (built on first use, see [`crate::terrain::cache`]), `color.ppm`'s header
//!   checked as `load` checks it but its pixels not read (`Terrain::color` is `None`; the
//!   colour is served another way). `map` is parsed by the same code, as strictly.
//!
//! The data set's hash (what recordings name, [`Terrain::content_hash`]) needs every height
//! and every colour: [`content_hash_cached`] keeps it in `.cache/content.hash`, keyed by
//! the heights' hash, the `map` parameters' hash and `color.ppm`'s stamp, so a warm
//! `serve` reads neither `hf.pgm` nor `color.ppm`. Measured at 16385² (2 shared cores,
//! busy): computed 1.4 s (some 15 s at a higher load), from the cache under 1 ms.

use std::fs;
use std::io;
use std::path::{Path, PathBuf};

use crate::terrain::cache::{self, Cache, CacheReport};
use crate::terrain::data_error::DataError;
use crate::terrain::heightfield::Heightfield;
use crate::terrain::map::{MapError, MapParams};
use crate::terrain::pnm;
use crate::terrain::variance::VarianceTree;

/// File name of the parameters inside a data-set directory.
pub const MAP_FILE: &str = "map";
/// File name of the heightfield.
pub const HEIGHTS_FILE: &str = "hf.pgm";
/// File name of the colour map.
pub const COLOR_FILE: &str = "color.ppm";
/// Largest accepted `map` file: it holds a dozen keys.
pub const MAX_MAP_BYTES: u64 = 1 << 20;

/// One RGB colour per grid cell: `cells × cells` pixels, row-major (row 0 is north). The
/// colour of cell `(x, z)` belongs to both triangles of the square between samples
/// `(x, z)` and `(x + 1, z + 1)`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ColorMap {
    cells: u32,
    rgb: Vec<[u8; 3]>,
}

impl ColorMap {
    /// A colour map of `cells × cells` pixels; `None` when `rgb` has another length.
    pub fn new(cells: u32, rgb: Vec<[u8; 3]>) -> Option<ColorMap> {
        (rgb.len() as u64 == u64::from(cells) * u64::from(cells)).then_some(ColorMap { cells, rgb })
    }

    /// Cells per row (and rows): the heightfield's `side − 1`.
    pub fn cells(&self) -> u32 {
        self.cells
    }

    /// All pixels, row-major.
    pub fn rgb(&self) -> &[[u8; 3]] {
        &self.rgb
    }

    /// Colour of cell column `x`, row `z`. Panics when out of range (a caller bug).
    #[inline]
    pub fn get(&self, x: u32, z: u32) -> [u8; 3] {
        self.rgb[z as usize * self.cells as usize + x as usize]
    }

    /// Bytes held by the pixels.
    pub fn heap_bytes(&self) -> usize {
        self.rgb.capacity() * 3
    }
}

/// A loaded data set.
#[derive(Clone, Debug, PartialEq)]
pub struct Terrain {
    /// Scales, sun, fog, water, start.
    pub map: MapParams,
    /// Heights (samples; world height is `map.v_scale · sample`).
    pub heights: Heightfield,
    /// One colour per cell; `None` when opened for serving ([`open_cached`]).
    pub color: Option<ColorMap>,
}

impl Terrain {
    /// World height of sample `(x, z)`.
    pub fn world_height(&self, x: u32, z: u32) -> f64 {
        self.map.v_scale * f64::from(self.heights.get(x, z))
    }

    /// A hash of everything in the data set (heights, colours, map parameters), so a
    /// recording can tell whether it is replayed on the terrain it was made on. A terrain
    /// opened without its colour map ([`open_cached`]) hashes only heights and map: use
    /// [`Terrain::content_hash_in`] for the data set's hash then.
    pub fn content_hash(&self) -> [u8; 32] {
        let mut h = self.hash_heights();
        if let Some(color) = &self.color {
            h.update(color.rgb().as_flattened());
        }
        h.update(self.map.to_toml().as_bytes());
        *h.finalize().as_bytes()
    }

    /// [`Terrain::content_hash`] of the data set in `dir` (the same bytes whether this
    /// terrain holds its colour map or not): without one, the colour bytes are streamed from
    /// `dir/color.ppm` (64 KiB at a time; 805 MB at 16385²) instead of read into memory.
    pub fn content_hash_in(
        &self,
        dir: &Path,
        progress: &mut dyn FnMut(u64, u64),
    ) -> Result<[u8; 32], DataError> {
        if self.color.is_some() {
            return Ok(self.content_hash());
        }
        let mut h = self.hash_heights();
        let path = dir.join(COLOR_FILE);
        let cells = self.heights.size();
        let header =
            pnm::read_ppm_header(&path, cells).map_err(|e| DataError::from_pnm(&path, e))?;
        let io = |action| {
            let file = path.clone();
            move |error| DataError::Io {
                file,
                action,
                error,
            }
        };
        let mut file = fs::File::open(&path).map_err(io("open"))?;
        io::Seek::seek(&mut file, io::SeekFrom::Start(header.data_offset)).map_err(io("read"))?;
        let total = u64::from(cells) * u64::from(cells) * 3;
        let mut left = total;
        let mut buf = vec![0u8; 1 << 16];
        while left > 0 {
            let n = (left.min(buf.len() as u64)) as usize;
            io::Read::read_exact(&mut file, &mut buf[..n]).map_err(io("read"))?;
            h.update(&buf[..n]);
            left -= n as u64;
            progress(total - left, total);
        }
        h.update(self.map.to_toml().as_bytes());
        Ok(*h.finalize().as_bytes())
    }

    /// The hasher after the prefix and the heights.
    fn hash_heights(&self) -> blake3::Hasher {
        let mut h = blake3::Hasher::new();
        h.update(b"roam data set v1");
        h.update(&self.heights.side().to_le_bytes());
        // The same bytes as one `update` per sample, 64 Ki samples at a time (~20× faster).
        let mut buf = Vec::with_capacity(1 << 17);
        for chunk in self.heights.samples().chunks(1 << 16) {
            buf.clear();
            buf.extend(chunk.iter().flat_map(|s| s.to_le_bytes()));
            h.update(&buf);
        }
        h
    }

    /// World extent along X and Z.
    pub fn world_size(&self) -> f64 {
        self.map.world_size(self.heights.side())
    }

    /// Check that the parts fit together: colour map `(side − 1)²`, map values valid and the
    /// start on the map.
    pub fn validate(&self) -> Result<(), MapError> {
        if let Some(color) = &self.color
            && color.cells() != self.heights.size()
        {
            return Err(MapError {
                field: "color".into(),
                line: None,
                message: format!(
                    "expected a {0} × {0} colour map, got {1} × {1}",
                    self.heights.size(),
                    color.cells()
                ),
            });
        }
        self.map.validate_for_side(self.heights.side())
    }
}

fn file_len(path: &Path) -> u64 {
    fs::metadata(path).map(|m| m.len()).unwrap_or(0)
}

/// Read the `map` file's text, refusing anything large or not UTF-8.
fn read_map_text(path: &Path) -> Result<String, DataError> {
    let io_err = |action| {
        move |error| DataError::Io {
            file: path.to_path_buf(),
            action,
            error,
        }
    };
    let meta = fs::metadata(path).map_err(io_err("open"))?;
    let invalid = |message: String| DataError::Invalid {
        file: path.to_path_buf(),
        line: None,
        field: "file".into(),
        message,
    };
    if !meta.is_file() {
        return Err(invalid("expected a regular file".into()));
    }
    if meta.len() > MAX_MAP_BYTES {
        return Err(invalid(format!(
            "expected a small TOML text (at most {MAX_MAP_BYTES} bytes), got {} bytes",
            meta.len()
        )));
    }
    let bytes = fs::read(path).map_err(io_err("read"))?;
    String::from_utf8(bytes).map_err(|e| {
        invalid(format!(
            "expected UTF-8 text, got an invalid byte at offset {}",
            e.utf8_error().valid_up_to()
        ))
    })
}

/// Load and validate the data set in `dir`. `progress(done, total)` gets the bytes read so
/// far out of the total size of the three files, every few MB.
///
/// Order: the heightfield header (for the side), the `map` file, the heightfield's samples,
/// then the colour map; the first problem found is returned.
pub fn load(dir: &Path, progress: &mut dyn FnMut(u64, u64)) -> Result<Terrain, DataError> {
    let map_path = dir.join(MAP_FILE);
    let hf_path = dir.join(HEIGHTS_FILE);
    let color_path = dir.join(COLOR_FILE);
    let total = file_len(&map_path) + file_len(&hf_path) + file_len(&color_path);

    let header = pnm::read_pgm_header(&hf_path).map_err(|e| DataError::from_pnm(&hf_path, e))?;
    let side = header.width;
    let text = read_map_text(&map_path)?;
    let map = MapParams::parse(&text, side).map_err(|e| DataError::from_map(&map_path, e))?;
    let mut done = text.len() as u64;
    progress(done, total);

    let heights = pnm::read_pgm(&hf_path, &mut |n| progress(done + n, total))
        .map_err(|e| DataError::from_pnm(&hf_path, e))?;
    done += file_len(&hf_path);
    if heights.side() != side {
        return Err(DataError::Invalid {
            file: hf_path,
            line: None,
            field: "width".into(),
            message: format!(
                "expected {side} (the file changed while loading), got {}",
                heights.side()
            ),
        });
    }
    let cells = heights.size();
    let rgb = pnm::read_ppm(&color_path, cells, &mut |n| progress(done + n, total))
        .map_err(|e| DataError::from_pnm(&color_path, e))?;
    let color = ColorMap::new(cells, rgb).ok_or_else(|| DataError::Invalid {
        file: color_path.clone(),
        line: None,
        field: "data".into(),
        message: format!("expected {cells} × {cells} pixels"),
    })?;
    progress(total, total);
    Ok(Terrain {
        map,
        heights,
        color: Some(color),
    })
}

/// Open the data set in `dir` for serving: validated as [`load`] validates it, the heights
/// and the variance tree mapped from `dir/.cache/` (converted and built on first use, or
/// when the cache is stale or damaged; kept in memory when `.cache/` cannot be written),
/// the colour map's header checked but its pixels not read (`color` is `None`).
/// `threads` bound the hashing and the build; `progress(stage, done, total)` reports the
/// steps that take a while.
///
/// Order: the heightfield header, the `map` file, the heights, the colour map's header,
/// then the variance tree; the first problem found is returned.
pub fn open_cached(
    dir: &Path,
    threads: usize,
    progress: cache::Progress,
) -> Result<(Terrain, VarianceTree, CacheReport), DataError> {
    open_cached_with(dir, threads, cache::Verify::Full, progress)
}

/// [`open_cached`], re-hashing the cache files' values as `verify` says (`serve` trusts
/// the files re-hashed whole since they last changed: [`cache::Verify::Stamps`]).
pub fn open_cached_with(
    dir: &Path,
    threads: usize,
    verify: cache::Verify,
    progress: cache::Progress,
) -> Result<(Terrain, VarianceTree, CacheReport), DataError> {
    let map_path = dir.join(MAP_FILE);
    let hf_path = dir.join(HEIGHTS_FILE);
    let color_path = dir.join(COLOR_FILE);
    let header = pnm::read_pgm_header(&hf_path).map_err(|e| DataError::from_pnm(&hf_path, e))?;
    let side = header.width;
    let text = read_map_text(&map_path)?;
    let map = MapParams::parse(&text, side).map_err(|e| DataError::from_map(&map_path, e))?;

    let mut cache = Cache::new(dir, threads, verify);
    let (heights, heights_source, heights_hash) =
        cache.heights(&hf_path, side, &mut *progress, &mut |p| {
            let hf = pnm::read_pgm(&hf_path, &mut |n| {
                p(n, header.data_offset + header.data_len())
            })
            .map_err(|e| DataError::from_pnm(&hf_path, e))?;
            if hf.side() != side {
                return Err(DataError::Invalid {
                    file: hf_path.clone(),
                    line: None,
                    field: "width".into(),
                    message: format!(
                        "expected {side} (the file changed while loading), got {}",
                        hf.side()
                    ),
                });
            }
            Ok(hf)
        })?;
    pnm::read_ppm_header(&color_path, heights.size())
        .map_err(|e| DataError::from_pnm(&color_path, e))?;
    let (vt, variance_source) = cache.variance(&heights, &heights_hash, &mut *progress);
    cache.finish();
    let terrain = Terrain {
        map,
        heights,
        color: None,
    };
    let report = CacheReport {
        heights_hash,
        heights: heights_source,
        variance: variance_source,
        notes: cache.notes,
    };
    Ok((terrain, vt, report))
}

/// Where [`content_hash_cached`] took the data set's hash from.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum HashSource {
    /// `.cache/content.hash` vouched for it: neither `color.ppm` nor the heights were read.
    Cached,
    /// Computed now (the terrain held its colour map, or the cache did not vouch: the
    /// reason), and cached when `.cache/` could be written.
    Computed(String),
}

/// The cached data set hash's file inside `.cache/`.
pub const CONTENT_HASH_FILE: &str = "content.hash";
const CONTENT_MAGIC: &[u8; 8] = b"ROAMDSH\0";
/// Layout: magic, [`cache::VERSION`], 4 zero bytes, the content hash, the heights' hash
/// ([`CacheReport::heights_hash`]), blake3 of the `map` parameters as hashed, `color.ppm`'s
/// stamp, zeros, then blake3 of everything before (a damaged file is recomputed).
const CONTENT_LEN: usize = 256;
const CONTENT_CHECKED: usize = CONTENT_LEN - 32;

/// [`Terrain::content_hash_in`] of a terrain opened by [`open_cached`] (whose `report` it
/// is), through `dir/.cache/content.hash`: that file names the hash with what it was
/// computed from: the heights' hash (the heights served: `open_cached` checked them
/// against `hf.pgm`), the `map` parameters' hash and `color.ppm`'s [`cache::FileStamp`]
/// (length, mtime, ctime, inode, device). When all three match, the hash is taken from it
/// and no source file is read (a warm `serve` at 32769² read 5 GB for it); else it is
/// computed (streaming `color.ppm`) and written. A stamp written less than 2 s after
/// `color.ppm`'s ctime is not trusted (a write within the same clock tick would not show),
/// as `heights.stamp` is not. A `.cache/` that cannot be written only costs the hashing
/// at each start.
pub fn content_hash_cached(
    dir: &Path,
    terrain: &Terrain,
    report: &CacheReport,
    progress: &mut dyn FnMut(u64, u64),
) -> Result<([u8; 32], HashSource), DataError> {
    if terrain.color.is_some() {
        return Ok((
            terrain.content_hash(),
            HashSource::Computed("colour map in memory".into()),
        ));
    }
    let color_path = dir.join(COLOR_FILE);
    let stat = || -> Result<cache::FileStamp, DataError> {
        let meta = fs::metadata(&color_path).map_err(|error| DataError::Io {
            file: color_path.clone(),
            action: "stat",
            error,
        })?;
        Ok(cache::FileStamp::of(&meta))
    };
    let before = stat()?;
    let map_hash = *blake3::hash(terrain.map.to_toml().as_bytes()).as_bytes();
    let cache_dir = dir.join(cache::CACHE_DIR);
    let path = cache_dir.join(CONTENT_HASH_FILE);
    let why = match read_content_hash(&path, &report.heights_hash, &map_hash, before) {
        Ok(hash) => return Ok((hash, HashSource::Cached)),
        Err(why) => why.to_string(),
    };
    let hash = terrain.content_hash_in(dir, progress)?;
    if stat()? == before {
        let mut b = vec![0u8; CONTENT_LEN];
        b[..8].copy_from_slice(CONTENT_MAGIC);
        b[8..12].copy_from_slice(&cache::VERSION.to_le_bytes());
        b[16..48].copy_from_slice(&hash);
        b[48..80].copy_from_slice(&report.heights_hash);
        b[80..112].copy_from_slice(&map_hash);
        b[112..112 + cache::FileStamp::BYTES].copy_from_slice(&before.to_bytes());
        let check = *blake3::hash(&b[..CONTENT_CHECKED]).as_bytes();
        b[CONTENT_CHECKED..].copy_from_slice(&check);
        // Not cached when `.cache/` cannot be written: computed again next time.
        let _ = fs::create_dir_all(&cache_dir)
            .and_then(|()| cache::write_atomically(&cache_dir, CONTENT_HASH_FILE, &[&b]));
    }
    Ok((hash, HashSource::Computed(why)))
}

/// Why `.cache/content.hash` does not vouch for the data set's hash (it is computed
/// again, and the reason reported in [`HashSource::Computed`]).
#[derive(Debug, thiserror::Error)]
pub enum ContentHashError {
    #[error("not cached yet")]
    NotCached,
    /// The file could not be stat'd or read (`action`).
    #[error("{}: cannot {action}: {error}", file.display())]
    Io {
        file: PathBuf,
        action: &'static str,
        error: io::Error,
    },
    #[error("{}: length: expected {expected} bytes, got {got}", file.display())]
    Length {
        file: PathBuf,
        expected: usize,
        got: u64,
    },
    /// Shorter when read than when stat'd.
    #[error("{}: changed while read", file.display())]
    ChangedWhileRead { file: PathBuf },
    /// Its magic or format version is not this cache's.
    #[error("{}: magic or version: not this cache's", file.display())]
    Foreign { file: PathBuf },
    /// Its bytes do not match their check.
    #[error("{}: corrupt: its check does not match", file.display())]
    Corrupt { file: PathBuf },
    /// It names other heights than the data set's.
    #[error("the heights changed")]
    Heights,
    /// It names other `map` parameters.
    #[error("the map parameters changed")]
    Map,
    /// It names another `color.ppm` stamp.
    #[error("{COLOR_FILE} changed (length, times, inode or device)")]
    Color,
    /// It was written within `secs` of `color.ppm`'s change: a write in the same clock tick
    /// would not show.
    #[error("stamped within {secs} s of {COLOR_FILE}'s change")]
    Racy { secs: i64 },
}

/// The hash `.cache/content.hash` vouches for, or why it does not.
fn read_content_hash(
    path: &Path,
    heights_hash: &[u8; 32],
    map_hash: &[u8; 32],
    color: cache::FileStamp,
) -> Result<[u8; 32], ContentHashError> {
    let file = || path.to_path_buf();
    let io = |action| {
        move |error| ContentHashError::Io {
            file: file(),
            action,
            error,
        }
    };
    let meta = match fs::metadata(path) {
        Ok(m) => m,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Err(ContentHashError::NotCached),
        Err(e) => return Err(io("stat")(e)),
    };
    if meta.len() != CONTENT_LEN as u64 {
        return Err(ContentHashError::Length {
            file: file(),
            expected: CONTENT_LEN,
            got: meta.len(),
        });
    }
    let b = fs::read(path).map_err(io("read"))?;
    let (Some(body), Some(check)) = (b.get(..CONTENT_CHECKED), b.get(CONTENT_CHECKED..)) else {
        return Err(ContentHashError::ChangedWhileRead { file: file() });
    };
    if body[..8] != CONTENT_MAGIC[..] || body[8..12] != cache::VERSION.to_le_bytes() {
        return Err(ContentHashError::Foreign { file: file() });
    }
    if blake3::hash(body).as_bytes()[..] != check[..] {
        return Err(ContentHashError::Corrupt { file: file() });
    }
    let field = |at: usize| -> [u8; 32] {
        body[at..at + 32]
            .try_into()
            .expect("a 32-byte range of a 224-byte body")
    };
    let stamp = cache::FileStamp::from_bytes(
        body[112..112 + cache::FileStamp::BYTES]
            .try_into()
            .expect("a FileStamp::BYTES range of a 224-byte body"),
    );
    // When the file was written, by the file system's clock.
    let written = meta
        .modified()
        .ok()
        .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
        .map_or(0, |d| d.as_secs() as i64);
    if &field(48) != heights_hash {
        Err(ContentHashError::Heights)
    } else if &field(80) != map_hash {
        Err(ContentHashError::Map)
    } else if stamp != color {
        Err(ContentHashError::Color)
    } else if written < color.ctime_secs() + cache::RACY_SECONDS {
        Err(ContentHashError::Racy {
            secs: cache::RACY_SECONDS,
        })
    } else {
        Ok(field(16))
    }
}

/// Read `dir`'s colour map for a heightfield of `cells + 1` samples a side, validated as
/// [`load`] validates it. `progress(done, total)` gets the bytes read.
pub fn load_color(
    dir: &Path,
    cells: u32,
    progress: &mut dyn FnMut(u64, u64),
) -> Result<ColorMap, DataError> {
    let color_path = dir.join(COLOR_FILE);
    let total = file_len(&color_path);
    let rgb = pnm::read_ppm(&color_path, cells, &mut |n| progress(n, total))
        .map_err(|e| DataError::from_pnm(&color_path, e))?;
    ColorMap::new(cells, rgb).ok_or_else(|| DataError::Invalid {
        file: color_path.clone(),
        line: None,
        field: "data".into(),
        message: format!("expected {cells} × {cells} pixels"),
    })
}

/// Write `terrain` into `dir` (created if missing) as `map`, `hf.pgm` and `color.ppm`.
/// Refuses (with `InvalidInput`) a terrain whose parts do not fit together.
pub fn save(dir: &Path, terrain: &Terrain) -> io::Result<()> {
    terrain
        .validate()
        .map_err(|e| io::Error::new(io::ErrorKind::InvalidInput, e.to_string()))?;
    let Some(color) = &terrain.color else {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            "the terrain has no colour map (opened for serving): load it to save it",
        ));
    };
    fs::create_dir_all(dir)?;
    pnm::write_pgm(&dir.join(HEIGHTS_FILE), &terrain.heights)?;
    let cells = color.cells();
    pnm::write_ppm(&dir.join(COLOR_FILE), cells, cells, color.rgb())?;
    fs::write(dir.join(MAP_FILE), terrain.map.to_toml())
}
