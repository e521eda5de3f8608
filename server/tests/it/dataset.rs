//! Data-set loading: one case per malformed-data rule, round trips, the generator, the
//! bundled data sets, and fuzzing of the PGM reader.

use std::fs;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU32, Ordering};

use proptest::prelude::*;
use roam_server::terrain::dataset::{self, ColorMap, Terrain};
use roam_server::terrain::generate;
use roam_server::terrain::map::MapParams;
use roam_server::terrain::pnm;

/// A fresh directory under the system temp dir, removed on drop.
struct TempDir(PathBuf);

impl TempDir {
    fn new(name: &str) -> TempDir {
        static COUNTER: AtomicU32 = AtomicU32::new(0);
        let n = COUNTER.fetch_add(1, Ordering::Relaxed);
        let dir = std::env::temp_dir().join(format!(
            "roam-dataset-test-{}-{n}-{name}",
            std::process::id()
        ));
        let _ = fs::remove_dir_all(&dir);
        fs::create_dir_all(&dir).expect("create temp dir");
        TempDir(dir)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = fs::remove_dir_all(&self.0);
    }
}

/// Side of the small valid data set every case starts from.
const SIDE: u32 = 5;
const GOOD_MAP: &str = "hScale = 2.0\nvScale = 0.5\n";

fn header(magic: &str, w: u32, h: u32, maxval: u32) -> Vec<u8> {
    format!("{magic}\n{w} {h}\n{maxval}\n").into_bytes()
}

/// A 16-bit PGM of `side²` samples `i * 7` plus `extra` bytes (negative: cut short).
fn pgm16(side: u32, extra: isize) -> Vec<u8> {
    let mut b = header("P5", side, side, 65535);
    for i in 0..side * side {
        b.extend_from_slice(&((i * 7) as u16).to_be_bytes());
    }
    resize(b, extra)
}

fn ppm(size: u32, extra: isize) -> Vec<u8> {
    let mut b = header("P6", size, size, 255);
    b.extend((0..size * size * 3).map(|i| i as u8));
    resize(b, extra)
}

fn resize(mut b: Vec<u8>, extra: isize) -> Vec<u8> {
    let len = (b.len() as isize + extra) as usize;
    b.resize(len, 0xAB);
    b
}

/// Write a data set; `None` leaves that file out.
fn write_set(dir: &Path, map: Option<&str>, hf: Option<&[u8]>, color: Option<&[u8]>) {
    if let Some(m) = map {
        fs::write(dir.join("map"), m).unwrap();
    }
    if let Some(h) = hf {
        fs::write(dir.join("hf.pgm"), h).unwrap();
    }
    if let Some(c) = color {
        fs::write(dir.join("color.ppm"), c).unwrap();
    }
}

fn load(dir: &Path) -> Result<Terrain, roam_server::DataError> {
    dataset::load(dir, &mut |_, _| {})
}

/// Load the set and assert the error names `file` (full path), and every `expected` part
/// (the field and what was expected).
fn check(
    map: Option<&str>,
    hf: Option<&[u8]>,
    color: Option<&[u8]>,
    file: &str,
    expected: &[&str],
) {
    let dir = TempDir::new(file);
    write_set(&dir.0, map, hf, color);
    let err = match load(&dir.0) {
        Ok(_) => panic!("expected an error about {file} {expected:?}, got Ok"),
        Err(e) => e,
    };
    let msg = err.to_string();
    let path = dir.0.join(file).display().to_string();
    assert!(msg.starts_with(&path), "{msg:?} should start with {path:?}");
    assert_eq!(err.file(), dir.0.join(file));
    for part in expected {
        assert!(msg.contains(part), "{msg:?} should contain {part:?}");
    }
}

/// A heightfield file against a valid map and colour map.
fn check_pgm(hf: &[u8], expected: &[&str]) {
    check(
        Some(GOOD_MAP),
        Some(hf),
        Some(&ppm(SIDE - 1, 0)),
        "hf.pgm",
        expected,
    );
}

/// A colour map against a valid heightfield and map.
fn check_ppm(color: &[u8], expected: &[&str]) {
    check(
        Some(GOOD_MAP),
        Some(&pgm16(SIDE, 0)),
        Some(color),
        "color.ppm",
        expected,
    );
}

/// A map file against a valid heightfield and colour map.
fn check_map(map: &str, expected: &[&str]) {
    check(
        Some(map),
        Some(&pgm16(SIDE, 0)),
        Some(&ppm(SIDE - 1, 0)),
        "map",
        expected,
    );
}

/// Load a set that must be valid.
fn load_ok(map: &str, hf: &[u8], color: &[u8]) -> Terrain {
    let dir = TempDir::new("ok");
    write_set(&dir.0, Some(map), Some(hf), Some(color));
    load(&dir.0).unwrap_or_else(|e| panic!("expected Ok, got {e}"))
}

// ---- hf.pgm ---------------------------------------------------------------------------

#[test]
fn pgm_bad_magic() {
    let mut b = pgm16(SIDE, 0);
    b[1] = b'2';
    check_pgm(&b, &["magic", "expected \"P5\" (binary PGM)", "got \"P2\""]);
}

#[test]
fn pgm_width_not_a_number() {
    let mut b = b"P5\nfive 5\n65535\n".to_vec();
    b.extend(vec![0; 50]);
    check_pgm(&b, &["width", "(a decimal number), got 'f'"]);
}

#[test]
fn pgm_side_not_power_of_two_plus_one() {
    check_pgm(
        &pgm16(6, 0),
        &["width", "expected 2^N + 1 (3, 5, 9, …, 32769), got 6"],
    );
    check_pgm(&pgm16(1, 0), &["width", "got 1"]);
}

#[test]
fn pgm_not_square() {
    let mut b = header("P5", 5, 9, 65535);
    b.extend(vec![0; 5 * 9 * 2]);
    check_pgm(&b, &["height", "expected 5", "square", "got 9"]);
}

#[test]
fn pgm_16_bit_ok() {
    let t = load_ok(GOOD_MAP, &pgm16(SIDE, 0), &ppm(SIDE - 1, 0));
    assert_eq!(t.heights.side(), SIDE);
    assert_eq!(t.heights.get(3, 2), (2 * SIDE + 3) as u16 * 7);
    assert_eq!(t.world_height(1, 0), 3.5);
}

#[test]
fn pgm_8_bit_ok() {
    let mut b = header("P5", SIDE, SIDE, 200);
    b.extend((0..SIDE * SIDE).map(|i| (i * 8) as u8));
    let t = load_ok(GOOD_MAP, &b, &ppm(SIDE - 1, 0));
    assert_eq!(
        t.heights.get(4, 4),
        192,
        "8-bit samples are stored as they are"
    );
}

#[test]
fn pgm_maxval_zero() {
    let mut b = header("P5", SIDE, SIDE, 0);
    b.extend(vec![0; 25]);
    check_pgm(&b, &["maxval", "expected 1 ..= 65535, got 0"]);
}

#[test]
fn pgm_maxval_too_large() {
    let mut b = header("P5", SIDE, SIDE, 70000);
    b.extend(vec![0; 50]);
    check_pgm(&b, &["maxval", "expected 1 ..= 65535, got 70000"]);
}

#[test]
fn pgm_sample_above_maxval() {
    let mut b = header("P5", SIDE, SIDE, 100);
    b.extend(vec![0; 25]);
    let at = b.len() - 25 + 2 * 5 + 3;
    b[at] = 101;
    check_pgm(
        &b,
        &["data", "samples ≤ maxval 100, got 101 at row 2, column 3"],
    );
}

#[test]
fn pgm_truncated() {
    check_pgm(
        &pgm16(SIDE, -1),
        &[
            "data",
            "expected 50 bytes (5 × 5 × 2 bytes), got 49",
            "truncated",
        ],
    );
    check_pgm(&header("P5", 5, 5, 65535), &["data", "got 0", "truncated"]);
}

#[test]
fn pgm_trailing_data() {
    check_pgm(
        &pgm16(SIDE, 3),
        &["data", "expected 50 bytes", "got 53", "3 trailing bytes"],
    );
}

#[test]
fn pgm_huge_declared_size_on_tiny_file() {
    // 32769² 16-bit samples would be 2 GiB: the length check must fail before allocating.
    let mut b = header("P5", 32769, 32769, 65535);
    b.extend(vec![0; 1000]);
    check_pgm(
        &b,
        &["data", "expected 2147614722 bytes", "got 1000", "truncated"],
    );
}

#[test]
fn pgm_header_comments_and_whitespace_accepted() {
    let mut b = b"P5 # a comment\n#another\n\t5  # width\r\n5\n# maxval next\n65535\n".to_vec();
    b.extend(pgm16(SIDE, 0).split_off(header("P5", 5, 5, 65535).len()));
    let t = load_ok(GOOD_MAP, &b, &ppm(SIDE - 1, 0));
    assert_eq!(t.heights.get(1, 0), 7);
}

#[test]
fn pgm_maxval_needs_one_whitespace_byte() {
    let mut b = b"P5\n5 5\n65535".to_vec();
    b.extend(vec![0; 50]);
    check_pgm(
        &b,
        &["maxval", "expected a single whitespace byte after maxval"],
    );
}

#[test]
fn missing_files() {
    let ppm = ppm(SIDE - 1, 0);
    let pgm = pgm16(SIDE, 0);
    check(
        Some(GOOD_MAP),
        None,
        Some(&ppm),
        "hf.pgm",
        &["cannot open", "No such file"],
    );
    check(None, Some(&pgm), Some(&ppm), "map", &["cannot open"]);
    check(
        Some(GOOD_MAP),
        Some(&pgm),
        None,
        "color.ppm",
        &["cannot open"],
    );
}

// ---- color.ppm ------------------------------------------------------------------------

#[test]
fn ppm_wrong_size() {
    check_ppm(
        &ppm(3, 0),
        &["width", "expected 4 (one pixel per grid cell), got 3"],
    );
    check_ppm(&ppm(SIDE, 0), &["width", "expected 4", "got 5"]);
    let mut b = header("P6", 4, 5, 255);
    b.extend(vec![0; 60]);
    check_ppm(&b, &["height", "expected 4", "got 5"]);
}

#[test]
fn ppm_wrong_maxval() {
    let mut b = header("P6", 4, 4, 65535);
    b.extend(vec![0; 96]);
    check_ppm(&b, &["maxval", "expected 255 (8-bit RGB), got 65535"]);
}

#[test]
fn ppm_bad_magic() {
    let mut b = ppm(SIDE - 1, 0);
    b[1] = b'3';
    check_ppm(&b, &["magic", "expected \"P6\" (binary PPM)", "got \"P3\""]);
}

#[test]
fn ppm_truncated_and_trailing() {
    check_ppm(&ppm(SIDE - 1, -2), &["data", "expected 48 bytes", "got 46"]);
    check_ppm(
        &ppm(SIDE - 1, 1),
        &["data", "expected 48 bytes", "1 trailing bytes"],
    );
}

// ---- map ------------------------------------------------------------------------------

#[test]
fn map_unknown_key() {
    check_map(
        "hScale = 2.0\nfog = 1\n",
        &["map:2: fog: unknown key: expected one of hScale, vScale"],
    );
}

#[test]
fn map_unknown_key_in_start() {
    check_map(
        "[start]\nx = 1\ny = 2\n",
        &[
            "map:3: start.y: unknown key",
            "expected one of start.x, start.z, start.heading",
        ],
    );
}

#[test]
fn map_wrong_type() {
    check_map(
        "hScale = \"big\"\n",
        &["map:1: hScale", "expected a number, got the string \"big\""],
    );
    check_map(
        "start = 3\n",
        &["start", "expected a table {x, z, heading}, got 3"],
    );
    check_map(
        "sunDir = [1, 2]\n",
        &["sunDir", "expected an array of 3 numbers"],
    );
    check_map(
        "fogColor = [1.5, 2, 3]\n",
        &["fogColor[0]", "integer 0 ..= 255, got 1.5"],
    );
}

#[test]
fn map_scale_not_positive() {
    check_map(
        "hScale = 0\n",
        &["map:1: hScale", "expected 1e-3 ..= 1e4", "got 0.0"],
    );
    check_map(
        "vScale = -0.5\n",
        &["map:1: vScale", "expected 1e-6 ..= 1e3", "got -0.5"],
    );
    check_map(
        "hScale = inf\n",
        &["hScale", "expected a finite number, got inf"],
    );
}

#[test]
fn map_fog_density_negative() {
    check_map(
        "fogDensity = -0.1\n",
        &[
            "map:1: fogDensity",
            "expected 0 ..= 10 (10 / hScale",
            "got -0.1",
        ],
    );
}

#[test]
fn map_sun_dir_zero() {
    check_map(
        "sunDir = [0, 0.0, 0]\n",
        &["sunDir", "expected a non-zero direction towards the sun"],
    );
}

#[test]
fn map_sun_color_component_256() {
    check_map(
        "sunColor = [255, 256, 0]\n",
        &[
            "map:1: sunColor[1]",
            "expected an integer 0 ..= 255, got 256",
        ],
    );
}

#[test]
fn map_start_outside() {
    // hScale 2 on a 5-sample map: the world is 8 units wide.
    check_map(
        "hScale = 2.0\n[start]\nz = 1\nx = 8.5\n",
        &["map:4: start.x", "expected 0 ..= 8 (on the map", "got 8.5"],
    );
    check_map("[start]\nz = -1\n", &["start.z", "got -1"]);
}

#[test]
fn map_invalid_toml() {
    check_map(
        "hScale = 1.0\nvScale = = 2\n",
        &["map:2: syntax", "expected valid TOML"],
    );
}

#[test]
fn map_defaults_and_integers() {
    let t = load_ok(
        "hScale = 3\nwaterLevel = 1\n[start]\nheading = -90\n",
        &pgm16(SIDE, 0),
        &ppm(SIDE - 1, 0),
    );
    let m = t.map;
    assert_eq!((m.h_scale, m.v_scale, m.water_level), (3.0, 0.1, Some(1.0)));
    assert_eq!(
        (m.start.x, m.start.z, m.start.heading_deg),
        (6.0, 6.0, -90.0)
    );
    let len: f64 = m.sun_dir.iter().map(|c| c * c).sum();
    assert!((len - 1.0).abs() < 1e-12);
}

// ---- round trips, generator, bundled data --------------------------------------------

#[test]
fn save_load_round_trip() {
    let dir = TempDir::new("round-trip");
    let mut t = generate::synthetic(33, 3);
    t.map.sun_dir = roam_server::terrain::map::normalize([-1.0, 2.0, 0.3]).unwrap();
    t.map.fog_density = 1.0 / 3.0;
    dataset::save(&dir.0, &t).unwrap();
    let mut calls = Vec::new();
    let back = dataset::load(&dir.0, &mut |done, total| calls.push((done, total))).unwrap();
    assert_eq!(back, t);
    let (done, total) = *calls.last().unwrap();
    assert_eq!(done, total);
    assert!(calls.windows(2).all(|w| w[0].0 <= w[1].0));
    // Without a water level too.
    t.map.water_level = None;
    dataset::save(&dir.0, &t).unwrap();
    assert_eq!(load(&dir.0).unwrap(), t);
}

#[test]
fn save_refuses_inconsistent_terrain() {
    let dir = TempDir::new("bad-save");
    let mut t = generate::synthetic(9, 1);
    t.color = Some(ColorMap::new(4, vec![[0; 3]; 16]).unwrap());
    assert!(dataset::save(&dir.0, &t).is_err());
    let mut t = generate::synthetic(9, 1);
    t.map.start.x = -1.0;
    assert!(dataset::save(&dir.0, &t).is_err());
}

#[test]
fn generator_is_deterministic() {
    let a = generate::heights(65, 7).unwrap();
    assert_eq!(a, generate::heights(65, 7).unwrap());
    assert_ne!(a, generate::heights(65, 8).unwrap());
    let t = generate::synthetic(65, 7);
    assert_eq!(t, generate::synthetic(65, 7));
    assert!(t.validate().is_ok());
    assert!(generate::heights(66, 7).is_err());
}

fn bundled(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../data")
        .join(name)
}

#[test]
fn bundled_synthetic_sets_match_the_generator() {
    for (name, side) in [("synth-65", 65), ("synth-257", 257)] {
        let t = load(&bundled(name)).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(t.heights.side(), side);
        assert_eq!(
            t,
            generate::synthetic(side, 7),
            "data/{name} is not generate --seed 7"
        );
    }
}

#[test]
fn bundled_kossou_loads() {
    let t = load(&bundled("kossou")).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(t.heights.side(), 1025);
    assert_eq!(t.heights.range(), (0, 27900));
    assert_eq!((t.map.h_scale, t.map.v_scale), (92.0, 0.01));
    let water = t.map.water_level.unwrap();
    // The lake surface (sample 2800, the commonest value) lies just below the water level.
    assert!(water > 28.0 && water < 29.0);
    // The start is on dry land.
    let (x, z) = (
        (t.map.start.x / 92.0).round() as u32,
        (t.map.start.z / 92.0).round() as u32,
    );
    assert!(t.world_height(x, z) > water + 5.0);
    assert_eq!(t.color, Some(generate::colorize(&t.heights, &t.map)));
}

#[test]
fn write_pgm_is_byte_exact() {
    let dir = TempDir::new("bytes");
    let path = dir.0.join("hf.pgm");
    fs::write(&path, pgm16(9, 0)).unwrap();
    let h = pnm::read_pgm(&path, &mut |_| {}).unwrap();
    let out = dir.0.join("out.pgm");
    pnm::write_pgm(&out, &h).unwrap();
    assert_eq!(fs::read(&out).unwrap(), pgm16(9, 0));
    let _ = MapParams::default_for_side(9);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(200))]

    #[test]
    fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..200)) {
        let dir = TempDir::new("fuzz");
        let path = dir.0.join("x.pgm");
        fs::write(&path, &bytes).unwrap();
        let _ = pnm::read_pgm(&path, &mut |_| {});
        let _ = pnm::read_ppm(&path, 4, &mut |_| {});
    }

    #[test]
    fn plausible_headers_never_panic(
        head in "P[56][ \t\n#a-z0-9]{0,30}",
        tail in proptest::collection::vec(any::<u8>(), 0..120),
    ) {
        let dir = TempDir::new("fuzz-head");
        let path = dir.0.join("x.pgm");
        let mut bytes = head.into_bytes();
        bytes.extend(tail);
        fs::write(&path, &bytes).unwrap();
        let _ = pnm::read_pgm(&path, &mut |_| {});
        let _ = pnm::read_ppm(&path, 2, &mut |_| {});
    }

    #[test]
    fn arbitrary_map_text_never_panics(text in "[a-zA-Z\\[\\]{}=,.0-9 \"\n_-]{0,80}") {
        let _ = MapParams::parse(&text, 9);
    }
}
