//! The network shell: the only module that touches QUIC (quinn), an async runtime (tokio) or
//! a clock for pacing. It turns traffic into the world thread's closed set of events
//! ([`crate::sim::world_core::Event`]), and snapshots of the world into frames for each viewer.
//!
//! ```text
//! viewer ──hello/acks/budget (control stream)──► viewer task ──frames (a uni stream each)──► viewer
//!        ──key datagrams──────────────────────► world thread (100 Hz) ──snapshot (latest)──┘
//! ```
//!
//! With [`Options::web`], browsers come too: the page over HTTPS and WebTransport sessions
//! on a second endpoint ([`web`]), admitted and served by the same code as native viewers
//! ([`link`] hides which), in the same world, under the same limits.

pub mod bus;
pub mod color_budget;
mod control;
mod handshake;
pub mod link;
pub mod makers;
pub mod replay;
mod seat;
mod serve_error;
mod server;
mod shared;
pub mod stats;
mod tickets;
pub mod viewer;
pub mod web;
pub mod world_loop;

pub use seat::MAX_CONTROL;
pub use serve_error::ServeError;
pub use server::{
    COLOR_RATE, COLOR_TOTAL, HELLO_TIMEOUT, HOLD, MAX_LEVELS, MAX_PENDING, MAX_VIEWERS, Options,
    Server, check_servable,
};
pub use shared::Shared;
pub use tickets::random_token;
