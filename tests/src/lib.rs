//! Helpers for the end-to-end tests in `tests/` and the measuring scripts: a seeded lossy
//! UDP relay ([`relay`], and the `roam-relay` binary) to put between a server and viewers.

pub mod relay;
