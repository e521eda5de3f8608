//! The data set's hash cached in `DIR/.cache/content.hash` (`dataset::content_hash_cached`):
//! always the hash a whole `dataset::load` computes (what recordings name); taken from the
//! cache without reading `color.ppm` when the heights, the map and `color.ppm`'s stamp are
//! the ones it names; computed again when any of them changed, when the stamp is racy, or
//! when the file is damaged.

use std::fs;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::Duration;

use roam_server::terrain::cache::{self, CacheReport};
use roam_server::terrain::dataset::{self, HashSource, Terrain};
use roam_server::terrain::generate;

/// A fresh directory under the system temp dir holding a generated 65² data set, removed
/// on drop.
struct DataSet(PathBuf);

impl DataSet {
    fn new(name: &str, seed: u64) -> DataSet {
        static COUNTER: AtomicU32 = AtomicU32::new(0);
        let n = COUNTER.fetch_add(1, Ordering::Relaxed);
        let dir = std::env::temp_dir().join(format!(
            "roam-content-hash-test-{}-{n}-{name}",
            std::process::id()
        ));
        let _ = fs::remove_dir_all(&dir);
        dataset::save(&dir, &generate::synthetic(65, seed)).expect("save the data set");
        DataSet(dir)
    }

    fn hash_file(&self) -> PathBuf {
        self.0
            .join(cache::CACHE_DIR)
            .join(dataset::CONTENT_HASH_FILE)
    }

    /// The hash a whole load computes.
    fn loaded_hash(&self) -> [u8; 32] {
        dataset::load(&self.0, &mut |_, _| {})
            .expect("the data set loads")
            .content_hash()
    }

    /// Opened for serving, then its hash through the cache, and the bytes of `color.ppm`
    /// streamed for it (none when cached).
    fn hash(&self) -> ([u8; 32], HashSource, u64) {
        let (terrain, _, report): (Terrain, _, CacheReport) =
            dataset::open_cached(&self.0, 1, &mut |_, _, _| {}).expect("the data set opens");
        let mut streamed = 0;
        let (hash, source) =
            dataset::content_hash_cached(&self.0, &terrain, &report, &mut |done, _| {
                streamed = done
            })
            .expect("the hash");
        (hash, source, streamed)
    }

    /// Dates `content.hash` well after `color.ppm`'s change, as a start at least 2 s later
    /// would have written it (a stamp written within 2 s of the change is not trusted).
    fn age_stamp(&self) {
        let file = fs::File::options()
            .write(true)
            .open(self.hash_file())
            .expect("content.hash exists");
        // A minute after its own mtime (no clock read: the tests keep to the I/O shells'
        // rule).
        let written = file
            .metadata()
            .and_then(|m| m.modified())
            .expect("an mtime");
        file.set_modified(written + Duration::from_secs(60))
            .expect("set its mtime");
    }
}

impl Drop for DataSet {
    fn drop(&mut self) {
        let _ = fs::remove_dir_all(&self.0);
    }
}

fn computed(source: &HashSource) -> &str {
    match source {
        HashSource::Computed(why) => why,
        HashSource::Cached => panic!("expected the hash computed, got it cached"),
    }
}

fn rewrite(path: &Path, how: &dyn Fn(&mut Vec<u8>)) {
    let mut bytes = fs::read(path).expect("the file exists");
    how(&mut bytes);
    fs::write(path, bytes).expect("rewrite it");
}

#[test]
fn a_warm_start_takes_the_hash_without_reading_the_colour_map() {
    let set = DataSet::new("warm", 3);
    let want = set.loaded_hash();
    let (hash, source, streamed) = set.hash();
    assert_eq!(hash, want, "the hash recordings name");
    assert_eq!(computed(&source), "not cached yet");
    assert_eq!(streamed, 64 * 64 * 3, "color.ppm's pixels streamed once");
    // Written just now, within 2 s of color.ppm's ctime: racy, so computed again.
    let (hash, source, _) = set.hash();
    assert_eq!(hash, want);
    assert!(computed(&source).contains("within 2 s"), "{source:?}");
    set.age_stamp();
    let (hash, source, streamed) = set.hash();
    assert_eq!((hash, source, streamed), (want, HashSource::Cached, 0));
}

#[test]
fn a_changed_colour_map_or_map_is_hashed_again() {
    let set = DataSet::new("changed", 4);
    let color = set.0.join(dataset::COLOR_FILE);
    set.hash();
    set.age_stamp();
    // The same bytes written again: a new stamp, the same hash.
    let before = set.loaded_hash();
    rewrite(&color, &|_| {});
    let (hash, source, _) = set.hash();
    assert_eq!(hash, before);
    assert!(
        computed(&source).contains("color.ppm changed"),
        "{source:?}"
    );
    // One pixel changed, the length kept: another hash, the whole load's.
    set.age_stamp();
    rewrite(&color, &|b| {
        let last = b.len() - 1;
        b[last] ^= 0x55;
    });
    let want = set.loaded_hash();
    assert_ne!(want, before);
    let (hash, source, _) = set.hash();
    assert_eq!(hash, want);
    assert!(
        computed(&source).contains("color.ppm changed"),
        "{source:?}"
    );
    // A comment added to `map`: the same parameters, the same hash, still cached.
    set.age_stamp();
    let map = set.0.join(dataset::MAP_FILE);
    let text = fs::read_to_string(&map).expect("map");
    fs::write(&map, format!("{text}\n# a comment only\n")).expect("rewrite map");
    assert_eq!(set.hash(), (want, HashSource::Cached, 0));
    // A parameter changed: another hash.
    fs::write(&map, text.replace("fogDensity = ", "fogDensity = 0.5 # ")).expect("rewrite map");
    let changed = set.loaded_hash();
    assert_ne!(changed, want);
    let (hash, source, _) = set.hash();
    assert_eq!(computed(&source), "the map parameters changed");
    assert_eq!(hash, changed);
}

#[test]
fn changed_heights_are_hashed_again() {
    let set = DataSet::new("heights", 5);
    set.hash();
    set.age_stamp();
    let other = generate::synthetic(65, 6);
    // Only hf.pgm: color.ppm keeps its stamp.
    roam_server::terrain::pnm::write_pgm(&set.0.join(dataset::HEIGHTS_FILE), &other.heights)
        .expect("write other heights");
    let (hash, source, _) = set.hash();
    assert_eq!(computed(&source), "the heights changed");
    assert_eq!(hash, set.loaded_hash());
}

#[test]
fn a_damaged_cached_hash_is_computed_again() {
    let set = DataSet::new("damaged", 7);
    let want = set.loaded_hash();
    type Damage = (fn(&mut Vec<u8>), &'static str);
    let cases: [Damage; 4] = [
        (|b| b[20] ^= 1, "corrupt: its check does not match"),
        (|b| b.truncate(100), "length: expected 256 bytes, got 100"),
        (|b| b[0] = b'X', "magic or version"),
        (|b| b.clear(), "length: expected 256 bytes, got 0"),
    ];
    for (how, reason) in cases {
        set.hash();
        set.age_stamp();
        let path = set.hash_file();
        let mut bytes = fs::read(&path).expect("content.hash");
        how(&mut bytes);
        fs::write(&path, bytes).expect("damage it");
        let (hash, source, _) = set.hash();
        assert_eq!(hash, want, "{reason}");
        assert!(computed(&source).contains(reason), "{reason}: {source:?}");
    }
}
