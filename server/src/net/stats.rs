//! What the server counts while it serves, and the periodic summary it logs from them:
//! viewers, frames a second served, CPU per frame (the whole process's, from
//! [`process_cpu`], over the frames served in the interval), bytes out a second (and the
//! colour and normal tiles' shares of them), and what admission did with connections that never said hello.
//!
//! Counters are relaxed atomics: each is a plain count that nothing else is ordered by.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

/// Running totals since the server started.
#[derive(Debug, Default)]
pub struct ServeStats {
    /// Frames made and sent, all viewers.
    pub frames: AtomicU64,
    /// UDP bytes sent to welcomed viewers.
    pub bytes_out: AtomicU64,
    /// Time spent making frames, nanoseconds.
    pub make_ns: AtomicU64,
    /// Key frames among the frames, and those that were not a viewer's first: asked for,
    /// made because acknowledgements fell behind the kept logs, or cheaper than the
    /// changes ([`crate::viewer::KeyCause`]).
    pub key_frames: AtomicU64,
    pub key_asked: AtomicU64,
    pub key_behind: AtomicU64,
    pub key_larger: AtomicU64,
    /// Frames whose cut stopped at the clock's allowance ([`crate::viewer::Allowance`]).
    pub short: AtomicU64,
    /// Served viewers' frames passed over while joining viewers' first frames waited
    /// ([`crate::viewer::conversation::Conversation::pass_over`]).
    pub passed_over: AtomicU64,
    /// Served viewers' frames made on a frame maker, off the clock's pass (a rebuild, a key
    /// frame's coding, more than `INLINE_CHANGES` changes).
    pub heavy: AtomicU64,
    /// Colour tile messages written to viewers' control streams, and their bytes (the
    /// coarsest tile sent before the first frame included).
    pub color_tiles: AtomicU64,
    pub color_bytes: AtomicU64,
    /// Normal tile messages written (one after each colour tile: never more tiles than
    /// the colour's), and their bytes.
    pub normal_tiles: AtomicU64,
    pub normal_bytes: AtomicU64,
    /// Viewers welcomed.
    pub joins: AtomicU64,
    /// Hellos refused (token, version, full, nothing to follow).
    pub refused: AtomicU64,
    /// Connections past the pending cap sent a QUIC Retry.
    pub retried: AtomicU64,
    /// Connections refused without a handshake (past the cap, address not provable).
    pub refused_early: AtomicU64,
    /// Pending connections evicted to make room (decided), and those closed for it.
    pub evicted: AtomicU64,
    pub evicted_closed: AtomicU64,
    /// Connections closed because no hello came by the deadline.
    pub timed_out: AtomicU64,
    /// Connections whose handshake failed or that sent something other than a hello.
    pub failed: AtomicU64,
    /// The longest a connection stayed pending (from its first packet to its hello, or to
    /// the server's close of it) since the last summary, milliseconds.
    pending_longest_ms: AtomicU64,
    /// Refusals logged at info since the last summary ([`REFUSALS_LOGGED`] at most).
    refusals_logged: AtomicU64,
    /// The latest a frame started after its tick was due since the last summary,
    /// microseconds (the core was busy: [`super::color_budget`] holds colour back then).
    late_longest_us: AtomicU64,
    /// How far below none the allowance went since the last summary: `u32::MAX` less the
    /// least allowance (0: none all along, so that the default is right).
    allowance_below: AtomicU64,
}

/// Refusals logged one line each between two summaries; the rest are counted (and logged
/// at debug).
pub const REFUSALS_LOGGED: u64 = 20;

/// The counters at one moment.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct Counts {
    pub frames: u64,
    pub bytes_out: u64,
    pub make_ns: u64,
    pub key_frames: u64,
    pub key_asked: u64,
    pub key_behind: u64,
    pub key_larger: u64,
    pub short: u64,
    pub passed_over: u64,
    pub heavy: u64,
    pub color_tiles: u64,
    pub color_bytes: u64,
    pub normal_tiles: u64,
    pub normal_bytes: u64,
    pub joins: u64,
    pub refused: u64,
    pub retried: u64,
    pub refused_early: u64,
    pub evicted: u64,
    pub evicted_closed: u64,
    pub timed_out: u64,
    pub failed: u64,
}

impl ServeStats {
    pub fn add(&self, counter: &AtomicU64, n: u64) {
        counter.fetch_add(n, Ordering::Relaxed);
    }

    /// Whether the next refusal gets a line of its own (false past [`REFUSALS_LOGGED`]
    /// since the last summary).
    pub fn refusal_logged(&self) -> bool {
        self.refusals_logged.fetch_add(1, Ordering::Relaxed) < REFUSALS_LOGGED
    }

    /// A connection stops being pending after `ms`: it said hello, or was closed.
    pub fn pending_ended(&self, ms: u64) {
        self.pending_longest_ms.fetch_max(ms, Ordering::Relaxed);
    }

    /// A frame started `late` after its tick was due.
    pub fn frame_late(&self, late: Duration) {
        let us = u64::try_from(late.as_micros()).unwrap_or(u64::MAX);
        self.late_longest_us.fetch_max(us, Ordering::Relaxed);
    }

    /// A summary is being logged: refusals get lines of their own again. Returns the
    /// longest pending time since the last one, and starts that over.
    pub fn summarized(&self) -> u64 {
        self.refusals_logged.store(0, Ordering::Relaxed);
        self.pending_longest_ms.swap(0, Ordering::Relaxed)
    }

    /// The clock's allowance ([`crate::viewer::Allowance::level`]) after a pass.
    pub fn allowance(&self, level: Option<u32>) {
        let below = level.map_or(0, |l| u64::from(u32::MAX - l));
        self.allowance_below.fetch_max(below, Ordering::Relaxed);
    }

    /// The least allowance since the last call (`None`: none all along), started over.
    pub fn allowance_least(&self) -> Option<u64> {
        let below = self.allowance_below.swap(0, Ordering::Relaxed);
        (below != 0).then(|| u64::from(u32::MAX) - below)
    }

    /// The latest a frame started since the last call (microseconds), started over.
    pub fn late_longest_us(&self) -> u64 {
        self.late_longest_us.swap(0, Ordering::Relaxed)
    }

    pub fn counts(&self) -> Counts {
        let get = |c: &AtomicU64| c.load(Ordering::Relaxed);
        Counts {
            frames: get(&self.frames),
            bytes_out: get(&self.bytes_out),
            make_ns: get(&self.make_ns),
            key_frames: get(&self.key_frames),
            key_asked: get(&self.key_asked),
            key_behind: get(&self.key_behind),
            key_larger: get(&self.key_larger),
            short: get(&self.short),
            passed_over: get(&self.passed_over),
            heavy: get(&self.heavy),
            color_tiles: get(&self.color_tiles),
            color_bytes: get(&self.color_bytes),
            normal_tiles: get(&self.normal_tiles),
            normal_bytes: get(&self.normal_bytes),
            joins: get(&self.joins),
            refused: get(&self.refused),
            retried: get(&self.retried),
            refused_early: get(&self.refused_early),
            evicted: get(&self.evicted),
            evicted_closed: get(&self.evicted_closed),
            timed_out: get(&self.timed_out),
            failed: get(&self.failed),
        }
    }
}

/// The process's CPU time so far (user and system, every thread), from
/// `clock_gettime(CLOCK_PROCESS_CPUTIME_ID)`: nanoseconds, no file read (the summary task
/// runs on the async runtime, whose workers must not block on I/O), and no assumption on
/// the kernel's clock tick (`/proc/self/stat`, read before, counts in ticks of
/// `sysconf(_SC_CLK_TCK)`, which was taken to be 100). `None` where there is no such clock.
pub fn process_cpu() -> Option<Duration> {
    let mut t = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `t` is a valid, writable timespec for the call's duration; the call writes
    // only it.
    let r = unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut t) };
    if r != 0 {
        return None;
    }
    let secs = u64::try_from(t.tv_sec).ok()?;
    let nanos = u32::try_from(t.tv_nsec).ok()?;
    Some(Duration::new(secs, nanos))
}

/// One summary line's figures, from the counts at the start and end of an interval.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Summary {
    pub frames_per_s: f64,
    pub bytes_out_per_s: f64,
    /// Colour tile bytes a second.
    pub color_bytes_per_s: f64,
    /// Normal tile bytes a second.
    pub normal_bytes_per_s: f64,
    /// Process CPU per frame served, microseconds (`None` without frames or a CPU clock).
    pub cpu_per_frame_us: Option<f64>,
    /// Time making a frame, microseconds, on average.
    pub make_us: Option<f64>,
    /// Connections closed before their hello (deadline, eviction, failure), retried and
    /// refused early, and hellos refused, in the interval.
    pub junk: u64,
    pub retried: u64,
    pub refused: u64,
}

impl Summary {
    pub fn between(a: &Counts, b: &Counts, seconds: f64, cpu: Option<Duration>) -> Summary {
        let frames = b.frames - a.frames;
        let per_frame = |total: f64| (frames > 0).then(|| total / frames as f64);
        Summary {
            frames_per_s: frames as f64 / seconds,
            bytes_out_per_s: (b.bytes_out - a.bytes_out) as f64 / seconds,
            color_bytes_per_s: (b.color_bytes - a.color_bytes) as f64 / seconds,
            normal_bytes_per_s: (b.normal_bytes - a.normal_bytes) as f64 / seconds,
            cpu_per_frame_us: cpu.and_then(|c| per_frame(c.as_secs_f64() * 1e6)),
            make_us: per_frame((b.make_ns - a.make_ns) as f64 / 1e3),
            junk: (b.timed_out + b.evicted_closed + b.failed)
                - (a.timed_out + a.evicted_closed + a.failed),
            retried: (b.retried + b.refused_early) - (a.retried + a.refused_early),
            refused: b.refused - a.refused,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_summary_divides_by_the_interval_and_the_frames() {
        let a = Counts {
            frames: 100,
            bytes_out: 1_000,
            make_ns: 0,
            timed_out: 3,
            ..Counts::default()
        };
        let b = Counts {
            frames: 700,
            bytes_out: 61_000,
            make_ns: 600_000_000,
            timed_out: 5,
            color_bytes: 20_000,
            normal_bytes: 10_000,
            evicted_closed: 1,
            retried: 4,
            ..Counts::default()
        };
        let s = Summary::between(&a, &b, 10.0, Some(Duration::from_millis(300)));
        assert_eq!(s.frames_per_s, 60.0);
        assert_eq!(s.bytes_out_per_s, 6_000.0);
        assert_eq!(s.color_bytes_per_s, 2_000.0);
        assert_eq!(s.normal_bytes_per_s, 1_000.0);
        assert_eq!(s.cpu_per_frame_us, Some(500.0));
        assert_eq!(s.make_us, Some(1_000.0));
        assert_eq!((s.junk, s.retried, s.refused), (3, 4, 0));
        let idle = Summary::between(&b, &b, 10.0, None);
        assert_eq!((idle.cpu_per_frame_us, idle.make_us), (None, None));
    }

    #[test]
    fn the_least_allowance_is_kept_and_started_over_at_each_summary() {
        let s = ServeStats::default();
        assert_eq!(s.allowance_least(), None, "none before any pass");
        s.allowance(Some(500));
        s.allowance(None);
        s.allowance(Some(24));
        s.allowance(Some(300));
        assert_eq!(s.allowance_least(), Some(24));
        s.allowance(None);
        assert_eq!(s.allowance_least(), None);
    }

    #[test]
    fn the_longest_pending_time_is_kept_and_started_over_at_each_summary() {
        let s = ServeStats::default();
        s.pending_ended(40);
        s.pending_ended(5_000);
        s.pending_ended(70);
        assert_eq!(s.summarized(), 5_000);
        s.pending_ended(30);
        assert_eq!(s.summarized(), 30);
        assert_eq!(s.summarized(), 0);
    }

    /// The process's CPU time (user and system) from `getrusage`, microseconds.
    fn rusage_cpu() -> Duration {
        // SAFETY: an all-zero `rusage` is a valid value of the plain C struct.
        let mut u: libc::rusage = unsafe { std::mem::zeroed() };
        // SAFETY: `u` is a valid, writable rusage for the call's duration.
        let r = unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
        assert_eq!(r, 0, "getrusage(RUSAGE_SELF) works on Linux");
        let us = |t: libc::timeval| t.tv_sec as u64 * 1_000_000 + t.tv_usec as u64;
        Duration::from_micros(us(u.ru_utime) + us(u.ru_stime))
    }

    #[test]
    fn the_cpu_time_agrees_with_getrusage_to_the_microsecond() {
        // Linux only: the CI and every supported server run it.
        let mut x = 0u64;
        for i in 0..20_000_000u64 {
            x = x.wrapping_add(std::hint::black_box(i * i));
        }
        std::hint::black_box(x);
        // getrusage's figure (whole microseconds, user and system each) lies between two
        // readings taken around it. Clock ticks (the old `/proc/self/stat` reading, in
        // 10 ms steps) are up to 20 ms behind it.
        let before = process_cpu().expect("CLOCK_PROCESS_CPUTIME_ID exists on Linux");
        let rusage = rusage_cpu();
        let after = process_cpu().expect("CLOCK_PROCESS_CPUTIME_ID exists on Linux");
        assert!(before > Duration::ZERO, "{before:?}");
        let slack = Duration::from_micros(2);
        assert!(
            before <= rusage + slack && rusage <= after + slack,
            "{before:?} <= {rusage:?} <= {after:?}"
        );
        // Nanoseconds: three readings are not all whole clock ticks.
        let tick = Duration::from_millis(10).as_nanos();
        let readings = [before, after, process_cpu().expect("as above")];
        assert!(
            readings.iter().any(|r| r.as_nanos() % tick != 0),
            "{readings:?}"
        );
    }
}
