//! Drivers' tickets: what one names ([`Claim`]), and fresh random tickets and join
//! tokens from the system's random source.

use roam_protocol::messages::Ticket;
use tokio::sync::oneshot;

use crate::sim::world::VehicleId;

/// What a ticket names: the vehicle, and how to end the connection driving it now.
pub(super) struct Claim {
    pub(super) vehicle: VehicleId,
    pub(super) replace: Option<oneshot::Sender<oneshot::Sender<()>>>,
}

/// A fresh random ticket (128 bits), for a driver's new vehicle.
pub(crate) fn random_ticket() -> Ticket {
    use ring::rand::SecureRandom;
    let mut t = [0u8; 16];
    ring::rand::SystemRandom::new()
        .fill(&mut t)
        .expect("the system's random source works");
    t
}

/// A fresh random join token (32 hex digits: 128 bits), for a server started in process.
pub fn random_token() -> String {
    use ring::rand::SecureRandom;
    let mut bytes = [0u8; 16];
    ring::rand::SystemRandom::new()
        .fill(&mut bytes)
        .expect("the system's random source works");
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}
