//! Input scripts: a scripted drive for `roam-server simulate`, the headless viewer and the
//! tests, and the benchmarks' drive ([`DRIVE_SCRIPT`]).
//!
//! One segment per line: `<ticks> <keys>`, holding `keys` for that many ticks (10 ms
//! each). Keys are any of `U` (accelerate), `D` (brake), `L`, `R` (turn), written together
//! (`UL`), or `-` for none. Blank lines are skipped and `#` starts a comment.
//!
//! ```text
//! # accelerate for two seconds, then a gentle left turn, then coast
//! 200 U
//! 150 UL
//! 300 -
//! ```

use crate::keys::{KeyStep, Keys};

/// The longest script, ticks (about 11.5 days of driving).
pub const MAX_TICKS: u64 = 100_000_000;

/// The drive of the benchmarks (the server's codec figures, the viewer's `--bench`): from
/// the map's start, throttle, turns both ways, a stretch of coasting.
pub const DRIVE_SCRIPT: &str = "150 U\n120 UL\n100 U\n120 UR\n60 -\n";

/// A parsed script.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Script {
    /// `(ticks, keys)` in order; ticks ≥ 1.
    pub segments: Vec<(u64, Keys)>,
}

/// A bad line: its 1-based number and what was expected.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("line {line}: {message}")]
pub struct ScriptError {
    pub line: usize,
    pub message: String,
}

impl Script {
    /// Total ticks.
    pub fn ticks(&self) -> u64 {
        self.segments.iter().map(|&(n, _)| n).sum()
    }

    /// The keys held at each tick, in order.
    pub fn keys(&self) -> impl Iterator<Item = Keys> + '_ {
        self.segments
            .iter()
            .flat_map(|&(n, keys)| std::iter::repeat_n(keys, n as usize))
    }

    /// Each tick's state as a viewer sends it: the held keys, and those down at this tick
    /// and not at the one before as pressed.
    pub fn steps(&self) -> impl Iterator<Item = KeyStep> + '_ {
        self.keys().scan(Keys::NONE, |last, held| {
            let pressed = held.without(*last);
            *last = held;
            Some(KeyStep { held, pressed })
        })
    }
}

fn parse_keys(word: &str) -> Option<Keys> {
    if word == "-" {
        return Some(Keys::NONE);
    }
    word.chars().try_fold(Keys::NONE, |keys, c| {
        let key = match c.to_ascii_uppercase() {
            'U' => Keys::UP,
            'D' => Keys::DOWN,
            'L' => Keys::LEFT,
            'R' => Keys::RIGHT,
            _ => return None,
        };
        Some(keys.union(key))
    })
}

/// Parses a script given as bytes: text that is not UTF-8 is an error at its line.
pub fn parse_bytes(bytes: &[u8]) -> Result<Script, ScriptError> {
    match std::str::from_utf8(bytes) {
        Ok(text) => parse(text),
        Err(e) => {
            let line = 1 + bytes[..e.valid_up_to()]
                .iter()
                .filter(|&&b| b == b'\n')
                .count();
            Err(ScriptError {
                line,
                message: "not UTF-8 text".into(),
            })
        }
    }
}

/// Parses a script.
pub fn parse(text: &str) -> Result<Script, ScriptError> {
    let mut segments = Vec::new();
    let mut total = 0u64;
    for (n, raw) in text.lines().enumerate() {
        let line = n + 1;
        let err = |message: String| ScriptError { line, message };
        let content = raw.split('#').next().unwrap_or("").trim();
        if content.is_empty() {
            continue;
        }
        let words: Vec<&str> = content.split_whitespace().collect();
        let [count, keys] = words[..] else {
            return Err(err(format!(
                "expected `<ticks> <keys>` (e.g. `100 UL`), got {content:?}"
            )));
        };
        let digits = count.bytes().all(|b| b.is_ascii_digit());
        let ticks: u64 = match count.parse() {
            Ok(t) if t >= 1 && digits => t,
            _ => {
                return Err(err(format!(
                    "ticks: expected a whole number ≥ 1, got {count:?}"
                )));
            }
        };
        let keys = parse_keys(keys).ok_or_else(|| {
            err(format!(
                "keys: expected `-` or letters from U, D, L, R, got {keys:?}"
            ))
        })?;
        total = total.saturating_add(ticks);
        if total > MAX_TICKS {
            return Err(err(format!(
                "the script runs past {MAX_TICKS} ticks (the longest allowed)"
            )));
        }
        segments.push((ticks, keys));
    }
    Ok(Script { segments })
}
