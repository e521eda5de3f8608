//! The simulation: vehicle physics, the world stepped one tick at a time and the decisions
//! around it (`world_core`: joins, keys, holds, leaves, snapshots), recordings (the format
//! in `recording`, its writer in `recorder`, the server's fail-safe rotating use of it in
//! `session`, its files in `record_files`), their replay (`replay`) and watching
//! (`watch`: a recording played at a pace, sought), and the benchmark's fly-over
//! cameras.

pub mod flyover;
pub mod physics;
pub mod record_files;
pub mod recorder;
pub mod recording;
pub mod replay;
pub mod session;
pub mod watch;
pub mod world;
pub mod world_core;
