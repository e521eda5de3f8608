//! `import_sources TILE.tif OUT_DIR`: the real SRTM3 GeoTIFF written in every other format
//! `roam-server import` reads, for `scripts/import_figures.sh` (import time and peak memory
//! per format). Not part of the server: it only calls the library's readers and the png and
//! tiff encoders.
//!
//! Written into `OUT_DIR`, heights rounded to whole metres as in the tile:
//! - `N07W006.hgt` (1201², big-endian `i16`), `grey16.png` (16-bit greyscale, metres),
//!   `terrarium.png` (8-bit RGB, `R·256 + G + B/256 − 32768`), `kossou.pgm` (the 1025² cut of
//!   `data/kossou`, rows and columns 88 .. 1112, since a PGM must be `2^N + 1` a side);
//! - `s1/`: the same tile bilinearly upsampled ×3 to 3601², as SRTM1 would hold it:
//!   `N07W006.hgt`, `n07_w006_1arc.tif` (GeoTIFF, 1″ pixels, the same tiepoint),
//!   `grey16.png`, `terrarium.png`.

use std::fs;
use std::io::{BufWriter, Cursor, Write};
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use roam_server::terrain::geotiff;
use roam_server::terrain::raster::Raster;
use tiff::encoder::{TiffEncoder, colortype};
use tiff::tags::Tag;

/// Whole metres of a raster without voids, row-major.
fn metres(r: &Raster) -> Result<Vec<i16>> {
    r.samples()
        .iter()
        .map(|&h| {
            if h.is_finite() {
                Ok(h.round() as i16)
            } else {
                bail!("the tile has a void; fill it first")
            }
        })
        .collect()
}

fn write_hgt(path: &Path, h: &[i16]) -> Result<()> {
    let bytes: Vec<u8> = h.iter().flat_map(|v| v.to_be_bytes()).collect();
    fs::write(path, bytes).with_context(|| path.display().to_string())
}

fn write_png(path: &Path, side: u32, color: png::ColorType, data: &[u8]) -> Result<()> {
    let file = fs::File::create(path).with_context(|| path.display().to_string())?;
    let mut enc = png::Encoder::new(BufWriter::new(file), side, side);
    enc.set_color(color);
    enc.set_depth(if color == png::ColorType::Grayscale {
        png::BitDepth::Sixteen
    } else {
        png::BitDepth::Eight
    });
    let mut w = enc.write_header()?;
    w.write_image_data(data)?;
    w.finish()?;
    Ok(())
}

fn write_pngs(dir: &Path, side: u32, h: &[i16]) -> Result<()> {
    let grey: Vec<u8> = h
        .iter()
        .flat_map(|&v| (v.max(0) as u16).to_be_bytes())
        .collect();
    write_png(
        &dir.join("grey16.png"),
        side,
        png::ColorType::Grayscale,
        &grey,
    )?;
    let rgb: Vec<u8> = h
        .iter()
        .flat_map(|&v| {
            let t = (i32::from(v) + 32768) as u32;
            [(t >> 8) as u8, (t & 255) as u8, 0]
        })
        .collect();
    write_png(&dir.join("terrarium.png"), side, png::ColorType::Rgb, &rgb)
}

fn write_pgm(path: &Path, side: u32, h: &[i16]) -> Result<()> {
    let mut w = BufWriter::new(fs::File::create(path)?);
    write!(w, "P5\n{side} {side}\n65535\n")?;
    for &v in h {
        w.write_all(&(v.max(0) as u16).to_be_bytes())?;
    }
    w.flush()?;
    Ok(())
}

/// A geographic GeoTIFF of `side²` samples `pixel_deg` apart, pixel (0, 0)'s centre at
/// 8°N 6°W (PixelIsPoint), as USGS writes SRTM tiles.
fn write_geotiff(path: &Path, side: u32, pixel_deg: f64, h: &[i16]) -> Result<()> {
    let mut cursor = Cursor::new(Vec::new());
    let mut enc = TiffEncoder::new(&mut cursor)?;
    let mut image = enc.new_image::<colortype::GrayI16>(side, side)?;
    let dir = image.encoder();
    dir.write_tag(Tag::Unknown(33550), &[pixel_deg, pixel_deg, 0.0][..])?;
    dir.write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, -6.0, 8.0, 0.0][..])?;
    let keys: [u16; 16] = [1, 1, 0, 3, 1024, 0, 1, 2, 1025, 0, 1, 2, 2048, 0, 1, 4326];
    dir.write_tag(Tag::Unknown(34735), &keys[..])?;
    dir.write_tag(Tag::Unknown(42113), "-32767")?;
    image.write_data(h)?;
    fs::write(path, cursor.into_inner()).with_context(|| path.display().to_string())
}

fn main() -> Result<()> {
    let args: Vec<PathBuf> = std::env::args_os().skip(1).map(PathBuf::from).collect();
    let [tile, out] = &args[..] else {
        bail!("usage: import_sources TILE.tif OUT_DIR");
    };
    let tiff = geotiff::read(tile, &mut |_, _| {})?;
    let r = tiff.raster;
    let side = r.width();
    if side != 1201 || r.height() != 1201 {
        bail!(
            "{}: expected a 1201² SRTM3 tile, got {side} × {}",
            tile.display(),
            r.height()
        );
    }
    let h = metres(&r)?;
    fs::create_dir_all(out.join("s1"))?;
    write_hgt(&out.join("N07W006.hgt"), &h)?;
    write_pngs(out, side, &h)?;
    let cut = r.crop(88, 88, 1025)?;
    write_pgm(&out.join("kossou.pgm"), 1025, &metres(&cut)?)?;
    // ×3: 1200 intervals become 3600.
    let (fine, _) = r.to_grid(1.0, 1.0, 3601, &mut |_, _| {})?;
    let h = metres(&fine)?;
    let s1 = out.join("s1");
    write_hgt(&s1.join("N07W006.hgt"), &h)?;
    write_geotiff(&s1.join("n07_w006_1arc.tif"), 3601, 1.0 / 3600.0, &h)?;
    write_pngs(&s1, 3601, &h)?;
    Ok(())
}
