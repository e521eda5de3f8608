//! The server-wide colour budget: frames first, colour in what is left.
//!
//! Each viewer's colour task ([`super::viewer`]'s `stream_color`) paces its tiles with a
//! token bucket; this decides the bucket's rate, and whether it may send now:
//!
//! - **One total, shared equally.** [`super::Options::color_total`] bytes a second for
//!   every viewer together, split equally among the viewers that still want tiles (their
//!   windows not yet full), each at most [`super::Options::color_rate`]. A viewer whose
//!   windows are full stops counting, so the others' shares grow. Before, each viewer had
//!   its own 2 MB/s, so N joiners cost N times the colour: 40 joining at once were sent
//!   their whole colour maps (76.8 MB on `data/kossou`) in the first 5 s (15.3 MB/s),
//!   which swamped the server's core and the viewers'.
//! - **Spread, not at once.** Each tile also comes out of one server-wide bucket filled at
//!   the total and holding at most [`BURST`] of it (or the largest tile): with a
//!   per-viewer share alone, every joiner's bucket filled at the same pace and all sent a
//!   tile in the same instant (20 joining at once: the longest gap after the first frame
//!   was 112 ms at a total of 1 MB/s, against 54 ms with no colour at all).
//! - **Frames first.** A viewer's frame that starts more than [`LATE`] after its tick was
//!   due (the core is busy: making frames, joining viewers, sending) slows the server-wide
//!   bucket to a trickle ([`TRICKLE`], so colour never stops for good on a busy core) for
//!   [`BACK_OFF`]: colour does not compete with frames that are already behind.
//!
//! Measured (server pinned to CPU 0, viewers of 32,768 triangles at 60 Hz, each driving,
//! `data/kossou`; on a 2-core machine shared with other builds, so server and load
//! generator ran at real-time priority, `chrt -r 10`, back to back; the longest frame gap
//! of a viewer after its first frame; "shares" is the per-viewer share alone, "now" adds
//! the server-wide bucket and [`super::makers`]' order):
//!
//! | join | old | shares | now |
//! | --- | --- | --- | --- |
//! | 20 at once | 384 ms | 125–130 ms | 35–43 ms |
//! | 10 while 20 drive: the 20 | 425–694 ms | 141–517 ms | 72–100 ms |
//! | 10 while 20 drive: the 10 | 154–216 ms | 126–205 ms | 49–108 ms |
//! | 40 at once | 3.66–3.70 s | 1.13–2.16 s | 1.09 s |
//!
//! The colour sent in the first 5 s of the 40: 76.8 MB before, 8 MB now. What is left at
//! 40 is the frames themselves: that machine's core spent 450–600 µs of CPU a frame (about
//! 270 on a quiet one), so 40 viewers at 60 Hz saturated it with frames alone, their
//! acknowledgements fell more than 32 frames behind and key frames followed (80–150 in
//! 5 s, one at a time on the one blocking maker).
//!
//! The decisions take the time as a parameter (the shell passes its clock), so they are
//! tested without one.

use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use roam_protocol::sync::lock;

/// A frame starting later than this after its tick was due counts as behind.
pub const LATE: Duration = Duration::from_millis(8);
/// Colour trickles for this long after the last frame that was behind.
pub const BACK_OFF: Duration = Duration::from_millis(250);
/// The share of the total that colour goes at while frames are behind.
pub const TRICKLE: f64 = 1.0 / 16.0;
/// The server-wide bucket holds this much of the total at most (and at least the largest
/// tile): tiles go out spread, not all viewers' at once.
pub const BURST: Duration = Duration::from_millis(50);

/// The colour budget every viewer's colour task shares.
#[derive(Debug)]
pub struct ColorBudget {
    /// Bytes a second for one viewer at most ([`super::Options::color_rate`]).
    per_viewer: u64,
    /// Bytes a second for all together ([`super::Options::color_total`]).
    total: u64,
    /// Viewers that still want tiles.
    wanting: AtomicUsize,
    /// When a frame was last behind: nanoseconds after `epoch`, plus one (0: never).
    late_at: AtomicU64,
    epoch: Instant,
    /// The server-wide bucket: its bytes, and when it was last filled.
    bucket: Mutex<(f64, Option<Instant>)>,
}

impl ColorBudget {
    pub fn new(per_viewer: u64, total: u64, epoch: Instant) -> ColorBudget {
        ColorBudget {
            per_viewer,
            total,
            wanting: AtomicUsize::new(0),
            late_at: AtomicU64::new(0),
            epoch,
            bucket: Mutex::new((0.0, None)),
        }
    }

    /// Bytes a second for one viewer that wants tiles, now: an equal share of the total,
    /// at most the per-viewer rate.
    pub fn rate(&self) -> f64 {
        let n = self.wanting.load(Ordering::Relaxed).max(1);
        (self.total as f64 / n as f64).min(self.per_viewer as f64)
    }

    /// A viewer with `own` bytes in its own bucket sends at `now`: `pick(allowance)`
    /// chooses what to send within the allowance (its own bytes, and no more than the
    /// server-wide bucket holds) and returns the bytes chosen, which both buckets lose
    /// (the caller takes them from its own). Returns them. The server-wide bucket fills at
    /// the total, a trickle of it while frames are behind, up to [`BURST`] of it or
    /// `largest` (a tile), whichever is more.
    pub fn spend(
        &self,
        now: Instant,
        largest: u64,
        own: u64,
        pick: impl FnOnce(u64) -> u64,
    ) -> u64 {
        let behind = self.frames_first(now);
        let mut b = lock(&self.bucket);
        let rate = self.total as f64 * if behind { TRICKLE } else { 1.0 };
        let burst = (self.total as f64 * BURST.as_secs_f64()).max(largest as f64);
        let since =
            b.1.map_or(Duration::ZERO, |t| now.saturating_duration_since(t));
        b.0 = (b.0 + rate * since.as_secs_f64()).min(burst);
        b.1 = Some(b.1.map_or(now, |t| t.max(now)));
        let spent = pick(own.min(b.0 as u64));
        b.0 -= spent as f64;
        spent
    }

    /// Viewers counted as wanting tiles.
    pub fn wanting(&self) -> usize {
        self.wanting.load(Ordering::Relaxed)
    }

    /// A viewer starts or stops wanting tiles (its windows not full, or full again).
    pub fn set_wanting(&self, was: bool, now: bool) {
        match (was, now) {
            (false, true) => {
                self.wanting.fetch_add(1, Ordering::Relaxed);
            }
            (true, false) => {
                self.wanting.fetch_sub(1, Ordering::Relaxed);
            }
            _ => {}
        }
    }

    /// A frame whose tick was due at `due` starts at `now`: behind if later than [`LATE`].
    pub fn frame_started(&self, due: Instant, now: Instant) {
        if now.saturating_duration_since(due) > LATE {
            let ns = now.saturating_duration_since(self.epoch).as_nanos();
            let ns = u64::try_from(ns).unwrap_or(u64::MAX - 1) + 1;
            self.late_at.fetch_max(ns, Ordering::Relaxed);
        }
    }

    /// Whether colour must trickle at `now`: a frame was behind less than [`BACK_OFF`] ago.
    pub fn frames_first(&self, now: Instant) -> bool {
        let late = self.late_at.load(Ordering::Relaxed);
        if late == 0 {
            return false;
        }
        let at = self.epoch + Duration::from_nanos(late - 1);
        now.saturating_duration_since(at) < BACK_OFF
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_total_is_shared_equally_by_the_viewers_that_want_tiles() {
        let b = ColorBudget::new(2_000_000, 4_000_000, Instant::now());
        assert_eq!(b.rate(), 2_000_000.0, "nobody wanting: one viewer's rate");
        b.set_wanting(false, true);
        assert_eq!(b.rate(), 2_000_000.0, "one viewer: its own cap");
        for _ in 0..39 {
            b.set_wanting(false, true);
        }
        assert_eq!(b.wanting(), 40);
        assert_eq!(b.rate(), 100_000.0, "40 share 4 MB/s");
        b.set_wanting(true, true);
        b.set_wanting(false, false);
        assert_eq!(b.wanting(), 40, "no change, no count");
        for _ in 0..38 {
            b.set_wanting(true, false);
        }
        assert_eq!(b.rate(), 2_000_000.0, "two left: each at its cap");
    }

    #[test]
    fn the_server_wide_bucket_spreads_tiles_and_trickles_while_frames_are_behind() {
        let t0 = Instant::now();
        let ms = |n| t0 + Duration::from_millis(n);
        // 1 MB/s for all: 50 kB at most in the bucket, or the largest tile (20 kB here).
        let b = ColorBudget::new(2_000_000, 1_000_000, t0);
        assert_eq!(
            b.spend(ms(0), 20_000, 1_000_000, |a| a),
            0,
            "empty at first"
        );
        // A second later it holds its burst only; a viewer's own bytes bound it too.
        assert_eq!(b.spend(ms(1_000), 20_000, 30_000, |a| a), 30_000);
        assert_eq!(b.spend(ms(1_000), 20_000, 1_000_000, |a| a), 20_000);
        // What the picker does not take stays.
        assert_eq!(b.spend(ms(1_010), 20_000, 1_000_000, |_| 0), 0);
        assert_eq!(b.spend(ms(1_010), 20_000, 1_000_000, |a| a), 10_000);
        // Frames behind: a sixteenth of the rate (270 ms at 62.5 kB/s).
        b.frame_started(ms(1_100), ms(1_120));
        assert_eq!(b.spend(ms(1_280), 20_000, 1_000_000, |a| a), 16_875);
        // Never less than the largest tile in the bucket, so every tile can go.
        let small = ColorBudget::new(2_000_000, 100_000, t0);
        assert_eq!(small.spend(ms(0), 20_000, 1_000_000, |a| a), 0);
        assert_eq!(small.spend(ms(10_000), 20_000, 1_000_000, |a| a), 20_000);
    }

    #[test]
    fn a_late_frame_holds_colour_back_for_a_while() {
        let t0 = Instant::now();
        let ms = |n| t0 + Duration::from_millis(n);
        let b = ColorBudget::new(2_000_000, 4_000_000, t0);
        assert!(!b.frames_first(ms(0)));
        b.frame_started(ms(100), ms(100) + LATE);
        assert!(!b.frames_first(ms(110)), "on time (at the bound)");
        b.frame_started(ms(100), ms(109));
        assert!(b.frames_first(ms(109)));
        assert!(b.frames_first(ms(109) + BACK_OFF - Duration::from_nanos(1)));
        assert!(!b.frames_first(ms(109) + BACK_OFF));
        // An older late frame reported after a newer one does not shorten the wait.
        b.frame_started(ms(500), ms(520));
        b.frame_started(ms(400), ms(420));
        assert!(b.frames_first(ms(520) + BACK_OFF / 2));
    }
}
