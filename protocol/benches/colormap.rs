//! `cargo bench -p roam-protocol --bench colormap [-- PATH.ppm]`: the colour map codec on a
//! binary P6 PPM (by default the bundled `data/kossou/color.ppm`): sizes (raw, coded) and
//! the best of a few encode and decode times. Prints one JSON object.
// A benchmark prints its figures (JSON), and shares helpers with the tests by path.
#![allow(unreachable_pub, clippy::print_stdout)]

use std::time::Instant;

use roam_protocol::colormap;

/// The side and texels of a square binary P6 PPM with maxval 255.
fn read_ppm(bytes: &[u8]) -> Option<(u32, &[u8])> {
    let mut fields = Vec::new();
    let mut at = 0;
    while fields.len() < 4 {
        while bytes.get(at)?.is_ascii_whitespace() {
            at += 1;
        }
        let start = at;
        while !bytes.get(at)?.is_ascii_whitespace() {
            at += 1;
        }
        fields.push(std::str::from_utf8(&bytes[start..at]).ok()?);
    }
    let (w, h): (u32, u32) = (fields[1].parse().ok()?, fields[2].parse().ok()?);
    if fields[0] != "P6" || fields[3] != "255" || w != h {
        return None;
    }
    let rgb = bytes.get(at + 1..)?;
    (rgb.len() == w as usize * h as usize * 3).then_some((w, rgb))
}

fn main() {
    let path = std::env::args()
        .skip(1)
        .find(|a| !a.starts_with('-'))
        .unwrap_or_else(|| concat!(env!("CARGO_MANIFEST_DIR"), "/../data/kossou/color.ppm").into());
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{path}: {e}"));
    let (cells, rgb) = read_ppm(&bytes).unwrap_or_else(|| panic!("{path}: not a square P6 PPM"));
    const RUNS: usize = 5;
    let (mut enc_s, mut dec_s) = (f64::MAX, f64::MAX);
    let mut coded = Vec::new();
    let mut back = Vec::new();
    for _ in 0..RUNS {
        coded.clear();
        let t = Instant::now();
        colormap::encode(cells, rgb, &mut coded).expect("texels of the right size");
        enc_s = enc_s.min(t.elapsed().as_secs_f64());
        let t = Instant::now();
        colormap::decode(cells, &coded, &mut back).expect("decodes");
        dec_s = dec_s.min(t.elapsed().as_secs_f64());
        assert!(back == rgb, "round trip");
    }
    println!(
        "{{\"path\":\"{path}\",\"cells\":{cells},\"raw\":{},\"coded\":{},\"ratio\":{:.3},\"bits_per_texel\":{:.3},\"encode_ms\":{:.1},\"decode_ms\":{:.1}}}",
        rgb.len(),
        coded.len(),
        rgb.len() as f64 / coded.len() as f64,
        coded.len() as f64 * 8.0 / f64::from(cells * cells),
        enc_s * 1e3,
        dec_s * 1e3,
    );
}
