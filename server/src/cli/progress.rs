//! Progress bars for slow loads and builds: drawn on stderr, only on a terminal, and only
//! once the work has taken more than a second. The library reports `(done, total)` through
//! a callback; the clock lives here, in the binary.

use std::io::IsTerminal;
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use roam_server::terrain::cache::Stage;

pub(crate) struct Progress {
    bar: ProgressBar,
    started: Instant,
    shown: bool,
    enabled: bool,
}

impl Progress {
    pub(crate) fn new(what: &str) -> Self {
        let bar = ProgressBar::with_draw_target(None, ProgressDrawTarget::hidden());
        let style = ProgressStyle::with_template("{msg:>12} [{bar:40}] {percent:>3}% {eta}")
            .expect("the template is a constant and valid")
            .progress_chars("=> ");
        bar.set_style(style);
        bar.set_message(what.to_string());
        Progress {
            bar,
            started: Instant::now(),
            shown: false,
            enabled: std::io::stderr().is_terminal(),
        }
    }

    /// Report `done` of `total` units.
    pub(crate) fn update(&mut self, done: u64, total: u64) {
        if !self.enabled {
            return;
        }
        if !self.shown && self.started.elapsed() > Duration::from_secs(1) {
            self.bar.set_draw_target(ProgressDrawTarget::stderr());
            self.shown = true;
        }
        self.bar.set_length(total);
        self.bar.set_position(done);
    }

    /// A callback for library code.
    pub(crate) fn callback(&mut self) -> impl FnMut(u64, u64) + '_ {
        move |done, total| self.update(done, total)
    }
}

impl Drop for Progress {
    fn drop(&mut self) {
        self.bar.finish_and_clear();
    }
}

/// One bar per step of a library call that reports its stage (opening a data set's cache:
/// hashing, converting, verifying, building the variance tree), each labelled by its stage.
#[derive(Default)]
pub(crate) struct Staged {
    current: Option<(Stage, Progress)>,
}

impl Staged {
    /// Report `done` of `total` units of `stage`; a new stage replaces the previous bar.
    pub(crate) fn update(&mut self, stage: Stage, done: u64, total: u64) {
        if self.current.as_ref().map(|(s, _)| *s) != Some(stage) {
            self.current = Some((stage, Progress::new(stage.label())));
        }
        if let Some((_, bar)) = &mut self.current {
            bar.update(done, total);
        }
    }

    /// A callback for library code.
    pub(crate) fn callback(&mut self) -> impl FnMut(Stage, u64, u64) + '_ {
        move |stage, done, total| self.update(stage, done, total)
    }
}
