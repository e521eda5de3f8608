//! `roam-server import --color IMAGE`: the colour map taken from an image instead of derived
//! from the heights. The resampling rule (the image spans the source raster edge sample to
//! edge sample, follows the crop and the padding; area-averaged when shrinking, bilinear when
//! growing) is checked case by case on `colorimage::resample`, then end to end through the
//! binary: PNG (grey, RGB, RGBA, palette) and PPM read exactly, a crop, a non-square raster,
//! `data/kossou`'s own colour map, and bad images refused with the file and the reason.

use std::fs;
use std::path::Path;

use crate::common;

use common::{TempDir, check, png_claiming, root};
use roam_server::terrain::colorimage::{Footprint, ResampleError, RgbImage, resample};
use roam_server::terrain::dataset::Terrain;

/// A `w × h` image of single-channel values (shown as `[v, v, v]`).
fn grey(w: u32, h: u32, v: &[u8]) -> RgbImage {
    assert_eq!(v.len() as u32, w * h);
    RgbImage {
        width: w,
        height: h,
        rgb: v.iter().map(|&v| [v; 3]).collect(),
        kind: "test".into(),
    }
}

/// Resamples `image` over `footprint` and compares the first channel with `expected`.
fn check_resample(name: &str, image: RgbImage, footprint: Footprint, expected: &[u8]) {
    let map = resample(&image, &footprint, &mut |_, _| {}).expect(name);
    let got: Vec<u8> = map.rgb().iter().map(|p| p[0]).collect();
    assert_eq!(got, expected, "{name}");
}

fn footprint(raster: (u32, u32), window: (u32, u32, u32, u32), step: f64, cells: u32) -> Footprint {
    Footprint {
        raster,
        window,
        step: (step, step),
        cells,
    }
}

#[test]
fn resampling_rule() {
    let ramp4: Vec<u8> = (0..16).map(|i| i * 10).collect();
    // One pixel a cell: a copy.
    check_resample(
        "copy",
        grey(4, 4, &ramp4),
        footprint((5, 5), (0, 0, 5, 5), 1.0, 4),
        &ramp4,
    );
    // Two pixels a cell each way: the mean of each 2 × 2 block, rounded.
    check_resample(
        "shrink ×2",
        grey(4, 4, &ramp4),
        footprint((3, 3), (0, 0, 3, 3), 1.0, 2),
        &[25, 45, 105, 125],
    );
    // 1.5 pixels a cell: pixels weighted by the area each cell covers (2/3, 1/3).
    check_resample(
        "shrink ×1.5",
        grey(3, 1, &[0, 90, 180]),
        Footprint {
            raster: (3, 2),
            window: (0, 0, 3, 2),
            step: (1.0, 0.5),
            cells: 2,
        },
        &[30, 150, 30, 150],
    );
    // Half a pixel a cell: bilinear between pixel centres, the edges held.
    check_resample(
        "grow ×2",
        grey(2, 1, &[0, 200]),
        Footprint {
            raster: (5, 2),
            window: (0, 0, 5, 2),
            step: (1.0, 0.25),
            cells: 4,
        },
        &[0, 50, 150, 200].repeat(4),
    );
    // A crop of 3 × 3 samples from column 1, row 1 of a 5 × 5 raster: pixels 1 and 2.
    check_resample(
        "crop",
        grey(4, 4, &ramp4),
        footprint((5, 5), (1, 1, 3, 3), 1.0, 2),
        &[50, 60, 90, 100],
    );
    // The same crop of an image twice as fine: 2 × 2 pixels a cell from pixels 2 .. 6.
    let ramp8: Vec<u8> = (0..64).map(|i| i * 3).collect();
    check_resample(
        "crop, shrink ×2",
        grey(8, 8, &ramp8),
        footprint((5, 5), (1, 1, 3, 3), 1.0, 2),
        // (18 + 19 + 26 + 27) · 3 / 4 = 67.5, rounded up; and so on.
        &[68, 74, 116, 122],
    );
    // A 5 × 3 raster on a 4-cell grid: the rows past its 2 cells repeat its last pixels;
    // pixels outside a crop window are never read.
    check_resample(
        "padding",
        grey(4, 2, &[10, 20, 30, 40, 50, 60, 70, 80]),
        footprint((5, 3), (0, 0, 5, 3), 1.0, 4),
        &[
            10, 20, 30, 40, 50, 60, 70, 80, 50, 60, 70, 80, 50, 60, 70, 80,
        ],
    );
    check_resample(
        "padding inside a crop",
        grey(4, 4, &ramp4),
        footprint((5, 5), (0, 0, 3, 3), 1.0, 4),
        &[
            0, 10, 10, 10, 40, 50, 50, 50, 40, 50, 50, 50, 40, 50, 50, 50,
        ],
    );
}

/// What cannot be resampled is refused, saying what was given and what was expected.
#[test]
fn an_empty_image_a_window_off_the_raster_or_no_step_is_refused() {
    let ok = footprint((5, 5), (0, 0, 5, 5), 1.0, 4);
    let image = || grey(4, 4, &[0; 16]);
    let short = RgbImage {
        rgb: vec![[0; 3]; 15],
        ..image()
    };
    let every_pixel = "expected at least 1 × 1, every pixel";
    let mut cases = vec![
        (
            grey(0, 0, &[]),
            ok,
            ResampleError::Image {
                width: 0,
                height: 0,
                pixels: 0,
            },
            format!("a 0 × 0 image of 0 pixels: {every_pixel}"),
        ),
        (
            short,
            ok,
            ResampleError::Image {
                width: 4,
                height: 4,
                pixels: 15,
            },
            format!("a 4 × 4 image of 15 pixels: {every_pixel}"),
        ),
    ];
    let inside = "expected a window inside the raster and at least one cell";
    for (window, cells, given) in [
        (
            (1, 0, 5, 5),
            4,
            "window 1,0 5 × 5 of a 5 × 5 raster, 4 cells",
        ),
        (
            (0, 0, 0, 5),
            4,
            "window 0,0 0 × 5 of a 5 × 5 raster, 4 cells",
        ),
        (
            (0, 0, 5, 5),
            0,
            "window 0,0 5 × 5 of a 5 × 5 raster, 0 cells",
        ),
    ] {
        let off = footprint((5, 5), window, 1.0, cells);
        let want = ResampleError::Window(off);
        cases.push((image(), off, want, format!("{given}: {inside}")));
    }
    for (x, y, given) in [(1.0, 0.0, "1 × 0"), (-1.0, 1.0, "-1 × 1")] {
        let step = Footprint { step: (x, y), ..ok };
        let want = ResampleError::Step { x, y };
        let words = format!("{given} samples a cell: expected numbers > 0");
        cases.push((image(), step, want, words));
    }
    for (image, footprint, want, words) in cases {
        let got = resample(&image, &footprint, &mut |_, _| {}).expect_err(&words);
        assert_eq!((got.to_string(), &got), (words, &want));
    }
}

/// A PNG of `width × height` pixels.
fn png_bytes(
    width: u32,
    height: u32,
    color: png::ColorType,
    depth: png::BitDepth,
    palette: Option<&[u8]>,
    data: &[u8],
) -> Vec<u8> {
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, width, height);
    enc.set_color(color);
    enc.set_depth(depth);
    if let Some(p) = palette {
        enc.set_palette(p.to_vec());
    }
    let mut w = enc.write_header().expect("PNG header");
    w.write_image_data(data).expect("PNG data");
    w.finish().expect("PNG end");
    out
}

fn ppm_bytes(width: u32, height: u32, rgb: &[[u8; 3]]) -> Vec<u8> {
    let mut out = format!("P6\n{width} {height}\n255\n").into_bytes();
    out.extend(rgb.as_flattened());
    out
}

/// A 65² PGM heightfield (a slope).
fn pgm65() -> Vec<u8> {
    let mut out = b"P5\n65 65\n65535\n".to_vec();
    for i in 0..65u32 * 65 {
        out.extend(((i % 65) * 100 + (i / 65) * 7).to_be_bytes()[2..].iter());
    }
    out
}

/// Writes `source` and `image` into a temp dir, runs `import SOURCE OUT --color IMAGE
/// extra…`, asserts the exit code and messages; returns the data set on success.
fn import(
    source: (&str, &[u8]),
    image: (&str, &[u8]),
    extra: &[&str],
    exit: i32,
    expected: &[&str],
) -> Option<Terrain> {
    let dir = TempDir::new(image.0);
    let (src, img) = (dir.path(source.0), dir.path(image.0));
    fs::write(&src, source.1).expect("write the heights");
    fs::write(&img, image.1).expect("write the image");
    let mut args = vec!["--color", img.to_str().expect("a UTF-8 temp path")];
    args.extend_from_slice(extra);
    common::import_file(&src, &dir.path("out"), &args, exit, expected).0
}

#[test]
fn every_image_kind_one_pixel_a_cell_is_copied() {
    let rgb: Vec<[u8; 3]> = (0..64u32 * 64)
        .map(|i| [(i % 64 * 4) as u8, (i / 64 * 4) as u8, (i % 251) as u8])
        .collect();
    let flat = rgb.as_flattened();
    let rgba: Vec<u8> = rgb.iter().flat_map(|p| [p[0], p[1], p[2], 9]).collect();
    let grey: Vec<u8> = rgb.iter().map(|p| p[2]).collect();
    let palette: Vec<u8> = (0..=255u8).flat_map(|i| [i, 255 - i, i / 2]).collect();
    let rgb8 = (png::ColorType::Rgb, png::BitDepth::Eight);
    for (name, bytes, kind, want) in [
        ("c.ppm", ppm_bytes(64, 64, &rgb), "PPM", rgb.clone()),
        (
            "rgb.png",
            png_bytes(64, 64, rgb8.0, rgb8.1, None, flat),
            "8-bit RGB PNG",
            rgb.clone(),
        ),
        (
            "rgba.png",
            png_bytes(64, 64, png::ColorType::Rgba, rgb8.1, None, &rgba),
            "8-bit RGBA PNG",
            rgb.clone(),
        ),
        (
            "grey.png",
            png_bytes(64, 64, png::ColorType::Grayscale, rgb8.1, None, &grey),
            "8-bit greyscale PNG",
            grey.iter().map(|&g| [g; 3]).collect(),
        ),
        (
            "palette.png",
            png_bytes(
                64,
                64,
                png::ColorType::Indexed,
                rgb8.1,
                Some(&palette),
                &grey,
            ),
            "8-bit palette PNG",
            grey.iter().map(|&g| [g, 255 - g, g / 2]).collect(),
        ),
    ] {
        let t = import(
            ("hf.pgm", &pgm65()),
            (name, &bytes),
            &[],
            0,
            &[
                &format!("colour: {kind}, 64 × 64 pixels"),
                "colour map: one pixel a cell, 64 × 64 cells copied from the image",
            ],
        )
        .unwrap();
        assert!(color(&t).rgb() == want.as_slice(), "{name}");
    }
}

#[test]
fn kossou_colour_map_round_trips() {
    let kossou = root().join("data/kossou");
    let dir = TempDir::new("kossou");
    let out = dir.path("out");
    let (hf, color) = (kossou.join("hf.pgm"), kossou.join("color.ppm"));
    check(
        &[
            "import",
            hf.to_str().unwrap(),
            out.to_str().unwrap(),
            "--color",
            color.to_str().unwrap(),
        ],
        0,
        &["colour: PPM, 1024 × 1024 pixels"],
    );
    let got = fs::read(out.join("color.ppm")).expect("written");
    assert!(
        got == fs::read(&color).expect("bundled"),
        "color.ppm differs"
    );
}

#[test]
fn crop_and_padding_follow_the_heights() {
    // A 128² image on the 65² PGM (2 pixels a cell), cropped to 33 samples from (16, 8):
    // cell (x, z) is the mean of pixels 32 + 2x .. 34 + 2x across, 16 + 2z .. 18 + 2z down.
    let px = |x: u32, y: u32| [x as u8, y as u8, ((x * 7 + y * 3) % 256) as u8];
    let rgb: Vec<[u8; 3]> = (0..128 * 128).map(|i| px(i % 128, i / 128)).collect();
    let t = import(
        ("hf.pgm", &pgm65()),
        ("c.ppm", &ppm_bytes(128, 128, &rgb)),
        &["--crop", "16,8,33"],
        0,
        &["colour map: 2.0000 × 2.0000 pixels a cell (area-averaged across, area-averaged down) to 32 × 32 cells"],
    )
    .unwrap();
    for z in 0..32 {
        for x in 0..32 {
            let want: [u8; 3] = std::array::from_fn(|c| {
                let sum: u32 = [(0, 0), (1, 0), (0, 1), (1, 1)]
                    .iter()
                    .map(|&(ox, oy)| u32::from(px(32 + 2 * x + ox, 16 + 2 * z + oy)[c]))
                    .sum();
                ((sum + 2) / 4) as u8
            });
            assert_eq!(color(&t).get(x, z), want, "cell ({x}, {z})");
        }
    }
    // A 40 × 20 raster (16-bit PNG heights) on a 65² grid with a 39 × 19 image: 0.61
    // pixels a cell, bilinear; past the raster's 19 rows the cells repeat its last one.
    let heights: Vec<u8> = (0..40 * 20u16)
        .flat_map(|i| (i % 40 + i / 40).to_be_bytes())
        .collect();
    let pgrey = png_bytes(
        40,
        20,
        png::ColorType::Grayscale,
        png::BitDepth::Sixteen,
        None,
        &heights,
    );
    let rgb: Vec<[u8; 3]> = (0..39 * 19)
        .map(|i| [(i % 39 * 6) as u8, (i / 39 * 13) as u8, 77])
        .collect();
    let t = import(
        ("h.png", &pgrey),
        ("c.ppm", &ppm_bytes(39, 19, &rgb)),
        &[],
        0,
        &["colour map: 0.6094 × 0.6094 pixels a cell (bilinear across, bilinear down) to 64 × 64 cells"],
    )
    .unwrap();
    for x in 0..64 {
        let last = color(&t).get(x, 63);
        assert_eq!(last[1], 18 * 13, "column {x}: the last image row");
        for z in 31..64 {
            assert_eq!(color(&t).get(x, z), last, "({x}, {z})");
        }
        assert_eq!(color(&t).get(x, 0)[2], 77);
        if x > 0 {
            assert!(
                color(&t).get(x, 0)[0] >= color(&t).get(x - 1, 0)[0],
                "a ramp across"
            );
        }
    }
}

#[test]
fn bad_images_say_what_is_wrong() {
    let rgb16 = png_bytes(
        2,
        2,
        png::ColorType::Rgb,
        png::BitDepth::Sixteen,
        None,
        &[7; 24],
    );
    let ok = ppm_bytes(64, 64, &[[1, 2, 3]; 64 * 64]);
    for (name, bytes, expected) in [
        (
            "notes.txt",
            b"hello".to_vec(),
            "notes.txt: not a colour image: expected an 8-bit PNG or a binary PPM (P6)",
        ),
        (
            "deep.png",
            rgb16,
            "deep.png: PNG of 16-bit colour (Rgb): expected 8 bits a channel",
        ),
        (
            "deep.ppm",
            b"P6\n1 1\n65535\n\0\0\0\0\0\0".to_vec(),
            "deep.ppm: PPM maxval: expected 255 (8 bits a channel), got 65535 (16-bit colour",
        ),
        (
            "empty.ppm",
            b"P6\n0 4\n255\n".to_vec(),
            "empty.ppm: PPM width: expected a size ≥ 1, got 0",
        ),
        (
            "cut.ppm",
            ok[..ok.len() - 5].to_vec(),
            "cut.ppm: PPM data: expected 12288 bytes (64 × 64 × 3 bytes), got 12283",
        ),
        (
            "huge.ppm",
            b"P6\n100000 100000\n255\n".to_vec(),
            "huge.ppm: PPM data: expected 30000000000 bytes",
        ),
        (
            "wide.png",
            png_claiming(40_000, 2, 8, 2),
            "wide.png: PNG of 40000 × 2 pixels: expected at most 32769 on each side",
        ),
        (
            "big.png",
            png_claiming(30_000, 30_000, 8, 2),
            "big.png: PNG of 30000 × 30000 pixels (2700030000 bytes raw) cannot fit in 33 bytes",
        ),
        (
            "zero.png",
            png_claiming(0, 5, 8, 2),
            "zero.png: PNG header: ",
        ),
    ] {
        import(("hf.pgm", &pgm65()), (name, &bytes), &[], 1, &[expected]);
    }
    // A missing image is named, before any work on the heights.
    let dir = TempDir::new("missing");
    let src = dir.path("hf.pgm");
    fs::write(&src, pgm65()).expect("write");
    let missing = dir.path("nope.png");
    check(
        &[
            "import",
            src.to_str().unwrap(),
            dir.path("out").to_str().unwrap(),
            "--color",
            missing.to_str().unwrap(),
        ],
        1,
        &["nope.png: cannot open"],
    );
    assert!(!Path::new(&dir.path("out")).exists());
}

/// The colour map of a data set read with `dataset::load` (which always reads it).
fn color(t: &roam_server::terrain::dataset::Terrain) -> &roam_server::terrain::dataset::ColorMap {
    t.color
        .as_ref()
        .expect("dataset::load reads the colour map")
}
