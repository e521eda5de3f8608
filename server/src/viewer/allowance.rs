//! How many changes each viewer's cut may make a frame while the server is loaded
//! ([`Allowance`]): the frame clock's one decision about load, clock-free (it is told how
//! late frames start) so that tests drive it with made-up lateness.
//!
//! **Why.** A cut's upkeep follows the view: driving straight, a frame makes a few changes
//! (12 µs, the median of `serve_many` along `scripts/capacity-drive.txt`); turning at the
//! fastest rate, some 400 (665 µs). Viewers that turn together (`scripts/capacity.sh
//! --in-step`) load the one core many times over for a second and leave it idle after: 100
//! such viewers got 38 frames a second from a core 63 % busy (2026-12-07), their frames
//! skipped while the turns' cuts were made. ROAM's optimisation may stop at any time with
//! the best cut so far (the queues are in priority order), so under load each cut makes at
//! most this many changes a frame and finishes its turn in the frames after, inside the
//! guard band (10° each side: eight frames of the fastest turn), and the frames keep
//! coming.
//!
//! **How.** The signal is how late frames start after their tick, the one figure that says
//! the core is short whatever takes it (the cuts, quinn, the kernel, colour). After each
//! pass of the clock: a frame more than [`LATE`] late cuts the allowance by a quarter,
//! more than twice that to a quarter, more than a frame period ([`FAR_BEHIND`]) to the
//! [`FLOOR`]; every frame within [`ON_TIME`] raises it by [`RISE`] (up to [`CEILING`],
//! which is none); in between it holds. At the floor the cut's lag is [`LAG_AT_FLOOR`]
//! times higher, and under any allowance its kept evaluations lag a turn inside the guard
//! band (`crate::tessellate::Coherent::set_allowance`). Down fast, up slowly (as TCP's
//! window), so that the core does not swing between late and idle every few passes. The deeper cuts are for the
//! start of a turn taken together: a quarter a pass took some 19 passes from none to the
//! floor while every cut made its turn's hundreds of changes, and the frames fell a tenth
//! of a second behind. With them, 100 viewers in step on `data/kossou` took 54.6–55.1 →
//! 59.1 frames/s (every frame sent taken), 64 on the steep map 56.3 → 56.5
//! (`scripts/capacity.sh --in-step`, `FRAMES=1800`, 2026-12-07, in turn). Lateness is
//! counted for want of the core only (`Conversation::late`: not a first frame's wait for
//! its turn, not a frame's wait for its core to come back from a heavy job). Passes come
//! more often the more viewers there are (16 phases a period), so the rise is per pass,
//! not per second: from the floor to none in about 0.13 s with many viewers, 2 s with
//! one; a clock with no viewers starts over at none.

use std::time::Duration;

/// The least allowance: a frame still makes this many changes, the most important first
/// (and past it every split above the lag the cut allows, `crate::tessellate::Coherent`,
/// which is what bounds the error, not this). With 24, 100 viewers in step on
/// `data/kossou` got 48.9 frames/s; with 4, 52.4 (`scripts/capacity.sh --in-step 100`,
/// `FRAMES=1200`, 2026-12-07, the first version of the lag). Along
/// `scripts/capacity-drive.txt` with 4 on every frame (`roam-server bench DIR --budget
/// 32768 --drive ... --allowance 4`: the most a loaded server holds back), 32 viewers' cuts
/// cost 29 µs a frame instead of 62 on `data/kossou`, leaving 1.0 px instead of 0.14 (p99);
/// on the steep map, where the budget leaves 2.5 px, little is held back (121 µs, 2.8 px).
const FLOOR: u32 = 4;

/// At the [`FLOOR`], what a cut lets lag past it is this many times more
/// ([`crate::tessellate::Coherent::set_lag_scale`]): where the budget leaves pixels (the
/// steep map), the splits above the lag's bound were most of a held frame's work. Along
/// `scripts/capacity-drive.txt`, 32 viewers' cuts at 4 changes a frame (`roam-server bench
/// DIR --budget 32768 --drive ... --allowance 4`, 2026-12-08, with the turn lag), ×1 / ×2 /
/// ×4: the steep map 146 / 126 / 84 µs a frame, 30.7 / 30.4 / 15.7 changes, the error left
/// (p99) 2.0–3.7 / 2.0 / 4.0 px; `data/kossou` 28 / 24 / 33 µs (its held frames are
/// evaluations: 5–6 changes), 1.0 / 2.0 / 3.5 px. In step, 100 viewers on the steep map
/// (`scripts/capacity.sh --in-step 100`, `DATA=/tmp/steep`, same day, in turn): 34.4 frames/s
/// with ×2, 41.3 with ×4; `data/kossou` 57.3 and 57.8. Only at the floor: a server that got
/// there is a frame period behind, and a few pixels for the frames of a turn beat frames
/// skipped.
const LAG_AT_FLOOR: f32 = 4.0;

/// What the lag's bound is multiplied by at an allowance of `changes` a frame.
pub(super) fn lag_scale(changes: u32) -> f32 {
    if changes <= FLOOR { LAG_AT_FLOOR } else { 1.0 }
}

/// At this allowance there is none (a frame's cut makes every change it wants, up to the
/// update's own bound, `crate::tessellate::Coherent`).
const CEILING: u32 = 1024;

/// A frame started later than this after its tick says the core is short.
const LATE: Duration = Duration::from_millis(4);

/// A frame started later than this (about a frame period at 60 Hz) says frames are being
/// skipped: every cut goes to the [`FLOOR`] at once. Between it and twice [`LATE`], a pass
/// cuts the allowance to a quarter.
const FAR_BEHIND: Duration = Duration::from_millis(16);

/// Frames that all start within this of their ticks say there is room.
const ON_TIME: Duration = Duration::from_millis(1);

/// What a pass of frames on time adds to the allowance.
const RISE: u32 = 8;

/// The changes a viewer's cut may make a frame, from how late the clock's frames start.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Allowance {
    changes: u32,
}

impl Default for Allowance {
    fn default() -> Self {
        Allowance { changes: CEILING }
    }
}

impl Allowance {
    /// The allowance now, for [`crate::viewer::ViewerCore::set_allowance`]: `u32::MAX` (none)
    /// at the ceiling.
    pub fn changes(&self) -> u32 {
        if self.changes >= CEILING {
            u32::MAX
        } else {
            self.changes
        }
    }

    /// The allowance now, `None` at the ceiling (for the server's summary).
    pub fn level(&self) -> Option<u32> {
        (self.changes < CEILING).then_some(self.changes)
    }

    /// A pass of the clock made frames, the latest starting `latest` after its tick
    /// (`None`: the pass made no frame, and says nothing).
    pub fn pass(&mut self, latest: Option<Duration>) {
        match latest {
            Some(late) if late > FAR_BEHIND => self.changes = FLOOR,
            Some(late) if late > 2 * LATE => self.changes = (self.changes / 4).max(FLOOR),
            Some(late) if late > LATE => self.changes = (self.changes * 3 / 4).max(FLOOR),
            Some(late) if late <= ON_TIME => self.changes = (self.changes + RISE).min(CEILING),
            _ => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Feeds passes of the given lateness (ms; `None`: no frame) and returns the
    /// allowance after each.
    fn run(start: u32, passes: &[Option<u64>]) -> Vec<Option<u32>> {
        let mut a = Allowance { changes: start };
        passes
            .iter()
            .map(|p| {
                a.pass(p.map(Duration::from_millis));
                a.level()
            })
            .collect()
    }

    fn check(start: u32, passes: &[Option<u64>], expected: &[Option<u32>]) {
        assert_eq!(
            run(start, passes),
            expected,
            "from {start}, passes {passes:?}"
        );
    }

    #[test]
    fn late_frames_cut_it_by_a_quarter_down_to_the_floor() {
        check(
            CEILING,
            &[Some(5), Some(6), Some(8)],
            &[Some(768), Some(576), Some(432)],
        );
        check(6, &[Some(5), Some(5)], &[Some(FLOOR), Some(FLOOR)]);
    }

    #[test]
    fn frames_far_behind_cut_it_deeper() {
        // More than twice LATE: to a quarter; more than a frame period: to the floor.
        check(CEILING, &[Some(9), Some(12)], &[Some(256), Some(64)]);
        check(CEILING, &[Some(17)], &[Some(FLOOR)]);
        check(
            CEILING,
            &[Some(16), Some(8), Some(5)],
            &[Some(256), Some(192), Some(144)],
        );
    }

    #[test]
    fn frames_on_time_raise_it_slowly_up_to_none() {
        check(FLOOR, &[Some(0), Some(1)], &[Some(12), Some(20)]);
        check(1020, &[Some(0), Some(0)], &[None, None]);
    }

    #[test]
    fn between_on_time_and_late_and_without_frames_it_holds() {
        check(
            500,
            &[Some(2), Some(4), None, Some(3)],
            &[Some(500), Some(500), Some(500), Some(500)],
        );
    }

    #[test]
    fn only_the_floor_lets_more_lag() {
        let scales = [FLOOR - 1, FLOOR, FLOOR + 1, 64, u32::MAX].map(lag_scale);
        assert_eq!(scales, [LAG_AT_FLOOR, LAG_AT_FLOOR, 1.0, 1.0, 1.0]);
    }

    #[test]
    fn none_is_no_allowance_for_the_cut() {
        assert_eq!(Allowance::default().changes(), u32::MAX);
        assert_eq!(Allowance { changes: 100 }.changes(), 100);
    }
}
