//! Tests of the normal pyramid: tiles decode to the heightfield's normals (level 0) and to
//! the averaged normals (coarser levels) within the code's quantisation, the bytes do not
//! depend on the thread count, and the cache round-trips and is rebuilt when stale or
//! damaged, a damaged tile never served.

use std::fs;

use super::*;
use crate::terrain::tile_store::{ENTRY, HASH};

/// Header bytes of the normal cache: magic, version, cells, tile, levels, key, tiles.
const HEADER: usize = 8 + 4 * 4 + 48 + 8;
/// The code's worst error (see `roam_protocol::normals`), degrees.
const QUANTUM_DEG: f64 = 0.6;

fn no_progress() -> impl FnMut(u64, u64) {
    |_, _| {}
}

/// A rough 65² heightfield (64 cells): hills and per-sample noise.
fn heights(side: u32) -> Heightfield {
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let samples = (0..side * side)
        .map(|i| {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let (x, z) = (f64::from(i % side), f64::from(i / side));
            let hill = 3000.0 + 900.0 * (x / 7.0).sin() * (z / 11.0).cos() + 40.0 * x;
            (hill + (state >> 58) as f64 * 20.0) as u16
        })
        .collect();
    Heightfield::new(side, samples).expect("a 2^N + 1 grid")
}

const SCALES: (f64, f64) = (30.0, 0.1);

/// Level `l`'s normals, averaged the plain way: level 0 from the heights, then whole
/// levels, each texel the renormalised sum of its four children.
fn level(hf: &Heightfield, l: u8) -> (usize, Vec<[f32; 3]>) {
    let cells = hf.size();
    let mut side = cells as usize;
    let mut n: Vec<[f32; 3]> = (0..cells * cells)
        .map(|i| {
            let (x, z) = (i % cells, i / cells);
            normals::cell_normal(
                hf.get(x, z),
                hf.get(x + 1, z),
                hf.get(x, z + 1),
                hf.get(x + 1, z + 1),
                SCALES.0,
                SCALES.1,
            )
        })
        .collect();
    for _ in 0..l {
        let h = side / 2;
        n = (0..h * h)
            .map(|i| {
                let (x, z) = (i % h * 2, i / h * 2);
                let at = |a: usize, b: usize| n[(z + a) * side + x + b];
                let (p, q, r, s) = (at(0, 0), at(0, 1), at(1, 0), at(1, 1));
                normals::normalize(std::array::from_fn(|c| p[c] + q[c] + r[c] + s[c]))
            })
            .collect();
        side = h;
    }
    (side, n)
}

#[test]
fn tiles_decode_to_the_heightfield_normals_and_their_averages() {
    let hf = heights(65);
    let mut seen = Vec::new();
    let p = NormalPyramid::build(&hf, SCALES, 16, 2, &mut |d, t| seen.push((d, t)))
        .expect("a valid grid");
    assert_eq!(p.levels(), 3);
    assert_eq!(seen.last(), Some(&(21, 21)));
    let layout = p.layout(2).expect("a valid layout");
    let mut worst = [0.0f64; 3];
    let mut steep = 0.0f64;
    for l in 0..p.levels() {
        let (side, want) = level(&hf, l);
        let t = layout.tile_side(l);
        for z in 0..layout.tiles(l) {
            for x in 0..layout.tiles(l) {
                let mut out = Vec::new();
                normals::decode_tile(t, p.tile(l, x, z).expect("in the pyramid"), &mut out)
                    .expect("a tile decodes");
                assert_eq!(out.len(), (t * t * 2) as usize);
                for (i, code) in out.chunks_exact(2).enumerate() {
                    let (i, t) = (i as u32, t);
                    let cell = ((z * t + i / t) as usize) * side + (x * t + i % t) as usize;
                    let got = normals::decode([code[0], code[1]]);
                    let e = normals::angle_deg(got, want[cell]);
                    worst[usize::from(l)] = worst[usize::from(l)].max(e);
                    steep = steep.max(normals::angle_deg(want[cell], [0.0, 1.0, 0.0]));
                }
            }
        }
    }
    assert!(worst.iter().all(|&w| w < QUANTUM_DEG), "{worst:?}");
    // The test means something: the ground is far from level.
    assert!(steep > 30.0, "steepest {steep}°");
    assert_eq!(p.tile(0, 4, 0), None);
    assert_eq!(p.tile(3, 0, 0), None);
}

#[test]
fn the_bytes_do_not_depend_on_the_thread_count() {
    let hf = heights(129);
    let one = NormalPyramid::build(&hf, SCALES, 16, 1, &mut no_progress()).expect("valid");
    let three = NormalPyramid::build(&hf, SCALES, 16, 3, &mut no_progress()).expect("valid");
    let eight = NormalPyramid::build(&hf, SCALES, 16, 8, &mut no_progress()).expect("valid");
    assert_eq!(one.store.payload_bytes(), three.store.payload_bytes());
    assert_eq!(one.store.index, three.store.index);
    assert_eq!(one.store.index, eight.store.index);
}

#[test]
fn a_grid_smaller_than_a_tile_is_one_tile() {
    let hf = heights(9);
    let p = NormalPyramid::build(&hf, SCALES, 256, 2, &mut no_progress()).expect("valid");
    assert_eq!(p.levels(), 1);
    let mut out = Vec::new();
    normals::decode_tile(8, p.tile(0, 0, 0).expect("the tile"), &mut out).expect("decodes");
    assert_eq!(out.len(), 8 * 8 * 2);
}

/// A fresh data-set folder (the normals' key is given, not read from a file).
fn dataset(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("roam-normals-{}-{name}", std::process::id()));
    let _ = fs::remove_dir_all(&dir);
    fs::create_dir_all(&dir).expect("temp folder");
    dir
}

fn open(dir: &Path, hf: &Heightfield, hash: [u8; 32]) -> (NormalPyramid, CacheOutcome) {
    NormalPyramid::open_or_build(dir, hf, SCALES, &hash, 16, 2, &mut no_progress())
        .expect("a valid grid")
}

#[test]
fn the_cache_round_trips_and_is_rebuilt_when_stale() {
    let dir = dataset("round-trip");
    let hf = heights(65);
    let (built, outcome) = open(&dir, &hf, [1; 32]);
    assert_eq!(outcome, CacheOutcome::Built);
    assert!(!built.is_mapped());
    let (mapped, outcome) = open(&dir, &hf, [1; 32]);
    assert_eq!(outcome, CacheOutcome::Mapped);
    assert!(mapped.is_mapped());
    assert_eq!(mapped.coded_bytes(), built.coded_bytes());
    for l in 0..3 {
        let n = 4 >> l;
        for i in 0..n * n {
            assert_eq!(mapped.tile(l, i % n, i / n), built.tile(l, i % n, i / n));
        }
    }
    // Other heights (their hash), other scales, another tile size: stale, rebuilt.
    let (_, outcome) = open(&dir, &hf, [2; 32]);
    assert!(
        matches!(&outcome, CacheOutcome::Rebuilt(why) if why.contains("stale")),
        "{outcome:?}"
    );
    let (_, outcome) =
        NormalPyramid::open_or_build(&dir, &hf, (30.0, 0.2), &[2; 32], 16, 2, &mut no_progress())
            .expect("valid");
    assert!(
        matches!(&outcome, CacheOutcome::Rebuilt(why) if why.contains("stale: the heights or the map's scales")),
        "{outcome:?}"
    );
    let (_, outcome) =
        NormalPyramid::open_or_build(&dir, &hf, (30.0, 0.2), &[2; 32], 32, 2, &mut no_progress())
            .expect("valid");
    assert!(matches!(&outcome, CacheOutcome::Rebuilt(why) if why.contains("tiles of 16")));
    let _ = fs::remove_dir_all(&dir);
}

#[test]
fn a_damaged_cache_is_rebuilt_and_a_damaged_tile_never_served() {
    let dir = dataset("damaged");
    let hf = heights(65);
    let path = cache_path(&dir);
    let (built, _) = open(&dir, &hf, [7; 32]);
    let good = fs::read(&path).expect("the cache was written");
    type Damage = Box<dyn Fn(&mut Vec<u8>)>;
    let damages: [(&str, Damage); 5] = [
        ("hash mismatch", Box::new(|b| b[HEADER + HASH + 5] ^= 1)),
        ("payload bytes", Box::new(|b| b.truncate(b.len() - 1))),
        ("header", Box::new(|b| b.truncate(HEADER - 1))),
        ("not a normal tile cache", Box::new(|b| b[0] = b'x')),
        // The coarsest tile's payload is the file's last bytes: checked at open.
        (
            "the coarsest tile",
            Box::new(|b| *b.last_mut().expect("bytes") ^= 0x40),
        ),
    ];
    for (want, damage) in damages {
        let mut bytes = good.clone();
        damage(&mut bytes);
        fs::write(&path, &bytes).expect("temp file");
        let (p, outcome) = open(&dir, &hf, [7; 32]);
        assert!(
            matches!(&outcome, CacheOutcome::Rebuilt(why) if why.contains(want)),
            "{want}: {outcome:?}"
        );
        assert!(p.tile(0, 3, 3).is_some());
        assert_eq!(fs::read(&path).expect("rewritten"), good, "{want}");
    }
    // A damaged finer tile (header and index intact): found at open, where every payload
    // is checked against its check, and the cache rebuilt.
    let base = HEADER + HASH + 21 * ENTRY;
    let mut bytes = good.clone();
    bytes[base + 20] ^= 0x40;
    fs::write(&path, &bytes).expect("temp file");
    let (_, outcome) = open(&dir, &hf, [7; 32]);
    assert!(
        matches!(&outcome, CacheOutcome::Rebuilt(why) if why.contains("tile (0, 0) of level 0")),
        "{outcome:?}"
    );
    assert_eq!(fs::read(&path).expect("rewritten"), good);
    // Checked whole, the cache is stamped. Damaged in place while mapped (the map sees
    // it): found when the tile is first served, reported once, never sent, and the stamp
    // removed, so the next open checks the file whole and rebuilds it.
    let (p, outcome) = open(&dir, &hf, [7; 32]);
    assert_eq!(outcome, CacheOutcome::Mapped);
    let stamp = path.with_extension("bin.verified");
    assert!(stamp.exists(), "{}", stamp.display());
    damage_in_place(&path, base + 20);
    assert_eq!(
        p.served_tile(0, 0, 0),
        Err(TileError::Damaged { first: true })
    );
    assert_eq!(
        p.served_tile(0, 0, 0),
        Err(TileError::Damaged { first: false })
    );
    assert_eq!(
        p.served_tile(0, 1, 0),
        Ok(built.tile(0, 1, 0).expect("a tile"))
    );
    assert_eq!(p.served_tile(0, 4, 0), Err(TileError::Outside));
    assert!(
        !stamp.exists(),
        "the stamp is removed with the first damaged tile"
    );
    drop(p);
    let (_, outcome) = open(&dir, &hf, [7; 32]);
    assert!(
        matches!(&outcome, CacheOutcome::Rebuilt(why) if why.contains("tile (0, 0) of level 0")),
        "{outcome:?}"
    );
    assert_eq!(fs::read(&path).expect("rewritten"), good);
    let _ = fs::remove_dir_all(&dir);
}

/// Flips the byte at `at` of the file at `path` in place (the same inode: a map of it sees
/// the change).
fn damage_in_place(path: &Path, at: usize) {
    use std::io::{Read, Seek, SeekFrom, Write};
    let mut f = fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(path)
        .expect("the temporary cache");
    let mut byte = [0u8];
    f.seek(SeekFrom::Start(at as u64)).expect("seek");
    f.read_exact(&mut byte).expect("a byte there");
    f.seek(SeekFrom::Start(at as u64)).expect("seek");
    f.write_all(&[byte[0] ^ 0x40]).expect("written in place");
}

#[test]
fn an_unwritable_cache_folder_keeps_the_pyramid_in_memory() {
    let dir = dataset("unwritable");
    fs::write(dir.join(store::CACHE_DIR), b"in the way").expect("temp file");
    let hf = heights(33);
    let (p, outcome) = open(&dir, &hf, [3; 32]);
    assert!(matches!(outcome, CacheOutcome::InMemory(_)), "{outcome:?}");
    assert!(!p.is_mapped() && p.tile(0, 1, 1).is_some() && p.tile(1, 0, 0).is_some());
    let _ = fs::remove_dir_all(&dir);
}
