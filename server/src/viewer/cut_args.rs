//! The command-line flags that say how a viewer's cut is made (`--fog-priority`,
//! `--guard-deg`, `--swap-margin`): [`CutArgs`], declared once and flattened into every
//! command that serves or measures serving (`roam-server serve`, `edge` and `bench`, and
//! `roam-client` for its in-process server). They fill the [`ViewerLimits`] fields of the
//! same names ([`CutArgs::limits`]) and default to what [`ViewerLimits::default`] serves.
//!
//! Decisions: the flags live in the library, beside the limits they fill, because both
//! binaries flatten them (the viewer's depends on this crate); nothing else in the library
//! knows of a command line, and nothing here parses or reads anything but clap's values.

use super::{
    DEFAULT_GUARD_DEG, DEFAULT_SWAP_MARGIN_PCT, MAX_GUARD_DEG, MAX_SWAP_MARGIN_PCT, ViewerLimits,
};
use crate::Terrain;

/// Whether the priority weighs each diamond's error by what the map's fog lets through of
/// it (`--fog-priority`, for `mesh`, `bench`, `serve` and the viewer's in-process server):
/// `off` gives the fog-unaware priority, for before/after comparisons.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum FogPriority {
    On,
    Off,
}

impl FogPriority {
    pub fn on(self) -> bool {
        self == FogPriority::On
    }

    /// The fog density the tessellator weighs errors by on `terrain`'s map.
    pub fn density(self, terrain: &Terrain) -> f32 {
        if self.on() {
            terrain.map.fog_density as f32
        } else {
            0.0
        }
    }
}

/// How the served cuts are made: the fog's weight, the guard band and the swap margin.
#[derive(clap::Args, Clone, Copy, Debug, PartialEq, Eq)]
pub struct CutArgs {
    /// Weigh each diamond's error by what the map's fog lets through of it, for viewers
    /// drawing their fog (`on`), or not (`off`: the fog-unaware priority, for comparisons).
    #[arg(long, value_enum, default_value_t = FogPriority::On)]
    pub fog_priority: FogPriority,
    /// A guard band: each viewer's cut is refined this many degrees beyond either side of
    /// its view, so that what it turns towards is detailed before it is seen (0: cull at
    /// the view's edges, the spec's split-only ROAM).
    #[arg(long, default_value_t = DEFAULT_GUARD_DEG,
          value_parser = clap::value_parser!(u8).range(0..=i64::from(MAX_GUARD_DEG)))]
    pub guard_deg: u8,
    /// Once a viewer's cut is at its budget, a merge makes room for a split only when the
    /// split's priority beats the merge's by more than this many percent, so diamonds of
    /// nearly equal priority are not traded back and forth as the eye moves (0: ROAM's
    /// rule, any gain, as before issue 24).
    #[arg(long, default_value_t = DEFAULT_SWAP_MARGIN_PCT,
          value_parser = clap::value_parser!(u16).range(0..=i64::from(MAX_SWAP_MARGIN_PCT)))]
    pub swap_margin: u16,
}

impl CutArgs {
    /// `limits` with these flags' fields.
    pub fn limits(&self, limits: ViewerLimits) -> ViewerLimits {
        ViewerLimits {
            fog_priority: self.fog_priority.on(),
            guard_deg: self.guard_deg,
            swap_margin_pct: self.swap_margin,
            ..limits
        }
    }
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::{CutArgs, FogPriority, ViewerLimits};

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        cut: CutArgs,
    }

    fn parse(args: &[&str]) -> Result<CutArgs, clap::Error> {
        Cli::try_parse_from([&["roam"], args].concat()).map(|c| c.cut)
    }

    /// No flag: what a server serves by default.
    #[test]
    fn the_defaults_are_the_default_limits() {
        let cut = parse(&[]).expect("no flags parse");
        let limits = ViewerLimits::default();
        assert_eq!(cut.limits(ViewerLimits::default()), limits);
        assert_eq!(cut.fog_priority, FogPriority::On);
    }

    #[test]
    fn the_flags_fill_the_limits_within_their_bounds() {
        let cut = parse(&[
            "--fog-priority",
            "off",
            "--guard-deg",
            "0",
            "--swap-margin",
            "400",
        ])
        .expect("valid flags");
        let limits = cut.limits(ViewerLimits {
            max_fps: 7,
            ..ViewerLimits::default()
        });
        assert_eq!(
            (
                limits.fog_priority,
                limits.guard_deg,
                limits.swap_margin_pct
            ),
            (false, 0, 400)
        );
        assert_eq!(limits.max_fps, 7, "the other limits kept");
        for bad in [
            &["--guard-deg", "31"][..],
            &["--swap-margin", "401"],
            &["--fog-priority", "maybe"],
        ] {
            assert!(parse(bad).is_err(), "{bad:?}");
        }
    }
}
