//! `import FILE OUT`: build a data set from a heightfield in any format `import` reads (PGM,
//! 16-bit or Terrain-RGB PNG, SRTM `.hgt`, GeoTIFF), through the raster pipeline of
//! [`roam_server::terrain::raster`]: fill voids, crop, pad and resample to `2^N + 1`,
//! quantise to 16 bits. A PGM that is already a data-set heightfield is copied unchanged.
//! The colour map is derived from the heights, or resampled from `--color IMAGE` over the
//! same footprint (see [`roam_server::terrain::colorimage`]). Every step that can take more
//! than a second (reading, void filling, resampling, the colour map, writing) reports
//! `(done, total)` to a [`Progress`] bar. The colour map derived from the heights
//! (`generate::colorize_with`, 2.8 s of a 3.3 s import to 4097² on one core) runs on every
//! core.

use std::fs;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::Args;
use roam_server::terrain::colorimage::{self, Footprint, RgbImage};
use roam_server::terrain::dataset::{COLOR_FILE, HEIGHTS_FILE, MAP_FILE, Terrain};
use roam_server::terrain::geotiff::{self, Georef};
use roam_server::terrain::heightfield::{Heightfield, levels_of_side};
use roam_server::terrain::hgt;
use roam_server::terrain::map::{MapParams, Start, normalize};
use roam_server::terrain::png16::{self, PngOptions, RgbEncoding};
use roam_server::terrain::raster::{Raster, default_side};
use roam_server::terrain::source::{self, Format};
use roam_server::terrain::{generate as gen_terrain, pnm};

use super::data::describe;
use super::progress::Progress;

#[derive(Args)]
pub(crate) struct ImportArgs {
    /// Source heightfield, recognised by content: binary PGM (side 2^N + 1), PNG (16-bit
    /// greyscale, or 8-bit RGB with --rgb-encoding), GeoTIFF (one 16/32-bit integer or
    /// 32/64-bit float sample a pixel) or SRTM .hgt (1201² or 3601²).
    pub file: PathBuf,
    /// Output directory (created if missing).
    pub out: PathBuf,
    /// World units (metres) between neighbouring source samples (`hScale` before any
    /// resampling); overrides a .hgt tile's or GeoTIFF's georeferencing [default: 1].
    #[arg(long, allow_hyphen_values = true)]
    pub h_scale: Option<f64>,
    /// World units per sample value (`vScale`) [default: 0.1 for a PGM; otherwise chosen to
    /// keep the heights' precision].
    #[arg(long, allow_hyphen_values = true)]
    pub v_scale: Option<f64>,
    /// Samples per side of the data set, 2^N + 1 [default: the smallest that holds the
    /// raster's longer side].
    #[arg(long)]
    pub side: Option<u32>,
    /// Take the window of W × W source samples whose top-left sample is column X, row Y.
    #[arg(long, value_parser = parse_crop, value_name = "X,Y,W")]
    pub crop: Option<[u32; 3]>,
    /// How an 8-bit RGB PNG encodes heights: `terrarium` or `mapbox` (Terrain-RGB).
    #[arg(long, value_parser = parse_encoding)]
    pub rgb_encoding: Option<RgbEncoding>,
    /// Metres per step of a 16-bit PNG sample.
    #[arg(long, default_value_t = 1.0, allow_hyphen_values = true)]
    pub z_scale: f64,
    /// Metres added to every 16-bit PNG sample.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub z_offset: f64,
    /// World height of a water surface (`waterLevel`); cells below it are coloured as water.
    #[arg(long, allow_hyphen_values = true)]
    pub water_level: Option<f64>,
    /// Vehicle start, world X (default: the map's centre).
    #[arg(long, allow_hyphen_values = true)]
    pub start_x: Option<f64>,
    /// Vehicle start, world Z (default: the map's centre).
    #[arg(long, allow_hyphen_values = true)]
    pub start_z: Option<f64>,
    /// Vehicle heading in degrees: 0 faces south (+Z), 90 east (+X).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub heading: f64,
    /// Direction towards the sun as X,Y,Z (normalised).
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true,
          conflicts_with_all = ["sun_azimuth", "sun_elevation"])]
    pub sun_dir: Option<[f64; 3]>,
    /// Sun azimuth in compass degrees (0 north, 90 east, 180 south, 270 west); needs
    /// --sun-elevation.
    #[arg(long, requires = "sun_elevation", allow_hyphen_values = true)]
    pub sun_azimuth: Option<f64>,
    /// Sun elevation above the horizon in degrees; needs --sun-azimuth.
    #[arg(long, requires = "sun_azimuth", allow_hyphen_values = true)]
    pub sun_elevation: Option<f64>,
    /// Sun colour as R,G,B (0..=255 each).
    #[arg(long, value_parser = parse_rgb)]
    pub sun_color: Option<[u8; 3]>,
    /// Exponential fog density per world unit.
    #[arg(long, allow_hyphen_values = true)]
    pub fog_density: Option<f64>,
    /// Fog colour as R,G,B (0..=255 each).
    #[arg(long, value_parser = parse_rgb)]
    pub fog_color: Option<[u8; 3]>,
    /// Colour map from this image (8-bit PNG or binary PPM) instead of one derived from the
    /// heights: it covers the source raster edge sample to edge sample, follows --crop and
    /// the padding, and is resampled to (side − 1)² cells (area-averaged when shrinking,
    /// bilinear when growing).
    #[arg(long, value_name = "IMAGE")]
    pub color: Option<PathBuf>,
}

/// The heights and scales `import` settles on, and where the grid's cells lie on the
/// source raster (for `--color`).
struct Imported {
    heights: Heightfield,
    h_scale: f64,
    v_scale: f64,
    footprint: Footprint,
}

/// `import FILE OUT`: read any supported heightfield, derive a colour map and write a data
/// set with a `map` file.
pub(crate) fn import(args: ImportArgs) -> Result<()> {
    let path = &args.file;
    let format = source::detect(path)?;
    if format != Format::Png
        && (args.rgb_encoding.is_some() || args.z_scale != 1.0 || args.z_offset != 0.0)
    {
        bail!(
            "{}: --rgb-encoding, --z-scale and --z-offset apply to PNG files only; this is {}",
            path.display(),
            describe_format(format)
        );
    }
    if let Some(side) = args.side
        && levels_of_side(u64::from(side)).is_none()
    {
        bail!("--side: expected 2^N + 1 (3, 5, 9, …, 32769), got {side}");
    }
    for (flag, v) in [
        ("--h-scale", args.h_scale),
        ("--v-scale", args.v_scale),
        ("--z-scale", Some(args.z_scale)),
        ("--z-offset", Some(args.z_offset)),
    ] {
        if let Some(v) = v
            && (!v.is_finite() || (flag != "--z-offset" && v <= 0.0))
        {
            bail!("{flag}: expected a finite number > 0, got {v}");
        }
    }
    // The colour image first: a bad one fails before the heights' work.
    let image = match &args.color {
        None => None,
        Some(color) => {
            let image = {
                let mut p = Progress::new("colour");
                colorimage::read(color, &mut p.callback())?
            };
            say!(
                "colour: {}, {} × {} pixels ({})",
                image.kind,
                image.width,
                image.height,
                color.display()
            );
            Some(image)
        }
    };
    let imported = match format {
        Format::Pgm => import_pgm(&args)?,
        Format::Hgt => {
            let tile = {
                let mut p = Progress::new("reading");
                hgt::read(path, &mut p.callback())?
            };
            say!(
                "format: SRTM .hgt ({}″ a sample), {} × {} samples",
                tile.arcsec,
                tile.raster.width(),
                tile.raster.height()
            );
            let spacing = match (args.h_scale, tile.spacing(), tile.latitude) {
                (Some(h), _, _) => {
                    say!("sample spacing {h} m (from --h-scale)");
                    (h, h)
                }
                (None, Some((dx, dy)), Some(lat)) => {
                    say!(
                        "geographic raster: {dx:.2} m a sample east–west, {dy:.2} m north–south \
                         at latitude {lat}° (from the file name); resampled to square samples"
                    );
                    (dx, dy)
                }
                _ => {
                    say!(
                        "no latitude in the file name (expected like N07W006.hgt): sample \
                         spacing 1 m; give --h-scale"
                    );
                    (1.0, 1.0)
                }
            };
            pipeline(&args, tile.raster, spacing, args.v_scale)?
        }
        Format::Png => {
            let options = PngOptions {
                rgb: args.rgb_encoding,
                z_scale: args.z_scale,
                z_offset: args.z_offset,
            };
            let png = {
                let mut p = Progress::new("reading");
                png16::read(path, options, &mut p.callback())?
            };
            say!(
                "format: {}, {} × {} samples",
                png.kind,
                png.raster.width(),
                png.raster.height()
            );
            let h = args.h_scale.unwrap_or(1.0);
            say!(
                "sample spacing {h} m (from --h-scale{}; a PNG carries no georeferencing)",
                if args.h_scale.is_none() {
                    ", default"
                } else {
                    ""
                }
            );
            pipeline(&args, png.raster, (h, h), args.v_scale)?
        }
        Format::GeoTiff => import_geotiff(&args)?,
    };
    write(&args, imported, image)
}

fn describe_format(format: Format) -> &'static str {
    match format {
        Format::Pgm => "a PGM",
        Format::Png => "a PNG",
        Format::Hgt => "an SRTM .hgt tile",
        Format::GeoTiff => "a GeoTIFF",
    }
}

/// A GeoTIFF: spacing from its georeferencing unless `--h-scale` is given, heights in
/// metres (converted from feet when its vertical units say so).
fn import_geotiff(args: &ImportArgs) -> Result<Imported> {
    let tiff = {
        let mut p = Progress::new("reading");
        geotiff::read(&args.file, &mut p.callback())?
    };
    say!(
        "format: {}, {} × {} samples",
        tiff.kind,
        tiff.raster.width(),
        tiff.raster.height()
    );
    if let Some(n) = tiff.nodata {
        say!("nodata value {n} (GDAL_NODATA): those samples are voids");
    }
    say!("heights {}", tiff.vertical);
    let spacing = match (args.h_scale, &tiff.georef) {
        (Some(h), _) => {
            say!("sample spacing {h} m (from --h-scale)");
            (h, h)
        }
        (None, Georef::Projected { dx, dy, unit }) => {
            say!(
                "projected raster: {dx} m a sample east–west, {dy} m north–south (from \
                 ModelPixelScale, in {unit})"
            );
            (*dx, *dy)
        }
        (None, Georef::Geographic { dx, dy, latitude }) => {
            say!(
                "geographic raster: {dx:.2} m a sample east–west, {dy:.2} m north–south at \
                 latitude {latitude:.4}° (from ModelPixelScale and ModelTiepoint); resampled \
                 to square samples"
            );
            (*dx, *dy)
        }
        (None, Georef::Unknown(why)) => {
            say!("no usable georeferencing ({why}): sample spacing 1 m; give --h-scale");
            (1.0, 1.0)
        }
    };
    pipeline(args, tiff.raster, spacing, args.v_scale)
}

/// A PGM: copied unchanged, unless `--crop` or another `--side` sends it through the
/// pipeline (heights `sample × vScale`, the same `vScale` kept).
fn import_pgm(args: &ImportArgs) -> Result<Imported> {
    let path = &args.file;
    let heights = {
        let mut p = Progress::new("reading");
        let total = std::fs::metadata(path).map(|m| m.len()).unwrap_or(0);
        let mut cb = p.callback();
        pnm::read_pgm(path, &mut |n| cb(n, total))
            .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?
    };
    let side = heights.side();
    let (h_scale, v_scale) = (args.h_scale.unwrap_or(1.0), args.v_scale.unwrap_or(0.1));
    say!("format: PGM, {side} × {side} samples");
    if args.crop.is_none() && args.side.is_none_or(|s| s == side) {
        say!("samples copied unchanged: hScale {h_scale}, vScale {v_scale}");
        return Ok(Imported {
            heights,
            h_scale,
            v_scale,
            footprint: Footprint {
                raster: (side, side),
                window: (0, 0, side, side),
                step: (1.0, 1.0),
                cells: side - 1,
            },
        });
    }
    let samples = heights
        .samples()
        .iter()
        .map(|&s| (f64::from(s) * v_scale) as f32)
        .collect();
    let raster = Raster::new(side, side, samples)?;
    say!("sample spacing {h_scale} m (from --h-scale)");
    pipeline(args, raster, (h_scale, h_scale), Some(v_scale))
}

/// Fill voids, crop, pad and resample, quantise; print what was done.
fn pipeline(
    args: &ImportArgs,
    mut raster: Raster,
    (dx, dy): (f64, f64),
    v_scale: Option<f64>,
) -> Result<Imported> {
    let path = &args.file;
    let total = raster.samples().len();
    let filled = {
        let mut p = Progress::new("filling");
        raster
            .fill_voids(&mut p.callback())
            .with_context(|| format!("{}", path.display()))?
    };
    say!(
        "voids filled: {filled} ({:.3} % of the samples)",
        100.0 * filled as f64 / total as f64
    );
    let full = (raster.width(), raster.height());
    let mut window = (0, 0, full.0, full.1);
    if let Some([x, y, w]) = args.crop {
        raster = raster.crop(x, y, w)?;
        window = (x, y, w, w);
        say!("cropped: {w} × {w} samples from column {x}, row {y}");
    }
    let (w, h) = (raster.width(), raster.height());
    let side = args.side.unwrap_or_else(|| default_side(w.max(h)));
    let (grid, h_scale) = {
        let mut p = Progress::new("resampling");
        raster.to_grid(dx, dy, side, &mut p.callback())?
    };
    if w == side && h == side && dx == dy {
        say!("kept at {side} × {side} samples (already 2^N + 1)");
    } else {
        let pad = if w == h && dx == dy {
            String::new()
        } else {
            "padded to a square with edge-extended heights, ".to_string()
        };
        say!("{w} × {h} samples {pad}resampled (bilinear) to {side} × {side}");
    }
    drop(raster);
    let q = grid.quantise(v_scale)?;
    say!("hScale {h_scale} m (world units, one a metre)");
    if v_scale.is_some() {
        say!("vScale {} m (given)", q.v_scale);
    } else {
        say!(
            "vScale {} m (chosen to keep the heights' precision: {:.3} m over 65535 steps)",
            q.v_scale,
            q.max - q.min
        );
    }
    say!(
        "heights {:.3} .. {:.3} m; heights shifted by {:.3} m so the lowest is 0",
        q.min,
        q.max,
        -q.min
    );
    Ok(Imported {
        heights: q.heights,
        h_scale,
        v_scale: q.v_scale,
        footprint: Footprint {
            raster: full,
            window,
            step: (h_scale / dx, h_scale / dy),
            cells: side - 1,
        },
    })
}

/// Derive the map and the colour map, and write the data set.
fn write(args: &ImportArgs, imported: Imported, image: Option<RgbImage>) -> Result<()> {
    let Imported {
        heights,
        h_scale,
        v_scale,
        footprint,
    } = imported;
    let side = heights.side();
    let mut map = MapParams::default_for_side(side);
    map.h_scale = h_scale;
    map.v_scale = v_scale;
    map.water_level = args.water_level;
    let centre = map.world_size(side) / 2.0;
    map.start = Start {
        x: args.start_x.unwrap_or(centre),
        z: args.start_z.unwrap_or(centre),
        heading_deg: args.heading,
    };
    if let Some(d) = args.sun_dir {
        map.sun_dir = normalize(d)
            .with_context(|| format!("--sun-dir: expected a non-zero direction, got {d:?}"))?;
    }
    if let (Some(az), Some(el)) = (args.sun_azimuth, args.sun_elevation) {
        map.sun_dir = sun_from_angles(az, el)
            .with_context(|| format!("--sun-azimuth/--sun-elevation: got {az}, {el}"))?;
    }
    if let Some(c) = args.sun_color {
        map.sun_color = c;
    }
    if let Some(f) = args.fog_density {
        map.fog_density = f;
    }
    if let Some(c) = args.fog_color {
        map.fog_color = c;
    }
    map.validate_for_side(side)
        .map_err(|e| anyhow::anyhow!("map parameters: {e}"))?;
    let color = match (image, &args.color) {
        (Some(image), Some(path)) => color_from_image(path, &image, &footprint)?,
        _ => {
            let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
            let mut p = Progress::new("colouring");
            gen_terrain::colorize_with(&heights, &map, threads, &mut p.callback())
        }
    };
    let terrain = Terrain {
        map,
        heights,
        color: Some(color),
    };
    save(Path::new(&args.out), &terrain)
}

/// The colour map resampled from `--color`'s image; says how.
fn color_from_image(
    path: &Path,
    image: &RgbImage,
    footprint: &Footprint,
) -> Result<roam_server::terrain::dataset::ColorMap> {
    let color = {
        let mut p = Progress::new("colour map");
        colorimage::resample(image, footprint, &mut p.callback())
            .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?
    };
    let (px, py) = footprint.pixels_per_cell(image);
    let filter = |k: f64| {
        if k >= 1.0 {
            "area-averaged"
        } else {
            "bilinear"
        }
    };
    let cells = footprint.cells;
    if px == 1.0 && py == 1.0 {
        say!("colour map: one pixel a cell, {cells} × {cells} cells copied from the image");
    } else {
        say!(
            "colour map: {px:.4} × {py:.4} pixels a cell ({} across, {} down) to {cells} × \
             {cells} cells",
            filter(px),
            filter(py)
        );
    }
    let (rw, rh) = footprint.raster;
    let (image_aspect, raster_aspect) = (
        f64::from(image.width) / f64::from(image.height),
        f64::from(rw.saturating_sub(1).max(1)) / f64::from(rh.saturating_sub(1).max(1)),
    );
    if (image_aspect / raster_aspect - 1.0).abs() > 0.01 {
        say!(
            "note: the image is {image_aspect:.3} times as wide as high, the raster's cells \
             {raster_aspect:.3}: the image is stretched to the raster"
        );
    }
    Ok(color)
}

/// Write `terrain` into `out` (created if missing) with a progress bar, then describe it.
fn save(out: &Path, terrain: &Terrain) -> Result<()> {
    terrain
        .validate()
        .map_err(|e| anyhow::anyhow!("writing {}: {e}", out.display()))?;
    let context = || format!("writing {}", out.display());
    let color = terrain
        .color
        .as_ref()
        .with_context(|| format!("writing {}: no colour map to write", out.display()))?;
    fs::create_dir_all(out).with_context(context)?;
    {
        let mut p = Progress::new("writing");
        let heights = terrain.heights.samples().len() as u64 * 2;
        let cells = color.cells();
        let total = heights + color.rgb().len() as u64 * 3;
        pnm::write_pgm_with(&out.join(HEIGHTS_FILE), &terrain.heights, &mut |d, _| {
            p.update(d * 2, total)
        })
        .with_context(context)?;
        pnm::write_ppm_with(
            &out.join(COLOR_FILE),
            cells,
            cells,
            color.rgb(),
            &mut |d, _| p.update(heights + d, total),
        )
        .with_context(context)?;
    }
    fs::write(out.join(MAP_FILE), terrain.map.to_toml()).with_context(context)?;
    say!("wrote {}", out.display());
    for line in describe(terrain) {
        say!("{line}");
    }
    Ok(())
}

/// Unit vector towards a sun at compass `azimuth` (0 north = −Z, 90 east = +X) and
/// `elevation` degrees above the horizon.
fn sun_from_angles(azimuth: f64, elevation: f64) -> Option<[f64; 3]> {
    if !(azimuth.is_finite() && (-90.0..=90.0).contains(&elevation)) {
        return None;
    }
    let (az, el) = (azimuth.to_radians(), elevation.to_radians());
    let d = [az.sin() * el.cos(), el.sin(), -az.cos() * el.cos()];
    normalize(d)
}

/// `X,Y,Z` as three numbers.
fn parse_vec3(s: &str) -> Result<[f64; 3], String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let [x, y, z] = parts[..] else {
        return Err(format!("expected X,Y,Z (three numbers), got {s:?}"));
    };
    let num = |t: &str| {
        t.parse::<f64>()
            .map_err(|_| format!("expected a number, got {t:?}"))
    };
    Ok([num(x)?, num(y)?, num(z)?])
}

/// `R,G,B` as three integers 0..=255.
fn parse_rgb(s: &str) -> Result<[u8; 3], String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let [r, g, b] = parts[..] else {
        return Err(format!(
            "expected R,G,B (three integers 0..=255), got {s:?}"
        ));
    };
    let byte = |t: &str| {
        t.parse::<u8>()
            .map_err(|_| format!("expected an integer 0..=255, got {t:?}"))
    };
    Ok([byte(r)?, byte(g)?, byte(b)?])
}

/// `X,Y,W` as three non-negative integers.
fn parse_crop(s: &str) -> Result<[u32; 3], String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let [x, y, w] = parts[..] else {
        return Err(format!("expected X,Y,W (three integers), got {s:?}"));
    };
    let int = |t: &str| {
        t.parse::<u32>()
            .map_err(|_| format!("expected an integer ≥ 0, got {t:?}"))
    };
    Ok([int(x)?, int(y)?, int(w)?])
}

/// `terrarium` or `mapbox`.
fn parse_encoding(s: &str) -> Result<RgbEncoding, String> {
    match s {
        "terrarium" => Ok(RgbEncoding::Terrarium),
        "mapbox" => Ok(RgbEncoding::Mapbox),
        _ => Err(format!("expected terrarium or mapbox, got {s:?}")),
    }
}
