//! roam-link: what both ends of a roam connection share and that touches QUIC: the
//! certificate and its pinning, the transport settings of each end ([`tls`]) with a congestion controller for
//! lossy links ([`congestion`]), and
//! length-prefixed messages on a stream ([`wire`]). The messages themselves, the close
//! codes and the limits are pure and live in `roam-protocol`.

pub mod congestion;
pub mod tls;
pub mod wire;
