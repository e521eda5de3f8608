//! Why a file of the data set's cache (`heights.bin`, `variance.bin`: `cache.rs`) is not
//! used: [`CacheError`], and [`MapError`] for a checked file that cannot be mapped. The
//! cache notes each (after the file's path) and rebuilds the file; the words are what
//! `CacheReport::notes` and the tests read.

use std::io;
use std::path::PathBuf;

use crate::terrain::backing::BackingError;
use crate::terrain::heightfield::ShapeError;
use crate::terrain::variance::CodesError;

/// Why a cache file is rejected (and rebuilt). The file's path is the note's, not this.
#[derive(Debug, thiserror::Error)]
pub enum CacheError {
    /// The file could not be opened, stat'd or read (`action`: `open`, `stat`,
    /// `read the header`).
    #[error("cannot {action}: {error}")]
    Io {
        action: &'static str,
        error: io::Error,
    },
    /// Shorter than the header every cache file starts with.
    #[error("truncated: expected at least a {expected}-byte header, got {got} bytes")]
    ShortHeader { expected: usize, got: u64 },
    /// Another program's file, or another cache file.
    #[error(
        "magic: expected {:?}, got {:?}: not this cache's file",
        String::from_utf8_lossy(.expected),
        String::from_utf8_lossy(.got)
    )]
    Magic { expected: [u8; 8], got: [u8; 8] },
    /// Written by another version of this cache.
    #[error("format version: expected {expected}, got {got}")]
    Version { expected: u32, got: u32 },
    /// `heights.bin`'s side (and sample count) is not `hf.pgm`'s.
    #[error("side: expected {expected} (hf.pgm's), got {got} ({samples} samples)")]
    HeightsSide {
        expected: u32,
        got: u32,
        samples: u64,
    },
    /// `variance.bin`'s side is not the heights'.
    #[error("side: expected {expected} (the heights'), got {got}")]
    VarianceSide { expected: u64, got: u64 },
    /// The file's length is not its header's and its values' (`codes`: how many codes
    /// the length is for, in `variance.bin`).
    #[error(
        "length: expected {expected} bytes{}, got {got}{}",
        codes.map(|c| format!(" ({c} codes)")).unwrap_or_default(),
        if got < expected { " (truncated)" } else { "" }
    )]
    Length {
        expected: u64,
        codes: Option<u64>,
        got: u64,
    },
    /// `variance.bin` was coded with another table of error bounds.
    #[error("code table: built with another table")]
    CodeTable,
    /// `hf.pgm` could not be read to hash it.
    #[error("cannot hash {}: {error}", file.display())]
    Hash { file: PathBuf, error: io::Error },
    /// `hf.pgm` is not what `heights.bin` was converted from.
    #[error(
        "stale: {} changed since the cache was built (content hash differs)",
        file.display()
    )]
    SourceChanged { file: PathBuf },
    /// `variance.bin` was built from other heights than those mapped.
    #[error("stale: built from other heights (heights hash differs)")]
    OtherHeights,
    /// The values re-hashed whole (`the samples`, `the codes`) do not match the header's
    /// hash.
    #[error("corrupt: {0} do not match their hash")]
    Corrupt(&'static str),
    /// A checked file could not be mapped.
    #[error("cannot map: {0}")]
    Map(#[source] MapError),
    /// Another process renamed its own file over the one just written, and it holds
    /// other values (`other heights`, `another tree`).
    #[error("replaced by {0} meanwhile")]
    Replaced(&'static str),
}

/// Why a checked cache file cannot be mapped as the values it holds.
#[derive(Debug, thiserror::Error)]
pub enum MapError {
    /// The map itself failed.
    #[error("{0}")]
    Mmap(io::Error),
    #[error(transparent)]
    Values(#[from] BackingError),
    #[error(transparent)]
    Heights(#[from] ShapeError),
    #[error(transparent)]
    Codes(#[from] CodesError),
    /// Fewer bytes than the values (read on a big-endian machine, which converts them).
    #[error("truncated")]
    Truncated,
}
