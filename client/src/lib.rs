//! roam-client: the viewer. A [`session::Session`] joins a server and decodes its frame
//! stream; the window ([`window`]) draws it with the [`render`] module, rides the vehicle
//! with [`camera`] and shows the [`hud`]; the headless viewer ([`headless`]) measures and
//! renders offscreen with the same renderer.

//!
//! The clock-free core ([`core`], [`color_cache`], [`camera`], [`edges`], [`watching`]), the [`render`]er and the
//! [`hud`] also build for `wasm32`, where the browser viewer (`web/`) uses them; the I/O
//! modules (QUIC, the window, the headless runs) are native only.

pub mod camera;
pub mod cockpit;
pub mod color_cache;
pub mod core;
pub mod edges;
pub mod hud;
pub mod joining;
pub mod render;
mod tile_slots;
pub mod watching;

#[cfg(not(target_arch = "wasm32"))]
pub mod bench;
#[cfg(not(target_arch = "wasm32"))]
mod connection;
#[cfg(not(target_arch = "wasm32"))]
pub mod headless;
#[cfg(not(target_arch = "wasm32"))]
pub mod join;
#[cfg(not(target_arch = "wasm32"))]
pub mod live;
#[cfg(not(target_arch = "wasm32"))]
pub mod session;
#[cfg(not(target_arch = "wasm32"))]
pub mod stats;
#[cfg(not(target_arch = "wasm32"))]
pub mod window;
