//! Tests of the colour pyramid: tiles decode to the box-filtered texels, the bytes do not
//! depend on the thread count, and the cache round-trips and is rebuilt when stale or
//! damaged.

use super::*;

/// A `cells²` map of smooth colour under noise.
fn map(cells: u32) -> ColorMap {
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let rgb = (0..cells * cells)
        .map(|i| {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let noise = (state >> 59) as u32;
            let (x, z) = (i % cells, i / cells);
            [
                (x * 3 + noise) as u8,
                (z * 2 + noise) as u8,
                ((x + z) + 2 * noise) as u8,
            ]
        })
        .collect();
    ColorMap::new(cells, rgb).expect("cells² texels")
}

/// Level `l` of `color`, averaged the plain way.
fn level(color: &ColorMap, l: u8) -> (u32, Vec<[u8; 3]>) {
    let mut side = color.cells();
    let mut texels = color.rgb().to_vec();
    for _ in 0..l {
        let h = side / 2;
        let at = |x: u32, z: u32| texels[(z * side + x) as usize];
        let next = (0..h * h)
            .map(|i| {
                let (x, z) = (i % h * 2, i / h * 2);
                std::array::from_fn(|c| {
                    let s: u32 = [at(x, z), at(x + 1, z), at(x, z + 1), at(x + 1, z + 1)]
                        .iter()
                        .map(|p| u32::from(p[c]))
                        .sum();
                    ((s + 2) / 4) as u8
                })
            })
            .collect();
        texels = next;
        side = h;
    }
    (side, texels)
}

fn no_progress() -> impl FnMut(u64, u64) {
    |_, _| {}
}

#[test]
fn tiles_decode_to_the_box_filtered_texels() {
    let color = map(64);
    let mut seen = Vec::new();
    let p = ColorPyramid::build(&color, 16, 2, &mut |d, t| seen.push((d, t))).expect("a valid map");
    assert_eq!(p.levels(), 3);
    assert_eq!(seen.last(), Some(&(16 + 4 + 1, 21)));
    let layout = p.layout(2).expect("a valid layout");
    for l in 0..p.levels() {
        let (side, texels) = level(&color, l);
        let t = layout.tile_side(l);
        for z in 0..layout.tiles(l) {
            for x in 0..layout.tiles(l) {
                let mut out = Vec::new();
                colormap::decode(t, p.tile(l, x, z).expect("in the pyramid"), &mut out)
                    .expect("a tile decodes");
                let want: Vec<u8> = (0..t * t)
                    .flat_map(|i| texels[((z * t + i / t) * side + x * t + i % t) as usize])
                    .collect();
                assert_eq!(out, want, "level {l} tile ({x}, {z})");
            }
        }
    }
    assert_eq!(p.tile(0, 4, 0), None);
    assert_eq!(p.tile(3, 0, 0), None);
}

#[test]
fn the_bytes_do_not_depend_on_the_thread_count() {
    let color = map(128);
    let one = ColorPyramid::build(&color, 32, 1, &mut no_progress()).expect("a valid map");
    let three = ColorPyramid::build(&color, 32, 3, &mut no_progress()).expect("a valid map");
    assert_eq!(one.payload_bytes(), three.payload_bytes());
    assert_eq!(one.store.index, three.store.index);
}

#[test]
fn a_map_smaller_than_a_tile_is_one_tile() {
    let color = map(8);
    let p = ColorPyramid::build(&color, 256, 2, &mut no_progress()).expect("a valid map");
    assert_eq!(p.levels(), 1);
    let mut out = Vec::new();
    colormap::decode(8, p.tile(0, 0, 0).expect("the tile"), &mut out).expect("decodes");
    assert_eq!(
        out,
        color.rgb().iter().flatten().copied().collect::<Vec<_>>()
    );
}

/// A fresh data-set folder holding a `color.ppm` (only its length and date matter here).
fn dataset(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("roam-pyramid-{}-{name}", std::process::id()));
    let _ = fs::remove_dir_all(&dir);
    fs::create_dir_all(&dir).expect("temp folder");
    fs::write(dir.join(COLOR_FILE), b"P6 stand-in").expect("temp file");
    dir
}

fn open(dir: &Path, color: &ColorMap) -> (ColorPyramid, CacheOutcome) {
    ColorPyramid::open_or_build(dir, color, 16, 2, &mut no_progress()).expect("a valid map")
}

#[test]
fn the_cache_round_trips_and_is_mapped() {
    let dir = dataset("round-trip");
    let color = map(64);
    let (built, outcome) = open(&dir, &color);
    assert_eq!(outcome, CacheOutcome::Built);
    assert!(!built.is_mapped());
    let (mapped, outcome) = open(&dir, &color);
    assert_eq!(outcome, CacheOutcome::Mapped);
    assert!(mapped.is_mapped());
    assert_eq!(mapped.coded_bytes(), built.coded_bytes());
    for l in 0..3 {
        let n = 4 >> l;
        for i in 0..n * n {
            assert_eq!(mapped.tile(l, i % n, i / n), built.tile(l, i % n, i / n));
        }
    }
    // Another tile size is another cache: rebuilt, and valid after.
    let (_, outcome) =
        ColorPyramid::open_or_build(&dir, &color, 32, 2, &mut no_progress()).expect("valid");
    assert!(matches!(&outcome, CacheOutcome::Rebuilt(why) if why.contains("tiles of 16")));
    let _ = fs::remove_dir_all(&dir);
}

#[test]
fn a_damaged_or_stale_cache_is_rebuilt() {
    let dir = dataset("damaged");
    let color = map(64);
    let path = cache_path(&dir);
    open(&dir, &color);
    let good = fs::read(&path).expect("the cache was written");
    type Damage = Box<dyn Fn(&mut Vec<u8>)>;
    let damages: [(&str, Damage); 4] = [
        ("hash mismatch", Box::new(|b| b[HEADER + HASH + 5] ^= 1)),
        ("payload bytes", Box::new(|b| b.truncate(b.len() - 1))),
        ("header", Box::new(|b| b.truncate(HEADER - 1))),
        ("not a colour tile cache", Box::new(|b| b[0] = b'x')),
    ];
    for (want, damage) in damages {
        let mut bytes = good.clone();
        damage(&mut bytes);
        fs::write(&path, &bytes).expect("temp file");
        let (p, outcome) = open(&dir, &color);
        assert!(
            matches!(&outcome, CacheOutcome::Rebuilt(why) if why.contains(want)),
            "{want}: {outcome:?}"
        );
        assert!(p.tile(0, 3, 3).is_some());
        assert_eq!(fs::read(&path).expect("rewritten"), good, "{want}");
    }
    // A changed color.ppm makes the cache stale.
    fs::write(dir.join(COLOR_FILE), b"P6 another stand-in").expect("temp file");
    let (_, outcome) = open(&dir, &color);
    assert!(
        matches!(&outcome, CacheOutcome::Rebuilt(why) if why.contains("stale")),
        "{outcome:?}"
    );
    assert_eq!(open(&dir, &color).1, CacheOutcome::Mapped);
    // So does one of the same length with its modification time set back (a copy keeping
    // times, `touch -r`): its change time moved.
    let mtime = fs::metadata(dir.join(COLOR_FILE))
        .and_then(|m| m.modified())
        .expect("a date");
    let same_length = b"P6 anotheR stand-in";
    assert_eq!(
        fs::metadata(dir.join(COLOR_FILE)).map(|m| m.len()).ok(),
        Some(same_length.len() as u64)
    );
    fs::write(dir.join(COLOR_FILE), same_length).expect("temp file");
    fs::File::options()
        .write(true)
        .open(dir.join(COLOR_FILE))
        .and_then(|f| f.set_modified(mtime))
        .expect("set the date back");
    let (_, outcome) = open(&dir, &color);
    assert!(
        matches!(&outcome, CacheOutcome::Rebuilt(why) if why.contains("stale")),
        "{outcome:?}"
    );
    let _ = fs::remove_dir_all(&dir);
}

/// A damaged tile payload (the header and index intact) is never served: found at open
/// (every payload checked) and the cache rebuilt; damaged after open, found the first time
/// the tile is asked for, reported once, and the cache's stamp removed so that the next
/// open rebuilds it.
#[test]
fn a_damaged_tile_is_not_served() {
    let dir = dataset("damaged-tile");
    let color = map(64);
    let path = cache_path(&dir);
    let (built, _) = open(&dir, &color);
    let good = fs::read(&path).expect("the cache was written");
    // 64² in tiles of 16: 16 + 4 + 1 tiles; the payloads follow the index, finest first.
    // A damaged finer tile (header and index intact): found at open, where every payload
    // is checked against its check, and the cache rebuilt.
    let base = HEADER + HASH + 21 * ENTRY;
    let mut bytes = good.clone();
    bytes[base + 20] ^= 0x40;
    fs::write(&path, &bytes).expect("temp file");
    let (_, outcome) = open(&dir, &color);
    assert!(
        matches!(&outcome, CacheOutcome::Rebuilt(why) if why.contains("tile (0, 0) of level 0")),
        "{outcome:?}"
    );
    assert_eq!(fs::read(&path).expect("rewritten"), good);
    // Checked whole, the cache is stamped. Damaged in place while mapped (the map sees
    // it): found when the tile is first served, reported once, never sent, and the stamp
    // removed, so the next open checks the file whole and rebuilds it.
    let (p, outcome) = open(&dir, &color);
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
    let (_, outcome) = open(&dir, &color);
    assert!(
        matches!(&outcome, CacheOutcome::Rebuilt(why) if why.contains("tile (0, 0) of level 0")),
        "{outcome:?}"
    );
    assert_eq!(fs::read(&path).expect("rewritten"), good);
    // The coarsest tile's payload is the file's last bytes.
    let mut bytes = good.clone();
    let last = bytes.len() - 1;
    bytes[last] ^= 0x40;
    fs::write(&path, &bytes).expect("temp file");
    let (_, outcome) = open(&dir, &color);
    assert!(
        matches!(&outcome, CacheOutcome::Rebuilt(why) if why.contains("the coarsest tile")),
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
    // A file where the cache folder should be: nothing can be written under it.
    fs::write(dir.join(CACHE_DIR), b"in the way").expect("temp file");
    let color = map(32);
    let (p, outcome) = open(&dir, &color);
    assert!(matches!(outcome, CacheOutcome::InMemory(_)), "{outcome:?}");
    assert!(!p.is_mapped() && p.tile(0, 1, 1).is_some() && p.tile(1, 0, 0).is_some());
    let _ = fs::remove_dir_all(&dir);
}
