//! The network shell: in the library, the only module that touches QUIC (quinn),
//! WebTransport, NATS, an async runtime (tokio) or a clock for pacing. (The binary's
//! command line runs it on a tokio runtime, and two of its commands speak to servers
//! themselves: `cli/color_bench.rs` is a QUIC viewer of a server it starts in process,
//! `cli/bus_load.rs` stands in for a world's edges on NATS.) It turns traffic into the
//! world thread's closed set of events ([`crate::sim::world_core::Event`]), and snapshots
//! of the world into frames for each viewer.
//!
//! ```text
//! viewer ──hello/acks/budget (control stream)──► viewer task ──► its Conversation
//!        ──key datagrams──► viewer task ──► world thread (100 Hz) ──snapshot (latest)──┐
//! viewer ◄──frames── frame clock: every due Conversation's frame, one pass ◄───────────┘
//! ```
//!
//! A change frame goes as one datagram when it fits (almost every frame), a larger one and
//! every key frame on a uni stream of its own; the welcome, the colour tiles and the news
//! go on the control stream, below every frame ([`viewer`]).
//!
//! With [`Options::web`], browsers come too: the page over HTTPS and WebTransport sessions
//! on a second endpoint ([`web`]), admitted and served by the same code as native viewers
//! ([`conn`] hides which), in the same world, under the same limits.
//!
//! The files, each referring only to those before it: `conn`, `stats`, `color_budget`,
//! `makers`, `world_loop` (the world thread), `tickets` and `serve_error`; `bus/mod.rs` and
//! `bus/edge.rs` (NATS, and an edge's way to its world); `replay`; `bus/world.rs` (the
//! world served over NATS), `clock` (the frame clock's viewers) and `shared` ([`Shared`],
//! what every connection task shares); `seat` and `control`; `frames` (the frame clock's
//! passes); `viewer` (a viewer after its hello); `handshake` (a connection up
//! to its hello); `web` (the browser viewer's endpoints); `server` ([`Server`] and its
//! [`Options`]). This file only declares them and re-exports.

pub mod bus;
mod clock;
pub mod color_budget;
pub mod conn;
mod control;
mod frames;
mod handshake;
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
