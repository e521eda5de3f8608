//! A file's identity on disk ([`FileStamp`]: length, mtime, ctime, inode, device), by which
//! the data set's cache tells that a source file or a cache file is the one it hashed
//! without reading it again, and the little-endian field reader of the cache's headers.
//! Any write to a file sets its ctime, which no program can set back, so a changed file
//! never keeps its stamp; a copy is a new inode.

use std::fs;
#[cfg(not(unix))]
use std::io;

/// A source file's identity on disk (`hf.pgm` when it was hashed; `color.ppm` when its
/// tiles were coded, see `color_pyramid`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct FileStamp {
    pub(crate) len: u64,
    pub(crate) mtime: (i64, i64),
    pub(crate) ctime: (i64, i64),
    pub(crate) ino: u64,
    pub(crate) dev: u64,
}

impl FileStamp {
    /// One number for the whole stamp (a blake3 of its fields), to keep in a header.
    pub(crate) fn digest(&self) -> u64 {
        let mut h = blake3::Hasher::new();
        h.update(&self.len.to_le_bytes());
        for v in [self.mtime.0, self.mtime.1, self.ctime.0, self.ctime.1] {
            h.update(&v.to_le_bytes());
        }
        h.update(&self.ino.to_le_bytes());
        h.update(&self.dev.to_le_bytes());
        let b = h.finalize();
        u64::from_le_bytes(
            b.as_bytes()[..8]
                .try_into()
                .expect("a blake3 hash is 32 bytes"),
        )
    }

    pub(crate) fn len(&self) -> u64 {
        self.len
    }

    /// The ctime's whole seconds (for the racy-stamp rule).
    pub(crate) fn ctime_secs(&self) -> i64 {
        self.ctime.0
    }

    /// Bytes in [`FileStamp::to_bytes`].
    pub(crate) const BYTES: usize = 56;

    /// The fields, little-endian: length, mtime, ctime (seconds, nanoseconds), inode, device.
    pub(crate) fn to_bytes(self) -> [u8; Self::BYTES] {
        let mut b = [0u8; Self::BYTES];
        let fields = [
            self.len,
            self.mtime.0 as u64,
            self.mtime.1 as u64,
            self.ctime.0 as u64,
            self.ctime.1 as u64,
            self.ino,
            self.dev,
        ];
        for (out, v) in b.chunks_exact_mut(8).zip(fields) {
            out.copy_from_slice(&v.to_le_bytes());
        }
        b
    }

    /// The inverse of [`FileStamp::to_bytes`].
    pub(crate) fn from_bytes(b: &[u8; Self::BYTES]) -> FileStamp {
        let mut f = Fields(b);
        FileStamp {
            len: f.u64(),
            mtime: (f.i64(), f.i64()),
            ctime: (f.i64(), f.i64()),
            ino: f.u64(),
            dev: f.u64(),
        }
    }

    pub(crate) fn of(meta: &fs::Metadata) -> FileStamp {
        #[cfg(unix)]
        {
            use std::os::unix::fs::MetadataExt;
            FileStamp {
                len: meta.len(),
                mtime: (meta.mtime(), meta.mtime_nsec()),
                ctime: (meta.ctime(), meta.ctime_nsec()),
                ino: meta.ino(),
                dev: meta.dev(),
            }
        }
        #[cfg(not(unix))]
        {
            let since = |t: io::Result<std::time::SystemTime>| {
                t.ok()
                    .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
                    .map_or((0, 0), |d| {
                        (d.as_secs() as i64, i64::from(d.subsec_nanos()))
                    })
            };
            FileStamp {
                len: meta.len(),
                mtime: since(meta.modified()),
                ctime: since(meta.modified()),
                ino: 0,
                dev: 0,
            }
        }
    }
}

/// Little-endian field reader over a header.
pub(crate) struct Fields<'a>(pub(crate) &'a [u8]);

impl Fields<'_> {
    pub(crate) fn bytes<const N: usize>(&mut self) -> [u8; N] {
        let (head, rest) = self.0.split_at(N);
        self.0 = rest;
        head.try_into().expect("split_at gave exactly N bytes")
    }
    pub(crate) fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.bytes())
    }
    pub(crate) fn u64(&mut self) -> u64 {
        u64::from_le_bytes(self.bytes())
    }
    pub(crate) fn i64(&mut self) -> i64 {
        i64::from_le_bytes(self.bytes())
    }
}
