//! The server's integration tests: one test binary, each file a module (a binary per file
//! linked the whole stack again for each of 23 files: docs/testing.md).
//!
//! The modules named `needs_…` need something outside Rust (a GPU driver, a display, a NATS
//! server, a browser); the fast tier, `scripts/test-fast`, leaves them out by those names.
// A test binary has no users: its helpers' `pub` reach no one else (the lint is for
// libraries' interfaces), and tests print their figures for `--nocapture`.
#![allow(unreachable_pub, clippy::print_stdout)]

mod common;
mod disk;
mod tess;

mod cache;
mod cli;
mod codec;
mod content_hash;
mod dataset;
mod fog;
mod guard;
mod import;
mod import_color;
mod import_srtm;
mod import_tiff;
mod no_alloc;
mod physics;
mod recording;
mod recording_faults;
mod serve_identity;
mod serve_recording;
mod sim_cli;
mod tessellate;
mod viewer_core;
mod watch;
mod world_loop;

/// Tests that start Debian's `nats-server`.
mod needs_nats {
    mod world_stop;
}
