//! roam-protocol: what crosses the wire between a roam server and its viewers, the mesh
//! codec, the colour map codec and the terrain normals' code. Pure: no I/O, no sockets, no
//! async runtime, no clock.
//! Any byte string decodes to a value or an error, never a panic, and never allocates
//! beyond the decode's limit (a message's fields are read by `bounded`).

pub mod bintree;
mod bounded;
pub mod bus;
pub mod changes;
pub mod codec;
pub mod colormap;
pub mod cut;
pub mod diamonds;
pub mod follow;
pub mod format;
pub mod keys;
pub mod mesh;
pub mod messages;
pub mod normals;
mod range;
mod rans;
pub mod script;
pub mod stats;
pub mod sync;
pub mod tiles;
pub mod validate;

pub use bintree::{BitSet, Grid};
pub use changes::{CHANGES_FORMAT, ChangeEncoder};
pub use codec::{Decoded, EncodeError, MeshDecoder, MeshEncoder, height_step};
pub use cut::CutHash;
pub use diamonds::DiamondMap;
pub use follow::Follower;
pub use format::DecodeError;
pub use keys::{KeyLatch, KeyStep, Keys};
pub use mesh::{LiveMesh, Mesh};
pub use tiles::ColorLayout;
