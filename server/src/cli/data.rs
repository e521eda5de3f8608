//! `check` and `generate`: data-set commands (`import` is in [`super::import`]).

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Args;
use roam_server::terrain::cache::{self, Source};
use roam_server::terrain::dataset::{self, Terrain};
use roam_server::terrain::generate as gen_terrain;
use roam_server::terrain::heightfield::levels_of_side;

use crate::cli::progress::Progress;

#[derive(Args)]
pub(crate) struct CheckArgs {
    /// Data-set directory (holding `map`, `hf.pgm`, `color.ppm`).
    pub dir: PathBuf,
}

#[derive(Args)]
pub(crate) struct GenerateArgs {
    /// Output directory (created if missing).
    pub out: PathBuf,
    /// Samples per side: 2^N + 1.
    #[arg(long, default_value_t = 129)]
    pub side: u32,
    /// Seed of the generator: the same seed always gives the same data set.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

/// `check DIR`: validate a data set as `serve` opens it (through its cache, built on first
/// use; the colour map's header checked, its pixels not read), then describe it.
pub(crate) fn check(args: CheckArgs) -> Result<()> {
    let opened = super::tess::open(&args.dir)?;
    let (terrain, vt, report) = (&opened.terrain, &opened.variance, &opened.report);
    for line in describe(terrain) {
        say!("{line}");
    }
    let samples = f64::from(terrain.heights.side()).powi(2);
    let how = |s: Source| match s {
        Source::Cached => "from the cache",
        Source::Built => "built, cached",
        Source::Memory => "built, in memory (cache not writable)",
    };
    say!(
        "cache: heights {}, variance tree {} ({}), opened in {:.0} ms",
        how(report.heights),
        how(report.variance),
        args.dir.join(cache::CACHE_DIR).display(),
        opened.ms
    );
    say!(
        "variance tree: {:.2} bytes/sample ({} bytes), {}",
        vt.bytes_per_sample(),
        thousands(vt.bytes() as u64),
        how(report.variance)
    );
    let resident = terrain.heights.bytes() + vt.bytes();
    // The colour map, when loaded, takes 3 bytes a cell (8-bit RGB).
    say!(
        "resident: {:.2} bytes/sample ({} bytes: heights + variance tree{}; colour map {:.2} \
         bytes/cell aside)",
        resident as f64 / samples,
        thousands(resident as u64),
        if terrain.heights.is_mapped() && vt.is_mapped() {
            ", mapped and shared between processes"
        } else {
            ""
        },
        3.0
    );
    if let Some(peak) = peak_rss_bytes() {
        say!(
            "peak RSS: {:.2} bytes/sample ({} bytes, whole process)",
            peak as f64 / samples,
            thousands(peak)
        );
    }
    Ok(())
}

/// The process's peak resident set size (`VmHWM` in `/proc/self/status`), where the
/// system reports it (Linux).
fn peak_rss_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let mut words = line["VmHWM:".len()..].split_whitespace();
    let kb: u64 = words.next()?.parse().ok()?;
    (words.next() == Some("kB")).then_some(kb * 1024)
}

/// `1234567` as `1,234,567`.
fn thousands(n: u64) -> String {
    let digits = n.to_string();
    let mut out = String::with_capacity(digits.len() + digits.len() / 3);
    for (i, c) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i).is_multiple_of(3) {
            out.push(',');
        }
        out.push(c);
    }
    out
}

/// Human-readable summary lines of a loaded data set.
pub(crate) fn describe(t: &Terrain) -> Vec<String> {
    let m = &t.map;
    let side = t.heights.side();
    let (lo, hi) = t.heights.range();
    let world = t.world_size();
    let mut out = vec![
        format!(
            "side {side} (N = {}), hScale {}, vScale {}: {world} × {world} world units",
            t.heights.levels(),
            m.h_scale,
            m.v_scale
        ),
        format!(
            "heights: samples {lo} .. {hi}, world {:.2} .. {:.2} units",
            f64::from(lo) * m.v_scale,
            f64::from(hi) * m.v_scale
        ),
        format!(
            "colour map: {0} × {0} cells{1}",
            t.heights.size(),
            if t.color.is_some() {
                ""
            } else {
                " (header checked, pixels not read)"
            }
        ),
    ];
    if let Some(w) = m.water_level {
        let cells = u64::from(t.heights.size()).pow(2);
        let mut wet = 0u64;
        let rows: Vec<&[u16]> = t.heights.samples().chunks(side as usize).collect();
        let h = |s: u16| m.v_scale * f64::from(s);
        for pair in rows.windows(2) {
            let (a, b) = (pair[0], pair[1]);
            for x in 0..a.len() - 1 {
                let mean = (h(a[x]) + h(a[x + 1]) + h(b[x]) + h(b[x + 1])) / 4.0;
                wet += u64::from(mean < w);
            }
        }
        out.push(format!(
            "water level {w} ({:.1} % of cells below it)",
            100.0 * wet as f64 / cells.max(1) as f64
        ));
    } else {
        out.push("no water".into());
    }
    let d = m.sun_dir;
    let elevation = d[1].clamp(-1.0, 1.0).asin().to_degrees();
    // Compass azimuth: 0 north (−Z), 90 east (+X).
    let azimuth = d[0].atan2(-d[2]).to_degrees().rem_euclid(360.0);
    out.push(format!(
        "sun: dir [{:.4}, {:.4}, {:.4}] (azimuth {azimuth:.1}°, elevation {elevation:.1}°), \
         colour {:?}",
        d[0], d[1], d[2], m.sun_color
    ));
    let fog = if m.fog_density > 0.0 {
        format!(
            "fog: density {} (half at {:.0}, 5 % contrast at {:.0} world units), colour {:?}",
            m.fog_density,
            std::f64::consts::LN_2 / m.fog_density,
            3.0 / m.fog_density,
            m.fog_color
        )
    } else {
        format!("fog: off (density 0), colour {:?}", m.fog_color)
    };
    out.push(fog);
    let s = m.start;
    let (gx, gz) = (
        ((s.x / m.h_scale).round() as u32).min(side - 1),
        ((s.z / m.h_scale).round() as u32).min(side - 1),
    );
    out.push(format!(
        "start: x {}, z {}, heading {}° (ground ≈ {:.2} units)",
        s.x,
        s.z,
        s.heading_deg,
        t.world_height(gx, gz)
    ));
    out
}

/// `generate OUT --side --seed`: write a synthetic data set.
pub(crate) fn generate(args: GenerateArgs) -> Result<()> {
    if levels_of_side(u64::from(args.side)).is_none() {
        bail!(
            "--side: expected 2^N + 1 (3, 5, 9, …, 32769), got {}",
            args.side
        );
    }
    // Every core: the bytes do not depend on how many.
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let terrain = {
        let mut p = Progress::new("generating");
        gen_terrain::synthetic_with(args.side, args.seed, threads, &mut p.callback())
    };
    save_and_describe(&args.out, &terrain)
}

/// Writes a data set and prints what was written.
pub(super) fn save_and_describe(out: &std::path::Path, terrain: &Terrain) -> Result<()> {
    dataset::save(out, terrain).with_context(|| format!("writing {}", out.display()))?;
    say!("wrote {}", out.display());
    for line in describe(terrain) {
        say!("{line}");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::thousands;

    #[test]
    fn thousands_groups_digits() {
        for (n, want) in [
            (0, "0"),
            (999, "999"),
            (1000, "1,000"),
            (524_800, "524,800"),
            (1_234_567, "1,234,567"),
            (u64::MAX, "18,446,744,073,709,551,615"),
        ] {
            assert_eq!(thousands(n), want);
        }
    }
}
