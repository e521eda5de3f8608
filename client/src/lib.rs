//! roam-client: the viewer, native and in the browser. A [`session::Session`] joins a
//! server over QUIC and decodes its frame stream; the window ([`window`]) draws it with the
//! [`render`] module, rides the vehicle with [`camera`] and shows the [`hud`]; the
//! headless viewer ([`headless`]) measures and renders offscreen with the same renderer.
//!
//! The clock-free parts ([`core`], [`color_cache`], [`camera`], [`cockpit`], [`edges`],
//! [`conversation`], [`supervisor`], [`watching`]), the [`render`]er and the [`hud`] also
//! build for `wasm32`: the browser viewer (`roam-web`, `web/`) is these over WebTransport
//! and a canvas, reconnecting as the same [`supervisor`] says. The I/O modules (QUIC, the
//! session's tasks, the window, the headless runs, the benchmarks) are native only.

pub mod camera;
pub mod cockpit;
pub mod color_cache;
pub mod conversation;
pub mod core;
pub mod edges;
pub mod hud;
pub mod render;
pub mod supervisor;
pub mod watching;

#[cfg(not(target_arch = "wasm32"))]
pub mod bench;
#[cfg(not(target_arch = "wasm32"))]
mod connection;
#[cfg(not(target_arch = "wasm32"))]
pub mod headless;
#[cfg(not(target_arch = "wasm32"))]
pub mod live;
#[cfg(not(target_arch = "wasm32"))]
pub mod quic;
#[cfg(not(target_arch = "wasm32"))]
pub mod session;
#[cfg(not(target_arch = "wasm32"))]
pub mod stats;
#[cfg(not(target_arch = "wasm32"))]
pub mod window;
