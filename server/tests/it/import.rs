//! End-to-end tests of `roam-server import` on the formats beyond PGM: SRTM `.hgt` tiles
//! (voids, georeferencing from the name), 16-bit greyscale PNGs (padding, resampling, the
//! z-scale), Terrarium and Mapbox Terrain-RGB PNGs, and bad files (clear errors, no panic).
//! Every source file is written by the test into its own temp directory.

use crate::common;

use common::{import_bytes as import, png_claiming};
use roam_server::terrain::dataset::Terrain;

/// A `.hgt` tile of `side²` big-endian samples from `h(x, y)`.
fn hgt_bytes(side: u32, h: impl Fn(u32, u32) -> i16) -> Vec<u8> {
    (0..side)
        .flat_map(|y| (0..side).map(move |x| (x, y)))
        .flat_map(|(x, y)| h(x, y).to_be_bytes())
        .collect()
}

/// A PNG of `width × height` pixels, `data` packed as the colour type and depth say.
fn png_bytes(
    width: u32,
    height: u32,
    color: png::ColorType,
    depth: png::BitDepth,
    data: &[u8],
) -> Vec<u8> {
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, width, height);
    enc.set_color(color);
    enc.set_depth(depth);
    let mut w = enc.write_header().expect("PNG header");
    w.write_image_data(data).expect("PNG data");
    w.finish().expect("PNG end");
    out
}

/// A 16-bit greyscale PNG from `s(x, y)`.
fn png16(width: u32, height: u32, s: impl Fn(u32, u32) -> u16) -> Vec<u8> {
    let data: Vec<u8> = (0..height)
        .flat_map(|y| (0..width).map(move |x| (x, y)))
        .flat_map(|(x, y)| s(x, y).to_be_bytes())
        .collect();
    png_bytes(
        width,
        height,
        png::ColorType::Grayscale,
        png::BitDepth::Sixteen,
        &data,
    )
}

/// The world height of sample `(x, z)` plus the shift `import` applied (its lowest height).
fn metres(t: &Terrain, x: u32, z: u32, lowest: f64) -> f64 {
    f64::from(t.heights.get(x, z)) * t.map.v_scale + lowest
}

#[test]
fn hgt_voids_are_filled_smoothly_and_counted() {
    let plane = |x: u32, y: u32| 500.0 + 0.1 * f64::from(x) + 0.2 * f64::from(y);
    let hole = |x: u32, y: u32| (300..320).contains(&x) && (200..220).contains(&y);
    let bytes = hgt_bytes(1201, |x, y| {
        if hole(x, y) || (x, y) == (700, 900) {
            -32768
        } else {
            plane(x, y).round() as i16
        }
    });
    let (_dir, t, _) = import(
        "N45E006.hgt",
        &bytes,
        &["--crop", "0,0,1025", "--h-scale", "90"],
        0,
        &[
            "format: SRTM .hgt (3″ a sample), 1201 × 1201 samples",
            "voids filled: 401 (",
            "sample spacing 90 m (from --h-scale)",
            "kept at 1025 × 1025 samples",
            "cropped: 1025 × 1025 samples from column 0, row 0",
            "heights shifted by -500.000 m so the lowest is 0",
        ],
    );
    let t = t.unwrap();
    assert_eq!(t.heights.side(), 1025);
    // The rim of the hole, two samples wide, bounds the fill.
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for y in 198..222 {
        for x in 298..322 {
            if !hole(x, y) {
                lo = lo.min(plane(x, y).round());
                hi = hi.max(plane(x, y).round());
            }
        }
    }
    for y in 190..230 {
        for x in 290..330 {
            let h = metres(&t, x, y, 500.0);
            if hole(x, y) {
                assert!(
                    (lo..=hi).contains(&h),
                    "({x}, {y}): {h} outside the rim's {lo} .. {hi}"
                );
                assert!(
                    (h - plane(x, y)).abs() < 2.0,
                    "({x}, {y}): {h}, a plane there is {}",
                    plane(x, y)
                );
            }
        }
    }
    // The whole tile, resampled to square samples: north–south is the longer extent.
    let (_dir, t, _) = import(
        "n45e006.hgt",
        &bytes,
        &[],
        0,
        &[
            "1201 × 1201 samples padded to a square with edge-extended heights, resampled (bilinear) to 2049 × 2049",
        ],
    );
    let t = t.unwrap();
    assert!(
        (t.map.h_scale - 1200.0 * 3.0 * 30.87 / 2048.0).abs() < 1e-9,
        "{}",
        t.map.h_scale
    );
    // The tile's east–west extent is cos 45.5° of its north–south one: the rest is edge.
    let last = t.heights.get(2048, 0);
    assert!(
        (f64::from(last) * t.map.v_scale - 120.0).abs() < 0.5,
        "{last}"
    );
    // No name: --h-scale, and said so.
    import(
        "tile.hgt",
        &bytes,
        &["--side", "129"],
        0,
        &[
            "no latitude in the file name",
            "give --h-scale",
            "to 129 × 129",
        ],
    );
}

#[test]
fn png16_round_trip_within_half_a_step() {
    let s = |x: u32, y: u32| (x * 977 + y * 331) as u16;
    let (_dir, t, _) = import(
        "square.png",
        &png16(65, 65, s),
        &["--z-scale", "0.25", "--z-offset", "-100", "--h-scale", "30"],
        0,
        &[
            "format: 16-bit greyscale PNG, 65 × 65 samples",
            "kept at 65 × 65 samples",
            "hScale 30 m",
            "vScale ",
        ],
    );
    let t = t.unwrap();
    assert_eq!(t.map.h_scale, 30.0);
    for y in 0..65 {
        for x in 0..65 {
            let want = f64::from(s(x, y)) * 0.25 - 100.0;
            let got = metres(&t, x, y, -100.0);
            assert!(
                (got - want).abs() <= t.map.v_scale / 2.0 + 1e-6,
                "({x}, {y}): {got} vs {want}"
            );
        }
    }
}

#[test]
fn non_square_png_is_padded_with_its_edges() {
    let s = |x: u32, y: u32| (1000 + 10 * x + 20 * y) as u16;
    let (_dir, t, _) = import(
        "wide.png",
        &png16(40, 20, s),
        &[],
        0,
        &[
            "40 × 20 samples padded to a square with edge-extended heights, resampled (bilinear) to 65 × 65",
            "hScale 0.609375 m",
        ],
    );
    let t = t.unwrap();
    assert_eq!(t.heights.side(), 65);
    for x in 0..65 {
        let sx = (f64::from(x) * 39.0 / 64.0).min(39.0);
        // Every row past the raster's bottom repeats its bottom edge: no cliff.
        for z in [40, 64] {
            let got = metres(&t, x, z, 1000.0);
            let want = 1000.0 + 10.0 * sx + 20.0 * 19.0;
            assert!((got - want).abs() < 0.01, "({x}, {z}): {got} vs {want}");
        }
    }
}

#[test]
fn terrain_rgb_encodings() {
    // (encoding, pixel, metres), the lowest pixel first (it becomes 0).
    let check_rgb = |encoding: &str, pixels: &[([u8; 3], f64)]| {
        let data: Vec<u8> = pixels.iter().flat_map(|(p, _)| *p).collect();
        let bytes = png_bytes(3, 3, png::ColorType::Rgb, png::BitDepth::Eight, &data);
        let (_dir, t, _) = import(
            "rgb.png",
            &bytes,
            &["--rgb-encoding", encoding],
            0,
            &["RGB PNG, 3 × 3 samples"],
        );
        let t = t.unwrap();
        let lowest = pixels[0].1;
        for (i, (p, want)) in pixels.iter().enumerate() {
            let got = metres(&t, i as u32 % 3, i as u32 / 3, lowest);
            assert!(
                (got - want).abs() <= t.map.v_scale / 2.0 + 1e-6,
                "{encoding} {p:?}: {got} vs {want}"
            );
        }
    };
    check_rgb(
        "terrarium",
        &[
            ([127, 255, 0], -1.0),
            ([128, 0, 0], 0.0),
            ([128, 100, 128], 100.5),
            ([128, 1, 0], 1.0),
            ([129, 0, 64], 256.25),
            ([130, 0, 0], 512.0),
            ([128, 2, 0], 2.0),
            ([128, 3, 0], 3.0),
            ([128, 4, 0], 4.0),
        ],
    );
    check_rgb(
        "mapbox",
        &[
            ([1, 134, 160], 0.0),
            ([1, 138, 136], 100.0),
            ([1, 134, 161], 0.1),
            ([1, 134, 170], 1.0),
            ([1, 135, 160], 25.6),
            ([1, 200, 0], 1673.6),
            ([1, 134, 162], 0.2),
            ([1, 134, 163], 0.3),
            ([1, 134, 164], 0.4),
        ],
    );
}

#[test]
fn bad_files_say_what_is_wrong() {
    let rgb = png_bytes(2, 2, png::ColorType::Rgb, png::BitDepth::Eight, &[128; 12]);
    let grey8 = png_bytes(
        2,
        2,
        png::ColorType::Grayscale,
        png::BitDepth::Eight,
        &[1; 4],
    );
    let good = png16(64, 64, |x, y| (x * y) as u16);
    let truncated = &good[..good.len() / 2];
    let voids = hgt_bytes(1201, |_, _| -32768);
    for (name, bytes, extra, expected) in [
        (
            "rgb.png",
            &rgb[..],
            &[][..],
            &[
                "rgb.png: an 8-bit RGB PNG: say how heights are encoded with --rgb-encoding terrarium or --rgb-encoding mapbox",
            ][..],
        ),
        (
            "grey.png",
            &good[..],
            &["--rgb-encoding", "mapbox"],
            &["--rgb-encoding applies to RGB PNGs only"],
        ),
        (
            "grey8.png",
            &grey8[..],
            &[],
            &["grey8.png: PNG of colour type Grayscale at 8 bits: expected 16-bit greyscale"],
        ),
        ("cut.png", truncated, &[], &["cut.png: PNG"]),
        (
            "huge.png",
            &png_claiming(100_000, 100_000, 16, 0)[..],
            &[],
            &["huge.png: PNG of 100000 × 100000 pixels: expected at most 32769 on each side"],
        ),
        (
            "big.png",
            &png_claiming(30_000, 30_000, 16, 0)[..],
            &[],
            &["big.png: PNG of 30000 × 30000 pixels (1800030000 bytes raw) cannot fit in 33 bytes"],
        ),
        (
            "cut.hgt",
            &voids[..1000],
            &[],
            &["cut.hgt: not a PGM, PNG, GeoTIFF or SRTM .hgt file: no PGM, PNG or TIFF signature"],
        ),
        (
            "N01E001.hgt",
            &voids[..],
            &[],
            &["N01E001.hgt: every sample is a void"],
        ),
        (
            "N01E002.hgt",
            &hgt_bytes(1201, |_, _| 5)[..],
            &["--crop", "1000,0,300"],
            &["--crop 1000,0,300: expected a window", "1201 × 1201 raster"],
        ),
        (
            "N01E003.hgt",
            &hgt_bytes(1201, |_, _| 5)[..],
            &["--z-scale", "2"],
            &["N01E003.hgt: --rgb-encoding, --z-scale and --z-offset apply to PNG files only"],
        ),
        (
            "s.png",
            &good[..],
            &["--side", "100"],
            &["--side: expected 2^N + 1"],
        ),
    ] {
        import(name, bytes, extra, 1, expected);
    }
}
