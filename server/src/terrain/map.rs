//! The `map` file of a data set: scales, sun, fog, water and the vehicle start, in TOML.
//!
//! ```toml
//! hScale = 92.0                 # world units between neighbouring samples (> 0)
//! vScale = 0.01                 # world units per sample step (> 0)
//! sunDir = [-0.76, 0.57, 0.31]  # towards the sun; normalised on load, must not be zero
//! sunColor = [255, 244, 225]    # 0 ..= 255 each
//! fogDensity = 5e-5             # exp(-density * distance), per world unit (>= 0)
//! fogColor = [200, 210, 218]
//! waterLevel = 28.5             # optional: world height of a water surface
//!
//! [start]                       # optional; default: map centre, heading 0
//! x = 41000.0                   # world X, 0 ..= hScale * (side - 1)
//! z = 78000.0                   # world Z, same range
//! heading = 300.0               # degrees: 0 faces south (+Z), 90 east (+X)
//! ```
//!
//! Every key is optional; integers are accepted where numbers are expected. Unknown keys
//! (also inside `start`), wrong types and out-of-range values are errors that name the key,
//! the line and what was expected.
//!
//! **Ranges.** Every number is bounded where a value could make no sense, and a value
//! outside is refused naming the key, the value and the range ([`MapParams::validate_for_side`];
//! a map of absurd values once passed `check` and `serve`: `vScale = 1e308` made the
//! heights infinite, and frames cost ten times as much). The ranges admit every real use:
//!
//! - `hScale` [`H_SCALE`] (1 mm to 10 km between samples: lidar to coarse global grids);
//! - `vScale` [`V_SCALE`] (a sample step of 1 µm to 1 km: the highest height,
//!   65535 · `vScale`, at most 6.6·10⁷, so every height is finite and exact enough in
//!   `f32`; real DEMs, trench to Everest in metres, need about 0.3, and a hundredfold
//!   vertical exaggeration 30);
//! - `fogDensity` 0 ..= 10 / `hScale` (the fog lets at least e⁻¹⁰ of the next sample
//!   through: a denser fog shows nothing but the ground under the vehicle; the bundled data
//!   sets use at most 0.047 / `hScale`, the generator at most 3 / `hScale`, and the
//!   default 0.0005 stays within for every `hScale`);
//! - `waterLevel` within the heights' range, 0 ..= 65535 · `vScale` (heights are
//!   `sample · vScale`, samples 0 ..= 65535: water below or above every height is none or
//!   all);
//! - `start.x`, `start.z` on the map; `start.heading` any finite number of degrees (wrapped
//!   when a vehicle is placed).

use std::fmt::Write as _;
use std::ops::Range;

use toml::de::{DeTable, DeValue};

/// Top-level keys, in the order [`MapParams::to_toml`] writes them.
pub const KEYS: [&str; 8] = [
    "hScale",
    "vScale",
    "sunDir",
    "sunColor",
    "fogDensity",
    "fogColor",
    "waterLevel",
    "start",
];
/// `hScale`'s range: world units between neighbouring samples.
pub const H_SCALE: (f64, f64) = (1e-3, 1e4);
/// `vScale`'s range: world units per sample step.
pub const V_SCALE: (f64, f64) = (1e-6, 1e3);
/// The most `fogDensity · hScale`: at least e⁻¹⁰ of the next sample shows through the fog.
pub const MAX_FOG_PER_SAMPLE: f64 = 10.0;
/// The highest sample value (`hf.pgm` is 16-bit): heights are `sample · vScale`.
const MAX_SAMPLE: f64 = 65535.0;

/// Keys of the `start` table.
pub const START_KEYS: [&str; 3] = ["x", "z", "heading"];

/// Default `sunDir` before normalisation: high in the south-east.
pub const DEFAULT_SUN_DIR: [f64; 3] = [0.4, 0.8, 0.3];
/// Default `sunColor`: slightly warm white.
pub const DEFAULT_SUN_COLOR: [u8; 3] = [255, 250, 235];
/// Default `fogDensity`: transmission `exp(-0.0005 d)` keeps 60 % at 1000 units and 8 % at
/// 5000 units, which suits the default `hScale = 1` on maps of about 1025 to 4097 samples.
/// Set it for the map's real extent.
pub const DEFAULT_FOG_DENSITY: f64 = 0.0005;
/// Default `fogColor`: pale sky blue.
pub const DEFAULT_FOG_COLOR: [u8; 3] = [190, 205, 225];

/// Where and how the vehicle starts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Start {
    /// World X (east), 0 ..= hScale · (side − 1).
    pub x: f64,
    /// World Z (south), 0 ..= hScale · (side − 1).
    pub z: f64,
    /// Degrees; 0 faces south (+Z), 90 east (+X), 180 north.
    pub heading_deg: f64,
}

/// The parsed and validated `map` file.
#[derive(Clone, Debug, PartialEq)]
pub struct MapParams {
    /// World units between neighbouring samples (`hScale`, > 0).
    pub h_scale: f64,
    /// World units per sample value (`vScale`, > 0).
    pub v_scale: f64,
    /// Unit vector towards the sun (`sunDir`).
    pub sun_dir: [f64; 3],
    /// Sun light colour (`sunColor`).
    pub sun_color: [u8; 3],
    /// Exponential fog density per world unit (`fogDensity`, ≥ 0).
    pub fog_density: f64,
    /// Fog (and horizon) colour (`fogColor`).
    pub fog_color: [u8; 3],
    /// World height of a water surface, if any (`waterLevel`).
    pub water_level: Option<f64>,
    /// Vehicle start (`start`).
    pub start: Start,
}

/// A problem in a `map` file: the key (`field`), the 1-based line when known, and a message
/// saying what was expected and what was found.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{field}: {message}")]
pub struct MapError {
    /// The key, e.g. `hScale`, `start.x`, `sunColor[1]`; `syntax` for TOML errors.
    pub field: String,
    /// 1-based line of the offending key or value, when known.
    pub line: Option<usize>,
    /// "expected …, got …".
    pub message: String,
}

impl MapParams {
    /// Defaults for a map of `side` samples: every key at its default, start at the centre.
    pub fn default_for_side(side: u32) -> MapParams {
        let h_scale = 1.0;
        let centre = h_scale * f64::from(side.saturating_sub(1)) / 2.0;
        MapParams {
            h_scale,
            v_scale: 0.1,
            sun_dir: normalize(DEFAULT_SUN_DIR).unwrap_or([0.0, 1.0, 0.0]),
            sun_color: DEFAULT_SUN_COLOR,
            fog_density: DEFAULT_FOG_DENSITY,
            fog_color: DEFAULT_FOG_COLOR,
            water_level: None,
            start: Start {
                x: centre,
                z: centre,
                heading_deg: 0.0,
            },
        }
    }

    /// World extent of a `side`-sample map along X and Z: `hScale · (side − 1)`.
    pub fn world_size(&self, side: u32) -> f64 {
        self.h_scale * f64::from(side.saturating_sub(1))
    }

    /// Parse a `map` file for a heightfield of `side` samples (needed to default the start to
    /// the centre and to check that it lies on the map).
    pub fn parse(text: &str, side: u32) -> Result<MapParams, MapError> {
        let doc = DeTable::parse(text).map_err(|e| MapError {
            field: "syntax".into(),
            line: e.span().map(|s| line_of(text, s.start)),
            message: format!("expected valid TOML, got: {}", e.message().trim()),
        })?;
        let p = Parser { text };
        let table = doc.get_ref();
        p.reject_unknown(table, &KEYS, "")?;
        let mut m = MapParams::default_for_side(side);
        let mut start_given = [None, None, None];
        // Each key's line, for the errors of `validate_for_side`.
        let mut key_lines: Vec<(String, Option<usize>)> = Vec::new();
        for (key, value) in table.iter() {
            let key_name: &str = key.get_ref();
            let line = Some(line_of(text, value.span().start));
            key_lines.push((key_name.to_owned(), line));
            let v = value.get_ref();
            match key_name {
                "hScale" => m.h_scale = p.number(key_name, line, v)?,
                "vScale" => m.v_scale = p.number(key_name, line, v)?,
                "sunDir" => {
                    let d = p.floats3(key_name, line, v)?;
                    m.sun_dir = normalize(d).ok_or_else(|| MapError {
                        field: key_name.into(),
                        line,
                        message: format!(
                            "expected a non-zero direction towards the sun, got {d:?}"
                        ),
                    })?;
                }
                "sunColor" => m.sun_color = p.color(key_name, line, v)?,
                "fogDensity" => m.fog_density = p.number(key_name, line, v)?,
                "fogColor" => m.fog_color = p.color(key_name, line, v)?,
                "waterLevel" => m.water_level = Some(p.number(key_name, line, v)?),
                "start" => {
                    let Some(t) = v.as_table() else {
                        return Err(p.type_err("start", line, "a table {x, z, heading}", v));
                    };
                    p.reject_unknown(t, &START_KEYS, "start.")?;
                    for (i, k) in START_KEYS.iter().enumerate() {
                        if let Some(sv) = t.get(*k) {
                            let field = format!("start.{k}");
                            let sline = Some(line_of(text, sv.span().start));
                            start_given[i] = Some((p.number(&field, sline, sv.get_ref())?, sline));
                        }
                    }
                }
                // `reject_unknown` has seen every key.
                _ => {}
            }
        }
        let lines: [Option<usize>; 3] = start_given.map(|g| g.and_then(|(_, l)| l));
        let centre = m.world_size(side) / 2.0;
        m.start = Start {
            x: start_given[0].map_or(centre, |g| g.0),
            z: start_given[1].map_or(centre, |g| g.0),
            heading_deg: start_given[2].map_or(0.0, |g| g.0),
        };
        m.validate_for_side(side).map_err(|mut e| {
            if e.line.is_none() {
                e.line = match e.field.as_str() {
                    "start.x" => lines[0],
                    "start.z" => lines[1],
                    "start.heading" => lines[2],
                    field => key_lines
                        .iter()
                        .find(|(k, _)| {
                            field == k
                                || field
                                    .strip_prefix(k.as_str())
                                    .is_some_and(|r| r.starts_with('['))
                        })
                        .and_then(|(_, l)| *l),
                };
            }
            e
        })?;
        Ok(m)
    }

    /// Check every value, including that the start lies on a `side`-sample map. [`parse`]
    /// calls this; use it for parameters built in code before saving them.
    ///
    /// [`parse`]: MapParams::parse
    pub fn validate_for_side(&self, side: u32) -> Result<(), MapError> {
        let err = |field: &str, message: String| MapError {
            field: field.into(),
            line: None,
            message,
        };
        let within = |key: &str, v: f64, (lo, hi): (f64, f64), what: &str| {
            if v.is_finite() && (lo..=hi).contains(&v) {
                Ok(())
            } else {
                Err(err(
                    key,
                    format!("expected {lo:e} ..= {hi:e} ({what}), got {v:?}"),
                ))
            }
        };
        within(
            "hScale",
            self.h_scale,
            H_SCALE,
            "world units between neighbouring samples",
        )?;
        within(
            "vScale",
            self.v_scale,
            V_SCALE,
            "world units per sample step; the highest height is 65535 × vScale",
        )?;
        let len = self.sun_dir.iter().map(|c| c * c).sum::<f64>().sqrt();
        if !len.is_finite() || (len - 1.0).abs() > 1e-9 {
            return Err(err(
                "sunDir",
                format!("expected a unit vector, got {:?}", self.sun_dir),
            ));
        }
        let fog_max = MAX_FOG_PER_SAMPLE / self.h_scale;
        if !(self.fog_density.is_finite() && (0.0..=fog_max).contains(&self.fog_density)) {
            return Err(err(
                "fogDensity",
                format!(
                    "expected 0 ..= {fog_max} ({MAX_FOG_PER_SAMPLE} / hScale: a fog through \
                     which the next sample still shows), got {:?}",
                    self.fog_density
                ),
            ));
        }
        let top = MAX_SAMPLE * self.v_scale;
        if let Some(w) = self.water_level
            && !(w.is_finite() && (0.0..=top).contains(&w))
        {
            return Err(err(
                "waterLevel",
                format!(
                    "expected 0 ..= {top} (the heights' range: 65535 × vScale = 65535 × {}), \
                     got {w:?}",
                    self.v_scale
                ),
            ));
        }
        let size = self.world_size(side);
        for (key, v) in [("start.x", self.start.x), ("start.z", self.start.z)] {
            if !(v.is_finite() && (0.0..=size).contains(&v)) {
                return Err(err(
                    key,
                    format!(
                        "expected 0 ..= {size} (on the map: hScale × (side − 1) = {} × {}), \
                         got {v:?}",
                        self.h_scale,
                        side.saturating_sub(1)
                    ),
                ));
            }
        }
        if !self.start.heading_deg.is_finite() {
            return Err(err(
                "start.heading",
                format!(
                    "expected a finite number of degrees, got {}",
                    self.start.heading_deg
                ),
            ));
        }
        Ok(())
    }

    /// The `map` file text for these parameters; [`MapParams::parse`] reads it back exactly.
    pub fn to_toml(&self) -> String {
        let mut s = String::new();
        let f = |v: f64| format!("{v:?}");
        let c = |v: [u8; 3]| format!("[{}, {}, {}]", v[0], v[1], v[2]);
        let _ = writeln!(s, "hScale = {}", f(self.h_scale));
        let _ = writeln!(s, "vScale = {}", f(self.v_scale));
        let d = self.sun_dir;
        let _ = writeln!(s, "sunDir = [{}, {}, {}]", f(d[0]), f(d[1]), f(d[2]));
        let _ = writeln!(s, "sunColor = {}", c(self.sun_color));
        let _ = writeln!(s, "fogDensity = {}", f(self.fog_density));
        let _ = writeln!(s, "fogColor = {}", c(self.fog_color));
        if let Some(w) = self.water_level {
            let _ = writeln!(s, "waterLevel = {}", f(w));
        }
        let _ = writeln!(s, "\n[start]");
        let _ = writeln!(s, "x = {}", f(self.start.x));
        let _ = writeln!(s, "z = {}", f(self.start.z));
        let _ = writeln!(s, "heading = {}", f(self.start.heading_deg));
        s
    }
}

/// `v / |v|`, or `None` when `v` is zero or not finite. A vector already of unit length (to
/// a few ulps) is returned unchanged, so writing and re-reading a map is exact.
pub fn normalize(v: [f64; 3]) -> Option<[f64; 3]> {
    let len = v.iter().map(|c| c * c).sum::<f64>().sqrt();
    if !len.is_finite() || len < 1e-12 || v.iter().any(|c| !c.is_finite()) {
        return None;
    }
    if (len - 1.0).abs() <= 4.0 * f64::EPSILON {
        return Some(v);
    }
    Some(v.map(|c| c / len))
}

/// 1-based line of byte offset `at`.
fn line_of(text: &str, at: usize) -> usize {
    let end = at.min(text.len());
    text.as_bytes()[..end]
        .iter()
        .filter(|&&b| b == b'\n')
        .count()
        + 1
}

struct Parser<'t> {
    text: &'t str,
}

impl Parser<'_> {
    fn line(&self, span: Range<usize>) -> Option<usize> {
        Some(line_of(self.text, span.start))
    }

    fn reject_unknown(
        &self,
        t: &DeTable<'_>,
        known: &[&str],
        prefix: &str,
    ) -> Result<(), MapError> {
        for (k, _) in t.iter() {
            let name: &str = k.get_ref();
            if !known.contains(&name) {
                return Err(MapError {
                    field: format!("{prefix}{name}"),
                    line: self.line(k.span()),
                    message: format!(
                        "unknown key: expected one of {}",
                        known
                            .iter()
                            .map(|k| format!("{prefix}{k}"))
                            .collect::<Vec<_>>()
                            .join(", ")
                    ),
                });
            }
        }
        Ok(())
    }

    fn type_err(&self, field: &str, line: Option<usize>, want: &str, v: &DeValue<'_>) -> MapError {
        MapError {
            field: field.into(),
            line,
            message: format!("expected {want}, got {}", show(v)),
        }
    }

    /// A finite number: TOML float or integer.
    fn number(&self, field: &str, line: Option<usize>, v: &DeValue<'_>) -> Result<f64, MapError> {
        let x = match v {
            DeValue::Integer(i) => i64::from_str_radix(i.as_str(), i.radix())
                .ok()
                .map(|i| i as f64),
            DeValue::Float(f) => f.as_str().parse::<f64>().ok(),
            _ => return Err(self.type_err(field, line, "a number", v)),
        };
        match x {
            Some(x) if x.is_finite() => Ok(x),
            _ => Err(self.type_err(field, line, "a finite number", v)),
        }
    }

    fn array3<'a, 'i>(
        &self,
        field: &str,
        line: Option<usize>,
        v: &'a DeValue<'i>,
        want: &str,
    ) -> Result<[&'a DeValue<'i>; 3], MapError> {
        let items: Vec<&DeValue<'_>> = match v.as_array() {
            Some(a) => a.iter().map(|x| x.get_ref()).collect(),
            None => return Err(self.type_err(field, line, want, v)),
        };
        match items[..] {
            [a, b, c] => Ok([a, b, c]),
            _ => Err(self.type_err(field, line, want, v)),
        }
    }

    fn floats3(
        &self,
        field: &str,
        line: Option<usize>,
        v: &DeValue<'_>,
    ) -> Result<[f64; 3], MapError> {
        let items = self.array3(field, line, v, "an array of 3 numbers")?;
        let mut out = [0.0; 3];
        for (i, (o, item)) in out.iter_mut().zip(items).enumerate() {
            *o = self.number(&format!("{field}[{i}]"), line, item)?;
        }
        Ok(out)
    }

    fn color(
        &self,
        field: &str,
        line: Option<usize>,
        v: &DeValue<'_>,
    ) -> Result<[u8; 3], MapError> {
        let want = "an array of 3 integers 0 ..= 255";
        let items = self.array3(field, line, v, want)?;
        let mut out = [0u8; 3];
        for (i, (o, item)) in out.iter_mut().zip(items).enumerate() {
            let value = match item {
                DeValue::Integer(n) => i64::from_str_radix(n.as_str(), n.radix()).ok(),
                _ => None,
            };
            *o = value.and_then(|n| u8::try_from(n).ok()).ok_or_else(|| {
                self.type_err(&format!("{field}[{i}]"), line, "an integer 0 ..= 255", item)
            })?;
        }
        Ok(out)
    }
}

/// A short rendering of a TOML value for error messages.
fn show(v: &DeValue<'_>) -> String {
    match v {
        DeValue::String(s) => format!("the string {s:?}"),
        DeValue::Integer(i) => i.to_string(),
        DeValue::Float(f) => f.to_string(),
        DeValue::Boolean(b) => format!("the boolean {b}"),
        DeValue::Datetime(d) => format!("the datetime {d}"),
        DeValue::Array(a) => {
            let items: Vec<String> = a.iter().map(|x| show(x.get_ref())).collect();
            format!("[{}]", items.join(", "))
        }
        DeValue::Table(_) => "a table".into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_and_round_trip() {
        let m = MapParams::parse("", 65).unwrap();
        assert_eq!(m, MapParams::default_for_side(65));
        assert_eq!(m.start.x, 32.0);
        let mut m = m;
        m.h_scale = 92.0;
        m.v_scale = 0.01;
        m.water_level = Some(28.5);
        m.sun_dir = normalize([-0.7568, 0.5736, 0.3135]).unwrap();
        m.fog_density = 5e-5;
        m.start = Start {
            x: 1234.5,
            z: 0.0,
            heading_deg: -30.25,
        };
        let text = m.to_toml();
        assert_eq!(MapParams::parse(&text, 65).unwrap(), m, "{text}");
    }

    #[test]
    fn lines_and_integers() {
        let m = MapParams::parse("hScale = 2\n[start]\nx = 0x10\n", 65).unwrap();
        assert_eq!(m.h_scale, 2.0);
        assert_eq!(m.start.x, 16.0);
        assert_eq!(m.start.z, 64.0);
        let e = MapParams::parse("vScale = 1.0\n\nhScale = -1\n", 65).unwrap_err();
        assert_eq!((e.field.as_str(), e.line), ("hScale", Some(3)));
        let e = MapParams::parse("[start]\nheading = 1\nx = 99\n", 65).unwrap_err();
        assert_eq!((e.field.as_str(), e.line), ("start.x", Some(3)));
        let e = MapParams::parse("fogDensity = nan\n", 65).unwrap_err();
        assert!(e.message.contains("finite"), "{e}");
    }

    /// Parses `text` for a 1025-sample map: `Ok(())` expected as `None`, else the error's
    /// field, line and a part of its message (the range, or what was refused).
    fn check(text: &str, expected: Option<(&str, usize, &str)>) {
        let got = MapParams::parse(text, 1025);
        match (expected, got) {
            (None, Ok(m)) => {
                // Every height of an accepted map is finite, and finite as an f32.
                let top = MAX_SAMPLE * m.v_scale;
                assert!((top as f32).is_finite() && top < 1e8, "{text}: top {top}");
            }
            (Some((field, line, part)), Err(e)) => {
                assert_eq!(
                    (e.field.as_str(), e.line),
                    (field, Some(line)),
                    "{text}: {e}"
                );
                assert!(e.message.contains(part), "{text}: {e:?} lacks {part:?}");
            }
            (want, got) => panic!("{text}: expected {want:?}, got {got:?}"),
        }
    }

    #[test]
    fn absurd_values_are_refused_naming_the_key_the_value_and_the_range() {
        // The bundled data sets' maps, and the extremes of every range, pass.
        check(include_str!("../../../data/kossou/map"), None);
        check(include_str!("../../../data/synth-257/map"), None);
        check(include_str!("../../../data/synth-65/map"), None);
        check("hScale = 0.001\nvScale = 1e-6\n[start]\nx = 0\n", None);
        check(
            "hScale = 10000\nvScale = 1000\nwaterLevel = 65535000\n",
            None,
        );
        check("hScale = 92\nfogDensity = 0.1086\nwaterLevel = 0\n", None);
        check("fogDensity = 0\n[start]\nheading = -7200\n", None);
        // Real DEMs: trench to Everest (19.8 km) in metres, and a hundredfold exaggeration.
        check("hScale = 30\nvScale = 0.303\nwaterLevel = 10994\n", None);
        check("hScale = 30\nvScale = 30.3\n", None);
        // What the attack used, and each range's edges.
        check(
            "vScale = 1e308\n",
            Some(("vScale", 1, "expected 1e-6 ..= 1e3")),
        );
        check("\nvScale = 1e308\n", Some(("vScale", 2, "got 1e308")));
        check("vScale = 1001\n", Some(("vScale", 1, "got 1001")));
        check("vScale = 0\n", Some(("vScale", 1, "expected 1e-6 ..= 1e3")));
        check("vScale = -0.01\n", Some(("vScale", 1, "got -0.01")));
        check("vScale = 1e-7\n", Some(("vScale", 1, "got 1e-7")));
        check(
            "hScale = 1e5\n",
            Some(("hScale", 1, "expected 1e-3 ..= 1e4")),
        );
        check("hScale = 0.0001\n", Some(("hScale", 1, "got 0.0001")));
        check(
            "vScale = 1.0\n\nhScale = -1\n",
            Some(("hScale", 3, "got -1")),
        );
        check(
            "fogDensity = 1e30\n",
            Some(("fogDensity", 1, "expected 0 ..= 10 (10 / hScale")),
        );
        check(
            "hScale = 92\nfogDensity = 0.109\n",
            Some(("fogDensity", 2, "got 0.109")),
        );
        check(
            "fogDensity = -1e-9\n",
            Some(("fogDensity", 1, "10 / hScale")),
        );
        check(
            "waterLevel = 1e300\n",
            Some(("waterLevel", 1, "expected 0 ..= 6553.5")),
        );
        check(
            "vScale = 0.01\nwaterLevel = 655.36\n",
            Some(("waterLevel", 2, "got 655.36")),
        );
        check(
            "waterLevel = -1\n",
            Some(("waterLevel", 1, "the heights' range")),
        );
        check(
            "waterLevel = inf\n",
            Some(("waterLevel", 1, "a finite number")),
        );
        check(
            "[start]\nheading = 1e400\n",
            Some(("start.heading", 2, "a finite number")),
        );
    }
}
