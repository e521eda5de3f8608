//! roam-link: what both ends of a roam connection share and that touches QUIC (the only
//! thing the workspace calls a *link*; the network between the ends is a *path*): the
//! certificate and its pinning and the transport settings of each end ([`tls`]), a
//! congestion controller for lossy paths ([`congestion`]), and length-prefixed messages
//! on a stream ([`wire`]). The messages themselves, the close codes and the limits are
//! pure and live in `roam-protocol`.

pub mod congestion;
pub mod tls;
pub mod wire;
