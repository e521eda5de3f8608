//! The data set's cache (`DIR/.cache/`): what `dataset::open_cached` maps equals what
//! `dataset::load` and `VarianceTree::build` make, byte for byte; a changed `hf.pgm`, and a
//! truncated, corrupt or foreign cache file, are rebuilt with the reason; a data set whose
//! cache cannot be written is served from memory; `serve`'s open trusts only files re-hashed
//! whole since they last changed.

use std::fs;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU32, Ordering};

use roam_server::terrain::cache::{self, CacheReport, Source, Stage};
use roam_server::terrain::dataset::{self, Terrain};
use roam_server::terrain::generate;
use roam_server::terrain::variance::VarianceTree;

/// A fresh directory under the system temp dir, removed on drop.
struct TempDir(PathBuf);

impl TempDir {
    fn new(name: &str) -> TempDir {
        static COUNTER: AtomicU32 = AtomicU32::new(0);
        let n = COUNTER.fetch_add(1, Ordering::Relaxed);
        let dir =
            std::env::temp_dir().join(format!("roam-cache-test-{}-{n}-{name}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        fs::create_dir_all(&dir).expect("create temp dir");
        TempDir(dir)
    }

    fn cache(&self, file: &str) -> PathBuf {
        self.0.join(cache::CACHE_DIR).join(file)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = fs::remove_dir_all(&self.0);
    }
}

const SIDE: u32 = 65;

/// A generated data set of `SIDE`² samples written to a fresh directory.
fn data_set(name: &str, seed: u64) -> TempDir {
    let dir = TempDir::new(name);
    dataset::save(&dir.0, &generate::synthetic(SIDE, seed)).expect("save the data set");
    dir
}

fn open(dir: &Path) -> (Terrain, VarianceTree, CacheReport) {
    let (terrain, vt, report, _) = open_staged(dir);
    (terrain, vt, report)
}

/// Opens through the cache; also returns the stages reported, each once, in order.
fn open_staged(dir: &Path) -> (Terrain, VarianceTree, CacheReport, Vec<Stage>) {
    let mut stages = Vec::new();
    let (terrain, vt, report) = dataset::open_cached(dir, 2, &mut |stage, done, total| {
        assert!(done <= total, "{stage:?}: {done} of {total}");
        if stages.last() != Some(&stage) {
            stages.push(stage);
        }
    })
    .expect("the data set opens");
    (terrain, vt, report, stages)
}

/// The opened heights and codes equal an in-memory load and build of the same directory.
fn assert_same_as_load(dir: &Path, terrain: &Terrain, vt: &VarianceTree) {
    let loaded = dataset::load(dir, &mut |_, _| {}).expect("the data set loads");
    assert_eq!(terrain.map, loaded.map);
    assert_eq!(terrain.heights.samples(), loaded.heights.samples());
    assert_eq!(terrain.color, None, "opened for serving: no colour map");
    let built = VarianceTree::build(&loaded.heights, 1, &mut |_, _| {});
    assert_eq!(vt.size(), built.size());
    assert_eq!(vt.codes(), built.codes());
}

/// What a report says, less the heights' hash (checked where it matters).
fn report(heights: Source, variance: Source) -> (Source, Source, Vec<String>) {
    (heights, variance, vec![])
}

fn said(r: &CacheReport) -> (Source, Source, Vec<String>) {
    (r.heights, r.variance, r.notes.clone())
}

#[test]
fn round_trip_equals_the_in_memory_build() {
    let dir = data_set("round-trip", 3);
    let (terrain, vt, got, stages) = open_staged(&dir.0);
    assert_eq!(said(&got), report(Source::Built, Source::Built));
    assert_eq!(
        stages,
        [
            Stage::Hashing,
            Stage::Converting,
            Stage::Verifying,
            Stage::Variance
        ]
    );
    assert!(terrain.heights.is_mapped() && vt.is_mapped());
    assert_same_as_load(&dir.0, &terrain, &vt);
    // The files: a header, then the values as they are in memory (little-endian).
    let heights = fs::read(dir.cache(cache::HEIGHTS_FILE)).expect("heights.bin");
    let le: Vec<u8> = terrain
        .heights
        .samples()
        .iter()
        .flat_map(|s| s.to_le_bytes())
        .collect();
    assert!(heights.ends_with(&le) && heights.len() == le.len() + 128);
    let variance = fs::read(dir.cache(cache::VARIANCE_FILE)).expect("variance.bin");
    assert!(variance.ends_with(vt.codes()) && variance.len() == vt.codes().len() + 128);

    // Opened again: mapped from the cache, the same bytes, no notes; nothing converted or
    // built. (hf.pgm is hashed again when the stamp is within 2 s of its ctime.)
    let (again, vt2, got, stages) = open_staged(&dir.0);
    assert_eq!(said(&got), report(Source::Cached, Source::Cached));
    assert!(
        stages.ends_with(&[Stage::Verifying])
            && !stages.contains(&Stage::Converting)
            && !stages.contains(&Stage::Variance),
        "{stages:?}"
    );
    assert!(again.heights.is_mapped() && vt2.is_mapped());
    assert_same_as_load(&dir.0, &again, &vt2);
    assert_eq!(again.content_hash(), terrain.content_hash());
}

#[test]
fn a_changed_heightfield_is_never_served_from_a_stale_cache() {
    let dir = data_set("changed", 3);
    let (before, _, _) = open(&dir.0);
    // The same bytes written again (new mtime and ctime): re-hashed, the cache kept.
    let bytes = fs::read(dir.0.join(dataset::HEIGHTS_FILE)).expect("hf.pgm");
    fs::write(dir.0.join(dataset::HEIGHTS_FILE), &bytes).expect("rewrite hf.pgm");
    let (_, _, got) = open(&dir.0);
    assert_eq!(said(&got), report(Source::Cached, Source::Cached));

    // Other heights of the same size: rebuilt, with the reason.
    let other = generate::synthetic(SIDE, 4);
    assert_ne!(other.heights, before.heights);
    dataset::save(&dir.0, &other).expect("save other heights");
    let (terrain, vt, got) = open(&dir.0);
    assert_eq!((got.heights, got.variance), (Source::Built, Source::Built));
    assert_eq!(got.notes.len(), 2, "{:?}", got.notes);
    assert!(
        got.notes[0].contains("heights.bin: stale: ") && got.notes[0].contains("hf.pgm changed"),
        "{:?}",
        got.notes
    );
    assert!(
        got.notes[1].contains("variance.bin: stale: built from other heights"),
        "{:?}",
        got.notes
    );
    assert_eq!(terrain.heights, other.heights);
    assert_same_as_load(&dir.0, &terrain, &vt);
}

/// Damages a cache file in place (as another program or a failing disk would).
fn damage(path: &Path, how: &dyn Fn(&mut Vec<u8>)) {
    let mut bytes = fs::read(path).expect("the cache file exists");
    how(&mut bytes);
    // A new file, not an in-place write: nothing still maps the old one here, but a rename
    // keeps the rule that cache files are never written in place.
    let tmp = path.with_extension("damaged");
    fs::write(&tmp, &bytes).expect("write the damaged copy");
    fs::rename(&tmp, path).expect("replace the cache file");
}

#[test]
fn damaged_cache_files_are_rebuilt_with_the_reason() {
    let dir = data_set("damaged", 5);
    open(&dir.0);
    type Damage = (&'static str, fn(&mut Vec<u8>), &'static str);
    let cases: [Damage; 8] = [
        (
            cache::HEIGHTS_FILE,
            |b| b.truncate(1000),
            "length: expected 8578 bytes, got 1000 (truncated)",
        ),
        (
            cache::HEIGHTS_FILE,
            |b| b.truncate(10),
            "truncated: expected at least a 128-byte header",
        ),
        (
            cache::HEIGHTS_FILE,
            |b| b[8] = 99,
            "format version: expected 1, got 99",
        ),
        (cache::HEIGHTS_FILE, |b| b[0] = b'X', "magic: expected"),
        (
            cache::HEIGHTS_FILE,
            |b| b[500] ^= 1,
            "corrupt: the samples do not match their hash",
        ),
        (cache::VARIANCE_FILE, |b| b.push(0), "length: expected"),
        (
            cache::VARIANCE_FILE,
            |b| b[200] ^= 0x40,
            "corrupt: the codes do not match their hash",
        ),
        (
            cache::VARIANCE_FILE,
            |b| b[20] ^= 1,
            "code table: built with another table",
        ),
    ];
    for (file, how, reason) in cases {
        damage(&dir.cache(file), &how);
        let (terrain, vt, got) = open(&dir.0);
        let rebuilt = if file == cache::HEIGHTS_FILE {
            got.heights
        } else {
            got.variance
        };
        assert_eq!(rebuilt, Source::Built, "{file}: {reason}");
        let note = format!("{}: {reason}", dir.cache(file).display());
        assert!(
            got.notes
                .first()
                .is_some_and(|n| n.starts_with(&note) && n.ends_with("; rebuilding it")),
            "{file}: expected {note:?}, got {:?}",
            got.notes
        );
        assert_same_as_load(&dir.0, &terrain, &vt);
        // And the next open trusts the rebuilt files.
        assert_eq!(
            said(&open(&dir.0).2),
            report(Source::Cached, Source::Cached)
        );
    }
}

#[test]
fn a_data_set_whose_cache_cannot_be_written_is_served_from_memory() {
    let dir = data_set("read-only", 6);
    // `.cache` a plain file: its directory cannot be made (a read-only directory does not
    // stop root, who runs some test machines).
    fs::write(dir.0.join(cache::CACHE_DIR), b"not a directory").expect("block the cache");
    let (terrain, vt, got) = open(&dir.0);
    assert_eq!(
        (got.heights, got.variance),
        (Source::Memory, Source::Memory)
    );
    assert_eq!(
        got.notes.len(),
        1,
        "one note, not one per file: {:?}",
        got.notes
    );
    assert!(
        got.notes[0].starts_with(&format!(
            "cannot write the cache in {}",
            dir.0.join(cache::CACHE_DIR).display()
        )) && got.notes[0].ends_with("serving from memory (built again on every start)"),
        "{:?}",
        got.notes
    );
    assert!(!terrain.heights.is_mapped() && !vt.is_mapped());
    assert_same_as_load(&dir.0, &terrain, &vt);
}

#[test]
fn open_cached_refuses_what_load_refuses() {
    let dir = data_set("broken", 7);
    open(&dir.0);
    let cases: [(&str, &[u8]); 3] = [
        (dataset::MAP_FILE, b"hScale = -1.0\nvScale = 0.5\n"),
        (dataset::HEIGHTS_FILE, b"P5\n65 65\n65535\n"),
        (dataset::COLOR_FILE, b"P6\n32 32\n255\n"),
    ];
    for (file, content) in cases {
        let good = fs::read(dir.0.join(file)).expect("the file exists");
        fs::write(dir.0.join(file), content).expect("break the file");
        let want = dataset::load(&dir.0, &mut |_, _| {})
            .expect_err("load refuses it")
            .to_string();
        let got = dataset::open_cached(&dir.0, 1, &mut |_, _, _| {})
            .expect_err("open_cached refuses it")
            .to_string();
        assert_eq!(got, want, "{file}");
        fs::write(dir.0.join(file), good).expect("restore the file");
    }
}

/// Opens as `serve` does ([`cache::Verify::Stamps`]); the stages reported, each once.
fn open_trusting(dir: &Path) -> (CacheReport, Vec<Stage>) {
    let mut stages = Vec::new();
    let (terrain, vt, report) =
        dataset::open_cached_with(dir, 2, cache::Verify::Stamps, &mut |stage, _, _| {
            if stages.last() != Some(&stage) {
                stages.push(stage);
            }
        })
        .expect("the data set opens");
    assert_same_as_load(dir, &terrain, &vt);
    (report, stages)
}

/// Dates `verified.stamp` a minute ahead, as an open at least 2 s after the files were
/// written would have (a stamp within 2 s of a file's ctime is not trusted).
fn age(path: &Path) {
    let file = fs::File::options()
        .write(true)
        .open(path)
        .expect("the file exists");
    // A minute after its own mtime (no clock read: the tests keep to the I/O shells' rule).
    let written = file
        .metadata()
        .and_then(|m| m.modified())
        .expect("an mtime");
    file.set_modified(written + std::time::Duration::from_secs(60))
        .expect("set its mtime");
}

#[test]
fn files_re_hashed_since_they_last_changed_are_trusted_by_their_stamps() {
    let dir = data_set("stamps", 8);
    open(&dir.0);
    // Built just now: re-hashed whole (and stamped) by the next open.
    let (got, stages) = open_trusting(&dir.0);
    assert_eq!(said(&got), report(Source::Cached, Source::Cached));
    assert!(stages.contains(&Stage::Verifying), "{stages:?}");
    let verified = dir.cache(cache::VERIFIED_FILE);
    assert!(verified.is_file(), "verified.stamp written");
    // Stamped within 2 s of the files' change: not trusted yet.
    let (_, stages) = open_trusting(&dir.0);
    assert!(stages.contains(&Stage::Verifying), "{stages:?}");
    age(&verified);
    let (got, stages) = open_trusting(&dir.0);
    assert_eq!(said(&got), report(Source::Cached, Source::Cached));
    // (hf.pgm itself is hashed again while its stamp is within 2 s of its ctime.)
    assert!(
        !stages.contains(&Stage::Verifying),
        "no cache file re-hashed: {stages:?}"
    );
    // `check` re-hashes everything whatever the stamps say.
    let (_, _, _, stages) = open_staged(&dir.0);
    assert!(stages.contains(&Stage::Verifying), "{stages:?}");
    // A damaged file is a new file (a new inode and ctime): re-hashed, found, rebuilt.
    age(&verified);
    damage(&dir.cache(cache::HEIGHTS_FILE), &|b| b[500] ^= 1);
    let (got, _) = open_trusting(&dir.0);
    assert_eq!(got.heights, Source::Built, "{:?}", got.notes);
    assert!(
        got.notes[0].contains("corrupt: the samples do not match their hash"),
        "{:?}",
        got.notes
    );
    age(&verified);
    damage(&dir.cache(cache::VARIANCE_FILE), &|b| b[200] ^= 0x40);
    let (got, _) = open_trusting(&dir.0);
    assert_eq!(got.variance, Source::Built, "{:?}", got.notes);
    assert!(
        got.notes[0].contains("corrupt: the codes do not match their hash"),
        "{:?}",
        got.notes
    );
}

/// Codes kept for a tree (`variance.bin`'s) that cannot be one are refused, naming the
/// size or the count expected: a note, and the file rebuilt.
#[test]
fn codes_of_another_size_or_count_are_no_tree() {
    use roam_server::terrain::backing::Backing;
    use roam_server::terrain::variance::CodesError;
    let n = VarianceTree::codes_len(8);
    let cases = [
        (
            0,
            1,
            CodesError::Size(0),
            "size: expected a power of two ≥ 2, got 0",
        ),
        (
            1,
            1,
            CodesError::Size(1),
            "size: expected a power of two ≥ 2, got 1",
        ),
        (
            6,
            1,
            CodesError::Size(6),
            "size: expected a power of two ≥ 2, got 6",
        ),
        (
            8,
            n - 1,
            CodesError::Count {
                expected: n,
                side: 9,
                got: n - 1,
            },
            &*format!("expected {n} codes for a side of 9, got {}", n - 1),
        ),
        (
            8,
            n + 1,
            CodesError::Count {
                expected: n,
                side: 9,
                got: n + 1,
            },
            &*format!("expected {n} codes for a side of 9, got {}", n + 1),
        ),
    ];
    for (size, count, want, words) in cases {
        let Err(got) = VarianceTree::from_codes(size, Backing::Owned(vec![0; count])) else {
            panic!("{words}: a tree");
        };
        assert_eq!((got, got.to_string().as_str()), (want, words));
    }
    assert!(VarianceTree::from_codes(8, Backing::Owned(vec![0; n])).is_ok());
}
