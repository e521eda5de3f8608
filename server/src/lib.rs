//! roam-server: terrain data sets, the variance tree and the split-only ROAM tessellator.
//!
//! Everything here is plain library code: no clocks, no sockets, no threads of its own
//! beyond scoped workers in builds. See `ARCHITECTURE.md` for the map.

pub mod camera;
pub mod dataset;
pub mod diamond;
pub mod flyover;
pub mod generate;
pub mod heightfield;
pub mod map;
pub mod net;
pub mod physics;
pub mod pnm;
pub mod queue;
pub mod recording;
pub mod replay;
pub mod script;
pub mod tessellate;
pub mod validate;
pub mod variance;
pub mod viewer;
pub mod world;

pub use dataset::{ColorMap, DataError, Terrain};
pub use heightfield::{Heightfield, ShapeError};
pub use map::{MapParams, Start};
