//! The simulation: vehicle physics, the world stepped one tick at a time, input scripts,
//! recordings and their replay, and the benchmark's fly-over cameras.

pub mod flyover;
pub mod physics;
pub mod recording;
pub mod replay;
pub mod script;
pub mod world;
