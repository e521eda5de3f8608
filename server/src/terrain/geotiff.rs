//! GeoTIFF heightfields, read with the `tiff` crate: the first image of a TIFF or BigTIFF,
//! one greyscale sample per pixel of `i16`, `u16`, `i32`, `u32`, `f32` or `f64`, in strips
//! or tiles, uncompressed or PackBits / LZW / Deflate compressed. Anything else (RGB,
//! separate planes, 8-bit or 64-bit integer samples, JPEG compression, …) is refused with a
//! message naming what the file holds.
//!
//! The GeoTIFF tags are read here, not through another crate; they are small:
//! - `GDAL_NODATA` (42113), an ASCII number: samples equal to it are voids, as are
//!   non-finite float samples.
//! - `ModelPixelScaleTag` (33550) gives the sample spacing; `GeoKeyDirectoryTag` (34735)
//!   says whether it is in a projected unit (`GTModelTypeGeoKey` 1: metres, feet or US
//!   survey feet by `ProjLinearUnitsGeoKey`, metres when unsaid) or in degrees (2). A
//!   geographic raster is converted with the convention `.hgt` tiles use
//!   ([`hgt::METRES_PER_ARCSEC`] north–south, times the cosine of the latitude east–west),
//!   at the latitude of the raster's centre from `ModelTiepointTag` (33922). The tiepoint
//!   names a pixel's corner, or its centre when `GTRasterTypeGeoKey` (1025) is 2
//!   (`PixelIsPoint`, as in USGS SRTM GeoTIFFs: `n07_w006_3arc_v2.tif` ties pixel (0, 0) to
//!   8°N, and its 1201 rows are centred on 7.5°N, not half a row further south).
//!   Georeferencing that is missing or not understood leaves the spacing to the caller,
//!   with the reason.
//! - `VerticalUnitsGeoKey` (4099): feet and US survey feet are converted to metres; heights
//!   are otherwise taken as metres.
//!
//! Nothing is trusted before it is checked: sides above 32769 are refused from the tags,
//! before any image data is decoded; a raster whose raw samples could not come out of a
//! file this small (the file's size for an uncompressed one, [`MAX_EXPANSION`] times it for
//! a compressed one) is refused as truncated or corrupt; and the decoder runs under an
//! allocation limit of a 32769² raster of 8-byte samples. The image is decoded strip by
//! strip (or tile by tile), each chunk converted to metres and placed as it comes: progress
//! is reported per chunk, and besides the `f32` raster only one chunk is held at a time.

use std::fs::File;
use std::io::BufReader;
use std::path::Path;

use tiff::decoder::{ChunkType, Decoder, DecodingResult, Limits};
use tiff::tags::Tag;

use crate::terrain::hgt::METRES_PER_ARCSEC;
use crate::terrain::raster::{MAX_SIDE, Raster};
use crate::terrain::source_error::SourceError;

/// Most raw bytes one compressed byte is taken to decode to (LZW reaches about 2730 : 1,
/// Deflate 1032 : 1, PackBits 64 : 1).
pub const MAX_EXPANSION: u64 = 4096;
/// The decoder's allocation limit: a 32769² raster of 8-byte samples.
const LIMIT_BYTES: u64 = (MAX_SIDE as u64) * (MAX_SIDE as u64) * 8;

const GDAL_NODATA: u16 = 42113;
const MODEL_PIXEL_SCALE: u16 = 33550;
const MODEL_TIEPOINT: u16 = 33922;
const GEO_KEY_DIRECTORY: u16 = 34735;
const GT_MODEL_TYPE: u16 = 1024;
const GT_RASTER_TYPE: u16 = 1025;
const GEOG_ANGULAR_UNITS: u16 = 2054;
const PROJ_LINEAR_UNITS: u16 = 3076;
const VERTICAL_UNITS: u16 = 4099;

/// Metres in one unit of an EPSG linear unit code, with the unit's name.
fn linear_unit(code: u16) -> Option<(f64, &'static str)> {
    match code {
        9001 => Some((1.0, "metre")),
        9002 => Some((0.3048, "foot")),
        9003 => Some((1200.0 / 3937.0, "US survey foot")),
        _ => None,
    }
}

/// How far apart the samples are, as far as the file says.
#[derive(Clone, Debug, PartialEq)]
pub enum Georef {
    /// A projected raster: metres east–west and north–south, and the unit it was given in.
    Projected {
        dx: f64,
        dy: f64,
        unit: &'static str,
    },
    /// A geographic raster: metres east–west and north–south at `latitude` (degrees, the
    /// raster's centre).
    Geographic { dx: f64, dy: f64, latitude: f64 },
    /// Missing or not understood; why.
    Unknown(String),
}

/// What a GeoTIFF held.
#[derive(Debug)]
pub struct GeoTiff {
    /// Heights in metres, voids as `NaN`.
    pub raster: Raster,
    /// "GeoTIFF, 32-bit float samples, LZW, tiles"
    pub kind: String,
    pub georef: Georef,
    /// The `GDAL_NODATA` value, if any.
    pub nodata: Option<f64>,
    /// How heights were taken: "metres (assumed: no VerticalUnitsGeoKey)", …
    pub vertical: String,
}

#[derive(Clone, Copy, Debug)]
enum Sample {
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Sample {
    fn bytes(self) -> u64 {
        match self {
            Sample::I16 | Sample::U16 => 2,
            Sample::I32 | Sample::U32 | Sample::F32 => 4,
            Sample::F64 => 8,
        }
    }

    fn name(self) -> &'static str {
        match self {
            Sample::I16 => "16-bit signed integer",
            Sample::U16 => "16-bit unsigned integer",
            Sample::I32 => "32-bit signed integer",
            Sample::U32 => "32-bit unsigned integer",
            Sample::F32 => "32-bit float",
            Sample::F64 => "64-bit float",
        }
    }
}

/// Whether `magic` (the file's first bytes) opens a TIFF or BigTIFF.
pub fn is_tiff(magic: &[u8]) -> bool {
    [b"II*\0", b"MM\0*", b"II+\0", b"MM\0+"]
        .iter()
        .any(|m| magic.starts_with(*m))
}

/// The GeoKeyDirectory's short-valued keys, as `(key, value)`.
fn geo_keys(dir: &[u16]) -> Vec<(u16, u16)> {
    let Some(&count) = dir.get(3) else {
        return Vec::new();
    };
    dir.get(4..)
        .unwrap_or_default()
        .chunks_exact(4)
        .take(usize::from(count))
        .filter(|e| e[1] == 0 && e[2] == 1)
        .map(|e| (e[0], e[3]))
        .collect()
}

/// The sample spacing from the pixel scale, tiepoint and geo keys of a `width × height`
/// raster.
fn georef(
    scale: Option<Vec<f64>>,
    tiepoint: Option<Vec<f64>>,
    keys: &[(u16, u16)],
    height: u32,
) -> Georef {
    let key = |k: u16| keys.iter().find(|(id, _)| *id == k).map(|&(_, v)| v);
    let Some(scale) = scale else {
        return Georef::Unknown("no ModelPixelScaleTag".into());
    };
    let (sx, sy) = match scale[..] {
        [sx, sy, ..] if sx.is_finite() && sy.is_finite() && sx > 0.0 && sy > 0.0 => (sx, sy),
        _ => {
            return Georef::Unknown(format!(
                "ModelPixelScaleTag {scale:?}: expected two numbers > 0"
            ));
        }
    };
    match key(GT_MODEL_TYPE) {
        Some(1) => {
            let (factor, unit) = match key(PROJ_LINEAR_UNITS) {
                None => (1.0, "metre (assumed: no ProjLinearUnitsGeoKey)"),
                Some(code) => match linear_unit(code) {
                    Some(u) => u,
                    None => {
                        return Georef::Unknown(format!(
                            "ProjLinearUnitsGeoKey {code}: expected 9001 (metre), 9002 (foot) \
                             or 9003 (US survey foot)"
                        ));
                    }
                },
            };
            Georef::Projected {
                dx: sx * factor,
                dy: sy * factor,
                unit,
            }
        }
        Some(2) => {
            if let Some(code) = key(GEOG_ANGULAR_UNITS)
                && code != 9102
            {
                return Georef::Unknown(format!(
                    "GeogAngularUnitsGeoKey {code}: expected 9102 (degree)"
                ));
            }
            let Some(&[_, j, _, _, y, ..]) = tiepoint.as_deref() else {
                return Georef::Unknown(
                    "a geographic raster without a ModelTiepointTag: its latitude is unknown"
                        .into(),
                );
            };
            // Raster coordinates count pixel corners; a PixelIsPoint tiepoint is a centre.
            let centre_of_tie = if key(GT_RASTER_TYPE) == Some(2) {
                0.5
            } else {
                0.0
            };
            let latitude = y - (f64::from(height) / 2.0 - j - centre_of_tie) * sy;
            if !latitude.is_finite() || latitude.abs() >= 90.0 {
                return Georef::Unknown(format!(
                    "a geographic raster centred at latitude {latitude}°: expected one \
                     between −90° and 90°"
                ));
            }
            let dy = sy * 3600.0 * METRES_PER_ARCSEC;
            let dx = sx * 3600.0 * METRES_PER_ARCSEC * latitude.to_radians().cos();
            Georef::Geographic { dx, dy, latitude }
        }
        Some(t) => Georef::Unknown(format!(
            "GTModelTypeGeoKey {t}: expected 1 (projected) or 2 (geographic)"
        )),
        None => Georef::Unknown("no GTModelTypeGeoKey".into()),
    }
}

/// Read the first image of a GeoTIFF. `progress` gets `(steps done, steps)`.
pub fn read(path: &Path, progress: &mut dyn FnMut(u64, u64)) -> Result<GeoTiff, SourceError> {
    let err = |m: String| SourceError::new(path, m);
    let file = File::open(path).map_err(|e| err(format!("cannot open: {e}")))?;
    let file_len = file
        .metadata()
        .map_err(|e| err(format!("cannot stat: {e}")))?
        .len();
    let mut limits = Limits::default();
    limits.decoding_buffer_size = usize::try_from(LIMIT_BYTES).unwrap_or(usize::MAX);
    let mut decoder = Decoder::new(BufReader::new(file))
        .map_err(|e| err(format!("TIFF header: {e}")))?
        .with_limits(limits);
    let (width, height) = decoder
        .dimensions()
        .map_err(|e| err(format!("TIFF header: {e}")))?;
    if width > MAX_SIDE || height > MAX_SIDE {
        return Err(err(format!(
            "TIFF of {width} × {height} pixels: expected at most {MAX_SIDE} on each side"
        )));
    }
    let tag_err = |tag: &str, e: tiff::TiffError| err(format!("TIFF tag {tag}: {e}"));
    let short = |d: &mut Decoder<_>, tag: Tag, name: &str, default: u16| {
        d.find_tag_unsigned::<u16>(tag)
            .map(|v| v.unwrap_or(default))
            .map_err(|e| tag_err(name, e))
    };
    let samples_per_pixel = short(&mut decoder, Tag::SamplesPerPixel, "SamplesPerPixel", 1)?;
    let planar = short(
        &mut decoder,
        Tag::PlanarConfiguration,
        "PlanarConfiguration",
        1,
    )?;
    let photometric = short(
        &mut decoder,
        Tag::PhotometricInterpretation,
        "PhotometricInterpretation",
        1,
    )?;
    if samples_per_pixel != 1 || !matches!(photometric, 0 | 1) {
        let layout = if planar == 2 {
            "planes stored separately"
        } else {
            "samples interleaved"
        };
        return Err(err(format!(
            "TIFF of {samples_per_pixel} samples a pixel ({layout}), photometric \
             interpretation {photometric}: expected one greyscale sample a pixel"
        )));
    }
    let bits = decoder
        .find_tag_unsigned_vec::<u16>(Tag::BitsPerSample)
        .map_err(|e| tag_err("BitsPerSample", e))?
        .and_then(|v| v.first().copied())
        .unwrap_or(1);
    let format = decoder
        .find_tag_unsigned_vec::<u16>(Tag::SampleFormat)
        .map_err(|e| tag_err("SampleFormat", e))?
        .and_then(|v| v.first().copied())
        .unwrap_or(1);
    let sample = match (format, bits) {
        (1, 16) => Sample::U16,
        (2, 16) => Sample::I16,
        (1, 32) => Sample::U32,
        (2, 32) => Sample::I32,
        (3, 32) => Sample::F32,
        (3, 64) => Sample::F64,
        _ => {
            let kind = match format {
                1 => "unsigned integer",
                2 => "signed integer",
                3 => "float",
                _ => "unknown format",
            };
            return Err(err(format!(
                "TIFF of {bits}-bit {kind} samples (SampleFormat {format}): expected 16- or \
                 32-bit integers, or 32- or 64-bit floats"
            )));
        }
    };
    let compression = short(&mut decoder, Tag::Compression, "Compression", 1)?;
    let (compression_name, expansion) = match compression {
        1 => ("uncompressed", 1),
        5 => ("LZW", MAX_EXPANSION),
        8 | 32946 => ("Deflate", MAX_EXPANSION),
        32773 => ("PackBits", MAX_EXPANSION),
        c => {
            let name = match c {
                2..=4 => "CCITT fax",
                6 | 7 => "JPEG",
                34887 => "LERC",
                34925 => "LZMA",
                50000 => "Zstandard",
                50001 => "WebP",
                _ => "unknown",
            };
            return Err(err(format!(
                "TIFF compressed with {name} (Compression {c}): expected uncompressed, LZW, \
                 Deflate or PackBits"
            )));
        }
    };
    let raw = u64::from(width) * u64::from(height) * sample.bytes();
    if raw > file_len.saturating_mul(expansion) {
        return Err(err(format!(
            "TIFF of {width} × {height} {} samples ({raw} bytes raw, {compression_name}) \
             cannot fit in {file_len} bytes: the file is truncated or corrupt",
            sample.name()
        )));
    }
    let layout = match decoder.get_chunk_type() {
        ChunkType::Strip => "strips",
        ChunkType::Tile => "tiles",
    };
    let nodata = match decoder
        .find_tag(Tag::Unknown(GDAL_NODATA))
        .map_err(|e| tag_err("GDAL_NODATA", e))?
    {
        None => None,
        Some(v) => {
            let text = v.into_string().map_err(|e| tag_err("GDAL_NODATA", e))?;
            let text = text.trim_matches(|c: char| c == '\0' || c.is_whitespace());
            let value = text.parse::<f64>().map_err(|_| {
                err(format!(
                    "TIFF tag GDAL_NODATA: expected a number, got {text:?}"
                ))
            })?;
            Some(value)
        }
    };
    let doubles = |d: &mut Decoder<_>, tag: u16, name: &str| -> Result<_, SourceError> {
        d.find_tag(Tag::Unknown(tag))
            .and_then(|v| v.map(|v| v.into_f64_vec()).transpose())
            .map_err(|e| tag_err(name, e))
    };
    let scale = doubles(&mut decoder, MODEL_PIXEL_SCALE, "ModelPixelScaleTag")?;
    let tiepoint = doubles(&mut decoder, MODEL_TIEPOINT, "ModelTiepointTag")?;
    let keys = decoder
        .find_tag_unsigned_vec::<u16>(Tag::Unknown(GEO_KEY_DIRECTORY))
        .map_err(|e| tag_err("GeoKeyDirectoryTag", e))?
        .map(|dir| geo_keys(&dir))
        .unwrap_or_default();
    let georef = georef(scale, tiepoint, &keys, height);
    let vertical_code = keys
        .iter()
        .find(|(k, _)| *k == VERTICAL_UNITS)
        .map(|&(_, v)| v);
    let (z_factor, vertical) = match vertical_code.map(|c| (c, linear_unit(c))) {
        None => (1.0, "metres (assumed: no VerticalUnitsGeoKey)".to_string()),
        Some((_, Some((f, "metre")))) => (f, "metres (VerticalUnitsGeoKey)".to_string()),
        Some((c, Some((f, name)))) => (
            f,
            format!("in {name} (VerticalUnitsGeoKey {c}), converted to metres"),
        ),
        Some((c, None)) => (
            1.0,
            format!("metres (assumed: VerticalUnitsGeoKey {c} is not a unit this reads)"),
        ),
    };

    let samples = read_chunks(
        &mut decoder,
        width,
        height,
        sample,
        nodata,
        z_factor,
        progress,
    )
    .map_err(|m| err(format!("TIFF data: {m}")))?;
    let raster = Raster::new(width, height, samples).map_err(|e| err(e.to_string()))?;
    Ok(GeoTiff {
        raster,
        kind: format!(
            "GeoTIFF, {} samples, {compression_name}, {layout}",
            sample.name()
        ),
        georef,
        nodata,
        vertical,
    })
}

/// Why a GeoTIFF's samples cannot be read (after "TIFF data: ").
#[derive(Debug, thiserror::Error)]
enum ChunkError {
    #[error("chunks of {width} × {height} pixels: expected at least 1 × 1")]
    Empty { width: u32, height: u32 },
    /// The decoder's own error: counting the chunks, or decoding one.
    #[error(transparent)]
    Tiff(#[from] tiff::TiffError),
    /// The file lists fewer chunks (`what`: `tiles`, `strips`) than the image needs.
    #[error("expected {needed} {what} for {width} × {height} pixels, the file lists {listed}")]
    Listed {
        needed: u64,
        what: &'static str,
        width: u32,
        height: u32,
        listed: u32,
    },
    #[error("{needed} chunks: too many")]
    TooMany { needed: u64 },
    #[error("cannot allocate {samples} samples")]
    Alloc { samples: usize },
    /// A chunk decoded as another sample type than the tags say (`tags`).
    #[error("decoded as another sample type than the tags' {tags}")]
    SampleType { tags: &'static str },
    /// Chunk `chunk` holds fewer samples than its `width × height`.
    #[error("chunk {chunk}: expected {width} × {height} samples, got {got}")]
    Short {
        chunk: u32,
        width: usize,
        height: usize,
        got: usize,
    },
}

/// Decode the image strip by strip (or tile by tile) into metres, voids as `NaN`, placing
/// each chunk's rows; `progress` gets `(chunks done, chunks)`.
fn read_chunks<R: std::io::Read + std::io::Seek>(
    decoder: &mut Decoder<R>,
    width: u32,
    height: u32,
    sample: Sample,
    nodata: Option<f64>,
    z_factor: f64,
    progress: &mut dyn FnMut(u64, u64),
) -> Result<Vec<f32>, ChunkError> {
    let tiled = matches!(decoder.get_chunk_type(), ChunkType::Tile);
    let (cw, ch) = decoder.chunk_dimensions();
    if cw == 0 || ch == 0 {
        return Err(ChunkError::Empty {
            width: cw,
            height: ch,
        });
    }
    let across = if tiled { width.div_ceil(cw) } else { 1 };
    let needed = u64::from(across) * u64::from(height.div_ceil(ch));
    let listed = if tiled {
        decoder.tile_count()
    } else {
        decoder.strip_count()
    }?;
    if u64::from(listed) < needed {
        return Err(ChunkError::Listed {
            needed,
            what: if tiled { "tiles" } else { "strips" },
            width,
            height,
            listed,
        });
    }
    let count = width as usize * height as usize;
    let mut out: Vec<f32> = Vec::new();
    out.try_reserve_exact(count)
        .map_err(|_| ChunkError::Alloc { samples: count })?;
    out.resize(count, f32::NAN);
    let void = |h: f64| !h.is_finite() || nodata == Some(h);
    let metres = |h: f64| {
        if void(h) {
            f32::NAN
        } else {
            (h * z_factor) as f32
        }
    };
    // GDAL writes a float32 raster's nodata in full f64 precision.
    let nodata32 = nodata.map(|n| n as f32);
    let needed = u32::try_from(needed).map_err(|_| ChunkError::TooMany { needed })?;
    for i in 0..needed {
        let (dw, dh) = decoder.chunk_data_dimensions(i);
        let (x0, y0) = ((i % across) * cw, (i / across) * ch);
        let chunk = decoder.read_chunk(i)?;
        let values: Vec<f32> = match chunk {
            DecodingResult::U16(v) => v.into_iter().map(|s| metres(f64::from(s))).collect(),
            DecodingResult::I16(v) => v.into_iter().map(|s| metres(f64::from(s))).collect(),
            DecodingResult::U32(v) => v.into_iter().map(|s| metres(f64::from(s))).collect(),
            DecodingResult::I32(v) => v.into_iter().map(|s| metres(f64::from(s))).collect(),
            DecodingResult::F32(v) => v
                .into_iter()
                .map(|s| {
                    if Some(s) == nodata32 {
                        f32::NAN
                    } else {
                        metres(f64::from(s))
                    }
                })
                .collect(),
            DecodingResult::F64(v) => v.into_iter().map(metres).collect(),
            _ => {
                let tags = sample.name();
                return Err(ChunkError::SampleType { tags });
            }
        };
        let (dw, dh) = (dw as usize, dh as usize);
        if dw == 0 || dh == 0 {
            continue;
        }
        if values.len() < dw * dh {
            return Err(ChunkError::Short {
                chunk: i,
                width: dw,
                height: dh,
                got: values.len(),
            });
        }
        // Clip to the image: a chunk never reaches past it, but the tags are outside data.
        let (x0, y0) = (x0 as usize, y0 as usize);
        let cols = dw.min((width as usize).saturating_sub(x0));
        for (r, row) in values.chunks_exact(dw).take(dh).enumerate() {
            let y = y0 + r;
            if y >= height as usize {
                break;
            }
            let start = y * width as usize + x0;
            out[start..start + cols].copy_from_slice(&row[..cols]);
        }
        progress(u64::from(i) + 1, u64::from(needed));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn georeferencing() {
        let keys = |model: u16, extra: &[(u16, u16)]| {
            let mut k = vec![(GT_MODEL_TYPE, model)];
            k.extend_from_slice(extra);
            k
        };
        let tie = Some(vec![0.0, 0.0, 0.0, 6.0, 46.0, 0.0]);
        let scale = Some(vec![30.0, 20.0, 0.0]);
        assert_eq!(
            georef(
                scale.clone(),
                None,
                &keys(1, &[(PROJ_LINEAR_UNITS, 9002)]),
                10
            ),
            Georef::Projected {
                dx: 30.0 * 0.3048,
                dy: 20.0 * 0.3048,
                unit: "foot"
            }
        );
        let deg = Some(vec![1.0 / 3600.0, 1.0 / 3600.0, 0.0]);
        // 3600 rows of 1″ from 46°N: centred at 45.5°N.
        let Georef::Geographic { dx, dy, latitude } = georef(deg, tie, &keys(2, &[]), 3600) else {
            panic!("expected a geographic raster");
        };
        assert!((latitude - 45.5).abs() < 1e-9, "{latitude}");
        assert!((dy - METRES_PER_ARCSEC).abs() < 1e-9, "{dy}");
        assert!((dx - METRES_PER_ARCSEC * 45.5f64.to_radians().cos()).abs() < 1e-9);
        // The same tiepoint naming pixel (0, 0)'s centre: half a row further north.
        let deg = Some(vec![1.0 / 3600.0, 1.0 / 3600.0, 0.0]);
        let tie = Some(vec![0.0, 0.0, 0.0, 6.0, 46.0, 0.0]);
        let Georef::Geographic { latitude, .. } =
            georef(deg, tie, &keys(2, &[(GT_RASTER_TYPE, 2)]), 3600)
        else {
            panic!("expected a geographic raster");
        };
        assert!(
            (latitude - (45.5 + 0.5 / 3600.0)).abs() < 1e-9,
            "{latitude}"
        );
        for (scale, keys, why) in [
            (None, keys(1, &[]), "no ModelPixelScaleTag"),
            (scale.clone(), vec![], "no GTModelTypeGeoKey"),
            (scale.clone(), keys(3, &[]), "GTModelTypeGeoKey 3"),
            (scale.clone(), keys(2, &[]), "without a ModelTiepointTag"),
            (
                scale.clone(),
                keys(1, &[(PROJ_LINEAR_UNITS, 9036)]),
                "ProjLinearUnitsGeoKey 9036",
            ),
            (Some(vec![0.0, 1.0]), keys(1, &[]), "expected two numbers"),
        ] {
            match georef(scale, None, &keys, 10) {
                Georef::Unknown(m) => assert!(m.contains(why), "{m}"),
                g => panic!("{why}: {g:?}"),
            }
        }
        // Version 1.1.0, two keys; a key stored in another tag is skipped.
        let dir = [1, 1, 0, 2, 1024, 0, 1, 2, 2057, 34736, 1, 0];
        assert_eq!(geo_keys(&dir), vec![(1024, 2)]);
        assert_eq!(geo_keys(&[1, 1, 0, 9, 1024, 0, 1]), vec![]);
    }
}
