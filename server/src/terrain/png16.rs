//! PNG heightfields: 16-bit greyscale (samples in metres, or `z_scale · s + z_offset`), and
//! 8-bit RGB(A) in one of the two web-tile encodings, which cannot be told apart by content
//! and so must be named: Terrarium (`h = R·256 + G + B/256 − 32768`) and Mapbox Terrain-RGB
//! (`h = −10000 + (R·65536 + G·256 + B) · 0.1`). In RGBA images a fully transparent pixel
//! is a void.
//!
//! Nothing is trusted before it is checked: sides above 32769 are refused from the header,
//! before any image data is decoded; a header whose raw image could not come out of a file
//! this small (deflate expands at most 1032 : 1) is refused as truncated or corrupt; and the
//! decoder runs under the `png` crate's allocation limit. Rows are converted as they are
//! decoded, so the only large allocation is the raster of `f32` heights itself.

use std::fs::File;
use std::io::BufReader;
use std::path::Path;

use png::{BitDepth, ColorType, Decoder, Limits, Transformations};

use crate::terrain::raster::{MAX_SIDE, Raster};
use crate::terrain::source_error::SourceError;

/// Deflate's best compression ratio: no PNG can hold more raw bytes than this × its size.
const MAX_INFLATE: u64 = 1032;
/// The decoder's allocation limit: a 32769² image at 8 bytes a pixel.
const LIMIT_BYTES: u64 = (MAX_SIDE as u64) * (MAX_SIDE as u64) * 8;

/// Which Terrain-RGB encoding an 8-bit RGB PNG uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RgbEncoding {
    /// Mapzen / AWS Terrarium: `R·256 + G + B/256 − 32768`.
    Terrarium,
    /// Mapbox Terrain-RGB: `−10000 + (R·65536 + G·256 + B) · 0.1`.
    Mapbox,
}

impl RgbEncoding {
    /// Height in metres of one pixel.
    pub fn decode(self, [r, g, b]: [u8; 3]) -> f64 {
        let (r, g, b) = (f64::from(r), f64::from(g), f64::from(b));
        match self {
            RgbEncoding::Terrarium => r * 256.0 + g + b / 256.0 - 32768.0,
            RgbEncoding::Mapbox => -10000.0 + (r * 65536.0 + g * 256.0 + b) * 0.1,
        }
    }
}

/// How to turn samples into metres.
#[derive(Clone, Copy, Debug)]
pub struct PngOptions {
    /// Required for RGB(A) PNGs.
    pub rgb: Option<RgbEncoding>,
    /// Metres per step of a 16-bit sample.
    pub z_scale: f64,
    /// Metres added to every 16-bit sample.
    pub z_offset: f64,
}

impl Default for PngOptions {
    fn default() -> Self {
        PngOptions {
            rgb: None,
            z_scale: 1.0,
            z_offset: 0.0,
        }
    }
}

/// What a PNG held.
#[derive(Debug)]
pub struct Png {
    pub raster: Raster,
    /// "16-bit greyscale PNG", "Terrarium RGB PNG", …
    pub kind: String,
}

#[derive(Clone, Copy)]
enum Pixels {
    Grey16,
    Rgb(RgbEncoding, usize),
}

/// Read a heightfield PNG. `progress` gets `(rows decoded, rows)`.
pub fn read(
    path: &Path,
    options: PngOptions,
    progress: &mut dyn FnMut(u64, u64),
) -> Result<Png, SourceError> {
    let err = |m: String| SourceError::new(path, m);
    let file = File::open(path).map_err(|e| err(format!("cannot open: {e}")))?;
    let file_len = file
        .metadata()
        .map_err(|e| err(format!("cannot stat: {e}")))?
        .len();
    let limits = Limits {
        bytes: usize::try_from(LIMIT_BYTES).unwrap_or(usize::MAX),
    };
    let mut decoder = Decoder::new_with_limits(BufReader::new(file), limits);
    decoder.set_transformations(Transformations::IDENTITY);
    let info = decoder
        .read_header_info()
        .map_err(|e| err(format!("PNG header: {e}")))?;
    let (width, height) = (info.width, info.height);
    let (color, depth) = (info.color_type, info.bit_depth);
    if width > MAX_SIDE || height > MAX_SIDE {
        return Err(err(format!(
            "PNG of {width} × {height} pixels: expected at most {MAX_SIDE} on each side"
        )));
    }
    let pixels = match (color, depth) {
        (ColorType::Grayscale, BitDepth::Sixteen) => {
            if options.rgb.is_some() {
                return Err(err(
                    "a 16-bit greyscale PNG: --rgb-encoding applies to RGB PNGs only".into(),
                ));
            }
            Pixels::Grey16
        }
        (ColorType::Rgb | ColorType::Rgba, BitDepth::Eight) => {
            let channels = if color == ColorType::Rgb { 3 } else { 4 };
            let Some(enc) = options.rgb else {
                return Err(err(
                    "an 8-bit RGB PNG: say how heights are encoded with --rgb-encoding \
                     terrarium or --rgb-encoding mapbox (they cannot be told apart by content)"
                        .into(),
                ));
            };
            if options.z_scale != 1.0 || options.z_offset != 0.0 {
                return Err(err(
                    "an RGB PNG: --z-scale and --z-offset apply to 16-bit greyscale PNGs only"
                        .into(),
                ));
            }
            Pixels::Rgb(enc, channels)
        }
        _ => {
            return Err(err(format!(
                "PNG of colour type {color:?} at {} bits: expected 16-bit greyscale, or 8-bit \
                 RGB / RGBA with --rgb-encoding",
                depth as u8
            )));
        }
    };
    let bytes_per_pixel: u64 = match pixels {
        Pixels::Grey16 => 2,
        Pixels::Rgb(_, c) => c as u64,
    };
    let raw = u64::from(height) * (1 + u64::from(width) * bytes_per_pixel);
    raw_fits(width, height, raw, file_len).map_err(|e| err(e.to_string()))?;
    let mut reader = decoder
        .read_info()
        .map_err(|e| err(format!("PNG header: {e}")))?;
    let count = width as usize * height as usize;
    let mut samples: Vec<f32> = Vec::new();
    samples
        .try_reserve_exact(count)
        .map_err(|_| err(format!("cannot allocate {count} samples")))?;
    let convert = |row: &[u8], out: &mut Vec<f32>| match pixels {
        Pixels::Grey16 => out.extend(row.chunks_exact(2).map(|p| {
            let s = f64::from(u16::from_be_bytes([p[0], p[1]]));
            (s * options.z_scale + options.z_offset) as f32
        })),
        Pixels::Rgb(enc, c) => out.extend(row.chunks_exact(c).map(|p| {
            if c == 4 && p[3] == 0 {
                f32::NAN
            } else {
                enc.decode([p[0], p[1], p[2]]) as f32
            }
        })),
    };
    let line = width as usize * bytes_per_pixel as usize;
    read_rows(&mut reader, line, height, &err, progress, |row| {
        convert(row, &mut samples)
    })?;
    let kind = match pixels {
        Pixels::Grey16 => "16-bit greyscale PNG".to_string(),
        Pixels::Rgb(enc, c) => format!(
            "{} {} PNG",
            match enc {
                RgbEncoding::Terrarium => "Terrarium",
                RgbEncoding::Mapbox => "Mapbox Terrain-RGB",
            },
            if c == 4 { "RGBA" } else { "RGB" }
        ),
    };
    let raster = Raster::new(width, height, samples).map_err(|e| err(e.to_string()))?;
    Ok(Png { raster, kind })
}

/// A PNG whose decoded rows cannot come out of its file: more than [`MAX_INFLATE`] times
/// its length.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error(
    "PNG of {width} × {height} pixels ({raw} bytes raw) cannot fit in {file_len} bytes: the \
     file is truncated or corrupt"
)]
pub(crate) struct TooRaw {
    width: u32,
    height: u32,
    /// Bytes of its decoded rows, filter bytes included.
    raw: u64,
    file_len: u64,
}

/// Whether `raw` bytes of decoded rows (filter bytes included) of a `width × height`
/// PNG can come out of a file of `file_len` bytes, checked before allocating for them.
pub(crate) fn raw_fits(width: u32, height: u32, raw: u64, file_len: u64) -> Result<(), TooRaw> {
    if raw > file_len.saturating_mul(MAX_INFLATE) {
        return Err(TooRaw {
            width,
            height,
            raw,
            file_len,
        });
    }
    Ok(())
}

/// Hands each of the image's `height` rows (`line` bytes) to `row` in order, reporting
/// `progress(rows, height)`: interlaced images (rows in passes) are decoded whole first,
/// the buffer reserved fallibly; others row by row.
pub(crate) fn read_rows<R: std::io::BufRead + std::io::Seek>(
    reader: &mut png::Reader<R>,
    line: usize,
    height: u32,
    err: &dyn Fn(String) -> SourceError,
    progress: &mut dyn FnMut(u64, u64),
    mut row: impl FnMut(&[u8]),
) -> Result<(), SourceError> {
    let decode_err = |e: png::DecodingError| err(format!("PNG data: {e}"));
    if reader.info().interlaced {
        let size = reader
            .output_buffer_size()
            .ok_or_else(|| err("PNG too large to decode".into()))?;
        let mut buf = Vec::new();
        buf.try_reserve_exact(size)
            .map_err(|_| err(format!("cannot allocate {size} bytes")))?;
        buf.resize(size, 0);
        reader.next_frame(&mut buf).map_err(decode_err)?;
        for r in buf.chunks_exact(line).take(height as usize) {
            row(r);
        }
        progress(u64::from(height), u64::from(height));
    } else {
        for y in 0..height {
            let r = reader
                .next_row()
                .map_err(decode_err)?
                .ok_or_else(|| err(format!("PNG data: expected {height} rows, got {y}")))?;
            row(&r.data()[..line]);
            if y % 256 == 255 || y + 1 == height {
                progress(u64::from(y) + 1, u64::from(height));
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::RgbEncoding::{Mapbox, Terrarium};

    #[test]
    fn encodings() {
        for (enc, rgb, want) in [
            (Terrarium, [128, 0, 0], 0.0),
            (Terrarium, [128, 100, 128], 100.5),
            (Terrarium, [127, 255, 0], -1.0),
            (Terrarium, [0, 0, 0], -32768.0),
            (Mapbox, [1, 134, 160], 0.0),
            (Mapbox, [1, 138, 136], 100.0),
            (Mapbox, [0, 0, 0], -10000.0),
        ] {
            let got = enc.decode(rgb);
            assert!((got - want).abs() < 1e-9, "{enc:?} {rgb:?}: {got}");
        }
    }
}
