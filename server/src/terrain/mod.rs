//! The terrain: a data set on disk (`map`, `hf.pgm`, `color.ppm`) loaded into a `Terrain`,
//! the synthetic generator, the source readers and raster pipeline of `import`, and the
//! variance tree built once from the heights and kept in the data set's cache (`.cache/`,
//! memory-mapped when served), and the colour and normal tile pyramids streamed to viewers
//! (cached there too, through `tile_store`).

pub mod backing;
pub mod cache;
pub mod cache_error;
pub mod color_pyramid;
pub mod colorimage;
pub mod data_error;
pub mod dataset;
pub mod generate;
pub mod geotiff;
pub mod heightfield;
pub mod hgt;
pub mod map;
pub mod normal_pyramid;
pub mod png16;
pub mod pnm;
pub mod raster;
pub mod source;
pub mod source_error;
pub(crate) mod stamp;
pub mod tile_store;
pub mod variance;

pub use cache::{CacheReport, Source};
pub use data_error::DataError;
pub use dataset::{ColorMap, Terrain};
pub use heightfield::{Heightfield, ShapeError};
pub use map::{MapParams, Start};
pub use variance::VarianceTree;
