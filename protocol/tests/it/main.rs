//! The protocol's integration tests: one test binary, each file a module (docs/testing.md).
//!
//! The modules named `needs_…` need something outside Rust (a GPU driver, a display, a NATS
//! server, a browser); the fast tier, `scripts/test-fast`, leaves them out by those names.
// A test binary has no users: its helpers' `pub` reach no one else (the lint is for
// libraries' interfaces), and tests print their figures for `--nocapture`.
#![allow(unreachable_pub, clippy::print_stdout)]

mod common;

mod changes;
mod codec;
mod colormap;
mod follow;
mod messages;
