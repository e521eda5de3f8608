//! Where the big arrays of a data set live: owned memory (generate, import, `load`, tests)
//! or a read-only memory map of a cache file (`serve`, `check`, `bench`; see
//! [`crate::terrain::cache`]).
//!
//! - **One type, a slice out.** [`Backing<T>`] derefs to `&[T]`; the heightfield and the
//!   variance tree keep one and their public API does not change. The tessellator takes the
//!   slices once per frame (`Heightfield::samples`, `VarianceTree::codes`), so the branch on
//!   the variant is not on its per-triangle path. Measured with `roam-server bench
//!   data/kossou` (1025², measure profile, 300 frames, fly-over, three runs each,
//!   alternated, on 2 cores shared with other builds), ns per triangle: before (`Vec`)
//!   25.5 / 25.8 / 25.7; mapped 25.7 / 26.6 / 26.4; owned `Backing` 25.5 / 26.4 / 25.2.
//!   Within the machine's noise; mapped may cost ~2 % (4 KiB pages of the page cache).
//! - **Shared between processes.** A map is `MAP_SHARED` and read-only: two servers on one
//!   data set share the page cache's copy; the pages count in each one's RSS but only once
//!   in the machine's memory.
//! - **No unsafe of our own beyond the map.** Mapped bytes are viewed as `[T]` with
//!   `bytemuck`, whose alignment and length are checked once when the backing is made (the
//!   map is page-aligned; the cache's headers keep samples aligned), so the view cannot
//!   fail later.

use std::fmt;
use std::sync::Arc;

use memmap2::Mmap;

/// A read-only array of plain values, owned or mapped from a file.
pub enum Backing<T> {
    /// In memory.
    Owned(Vec<T>),
    /// `len` values starting `offset` bytes into a read-only map.
    Mapped {
        map: Arc<Mmap>,
        offset: usize,
        len: usize,
    },
}

/// Why a map's bytes cannot be viewed as the values asked for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum BackingError {
    /// The values reach past the map's end (or past `usize`).
    #[error(
        "expected {len} values of {size} bytes at offset {offset}, the file has {file_len} bytes"
    )]
    Range {
        len: usize,
        /// Bytes a value.
        size: usize,
        offset: usize,
        file_len: usize,
    },
    /// The bytes cannot be viewed as values: misaligned.
    #[error("values at offset {offset}: {error}")]
    Cast {
        offset: usize,
        error: bytemuck::PodCastError,
    },
}

impl<T: bytemuck::Pod> Backing<T> {
    /// `len` values of `T` at byte `offset` of `map`, or why not (out of range, misaligned).
    pub fn mapped(map: Arc<Mmap>, offset: usize, len: usize) -> Result<Backing<T>, BackingError> {
        let bytes = len
            .checked_mul(size_of::<T>())
            .and_then(|n| n.checked_add(offset))
            .filter(|&end| end <= map.len())
            .ok_or(BackingError::Range {
                len,
                size: size_of::<T>(),
                offset,
                file_len: map.len(),
            })?;
        bytemuck::try_cast_slice::<u8, T>(&map[offset..bytes])
            .map_err(|error| BackingError::Cast { offset, error })?;
        Ok(Backing::Mapped { map, offset, len })
    }

    /// The values.
    #[inline]
    pub fn as_slice(&self) -> &[T] {
        match self {
            Backing::Owned(v) => v,
            Backing::Mapped { map, offset, len } => {
                bytemuck::cast_slice(&map[*offset..*offset + *len * size_of::<T>()])
            }
        }
    }

    /// Whether the values are in a file's map rather than owned memory.
    pub fn is_mapped(&self) -> bool {
        matches!(self, Backing::Mapped { .. })
    }

    /// Bytes on the heap (0 when mapped).
    pub fn heap_bytes(&self) -> usize {
        match self {
            Backing::Owned(v) => v.capacity() * size_of::<T>(),
            Backing::Mapped { .. } => 0,
        }
    }

    /// Bytes of the values, wherever they are: what they take once all are resident.
    pub fn bytes(&self) -> usize {
        match self {
            Backing::Owned(v) => v.capacity() * size_of::<T>(),
            Backing::Mapped { len, .. } => len * size_of::<T>(),
        }
    }
}

impl<T: bytemuck::Pod> std::ops::Deref for Backing<T> {
    type Target = [T];

    #[inline]
    fn deref(&self) -> &[T] {
        self.as_slice()
    }
}

impl<T: Clone> Clone for Backing<T> {
    fn clone(&self) -> Self {
        match self {
            Backing::Owned(v) => Backing::Owned(v.clone()),
            Backing::Mapped { map, offset, len } => Backing::Mapped {
                map: map.clone(),
                offset: *offset,
                len: *len,
            },
        }
    }
}

impl<T> fmt::Debug for Backing<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Backing::Owned(v) => write!(f, "Owned({} values)", v.len()),
            Backing::Mapped { offset, len, .. } => {
                write!(f, "Mapped({len} values at offset {offset})")
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map_of(bytes: &[u8]) -> Arc<Mmap> {
        let path = std::env::temp_dir().join(format!(
            "roam-backing-test-{}-{}",
            std::process::id(),
            bytes.len()
        ));
        std::fs::write(&path, bytes).expect("write the temp file");
        let file = std::fs::File::open(&path).expect("open the temp file");
        // SAFETY: the file is ours, in a fresh path, and nothing writes it while mapped.
        let map = unsafe { Mmap::map(&file) }.expect("map the temp file");
        let _ = std::fs::remove_file(&path);
        Arc::new(map)
    }

    #[test]
    fn mapped_values_are_read_in_place_and_checked() {
        let map = map_of(&[9, 9, 1, 0, 2, 0, 3, 0]);
        let b = Backing::<u16>::mapped(map.clone(), 2, 3).expect("in range and aligned");
        assert_eq!(&*b, &[1, 2, 3]);
        assert!(b.is_mapped());
        assert_eq!((b.bytes(), b.heap_bytes()), (6, 0));
        let range = |offset, len| BackingError::Range {
            len,
            size: 2,
            offset,
            file_len: 8,
        };
        for (offset, len, want, message) in [
            (
                2,
                4,
                range(2, 4),
                "expected 4 values of 2 bytes at offset 2, the file has 8 bytes",
            ),
            (
                usize::MAX,
                2,
                range(usize::MAX, 2),
                "expected 2 values of 2 bytes at offset 18446744073709551615, the file has 8 bytes",
            ),
            (
                1,
                2,
                BackingError::Cast {
                    offset: 1,
                    error: bytemuck::PodCastError::TargetAlignmentGreaterAndInputNotAligned,
                },
                "values at offset 1: TargetAlignmentGreaterAndInputNotAligned",
            ),
        ] {
            let Err(got) = Backing::<u16>::mapped(map.clone(), offset, len) else {
                panic!("{message}: values past the end, past usize or misaligned taken");
            };
            assert_eq!((got, got.to_string().as_str()), (want, message));
        }
        let owned = Backing::Owned(vec![1u16, 2, 3]);
        assert_eq!(&*owned, &*b);
        assert!(!owned.is_mapped());
    }
}
