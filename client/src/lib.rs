//! roam-client: the viewer. A [`session::Session`] joins a server and decodes its frame
//! stream; the window ([`window`]) draws it with the [`render`] module, rides the vehicle
//! with [`camera`] and shows the [`hud`]; the headless viewer ([`headless`]) measures and
//! renders offscreen with the same renderer.

pub mod bench;
pub mod camera;
pub mod color_cache;
mod connection;
pub mod core;
pub mod headless;
pub mod hud;
pub mod join;
pub mod live;
pub mod render;
pub mod session;
pub mod stats;
pub mod window;
