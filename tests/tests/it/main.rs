//! The end-to-end tests: one test binary, each file a module (a binary per file linked the
//! whole server, viewer, QUIC and NATS stack again for each of 23 files: docs/testing.md).
//!
//! The modules named `needs_…` need something outside Rust (a GPU driver, a display, a NATS
//! server, a browser); the fast tier, `scripts/test-fast`, leaves them out by those names.
// A test binary has no users: its helpers' `pub` reach no one else (the lint is for
// libraries' interfaces), and tests print their figures for `--nocapture`.
#![allow(unreachable_pub, clippy::print_stdout)]

/// The tests that run a server with its 100 Hz world and viewers, a cluster, or a browser
/// take this lock: one at a time, so that on a 2-core machine none starves another of the
/// CPU. (When each file was a binary of its own, each had its own lock, and the binaries
/// ran one after another.)
static ONE_AT_A_TIME: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

mod admission;
mod client_core;
mod color_stream;
mod connect_many;
mod docs;
mod e2e;
mod flood;
mod fuzz;
mod hostile_server;
mod imports;
mod reconnect;
mod relay;
mod replay;
mod serving;
mod simnet;
mod supervisor;
mod tidy;
mod web;

/// Tests that run the page in Chromium (the page built by `scripts/build-web`).
mod needs_browser {
    mod browser;
}

/// Tests that start Debian's `nats-server`.
mod needs_nats {
    mod bus_trust;
    mod cluster;
    mod hostile_bus;
    mod nats_tls;
}
