//! roam-protocol: what crosses the wire between a roam server and its viewers, and the mesh
//! codec. Pure: no I/O, no sockets, no async runtime, no clock. Any byte string decodes to
//! a value or an error, never a panic, and never allocates beyond the decode's limit.

pub mod bintree;
pub mod codec;
pub mod mesh;
pub mod messages;
mod range;

pub use bintree::{BitSet, Grid};
pub use codec::{DecodeError, Decoded, EncodeError, MeshDecoder, MeshEncoder, height_step};
pub use mesh::Mesh;
