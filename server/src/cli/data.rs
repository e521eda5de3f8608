//! `check`, `generate` and `import`: data-set commands.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Args;
use roam_server::terrain::dataset::{self, Terrain};
use roam_server::terrain::heightfield::levels_of_side;
use roam_server::terrain::map::{MapParams, Start, normalize};
use roam_server::terrain::{generate as gen_terrain, pnm};

use super::progress::Progress;

#[derive(Args)]
pub struct CheckArgs {
    /// Data-set directory (holding `map`, `hf.pgm`, `color.ppm`).
    pub dir: PathBuf,
}

#[derive(Args)]
pub struct GenerateArgs {
    /// Output directory (created if missing).
    pub out: PathBuf,
    /// Samples per side: 2^N + 1.
    #[arg(long, default_value_t = 129)]
    pub side: u32,
    /// Seed of the generator: the same seed always gives the same data set.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

#[derive(Args)]
pub struct ImportArgs {
    /// Source heightfield (binary PGM, side 2^N + 1).
    pub pgm: PathBuf,
    /// Output directory (created if missing).
    pub out: PathBuf,
    /// World units between neighbouring samples (`hScale`).
    #[arg(long, default_value_t = 1.0, allow_hyphen_values = true)]
    pub h_scale: f64,
    /// World units per sample value (`vScale`).
    #[arg(long, default_value_t = 0.1, allow_hyphen_values = true)]
    pub v_scale: f64,
    /// World height of a water surface (`waterLevel`); cells below it are coloured as water.
    #[arg(long, allow_hyphen_values = true)]
    pub water_level: Option<f64>,
    /// Vehicle start, world X (default: the map's centre).
    #[arg(long, allow_hyphen_values = true)]
    pub start_x: Option<f64>,
    /// Vehicle start, world Z (default: the map's centre).
    #[arg(long, allow_hyphen_values = true)]
    pub start_z: Option<f64>,
    /// Vehicle heading in degrees: 0 faces south (+Z), 90 east (+X).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub heading: f64,
    /// Direction towards the sun as X,Y,Z (normalised).
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true,
          conflicts_with_all = ["sun_azimuth", "sun_elevation"])]
    pub sun_dir: Option<[f64; 3]>,
    /// Sun azimuth in compass degrees (0 north, 90 east, 180 south, 270 west); needs
    /// --sun-elevation.
    #[arg(long, requires = "sun_elevation", allow_hyphen_values = true)]
    pub sun_azimuth: Option<f64>,
    /// Sun elevation above the horizon in degrees; needs --sun-azimuth.
    #[arg(long, requires = "sun_azimuth", allow_hyphen_values = true)]
    pub sun_elevation: Option<f64>,
    /// Sun colour as R,G,B (0..=255 each).
    #[arg(long, value_parser = parse_rgb)]
    pub sun_color: Option<[u8; 3]>,
    /// Exponential fog density per world unit.
    #[arg(long, allow_hyphen_values = true)]
    pub fog_density: Option<f64>,
    /// Fog colour as R,G,B (0..=255 each).
    #[arg(long, value_parser = parse_rgb)]
    pub fog_color: Option<[u8; 3]>,
}

/// `check DIR`: load and validate a data set, then describe it.
pub fn check(args: CheckArgs) -> Result<()> {
    let (terrain, vt, build_ms) = super::tess::load(&args.dir)?;
    for line in describe(&terrain) {
        say!("{line}");
    }
    let samples = f64::from(terrain.heights.side()).powi(2);
    say!(
        "variance tree: {:.2} bytes/sample ({} bytes), built in {build_ms:.0} ms",
        vt.bytes_per_sample(),
        thousands(vt.heap_bytes() as u64)
    );
    let resident = terrain.heights.heap_bytes() + vt.heap_bytes();
    say!(
        "resident: {:.2} bytes/sample ({} bytes: heights + variance tree; colour map {:.2} \
         bytes/cell aside)",
        resident as f64 / samples,
        thousands(resident as u64),
        terrain.color.heap_bytes() as f64 / f64::from(terrain.color.cells()).powi(2).max(1.0)
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
pub fn describe(t: &Terrain) -> Vec<String> {
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
        format!("colour map: {0} × {0} cells", t.color.cells()),
    ];
    if let Some(w) = m.water_level {
        let cells = u64::from(t.heights.size()).pow(2);
        let mut wet = 0u64;
        for z in 0..t.heights.size() {
            for x in 0..t.heights.size() {
                let mean = (t.world_height(x, z)
                    + t.world_height(x + 1, z)
                    + t.world_height(x, z + 1)
                    + t.world_height(x + 1, z + 1))
                    / 4.0;
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
pub fn generate(args: GenerateArgs) -> Result<()> {
    if levels_of_side(u64::from(args.side)).is_none() {
        bail!(
            "--side: expected 2^N + 1 (3, 5, 9, …, 32769), got {}",
            args.side
        );
    }
    let terrain = gen_terrain::synthetic(args.side, args.seed);
    save_and_describe(&args.out, &terrain)
}

/// Writes a data set and prints what was written.
fn save_and_describe(out: &std::path::Path, terrain: &Terrain) -> Result<()> {
    dataset::save(out, terrain).with_context(|| format!("writing {}", out.display()))?;
    say!("wrote {}", out.display());
    for line in describe(terrain) {
        say!("{line}");
    }
    Ok(())
}

/// `import PGM OUT`: copy a heightfield, derive a colour map and write a `map` file.
pub fn import(args: ImportArgs) -> Result<()> {
    let heights = {
        let mut p = Progress::new("reading");
        let total = std::fs::metadata(&args.pgm).map(|m| m.len()).unwrap_or(0);
        let mut cb = p.callback();
        pnm::read_pgm(&args.pgm, &mut |n| cb(n, total))
            .map_err(|e| anyhow::anyhow!("{}: {e}", args.pgm.display()))?
    };
    let side = heights.side();
    let mut map = MapParams::default_for_side(side);
    map.h_scale = args.h_scale;
    map.v_scale = args.v_scale;
    map.water_level = args.water_level;
    let centre = map.world_size(side) / 2.0;
    map.start = Start {
        x: args.start_x.unwrap_or(centre),
        z: args.start_z.unwrap_or(centre),
        heading_deg: args.heading,
    };
    if let Some(d) = args.sun_dir {
        map.sun_dir = normalize(d)
            .with_context(|| format!("--sun-dir: expected a non-zero direction, got {d:?}"))?;
    }
    if let (Some(az), Some(el)) = (args.sun_azimuth, args.sun_elevation) {
        map.sun_dir = sun_from_angles(az, el)
            .with_context(|| format!("--sun-azimuth/--sun-elevation: got {az}, {el}"))?;
    }
    if let Some(c) = args.sun_color {
        map.sun_color = c;
    }
    if let Some(f) = args.fog_density {
        map.fog_density = f;
    }
    if let Some(c) = args.fog_color {
        map.fog_color = c;
    }
    map.validate_for_side(side)
        .map_err(|e| anyhow::anyhow!("map parameters: {e}"))?;
    let color = gen_terrain::colorize(&heights, &map);
    let terrain = Terrain {
        map,
        heights,
        color,
    };
    save_and_describe(&args.out, &terrain)
}

/// Unit vector towards a sun at compass `azimuth` (0 north = −Z, 90 east = +X) and
/// `elevation` degrees above the horizon.
fn sun_from_angles(azimuth: f64, elevation: f64) -> Option<[f64; 3]> {
    if !(azimuth.is_finite() && (-90.0..=90.0).contains(&elevation)) {
        return None;
    }
    let (az, el) = (azimuth.to_radians(), elevation.to_radians());
    let d = [az.sin() * el.cos(), el.sin(), -az.cos() * el.cos()];
    normalize(d)
}

/// `X,Y,Z` as three numbers.
fn parse_vec3(s: &str) -> Result<[f64; 3], String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let [x, y, z] = parts[..] else {
        return Err(format!("expected X,Y,Z (three numbers), got {s:?}"));
    };
    let num = |t: &str| {
        t.parse::<f64>()
            .map_err(|_| format!("expected a number, got {t:?}"))
    };
    Ok([num(x)?, num(y)?, num(z)?])
}

/// `R,G,B` as three integers 0..=255.
fn parse_rgb(s: &str) -> Result<[u8; 3], String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let [r, g, b] = parts[..] else {
        return Err(format!(
            "expected R,G,B (three integers 0..=255), got {s:?}"
        ));
    };
    let byte = |t: &str| {
        t.parse::<u8>()
            .map_err(|_| format!("expected an integer 0..=255, got {t:?}"))
    };
    Ok([byte(r)?, byte(g)?, byte(b)?])
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
