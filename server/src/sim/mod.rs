//! The simulation: vehicle physics, the world stepped one tick at a time and the decisions
//! around it (`world_core`: joins, keys, leaves, snapshots), recordings and their replay,
//! and the benchmark's fly-over cameras.

pub mod flyover;
pub mod physics;
pub mod recording;
pub mod replay;
pub mod world;
pub mod world_core;
