//! Source files for `import`: which format a file holds (by content, never by its name).
//! This and the readers ([`crate::terrain::png16`], [`crate::terrain::hgt`],
//! [`crate::terrain::geotiff`], [`crate::terrain::colorimage`]) return a
//! [`SourceError`] naming the file and what is wrong with it.
//!
//! Detection reads the first bytes: `\x89PNG` is a PNG, `P5` a binary PGM, `II*\0` /
//! `MM\0*` (or BigTIFF's `II+\0` / `MM\0+`) a (Geo)TIFF; otherwise a file of exactly
//! 1201² × 2 or 3601² × 2 bytes is an SRTM `.hgt` tile (they carry no header).

use std::io::Read;
use std::path::Path;

use crate::terrain::source_error::SourceError;
use crate::terrain::{geotiff, hgt};

/// The formats `import` reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    /// Binary PGM (`P5`), side 2^N + 1.
    Pgm,
    /// PNG: 16-bit greyscale, or 8-bit RGB(A) Terrarium / Mapbox Terrain-RGB.
    Png,
    /// SRTM `.hgt`: 1201² or 3601² big-endian `i16`, −32768 a void.
    Hgt,
    /// GeoTIFF (or plain TIFF): one greyscale integer or float sample a pixel.
    GeoTiff,
}

/// The format of `path`, from its content and size.
pub fn detect(path: &Path) -> Result<Format, SourceError> {
    let mut file = std::fs::File::open(path)
        .map_err(|e| SourceError::new(path, format!("cannot open: {e}")))?;
    let meta = file
        .metadata()
        .map_err(|e| SourceError::new(path, format!("cannot stat: {e}")))?;
    if !meta.is_file() {
        return Err(SourceError::new(path, "not a regular file"));
    }
    let mut magic = Vec::with_capacity(8);
    (&mut file)
        .take(8)
        .read_to_end(&mut magic)
        .map_err(|e| SourceError::new(path, format!("cannot read: {e}")))?;
    if magic.starts_with(b"\x89PNG") {
        Ok(Format::Png)
    } else if magic.starts_with(b"P5") {
        Ok(Format::Pgm)
    } else if geotiff::is_tiff(&magic) {
        Ok(Format::GeoTiff)
    } else if hgt::side_of_len(meta.len()).is_some() {
        Ok(Format::Hgt)
    } else {
        Err(SourceError::new(
            path,
            format!(
                "not a PGM, PNG, GeoTIFF or SRTM .hgt file: no PGM, PNG or TIFF signature, \
                 and {} bytes is not the size of a .hgt tile ({} or {})",
                meta.len(),
                hgt::len_of_side(hgt::SRTM3_SIDE),
                hgt::len_of_side(hgt::SRTM1_SIDE)
            ),
        ))
    }
}
