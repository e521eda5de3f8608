//! End-to-end tests of `roam-server import` on GeoTIFFs: integer and float samples,
//! uncompressed and LZW / Deflate, nodata, projected and geographic georeferencing, feet,
//! and bad files (clear errors naming the file, no panic, no allocation from the tags).
//! Every file is written by the test, with the `tiff` crate's encoder or byte by byte.

use std::io::Cursor;

use crate::common;

use common::TempDir;
use roam_server::terrain::dataset::Terrain;
use tiff::encoder::colortype::{self, ColorType};
use tiff::encoder::{
    Compression, DeflateLevel, TiffEncoder, TiffKind, TiffKindBig, TiffKindStandard, TiffValue,
};
use tiff::tags::Tag;

/// The GeoTIFF tags a test file carries.
#[derive(Clone, Default)]
struct Geo {
    /// ModelPixelScaleTag.
    scale: Option<[f64; 3]>,
    /// ModelTiepointTag: raster (I, J, K) at model (X, Y, Z).
    tiepoint: Option<[f64; 6]>,
    /// GeoKeyDirectoryTag's short keys, `(key, value)`.
    keys: Vec<(u16, u16)>,
    /// GDAL_NODATA.
    nodata: Option<&'static str>,
}

/// A projected raster of `spacing` metres.
fn projected(spacing: f64) -> Geo {
    Geo {
        scale: Some([spacing, spacing, 0.0]),
        keys: vec![(1024, 1), (3076, 9001)],
        ..Geo::default()
    }
}

/// A one-image TIFF of `width × height` samples of colour type `C`.
fn tiff_bytes<C: ColorType>(
    width: u32,
    height: u32,
    data: &[C::Inner],
    compression: Compression,
    geo: &Geo,
) -> Vec<u8>
where
    [C::Inner]: TiffValue,
{
    tiff_of_kind::<C, TiffKindStandard>(width, height, data, compression, geo)
}

/// [`tiff_bytes`] as a classic TIFF or a BigTIFF (`K`).
fn tiff_of_kind<C: ColorType, K: TiffKind>(
    width: u32,
    height: u32,
    data: &[C::Inner],
    compression: Compression,
    geo: &Geo,
) -> Vec<u8>
where
    [C::Inner]: TiffValue,
{
    let mut cursor = Cursor::new(Vec::new());
    let mut enc = TiffEncoder::<_, K>::new_generic(&mut cursor)
        .expect("TIFF header")
        .with_compression(compression);
    let mut image = enc.new_image::<C>(width, height).expect("TIFF image");
    let dir = image.encoder();
    if let Some(s) = geo.scale {
        dir.write_tag(Tag::Unknown(33550), &s[..]).expect("scale");
    }
    if let Some(t) = geo.tiepoint {
        dir.write_tag(Tag::Unknown(33922), &t[..])
            .expect("tiepoint");
    }
    if !geo.keys.is_empty() {
        let mut keys = vec![1u16, 1, 0, geo.keys.len() as u16];
        for &(k, v) in &geo.keys {
            keys.extend([k, 0, 1, v]);
        }
        dir.write_tag(Tag::Unknown(34735), &keys[..])
            .expect("geo keys");
    }
    if let Some(n) = geo.nodata {
        dir.write_tag(Tag::Unknown(42113), n).expect("nodata");
    }
    image.write_data(data).expect("TIFF data");
    cursor.into_inner()
}

/// [`common::import_bytes`] without stdout.
fn import(
    name: &str,
    bytes: &[u8],
    extra: &[&str],
    exit: i32,
    expected: &[&str],
) -> (TempDir, Option<Terrain>) {
    let (dir, terrain, _) = common::import_bytes(name, bytes, extra, exit, expected);
    (dir, terrain)
}

/// Asserts every sample of the `side²` data set is `want(x, y)` metres within half a
/// vScale step, `lowest` being the height `import` shifted to 0.
fn assert_heights(t: &Terrain, side: u32, lowest: f64, want: impl Fn(u32, u32) -> f64) {
    assert_eq!(t.heights.side(), side);
    for y in 0..side {
        for x in 0..side {
            let got = f64::from(t.heights.get(x, y)) * t.map.v_scale + lowest;
            let w = want(x, y);
            assert!(
                (got - w).abs() <= t.map.v_scale / 2.0 + 1e-4,
                "({x}, {y}): {got} vs {w}"
            );
        }
    }
}

#[test]
fn integer_samples_round_trip_with_projected_spacing() {
    let s = |x: u32, y: u32| (x * 977 + y * 331) as u16;
    let data: Vec<u16> = (0..65 * 65).map(|i| s(i % 65, i / 65)).collect();
    let bytes = tiff_bytes::<colortype::Gray16>(65, 65, &data, Compression::Uncompressed, &{
        projected(30.0)
    });
    let (_dir, t) = import(
        "u16.tif",
        &bytes,
        &[],
        0,
        &[
            "format: GeoTIFF, 16-bit unsigned integer samples, uncompressed, strips, 65 × 65 samples",
            "heights metres (assumed: no VerticalUnitsGeoKey)",
            "projected raster: 30 m a sample east–west, 30 m north–south (from ModelPixelScale, in metre)",
            "kept at 65 × 65 samples",
            "hScale 30 m",
        ],
    );
    let t = t.unwrap();
    assert_eq!(t.map.h_scale, 30.0);
    assert_heights(&t, 65, 0.0, |x, y| f64::from(s(x, y)));

    // Signed samples in feet, horizontally and vertically.
    let s = |x: u32, y: u32| (x as i32 * 40 - y as i32 * 25 - 300) as i16;
    let data: Vec<i16> = (0..33 * 33).map(|i| s(i % 33, i / 33)).collect();
    let geo = Geo {
        scale: Some([10.0, 10.0, 0.0]),
        keys: vec![(1024, 1), (3076, 9002), (4099, 9002)],
        ..Geo::default()
    };
    let bytes = tiff_bytes::<colortype::GrayI16>(33, 33, &data, Compression::Lzw, &geo);
    let (_dir, t) = import(
        "feet.tif",
        &bytes,
        &[],
        0,
        &[
            "16-bit signed integer samples, LZW, strips, 33 × 33 samples",
            "heights in foot (VerticalUnitsGeoKey 9002), converted to metres",
            "in foot)",
        ],
    );
    let t = t.unwrap();
    assert!((t.map.h_scale - 3.048).abs() < 1e-9, "{}", t.map.h_scale);
    let lowest = f64::from(s(0, 32)) * 0.3048;
    assert_heights(&t, 33, lowest, |x, y| f64::from(s(x, y)) * 0.3048);
}

/// A BigTIFF (64-bit offsets, as GDAL writes past 4 GiB) reads as the classic TIFF of the
/// same samples does.
#[test]
fn bigtiff_reads_as_tiff() {
    let s = |x: u32, y: u32| (x * 613 + y * 211) as u16;
    let data: Vec<u16> = (0..33 * 33).map(|i| s(i % 33, i / 33)).collect();
    let compression = Compression::Deflate(DeflateLevel::Balanced);
    let big = tiff_of_kind::<colortype::Gray16, TiffKindBig>(33, 33, &data, compression, &{
        projected(10.0)
    });
    assert_eq!(&big[..4], b"II+\0", "a BigTIFF header");
    let (_dir, t) = import(
        "big.tif",
        &big,
        &[],
        0,
        &["16-bit unsigned integer samples", "hScale 10 m"],
    );
    let t = t.expect("imported");
    let lowest = f64::from(data.iter().copied().min().expect("samples"));
    assert_heights(&t, 33, lowest, |x, y| f64::from(s(x, y)));
}

#[test]
fn float_samples_with_nodata_in_every_compression() {
    let h = |x: u32, y: u32| 1000.0 + 0.37 * x as f32 - 0.61 * y as f32;
    let void = |x: u32, y: u32| (10..12).contains(&x) && y == 20;
    let data: Vec<f32> = (0..65 * 65)
        .map(|i| {
            let (x, y) = (i % 65, i / 65);
            if void(x, y) {
                -9999.0
            } else if (x, y) == (40, 40) {
                f32::NAN
            } else {
                h(x, y)
            }
        })
        .collect();
    let geo = Geo {
        nodata: Some("-9999"),
        ..projected(2.0)
    };
    for (compression, name) in [
        (Compression::Uncompressed, "uncompressed"),
        (Compression::Lzw, "LZW"),
        (Compression::Deflate(DeflateLevel::Balanced), "Deflate"),
    ] {
        let bytes = tiff_bytes::<colortype::Gray32Float>(65, 65, &data, compression, &geo);
        let (_dir, t) = import(
            "f32.tif",
            &bytes,
            &[],
            0,
            &[
                &format!("format: GeoTIFF, 32-bit float samples, {name}, strips, 65 × 65"),
                "nodata value -9999 (GDAL_NODATA): those samples are voids",
                "voids filled: 3 (",
                "hScale 2 m",
            ],
        );
        let t = t.unwrap();
        let lowest = f64::from(h(0, 64));
        let t = &t;
        // A plane's voids are filled close to the plane.
        assert_heights(t, 65, lowest, |x, y| f64::from(h(x, y)));
    }
}

#[test]
fn georeferencing_sets_the_spacing() {
    let data: Vec<u16> = (0..65 * 65).map(|i| (i % 65 + i / 65) as u16).collect();
    let write =
        |geo: &Geo| tiff_bytes::<colortype::Gray16>(65, 65, &data, Compression::Uncompressed, geo);
    // 1″ samples whose top edge is at 46°N: centred 32.5″ further south.
    let geographic = Geo {
        scale: Some([1.0 / 3600.0, 1.0 / 3600.0, 0.0]),
        tiepoint: Some([0.0, 0.0, 0.0, 6.0, 46.0, 0.0]),
        keys: vec![(1024, 2), (2054, 9102)],
        ..Geo::default()
    };
    let latitude: f64 = 46.0 - 32.5 / 3600.0;
    let dx = 30.87 * latitude.to_radians().cos();
    let (_dir, t) = import(
        "geo.tif",
        &write(&geographic),
        &[],
        0,
        &[
            &format!(
                "geographic raster: {dx:.2} m a sample east–west, 30.87 m north–south at \
                 latitude {latitude:.4}° (from ModelPixelScale and ModelTiepoint)"
            ),
            "65 × 65 samples padded to a square with edge-extended heights, resampled",
        ],
    );
    // North–south is the longer extent: 64 samples of 30.87 m over 64 intervals.
    let t = t.unwrap();
    assert!((t.map.h_scale - 30.87).abs() < 1e-9, "{}", t.map.h_scale);
    // --h-scale overrides; no georeferencing or an unknown unit leaves the spacing at 1 m.
    let feet_model = Geo {
        keys: vec![(1024, 1), (3076, 9036)],
        ..projected(5.0)
    };
    for (name, geo, extra, expected) in [
        (
            "over.tif",
            geographic.clone(),
            &["--h-scale", "12"][..],
            "sample spacing 12 m (from --h-scale)",
        ),
        (
            "plain.tif",
            Geo::default(),
            &[],
            "no usable georeferencing (no ModelPixelScaleTag): sample spacing 1 m; give --h-scale",
        ),
        (
            "unit.tif",
            feet_model,
            &[],
            "no usable georeferencing (ProjLinearUnitsGeoKey 9036: expected 9001",
        ),
    ] {
        import(name, &write(&geo), extra, 0, &[expected]);
    }
}

/// A little-endian TIFF header and IFD claiming `width × height` 16-bit samples in one
/// strip, and no image data.
fn tiff_claiming(width: u32, height: u32) -> Vec<u8> {
    // (tag, type: 3 SHORT / 4 LONG, value)
    let entries: [(u16, u16, u32); 8] = [
        (256, 4, width),
        (257, 4, height),
        (258, 3, 16),
        (259, 3, 1),
        (262, 3, 1),
        (273, 4, 8),
        (278, 4, height),
        (279, 4, width.wrapping_mul(height).wrapping_mul(2)),
    ];
    let mut out = b"II*\0".to_vec();
    out.extend(8u32.to_le_bytes());
    out.extend((entries.len() as u16).to_le_bytes());
    for (tag, ty, value) in entries {
        out.extend(tag.to_le_bytes());
        out.extend(ty.to_le_bytes());
        out.extend(1u32.to_le_bytes());
        if ty == 3 {
            out.extend((value as u16).to_le_bytes());
            out.extend([0, 0]);
        } else {
            out.extend(value.to_le_bytes());
        }
    }
    out.extend(0u32.to_le_bytes());
    out
}

/// A little-endian, uncompressed, tiled TIFF of `side²` 16-bit samples `s(x, y)` in tiles of
/// 16 × 16; the padding past the image's edges holds 65535.
fn tiled_tiff(side: u32, s: impl Fn(u32, u32) -> u16) -> Vec<u8> {
    let across = side.div_ceil(16);
    let tiles = across * across;
    let tile_bytes = 16 * 16 * 2;
    // Header, IFD (2 + 10 entries × 12 + 4), the two offset arrays, then the tiles.
    let ifd_len = 2 + 10 * 12 + 4;
    let offsets_at = 8 + ifd_len;
    let counts_at = offsets_at + 4 * tiles;
    let data_at = counts_at + 4 * tiles;
    let entries: [(u16, u16, u32, u32); 10] = [
        (256, 4, 1, side),
        (257, 4, 1, side),
        (258, 3, 1, 16),
        (259, 3, 1, 1),
        (262, 3, 1, 1),
        (277, 3, 1, 1),
        (322, 4, 1, 16),
        (323, 4, 1, 16),
        (324, 4, tiles, offsets_at),
        (325, 4, tiles, counts_at),
    ];
    let mut out = b"II*\0".to_vec();
    out.extend(8u32.to_le_bytes());
    out.extend((entries.len() as u16).to_le_bytes());
    for (tag, ty, count, value) in entries {
        out.extend(tag.to_le_bytes());
        out.extend(ty.to_le_bytes());
        out.extend(count.to_le_bytes());
        if ty == 3 {
            out.extend((value as u16).to_le_bytes());
            out.extend([0, 0]);
        } else {
            out.extend(value.to_le_bytes());
        }
    }
    out.extend(0u32.to_le_bytes());
    for t in 0..tiles {
        out.extend((data_at + t * tile_bytes).to_le_bytes());
    }
    for _ in 0..tiles {
        out.extend(tile_bytes.to_le_bytes());
    }
    for t in 0..tiles {
        let (tx, ty) = (t % across * 16, t / across * 16);
        for y in ty..ty + 16 {
            for x in tx..tx + 16 {
                let v = if x < side && y < side { s(x, y) } else { 65535 };
                out.extend(v.to_le_bytes());
            }
        }
    }
    out
}

#[test]
fn tiles_are_placed_and_their_padding_dropped() {
    let s = |x: u32, y: u32| (1000 + x * 7 + y * 3) as u16;
    let (_dir, t) = import(
        "tiled.tif",
        &tiled_tiff(33, s),
        &[],
        0,
        &[
            "format: GeoTIFF, 16-bit unsigned integer samples, uncompressed, tiles, 33 × 33",
            "kept at 33 × 33 samples",
        ],
    );
    assert_heights(&t.unwrap(), 33, 1000.0, |x, y| f64::from(s(x, y)));
}

#[test]
fn bad_tiffs_say_what_is_wrong() {
    let plain = Geo::default();
    let rgb = tiff_bytes::<colortype::RGB8>(2, 2, &[9; 12], Compression::Uncompressed, &plain);
    let grey8 = tiff_bytes::<colortype::Gray8>(2, 2, &[9; 4], Compression::Uncompressed, &plain);
    let voids = tiff_bytes::<colortype::Gray32Float>(
        4,
        4,
        &[-1.0; 16],
        Compression::Lzw,
        &Geo {
            nodata: Some("-1"),
            ..Geo::default()
        },
    );
    let good =
        tiff_bytes::<colortype::Gray16>(64, 64, &[7; 64 * 64], Compression::Uncompressed, &plain);
    for (name, bytes, extra, expected) in [
        (
            "junk.tif",
            &b"II*\0\xff\xff\xff\xff"[..],
            &[][..],
            "junk.tif: TIFF header: ",
        ),
        (
            "text.tif",
            &b"not a tiff at all"[..],
            &[],
            "text.tif: not a PGM, PNG, GeoTIFF or SRTM .hgt file",
        ),
        (
            "rgb.tif",
            &rgb[..],
            &[],
            "rgb.tif: TIFF of 3 samples a pixel (samples interleaved), photometric \
             interpretation 2: expected one greyscale sample a pixel",
        ),
        (
            "grey8.tif",
            &grey8[..],
            &[],
            "grey8.tif: TIFF of 8-bit unsigned integer samples (SampleFormat 1): expected 16- \
             or 32-bit integers, or 32- or 64-bit floats",
        ),
        (
            "wide.tif",
            &tiff_claiming(40_000, 40_000)[..],
            &[],
            "wide.tif: TIFF of 40000 × 40000 pixels: expected at most 32769 on each side",
        ),
        (
            "big.tif",
            &tiff_claiming(30_000, 30_000)[..],
            &[],
            "big.tif: TIFF of 30000 × 30000 16-bit unsigned integer samples (1800000000 bytes \
             raw, uncompressed) cannot fit in 110 bytes",
        ),
        (
            "voids.tif",
            &voids[..],
            &[],
            "voids.tif: every sample is a void",
        ),
        ("cut.tif", &good[..good.len() / 2], &[], "cut.tif: TIFF "),
        (
            "z.tif",
            &good[..],
            &["--z-scale", "2"],
            "z.tif: --rgb-encoding, --z-scale and --z-offset apply to PNG files only; this is a GeoTIFF",
        ),
    ] {
        import(name, bytes, extra, 1, &[expected]);
    }
}
