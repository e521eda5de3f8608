//! The end-to-end tests: one test binary, each file a module (a binary per file linked the
//! whole server, viewer, QUIC and NATS stack again for each of 23 files: docs/testing.md).
//!
//! The modules named `needs_…` need something outside Rust (a GPU driver, a display, a NATS
//! server, a browser); the fast tier, `scripts/test-fast`, leaves them out by those names.
// A test binary has no users: its helpers' `pub` reach no one else (the lint is for
// libraries' interfaces), and tests print their figures for `--nocapture`.
#![allow(unreachable_pub, clippy::print_stdout)]

/// The tests that run a server with its 100 Hz world and viewers, or a cluster, take a
/// [`turn`]: two at a time. They mostly wait (on the world's ticks, frames at 60 Hz, a
/// hold running out), using about a quarter of a core each, so two at once keep a 2-core
/// machine busier without starving either (docs/testing.md#times). A browser rendering on
/// the CPU takes every turn: it runs [`alone`].
static TURNS: tokio::sync::Semaphore = tokio::sync::Semaphore::const_new(AT_ONCE as usize);
const AT_ONCE: u32 = 2;

/// One of the [`TURNS`].
async fn turn() -> tokio::sync::SemaphorePermit<'static> {
    TURNS.acquire().await.expect("TURNS is never closed")
}

/// Every one of the [`TURNS`]: no other such test runs meanwhile.
async fn alone() -> tokio::sync::SemaphorePermit<'static> {
    TURNS
        .acquire_many(AT_ONCE)
        .await
        .expect("TURNS is never closed")
}

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
