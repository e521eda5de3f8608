//! A data set opened for serving, as `serve`, `world`, `edge`, `bus-load` and
//! `color-bench` open it: heights and variance tree mapped from its cache, the colour and
//! normal tiles from theirs (each built on first use, with progress bars; a damaged tile
//! cache is found at open and rebuilt: `terrain::tile_store`); its content hash (cached);
//! the recording directory; a recording opened to be served (`serve --replay`).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, Result};
use roam_server::net;
use roam_server::sim::record_files::RecordDir;
use roam_server::terrain::color_pyramid::{CacheOutcome, ColorPyramid};
use roam_server::terrain::dataset::{HashSource, Terrain};
use roam_server::terrain::normal_pyramid::NormalPyramid;
use roam_server::terrain::variance::VarianceTree;

/// The recording directory (`record_dir`, else `recordings` in `state_dir`), made if
/// absent, and its files.
pub(crate) fn record_files(
    state_dir: &Path,
    record_dir: Option<&Path>,
) -> Result<(PathBuf, RecordDir)> {
    let dir = record_dir.map_or_else(|| state_dir.join("recordings"), Path::to_owned);
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let files = RecordDir::new(&dir, net::world_loop::unix_seconds);
    Ok((dir, files))
}

/// The data set's content hash: the recordings name the data set by it (colour included,
/// as `replay`, which loads it whole, computes it), and a world and its edges check they
/// serve the same one. Cached in `.cache/content.hash`, so a warm start reads neither
/// `hf.pgm` nor `color.ppm`.
pub(crate) fn data_hash(
    dir: &Path,
    terrain: &Terrain,
    report: &roam_server::terrain::cache::CacheReport,
) -> Result<[u8; 32]> {
    let started = std::time::Instant::now();
    let mut p = super::progress::Progress::new("hashing");
    let (hash, source) = roam_server::terrain::dataset::content_hash_cached(
        dir,
        terrain,
        report,
        &mut p.callback(),
    )?;
    let ms = started.elapsed().as_secs_f64() * 1e3;
    match source {
        HashSource::Cached => tracing::info!("data set hash cached in {ms:.0} ms"),
        HashSource::Computed(why) => {
            tracing::info!("data set hash computed in {ms:.0} ms ({why})")
        }
    }
    Ok(hash)
}

/// A data set opened for serving: heights and variance tree mapped from its cache, the
/// colour and normal tiles mapped from theirs (each built on first use, with progress
/// bars).
pub(crate) struct Served {
    pub terrain: Terrain,
    pub variance: VarianceTree,
    pub pyramid: ColorPyramid,
    pub normals: NormalPyramid,
    /// What the cache did (its `heights_hash` keys the data set's cached hash).
    pub report: roam_server::terrain::cache::CacheReport,
}

/// Opens `dir` as `serve` does: refused if it is too large to serve before anything but
/// its headers is read; `color.ppm`'s pixels are read only to build the tile cache.
pub(crate) fn open_served(dir: &Path) -> Result<Served> {
    // The cache files re-hashed whole since they last changed are trusted (`check`
    // re-hashes everything).
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let started = std::time::Instant::now();
    let (terrain, variance, report) = {
        let mut p = super::progress::Staged::default();
        roam_server::terrain::dataset::open_cached_with(
            dir,
            threads,
            roam_server::terrain::cache::Verify::Stamps,
            &mut p.callback(),
        )?
    };
    let ms = started.elapsed().as_secs_f64() * 1e3;
    for note in &report.notes {
        tracing::warn!("{note}");
    }
    tracing::info!(
        "opened {} in {ms:.0} ms (heights {:?}, variance tree {:?})",
        dir.display(),
        report.heights,
        report.variance
    );
    net::check_servable(&terrain).with_context(|| dir.display().to_string())?;
    let mut p = super::progress::Progress::new("colour tiles");
    let cells = terrain.heights.size();
    let started = std::time::Instant::now();
    let (pyramid, outcome) = ColorPyramid::open_or_load(
        dir,
        cells,
        roam_protocol::tiles::DEFAULT_TILE,
        threads,
        || {
            let mut p = super::progress::Progress::new("colour");
            roam_server::terrain::dataset::load_color(dir, cells, &mut p.callback())
                .map(std::borrow::Cow::Owned)
        },
        &mut p.callback(),
    )
    .with_context(|| dir.display().to_string())?;
    drop(p);
    log_outcome("colour", outcome);
    tracing::info!(
        levels = pyramid.levels(),
        kbytes = pyramid.coded_bytes() / 1000,
        mapped = pyramid.is_mapped(),
        ms = %format!("{:.2}", started.elapsed().as_secs_f64() * 1e3),
        "colour pyramid"
    );
    let mut p = super::progress::Progress::new("normal tiles");
    let started = std::time::Instant::now();
    let (normals, outcome) = NormalPyramid::open_or_build(
        dir,
        &terrain.heights,
        (terrain.map.h_scale, terrain.map.v_scale),
        &report.heights_hash,
        roam_protocol::tiles::DEFAULT_TILE,
        threads,
        &mut p.callback(),
    )
    .with_context(|| dir.display().to_string())?;
    drop(p);
    log_outcome("normal", outcome);
    tracing::info!(
        levels = normals.levels(),
        kbytes = normals.coded_bytes() / 1000,
        mapped = normals.is_mapped(),
        ms = %format!("{:.2}", started.elapsed().as_secs_f64() * 1e3),
        "normal pyramid"
    );
    Ok(Served {
        terrain,
        variance,
        pyramid,
        normals,
        report,
    })
}

/// Opens `file` to serve it (`serve --replay`), logging how far it is valid.
pub(crate) fn open_replay(
    file: &Path,
    (control, follow): (&Option<String>, bool),
    terrain: &Arc<roam_server::Terrain>,
    hash: &[u8; 32],
) -> Result<net::replay::Replaying> {
    if let Some(t) = control {
        super::token::check(t).map_err(|e| anyhow::anyhow!("--control: {e}"))?;
    }
    let name = file.display();
    let started = std::time::Instant::now();
    let replaying =
        net::replay::Replaying::open(file, follow, control.clone(), terrain.clone(), hash)
            .with_context(|| format!("watching {name}"))?;
    tracing::info!(
        "replaying {name}: {} (opened in {:.0} ms)",
        roam_server::sim::watch::describe(&replaying.watch),
        started.elapsed().as_secs_f64() * 1e3
    );
    if follow && replaying.watch.growing() {
        tracing::info!("following {name} as it grows");
    }
    Ok(replaying)
}

/// Logs what became of a tile pyramid's cache (`kind`: "colour" or "normal").
fn log_outcome(kind: &str, outcome: CacheOutcome) {
    match outcome {
        CacheOutcome::Mapped => {}
        CacheOutcome::Built => tracing::info!("{kind} tiles cached"),
        CacheOutcome::Rebuilt(why) => tracing::warn!("{kind} tile cache rebuilt: {why}"),
        CacheOutcome::InMemory(why) => {
            tracing::warn!("{kind} tiles kept in memory, not cached: {why}")
        }
    }
}

#[cfg(test)]
mod tests {
    use std::fs;
    use std::path::{Path, PathBuf};

    use roam_server::terrain::color_pyramid::{self, TileError};
    use roam_server::terrain::normal_pyramid;

    use super::{Served, open_served};

    /// A copy of `data/kossou` (1024² cells: 21 colour and 21 normal tiles of 256) in a
    /// temporary folder of its own.
    fn kossou_copy(name: &str) -> PathBuf {
        let from = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/kossou");
        let dir = std::env::temp_dir().join(format!("roam-served-{name}-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        fs::create_dir_all(&dir).expect("a temporary folder");
        for file in ["hf.pgm", "color.ppm", "map"] {
            fs::copy(from.join(file), dir.join(file)).expect("the bundled data set");
        }
        dir
    }

    /// Every tile of both pyramids as a viewer would be served it.
    fn served_tiles(s: &Served) -> Vec<Result<Vec<u8>, TileError>> {
        let layout = s.pyramid.layout(1).expect("the pyramid's layout");
        let mut out = Vec::new();
        for level in 0..layout.levels {
            let n = layout.tiles(level);
            for (x, z) in (0..n * n).map(|i| (i % n, i / n)) {
                out.push(s.pyramid.served_tile(level, x, z).map(<[u8]>::to_vec));
                out.push(s.normals.served_tile(level, x, z).map(<[u8]>::to_vec));
            }
        }
        out
    }

    /// Flips `count` bytes spread over the middle half of the file at `path`: payloads of
    /// finer tiles, the header, the index and the coarsest tile (the file's end) untouched.
    fn flip(path: &Path, count: usize) {
        let mut bytes = fs::read(path).expect("the cache was written");
        let (from, span) = (bytes.len() / 4, bytes.len() / 2);
        for k in 0..count {
            bytes[from + k * span / count] ^= 0x5a;
        }
        fs::write(path, bytes).expect("the temporary cache");
    }

    /// Issue 39's defect 5: 150 bytes flipped in each tile cache once left a server that
    /// withheld most tiles on every start. Opened as `serve` opens it, every tile is served,
    /// the same as fresh.
    #[test]
    fn damaged_tile_caches_are_rebuilt_at_start() {
        let dir = kossou_copy("damaged-tiles");
        let fresh = served_tiles(&open_served(&dir).expect("kossou opens"));
        assert_eq!(fresh.len(), 2 * 21);
        assert!(fresh.iter().all(Result::is_ok));
        for cache in [
            color_pyramid::cache_path(&dir),
            normal_pyramid::cache_path(&dir),
        ] {
            flip(&cache, 150);
        }
        let reopened = open_served(&dir).expect("kossou opens");
        assert!(
            served_tiles(&reopened) == fresh,
            "a tile differs from a fresh build"
        );
        drop(reopened);
        // And again: the rebuilt caches are mapped and whole.
        let again = open_served(&dir).expect("kossou opens");
        assert!(again.pyramid.is_mapped() && again.normals.is_mapped());
        assert!(
            served_tiles(&again) == fresh,
            "a tile differs from a fresh build"
        );
        let _ = fs::remove_dir_all(&dir);
    }
}
