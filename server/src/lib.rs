//! roam-server: terrain data sets, the variance tree and the split-only ROAM tessellator.
//!
//! Everything here is plain library code: no clocks, no sockets, no threads of its own
//! beyond scoped workers in builds. See `ARCHITECTURE.md` for the map.

pub mod net;
pub mod sim;
pub mod terrain;
pub mod tessellate;
pub mod viewer;
pub mod web;

pub use terrain::{ColorMap, DataError, Heightfield, MapParams, ShapeError, Start, Terrain};
