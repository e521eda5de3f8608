//! SRTM `.hgt` tiles: a headerless square of big-endian `i16` heights in metres, 1201² (3
//! arc-seconds a sample) or 3601² (1″), rows north to south; −32768 marks a void.
//!
//! The tile's position is only in its name (`N07W006.hgt`: the south-west corner at 7°N
//! 6°W, so the tile spans 7°N … 8°N). From it the sample spacing in metres is derived:
//! [`METRES_PER_ARCSEC`] north–south, times the cosine of the latitude at the tile's centre
//! east–west. A tile whose name says nothing leaves the spacing to the caller.

use std::io::Read;
use std::path::Path;

use crate::terrain::raster::Raster;
use crate::terrain::source_error::SourceError;

/// Side of an SRTM3 (3″) tile.
pub const SRTM3_SIDE: u32 = 1201;
/// Side of an SRTM1 (1″) tile.
pub const SRTM1_SIDE: u32 = 3601;
/// Metres in one arc-second of latitude (and of longitude at the equator).
pub const METRES_PER_ARCSEC: f64 = 30.87;
/// The void marker.
pub const VOID: i16 = -32768;

/// File length of a tile of `side² ` samples.
pub fn len_of_side(side: u32) -> u64 {
    u64::from(side) * u64::from(side) * 2
}

/// The side of a tile whose file is `len` bytes long, if it is one.
pub fn side_of_len(len: u64) -> Option<u32> {
    [SRTM3_SIDE, SRTM1_SIDE]
        .into_iter()
        .find(|&s| len_of_side(s) == len)
}

/// A tile read from disk.
#[derive(Debug)]
pub struct Hgt {
    /// Heights in metres, voids as `NaN`.
    pub raster: Raster,
    /// Arc-seconds between samples: 3 or 1.
    pub arcsec: u32,
    /// Latitude of the tile's centre in degrees (north positive), from the file name.
    pub latitude: Option<f64>,
}

impl Hgt {
    /// Sample spacing east–west and north–south in metres, when the latitude is known.
    pub fn spacing(&self) -> Option<(f64, f64)> {
        let lat = self.latitude?;
        let dy = f64::from(self.arcsec) * METRES_PER_ARCSEC;
        Some((dy * lat.to_radians().cos(), dy))
    }
}

/// The latitude of the centre of the tile named like `N07W006` or `s12e130.hgt`.
pub fn tile_latitude(path: &Path) -> Option<f64> {
    let name = path.file_stem()?.to_str()?.to_ascii_uppercase();
    let b = name.as_bytes();
    if b.len() != 7 || !b[1..3].iter().chain(&b[4..7]).all(u8::is_ascii_digit) {
        return None;
    }
    let lat: f64 = name[1..3].parse().ok()?;
    let lon: f64 = name[4..7].parse().ok()?;
    if lon > 180.0 || !matches!(b[3], b'E' | b'W') {
        return None;
    }
    match b[0] {
        b'N' if lat <= 89.0 => Some(lat + 0.5),
        b'S' if (1.0..=90.0).contains(&lat) => Some(-lat + 0.5),
        _ => None,
    }
}

/// Read a tile. `progress` gets `(bytes read, bytes)`.
pub fn read(path: &Path, progress: &mut dyn FnMut(u64, u64)) -> Result<Hgt, SourceError> {
    let err = |m: String| SourceError::new(path, m);
    let mut file = std::fs::File::open(path).map_err(|e| err(format!("cannot open: {e}")))?;
    let len = file
        .metadata()
        .map_err(|e| err(format!("cannot stat: {e}")))?
        .len();
    let side = side_of_len(len).ok_or_else(|| {
        err(format!(
            "SRTM .hgt: expected {} bytes (1201² × 2) or {} bytes (3601² × 2), got {len}",
            len_of_side(SRTM3_SIDE),
            len_of_side(SRTM1_SIDE)
        ))
    })?;
    // At most 26 MB, and exactly the file's length.
    let mut bytes = vec![0u8; len as usize];
    let mut done = 0;
    for chunk in bytes.chunks_mut(1 << 20) {
        file.read_exact(chunk).map_err(|e| {
            err(format!(
                "SRTM .hgt: cannot read {len} bytes (the file shrank?): {e}"
            ))
        })?;
        done += chunk.len() as u64;
        progress(done, len);
    }
    let samples = bytes
        .chunks_exact(2)
        .map(|p| match i16::from_be_bytes([p[0], p[1]]) {
            VOID => f32::NAN,
            h => f32::from(h),
        })
        .collect();
    let raster = Raster::new(side, side, samples).map_err(|e| err(e.to_string()))?;
    Ok(Hgt {
        raster,
        arcsec: if side == SRTM3_SIDE { 3 } else { 1 },
        latitude: tile_latitude(path),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn latitudes_from_names() {
        for (name, want) in [
            ("N07W006.hgt", Some(7.5)),
            ("dir/s12e130.HGT", Some(-11.5)),
            ("N00E000.hgt", Some(0.5)),
            ("S90W180.hgt", Some(-89.5)),
            ("N90E000.hgt", None),
            ("S00E000.hgt", None),
            ("N07X006.hgt", None),
            ("N07W181.hgt", None),
            ("tile.hgt", None),
            ("N7W6.hgt", None),
        ] {
            assert_eq!(tile_latitude(Path::new(name)), want, "{name}");
        }
        assert_eq!(side_of_len(2_884_802), Some(1201));
        assert_eq!(side_of_len(25_934_402), Some(3601));
        assert_eq!(side_of_len(2_884_801), None);
    }
}
