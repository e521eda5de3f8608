//! `roam-server import` on one real SRTM GeoTIFF, `data/srtm/n07_w006_3arc_v2.tif` (the
//! SRTM3 tile `data/kossou` was cut from; see `data/srtm/README.md`): the geometry follows
//! its georeferencing, resampled heights match the file's samples as read here with the
//! `tiff` crate, voids punched into it are filled close to the truth, and the cut with
//! `data/kossou/PROVENANCE.md`'s parameters rebuilds `data/kossou` byte for byte.

use std::fs;
use std::io::Cursor;
use std::path::{Path, PathBuf};

use crate::common;

use common::{TempDir, root};
use roam_server::terrain::dataset::Terrain;
use tiff::decoder::{Decoder, DecodingResult};
use tiff::encoder::{TiffEncoder, colortype};
use tiff::tags::Tag;

/// Metres in one arc-second, the `.hgt` convention the importer uses.
const METRES_PER_ARCSEC: f64 = 30.87;

/// The tile's path, from the workspace root.
fn tile_path() -> PathBuf {
    root().join("data/srtm/n07_w006_3arc_v2.tif")
}

/// The tile as the `tiff` crate reads it: samples, pixel scale, tiepoint, geo keys.
struct Tile {
    side: u32,
    samples: Vec<i16>,
    scale: Vec<f64>,
    tiepoint: Vec<f64>,
    keys: Vec<u16>,
}

impl Tile {
    fn read() -> Tile {
        let bytes =
            fs::read(tile_path()).expect("data/srtm/n07_w006_3arc_v2.tif is in the repository");
        let mut d = Decoder::new(Cursor::new(bytes)).expect("a TIFF");
        let (w, h) = d.dimensions().expect("dimensions");
        assert_eq!((w, h), (1201, 1201), "an SRTM3 tile");
        let mut f64s = |tag: u16| {
            d.get_tag(Tag::Unknown(tag))
                .and_then(|v| v.into_f64_vec())
                .expect("the GeoTIFF tag")
        };
        let (scale, tiepoint) = (f64s(33550), f64s(33922));
        let keys = d.get_tag_u16_vec(Tag::Unknown(34735)).expect("geo keys");
        let DecodingResult::I16(samples) = d.read_image().expect("the image") else {
            panic!("expected 16-bit signed samples");
        };
        Tile {
            side: w,
            samples,
            scale,
            tiepoint,
            keys,
        }
    }

    fn at(&self, x: u32, y: u32) -> f64 {
        f64::from(self.samples[(y * self.side + x) as usize])
    }

    /// The value of geo key `key`.
    fn key(&self, key: u16) -> Option<u16> {
        self.keys[4..]
            .chunks_exact(4)
            .find(|e| e[0] == key)
            .map(|e| e[3])
    }

    /// Bilinear height at source coordinates `(x, y)` (clamped: edge extension).
    fn bilinear(&self, x: f64, y: f64) -> f64 {
        let n = f64::from(self.side - 1);
        let (x, y) = (x.clamp(0.0, n), y.clamp(0.0, n));
        let (x0, y0) = (x.floor() as u32, y.floor() as u32);
        let (x1, y1) = ((x0 + 1).min(self.side - 1), (y0 + 1).min(self.side - 1));
        let (fx, fy) = (x - f64::from(x0), y - f64::from(y0));
        let top = self.at(x0, y0) + (self.at(x1, y0) - self.at(x0, y0)) * fx;
        let bottom = self.at(x0, y1) + (self.at(x1, y1) - self.at(x0, y1)) * fx;
        top + (bottom - top) * fy
    }
}

/// Runs `import SOURCE OUT extra…` into a fresh temp dir; returns it, the data set and stdout.
fn import(source: &Path, extra: &[&str], expected: &[&str]) -> (TempDir, Terrain, String) {
    let dir = TempDir::new("srtm");
    let (t, stdout) = common::import_file(source, &dir.path("out"), extra, 0, expected);
    (dir, t.expect("imported"), stdout)
}

/// The number after `prefix` in `text`.
fn number_after(text: &str, prefix: &str) -> f64 {
    let rest = &text[text
        .find(prefix)
        .unwrap_or_else(|| panic!("{prefix:?} in {text}"))
        + prefix.len()..];
    let end = rest
        .find(|c: char| !(c.is_ascii_digit() || c == '.' || c == '-'))
        .unwrap_or(rest.len());
    rest[..end].parse().expect("a number")
}

#[test]
fn real_srtm_geotiff_geometry_and_heights() {
    let tile = Tile::read();
    // Void-filled SRTM: no sample is GDAL_NODATA.
    assert_eq!(tile.samples.iter().filter(|&&s| s == -32767).count(), 0);
    // The georeferencing, from the tags: 3″ pixels, pixel (0, 0)'s centre at 8°N
    // (PixelIsPoint), so the centre row 600 is at 7.5°N.
    assert_eq!(tile.key(1024), Some(2), "geographic");
    assert_eq!(tile.key(1025), Some(2), "PixelIsPoint");
    let arcsec = tile.scale[0] * 3600.0;
    assert!((arcsec - 3.0).abs() < 1e-9, "{arcsec}″");
    let latitude = tile.tiepoint[4] - 600.0 * tile.scale[1];
    let dy = tile.scale[1] * 3600.0 * METRES_PER_ARCSEC;
    let dx = tile.scale[0] * 3600.0 * METRES_PER_ARCSEC * latitude.to_radians().cos();
    println!("latitude {latitude}°, {dx:.3} m east–west, {dy:.3} m north–south");
    let (_dir, t, stdout) = import(
        &tile_path(),
        &[],
        &[
            "format: GeoTIFF, 16-bit signed integer samples, uncompressed, strips, 1201 × 1201",
            "nodata value -32767 (GDAL_NODATA)",
            &format!(
                "geographic raster: {dx:.2} m a sample east–west, {dy:.2} m north–south at \
                 latitude {latitude:.4}°"
            ),
            "voids filled: 0 (",
            "1201 × 1201 samples padded to a square with edge-extended heights, resampled \
             (bilinear) to 2049 × 2049",
        ],
    );
    assert_eq!(format!("{latitude:.4}"), "7.5000");
    // North–south is the longer extent: 1200 rows over the grid's 2048 intervals.
    let h = t.map.h_scale;
    println!("hScale {h} m, vScale {} m", t.map.v_scale);
    assert!((h - 1200.0 * dy / 2048.0).abs() < 1e-9, "{h}");
    assert_eq!(t.heights.side(), 2049);
    let lowest = -number_after(&stdout, "heights shifted by ");
    // Probes: each grid sample is the bilinear interpolation of the file's samples at its
    // position (edge-extended past the tile's east edge, at x > 1200 · dx / h ≈ 2030.5),
    // within half a vScale step plus the printed lowest height's rounding; and it lies
    // within the range of the four source samples around it.
    for gy in [0, 1, 255, 256, 1000, 1537, 2048] {
        for gx in [0, 3, 700, 1024, 2030, 2031, 2048] {
            let (sx, sy) = (f64::from(gx) * h / dx, f64::from(gy) * h / dy);
            let want = tile.bilinear(sx, sy);
            let got = f64::from(t.heights.get(gx, gy)) * t.map.v_scale + lowest;
            let tol = t.map.v_scale / 2.0 + 0.0005 + 1e-3;
            assert!((got - want).abs() <= tol, "({gx}, {gy}): {got} vs {want}");
            let (x0, y0) = (sx.min(1200.0).floor() as u32, sy.min(1200.0).floor() as u32);
            let around = [(0, 0), (1, 0), (0, 1), (1, 1)]
                .map(|(ox, oy)| tile.at((x0 + ox).min(1200), (y0 + oy).min(1200)));
            let (lo, hi) = around
                .iter()
                .fold((f64::MAX, f64::MIN), |(l, u), &v| (l.min(v), u.max(v)));
            assert!(
                (lo - tol..=hi + tol).contains(&got),
                "({gx}, {gy}): {got} outside {lo} .. {hi}"
            );
        }
    }
    // Grid rows 256 k fall on source rows 150 k exactly.
    let got = f64::from(t.heights.get(0, 256)) * t.map.v_scale + lowest;
    assert!((got - tile.at(0, 150)).abs() <= t.map.v_scale / 2.0 + 2e-3);
}

#[test]
fn real_srtm_tile_rebuilds_data_kossou() {
    let kossou = root().join("data/kossou");
    let (dir, _t, _) = import(
        &tile_path(),
        &[
            "--crop",
            "88,88,1025",
            "--h-scale",
            "92",
            "--v-scale",
            "0.01",
            "--water-level",
            "28.5",
            "--start-x",
            "37628",
            "--start-z",
            "82984",
            "--heading",
            "53",
            "--sun-azimuth",
            "247.5",
            "--sun-elevation",
            "35",
            "--sun-color",
            "255,244,225",
            "--fog-density",
            "5e-5",
            "--fog-color",
            "200,210,218",
        ],
        &[
            "cropped: 1025 × 1025 samples from column 88, row 88",
            "kept at 1025 × 1025 samples",
            "heights 157.000 .. 436.000 m",
        ],
    );
    for file in ["map", "hf.pgm", "color.ppm"] {
        let got = fs::read(dir.path("out").join(file)).expect("written");
        let want = fs::read(kossou.join(file)).expect("bundled");
        assert!(
            got == want,
            "data/kossou/{file} differs from the import of the tile"
        );
    }
}

/// The tile rewritten as a GeoTIFF with the same georeferencing, GDAL_NODATA −32767 and
/// `samples` in place of its own.
fn geotiff_with(tile: &Tile, samples: &[i16]) -> Vec<u8> {
    let mut cursor = Cursor::new(Vec::new());
    let mut enc = TiffEncoder::new(&mut cursor).expect("TIFF header");
    let mut image = enc
        .new_image::<colortype::GrayI16>(tile.side, tile.side)
        .expect("TIFF image");
    let dir = image.encoder();
    dir.write_tag(Tag::Unknown(33550), &tile.scale[..])
        .expect("scale");
    dir.write_tag(Tag::Unknown(33922), &tile.tiepoint[..])
        .expect("tiepoint");
    dir.write_tag(Tag::Unknown(34735), &tile.keys[..])
        .expect("geo keys");
    dir.write_tag(Tag::Unknown(42113), "-32767")
        .expect("nodata");
    image.write_data(samples).expect("TIFF data");
    cursor.into_inner()
}

#[test]
fn real_srtm_voids_are_filled_near_the_truth() {
    let tile = Tile::read();
    // A 24 × 24 hole on a hillside, a 3 × 40 gash, and every 97th sample: 15,000-odd voids.
    let hole = |x: u32, y: u32| {
        ((500..524).contains(&x) && (600..624).contains(&y))
            || ((300..303).contains(&x) && (700..740).contains(&y))
            || (y * tile.side + x).is_multiple_of(97)
    };
    let mut samples = tile.samples.clone();
    let mut voids = 0;
    for y in 0..tile.side {
        for x in 0..tile.side {
            if hole(x, y) {
                samples[(y * tile.side + x) as usize] = -32767;
                voids += 1;
            }
        }
    }
    let dir = TempDir::new("voids");
    let source = dir.path("voids.tif");
    fs::write(&source, geotiff_with(&tile, &samples)).expect("write the GeoTIFF");
    // The data/kossou cut, copied sample for sample (hScale 92 m, vScale 1 cm from 157 m).
    let (_out, t, _) = import(
        &source,
        &[
            "--crop",
            "88,88,1025",
            "--h-scale",
            "92",
            "--v-scale",
            "0.01",
        ],
        &[&format!("voids filled: {voids} (")],
    );
    let metres = |x: u32, y: u32| f64::from(t.heights.get(x - 88, y - 88)) * 0.01 + 157.0;
    let (mut err2, mut dev2, mut n) = (0.0, 0.0, 0.0);
    let (mut single, mut single_err2) = (0, 0.0);
    // The big hole's rim: the ring of valid samples around it.
    let rim: Vec<f64> = (599..625)
        .flat_map(|y| (499..525).map(move |x| (x, y)))
        .filter(|&(x, y)| !hole(x, y))
        .map(|(x, y)| tile.at(x, y))
        .collect();
    let rim_mean = rim.iter().sum::<f64>() / rim.len() as f64;
    for y in 88..1113 {
        for x in 88..1113 {
            let (got, truth) = (metres(x, y), tile.at(x, y));
            if !hole(x, y) {
                assert!(
                    (got - truth).abs() < 1e-6,
                    "({x}, {y}) changed: {got} vs {truth}"
                );
                continue;
            }
            // The fill stays within the range of the valid samples up to 30 away.
            let (mut lo, mut hi) = (f64::MAX, f64::MIN);
            for sy in y.saturating_sub(30)..(y + 30).min(1201) {
                for sx in x.saturating_sub(30)..(x + 30).min(1201) {
                    if !hole(sx, sy) {
                        lo = lo.min(tile.at(sx, sy));
                        hi = hi.max(tile.at(sx, sy));
                    }
                }
            }
            assert!(
                (lo - 0.005..=hi + 0.005).contains(&got),
                "({x}, {y}): {got} outside {lo} .. {hi}"
            );
            if (500..524).contains(&x) && (600..624).contains(&y) {
                err2 += (got - truth).powi(2);
                n += 1.0;
                dev2 += (truth - rim_mean).powi(2);
            } else if [(1, 0), (0, 1), (2, 1), (1, 2)]
                .iter()
                .all(|&(ox, oy)| !hole(x + ox - 1, y + oy - 1))
            {
                // A void with four valid neighbours becomes their mean (Laplace).
                let mean = (tile.at(x - 1, y) + tile.at(x + 1, y))
                    + (tile.at(x, y - 1) + tile.at(x, y + 1));
                assert!(
                    (got - mean / 4.0).abs() <= 0.0051,
                    "({x}, {y}): {got} vs {mean} / 4"
                );
                single += 1;
                single_err2 += (got - truth).powi(2);
            }
        }
    }
    let (rms, spread) = ((err2 / n).sqrt(), (dev2 / n).sqrt());
    println!("24 × 24 hole: fill RMS error {rms:.2} m; {spread:.2} m filled with its rim's mean");
    println!(
        "{single} isolated voids: fill RMS error {:.2} m",
        (single_err2 / f64::from(single)).sqrt()
    );
    assert!(single > 10_000, "{single} isolated voids checked");
    assert!(
        rms < spread,
        "RMS error {rms} m, {spread} m with the rim's mean"
    );
}
