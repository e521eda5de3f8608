//! roam-server: terrain data sets, the variance tree, the ROAM tessellators (split-only
//! from scratch, and the frame-coherent split/merge one), the simulation and the
//! per-viewer and world decisions, and the shells that serve them.
//!
//! `terrain`, `tessellate`, `sim` and `viewer` are sans-IO cores: no clocks, no sockets,
//! no threads of their own beyond scoped workers in builds (the tidy test holds the clock
//! reads to the files it names). `net` (QUIC, tokio, the clock, NATS) and `web` (the
//! browser viewer's WebTransport and page server) are the I/O shells that feed them. See
//! `ARCHITECTURE.md` for the map.

pub mod net;
pub mod sim;
pub mod terrain;
pub mod tessellate;
pub mod viewer;
pub mod web;

pub use terrain::{ColorMap, DataError, Heightfield, MapParams, ShapeError, Start, Terrain};
