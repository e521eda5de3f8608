//! Helpers for the end-to-end tests in `tests/` and the measuring scripts: a seeded lossy
//! UDP relay ([`relay`], and the `roam-relay` binary) to put between a server and viewers,
//! and a simulated network ([`simnet`]) driving the server's and the viewer's sans-IO
//! cores together with virtual time, no sockets; and the inputs and decoders of the
//! fuzzing bench and test ([`fuzz`]); a flood of junk connections ([`flood`], and the
//! `roam-flood` binary); a server with the browser viewer and a WebTransport client
//! speaking as the page does ([`web`]); reading the documents and the workspace's
//! names for the test that keeps the documents true ([`docs`]).

pub mod browser;
pub mod docs;
pub mod fixtures;
pub mod flood;
pub mod fuzz;
pub mod nats;
pub mod relay;
pub mod simnet;
pub mod web;
