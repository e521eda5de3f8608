//! roam-server: terrain data sets, the variance tree, the ROAM tessellators (split-only
//! from scratch, and the frame-coherent split/merge one), the simulation and the
//! per-viewer and world decisions, and the shells that serve them.
//!
//! `terrain`, `tessellate`, `sim`, `viewer` and `web` (the browser viewer's page, its
//! answers and certificate) are sans-IO cores: no clocks, no sockets, no threads of their
//! own beyond scoped workers in builds (the tidy test holds the clock reads to the files
//! it names). `net` (QUIC, WebTransport, tokio, the clock, NATS) is the I/O shell that
//! feeds them. See `ARCHITECTURE.md` for the map.

pub mod net;
pub mod sim;
pub mod terrain;
pub mod tessellate;
pub mod viewer;
pub mod web;

pub use terrain::{ColorMap, DataError, Heightfield, MapParams, ShapeError, Start, Terrain};
