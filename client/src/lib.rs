//! roam-client: the viewer. For now, the headless viewer (and load generator) that connects
//! to a roam server, plays an input script, decodes and checks every frame, and measures.

pub mod headless;
pub mod render;
pub mod stats;
