//! `import --color IMAGE`: a colour image (imagery, a hand-painted map) read and resampled
//! into the data set's colour map, in place of the one derived from the heights.
//!
//! **Reading.** By content: an 8-bit PNG (greyscale, greyscale + alpha, RGB, RGBA, or
//! palette / 1-, 2-, 4-bit greyscale expanded to 8 bits; alpha is ignored) or a binary PPM
//! (`P6`, maxval 255). 16-bit colour is refused (convert it to 8 bits), as is a zero-sized
//! image. A PNG larger than [`MAX_SIDE`] on a side, or whose raw rows could not come out of a
//! file this small (deflate expands at most 1032 : 1), is refused from its header before any
//! pixel is decoded; a PPM must hold exactly the bytes its header declares, checked before
//! allocating. So the only large allocation, the RGB pixels, is bounded by the file's real
//! size.
//!
//! **Where the image lies.** The image covers the source raster's whole extent, edge sample
//! to edge sample: its `W × H` pixels span the raster's `(w − 1) × (h − 1)` cells, which makes
//! an image of exactly `(side − 1)²` pixels for a `side²` raster one pixel per cell (a data
//! set's own `color.ppm` with its `hf.pgm` is copied unchanged). So a source cell is
//! `kx = W / (w − 1)` by `ky = H / (h − 1)` pixels, and everything the heights go through is
//! mapped proportionally: `--crop X,Y,S` (in source samples) takes the pixels
//! `X·kx ..= (X + S − 1)·kx` across and `Y·ky ..= (Y + S − 1)·ky` down; the grid's cell `c`,
//! `step` source samples wide (`hScale / dx`, different across and down for a geographic
//! raster), covers pixels `(X + c·step)·kx ..= (X + (c + 1)·step)·kx`; and cells past the
//! shorter side of a non-square raster, whose heights are edge-extended, take the edge
//! pixels of the window (pixels outside the crop window are never read).
//!
//! **Filter**, separable, chosen per axis: when a cell spans at least one pixel (shrinking),
//! a box (area) filter: each pixel weighted by how much of it the cell covers, so no pixel is
//! skipped; when it spans less (growing), bilinear interpolation at the cell's centre, with
//! pixel centres at `i + 0.5`. Weights sum to 1, the result is rounded to the nearest
//! integer, so a uniform image stays uniform and one pixel per cell is an exact copy.

use std::fs::File;
use std::io::{BufReader, Read};
use std::path::Path;

use png::{BitDepth, ColorType, Decoder, Limits, Transformations};

use crate::terrain::dataset::ColorMap;
use crate::terrain::pnm;
use crate::terrain::raster::MAX_SIDE;
use crate::terrain::source_error::SourceError;

/// A decoded colour image.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RgbImage {
    pub width: u32,
    pub height: u32,
    /// `width × height` pixels, row-major, row 0 north.
    pub rgb: Vec<[u8; 3]>,
    /// "8-bit RGBA PNG", "PPM", …
    pub kind: String,
}

/// Read a colour image (PNG or PPM, by content). `progress` gets `(done, total)`: rows for a
/// PNG, bytes for a PPM.
pub fn read(path: &Path, progress: &mut dyn FnMut(u64, u64)) -> Result<RgbImage, SourceError> {
    let err = |m: String| SourceError::new(path, m);
    let mut file = File::open(path).map_err(|e| err(format!("cannot open: {e}")))?;
    let meta = file
        .metadata()
        .map_err(|e| err(format!("cannot stat: {e}")))?;
    if !meta.is_file() {
        return Err(err("not a regular file".into()));
    }
    let mut magic = Vec::with_capacity(8);
    (&mut file)
        .take(8)
        .read_to_end(&mut magic)
        .map_err(|e| err(format!("cannot read: {e}")))?;
    drop(file);
    if magic.starts_with(b"\x89PNG") {
        read_png(path, meta.len(), progress)
    } else if magic.starts_with(b"P6") {
        let total = meta.len();
        let (width, height, rgb) = pnm::read_ppm_any(path, &mut |n| progress(n, total))
            .map_err(|e| err(format!("PPM {e}")))?;
        Ok(RgbImage {
            width,
            height,
            rgb,
            kind: "PPM".into(),
        })
    } else {
        Err(err(
            "not a colour image: expected an 8-bit PNG or a binary PPM (P6)".into(),
        ))
    }
}

fn read_png(
    path: &Path,
    file_len: u64,
    progress: &mut dyn FnMut(u64, u64),
) -> Result<RgbImage, SourceError> {
    let err = |m: String| SourceError::new(path, m);
    let file = File::open(path).map_err(|e| err(format!("cannot open: {e}")))?;
    let limits = Limits {
        bytes: usize::try_from(u64::from(MAX_SIDE) * u64::from(MAX_SIDE) * 4).unwrap_or(usize::MAX),
    };
    let mut decoder = Decoder::new_with_limits(BufReader::new(file), limits);
    decoder.set_transformations(Transformations::EXPAND);
    let info = decoder
        .read_header_info()
        .map_err(|e| err(format!("PNG header: {e}")))?;
    let (width, height, color, depth) = (info.width, info.height, info.color_type, info.bit_depth);
    if width == 0 || height == 0 {
        return Err(err(format!(
            "PNG of {width} × {height} pixels: expected at least 1 × 1"
        )));
    }
    if width > MAX_SIDE || height > MAX_SIDE {
        return Err(err(format!(
            "PNG of {width} × {height} pixels: expected at most {MAX_SIDE} on each side"
        )));
    }
    if depth == BitDepth::Sixteen {
        return Err(err(format!(
            "PNG of 16-bit colour ({color:?}): expected 8 bits a channel (convert it to 8 bits)"
        )));
    }
    let channels: u64 = match color {
        ColorType::Grayscale | ColorType::Indexed => 1,
        ColorType::GrayscaleAlpha => 2,
        ColorType::Rgb => 3,
        ColorType::Rgba => 4,
    };
    let raw = u64::from(height) * (1 + (u64::from(width) * channels * depth as u64).div_ceil(8));
    crate::terrain::png16::raw_fits(width, height, raw, file_len)
        .map_err(|e| err(e.to_string()))?;
    let mut reader = decoder
        .read_info()
        .map_err(|e| err(format!("PNG header: {e}")))?;
    // After EXPAND: 8 bits a channel; palettes become RGB or RGBA.
    let (out_color, _) = reader.output_color_type();
    let step = match out_color {
        ColorType::Grayscale => 1,
        ColorType::GrayscaleAlpha => 2,
        ColorType::Rgb => 3,
        ColorType::Rgba => 4,
        ColorType::Indexed => {
            return Err(err("PNG palette: could not be expanded".into()));
        }
    };
    let count = width as usize * height as usize;
    let mut rgb: Vec<[u8; 3]> = Vec::new();
    rgb.try_reserve_exact(count)
        .map_err(|_| err(format!("cannot allocate {count} pixels")))?;
    let convert = |row: &[u8], out: &mut Vec<[u8; 3]>| {
        out.extend(row.chunks_exact(step).map(|p| {
            if step < 3 {
                [p[0]; 3]
            } else {
                [p[0], p[1], p[2]]
            }
        }));
    };
    let line = width as usize * step;
    crate::terrain::png16::read_rows(&mut reader, line, height, &err, progress, |row| {
        convert(row, &mut rgb)
    })?;
    let kind = match color {
        ColorType::Grayscale => "greyscale",
        ColorType::GrayscaleAlpha => "greyscale + alpha",
        ColorType::Rgb => "RGB",
        ColorType::Rgba => "RGBA",
        ColorType::Indexed => "palette",
    };
    Ok(RgbImage {
        width,
        height,
        rgb,
        kind: format!("{}-bit {kind} PNG", depth as u8),
    })
}

/// Where the colour map's cells fall on the source raster (see the module header).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Footprint {
    /// The source raster's width and height in samples, before any crop: the image spans it.
    pub raster: (u32, u32),
    /// The window the heights were taken from: left column, top row, width, height.
    pub window: (u32, u32, u32, u32),
    /// Source samples per grid cell, across and down (`hScale / dx`, `hScale / dy`).
    pub step: (f64, f64),
    /// Cells a side of the colour map: the grid's `side − 1`.
    pub cells: u32,
}

impl Footprint {
    /// Image pixels a grid cell spans, across and down.
    pub fn pixels_per_cell(&self, image: &RgbImage) -> (f64, f64) {
        let k = |pixels: u32, samples: u32| {
            f64::from(pixels) / f64::from(samples.saturating_sub(1).max(1))
        };
        (
            self.step.0 * k(image.width, self.raster.0),
            self.step.1 * k(image.height, self.raster.1),
        )
    }
}

/// Why an image cannot be resampled onto a footprint.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ResampleError {
    /// An empty image, or one whose pixels are not its width times its height.
    #[error("a {width} × {height} image of {pixels} pixels: expected at least 1 × 1, every pixel")]
    Image {
        width: u32,
        height: u32,
        pixels: usize,
    },
    /// The footprint's window is not inside its raster, or it has no cell.
    #[error(
        "window {},{} {} × {} of a {} × {} raster, {} cells: expected a window inside the \
         raster and at least one cell",
        .0.window.0, .0.window.1, .0.window.2, .0.window.3, .0.raster.0, .0.raster.1, .0.cells
    )]
    Window(Footprint),
    /// The footprint's samples a cell are not positive numbers.
    #[error("{x} × {y} samples a cell: expected numbers > 0")]
    Step { x: f64, y: f64 },
    /// The colour map's memory could not be had.
    #[error("cannot allocate {cells} colour cells")]
    Alloc { cells: usize },
}

/// One output pixel's taps along an axis: `(pixel, weight)`.
type Taps = Vec<(usize, f32)>;

/// The taps of each of `cells` outputs along one axis. `pixels`: the image's size along it;
/// `samples`: the raster's; `start`, `len`: the window in samples; `step`: samples a cell.
fn axis_taps(pixels: u32, samples: u32, start: u32, len: u32, step: f64, cells: u32) -> Vec<Taps> {
    let k = f64::from(pixels) / f64::from(samples.saturating_sub(1).max(1));
    let a0 = f64::from(start) * k;
    let a1 = (f64::from(start + len.saturating_sub(1).max(1)) * k).min(f64::from(pixels));
    // The window's pixels, at least one.
    let lo = (a0.floor() as usize).min(pixels as usize - 1);
    let hi = (a1.ceil() as usize).clamp(lo + 1, pixels as usize);
    let span = step * k;
    (0..cells)
        .map(|c| {
            let a = a0 + f64::from(c) * span;
            let b = a + span;
            let mut taps: Taps = Vec::new();
            let mut add = |p: usize, w: f64| match taps.last_mut() {
                Some((q, v)) if *q == p => *v += w as f32,
                _ => taps.push((p, w as f32)),
            };
            if span >= 1.0 - 1e-9 {
                // Box: the overlap of [a, b) with each pixel [p, p + 1), edge-extended.
                let (first, last) = (a.floor().max(0.0), b.ceil());
                let mut p = first;
                while p < last {
                    let overlap = b.min(p + 1.0) - a.max(p);
                    if overlap > 1e-9 {
                        add((p as usize).clamp(lo, hi - 1), overlap / span);
                    }
                    p += 1.0;
                }
            } else {
                // Bilinear at the centre, pixel centres at i + 0.5, clamped to the window.
                let centre = ((a + b) / 2.0 - 0.5).clamp(lo as f64, (hi - 1) as f64);
                let p0 = centre.floor() as usize;
                let f = centre - p0 as f64;
                add(p0, 1.0 - f);
                if f > 1e-9 {
                    add((p0 + 1).min(hi - 1), f);
                }
            }
            taps
        })
        .collect()
}

/// Resample `image` into the `cells²` colour map of `footprint`. `progress` gets
/// `(rows done, rows)`.
pub fn resample(
    image: &RgbImage,
    footprint: &Footprint,
    progress: &mut dyn FnMut(u64, u64),
) -> Result<ColorMap, ResampleError> {
    let Footprint {
        raster: (rw, rh),
        window: (wx, wy, ww, wh),
        step: (sx, sy),
        cells,
    } = *footprint;
    let (iw, ih) = (image.width, image.height);
    if iw == 0 || ih == 0 || image.rgb.len() as u64 != u64::from(iw) * u64::from(ih) {
        return Err(ResampleError::Image {
            width: iw,
            height: ih,
            pixels: image.rgb.len(),
        });
    }
    let fits = |start: u32, len: u32, n: u32| {
        len >= 1 && u64::from(start) + u64::from(len) <= u64::from(n)
    };
    if !fits(wx, ww, rw) || !fits(wy, wh, rh) || cells == 0 {
        return Err(ResampleError::Window(*footprint));
    }
    if !(sx.is_finite() && sx > 0.0 && sy.is_finite() && sy > 0.0) {
        return Err(ResampleError::Step { x: sx, y: sy });
    }
    let xs = axis_taps(iw, rw, wx, ww, sx, cells);
    let ys = axis_taps(ih, rh, wy, wh, sy, cells);
    // The columns any output reads, so each output row blends only those.
    let (c0, c1) = xs
        .iter()
        .flatten()
        .fold((usize::MAX, 0), |(l, h), &(p, _)| (l.min(p), h.max(p + 1)));
    let count = cells as usize * cells as usize;
    let mut out: Vec<[u8; 3]> = Vec::new();
    out.try_reserve_exact(count)
        .map_err(|_| ResampleError::Alloc { cells: count })?;
    let mut row = vec![[0f32; 3]; c1 - c0];
    let width = iw as usize;
    for (z, taps_y) in ys.iter().enumerate() {
        row.fill([0.0; 3]);
        for &(py, wy) in taps_y {
            let src = &image.rgb[py * width + c0..py * width + c1];
            for (acc, p) in row.iter_mut().zip(src) {
                for ch in 0..3 {
                    acc[ch] += wy * f32::from(p[ch]);
                }
            }
        }
        out.extend(xs.iter().map(|taps_x| {
            let mut sum = [0f32; 3];
            for &(px, wx) in taps_x {
                let v = row[px - c0];
                for ch in 0..3 {
                    sum[ch] += wx * v[ch];
                }
            }
            sum.map(|v| (v + 0.5).floor().clamp(0.0, 255.0) as u8)
        }));
        if z % 256 == 255 || z + 1 == ys.len() {
            progress(z as u64 + 1, ys.len() as u64);
        }
    }
    Ok(ColorMap::new(cells, out).expect("`cells²` cells, one an output pixel"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn taps_box_bilinear_and_edges() {
        // One pixel a cell: single taps, exact.
        let t = axis_taps(4, 5, 0, 5, 1.0, 4);
        assert_eq!(
            t,
            vec![
                vec![(0, 1.0)],
                vec![(1, 1.0)],
                vec![(2, 1.0)],
                vec![(3, 1.0)]
            ]
        );
        // Three pixels over two cells: 1.5 pixels a cell.
        let t = axis_taps(3, 3, 0, 3, 1.0, 2);
        assert_eq!(t[0], vec![(0, 2.0 / 3.0), (1, 1.0 / 3.0)]);
        assert_eq!(t[1], vec![(1, 1.0 / 3.0), (2, 2.0 / 3.0)]);
        // Two cells a pixel: bilinear between the centres, clamped at the edges.
        let t = axis_taps(2, 5, 0, 5, 1.0, 4);
        assert_eq!(t[0], vec![(0, 1.0)]);
        assert_eq!(t[1], vec![(0, 0.75), (1, 0.25)]);
        assert_eq!(t[2], vec![(0, 0.25), (1, 0.75)]);
        assert_eq!(t[3], vec![(1, 1.0)]);
        // Padding: cells past the window take its last pixel.
        let t = axis_taps(4, 5, 0, 5, 0.5, 16);
        assert_eq!(t[15], vec![(3, 1.0)]);
        let t = axis_taps(4, 5, 0, 3, 1.0, 4);
        assert_eq!(t[3], vec![(1, 1.0)]);
    }

    #[test]
    fn progress_reaches_every_row() {
        let image = RgbImage {
            width: 600,
            height: 600,
            rgb: vec![[9, 8, 7]; 600 * 600],
            kind: "test".into(),
        };
        let footprint = Footprint {
            raster: (601, 601),
            window: (0, 0, 601, 601),
            step: (1.0, 1.0),
            cells: 600,
        };
        let mut reports = Vec::new();
        let map = resample(&image, &footprint, &mut |d, t| reports.push((d, t))).unwrap();
        assert!(map.rgb().iter().all(|&p| p == [9, 8, 7]));
        assert_eq!(reports, vec![(256, 600), (512, 600), (600, 600)]);
    }
}
