//! A viewer past its hello, as the handshake hands it to the viewer task: its [`Seat`]
//! (counted, and its state's bytes reserved against the memory limit, until it leaves)
//! and its place in the world ([`Joined`]); and what both read a control stream by
//! ([`MAX_CONTROL`]) and log a role as.

use std::sync::Arc;

use roam_protocol::messages::{Role, Ticket};
use tokio::sync::oneshot;

use super::shared::Shared;
use crate::sim::world::VehicleId;
use crate::viewer::admission;

/// Control-stream messages from a viewer are at most this long (a hello is well under).
pub const MAX_CONTROL: usize = 4096;

/// A viewer being served: counted, and its state's bytes reserved, until dropped.
pub(super) struct Seat {
    shared: Arc<Shared>,
    /// Taken only by the drop.
    seat: Option<admission::Seat>,
}

impl Seat {
    /// The seat admission gave a viewer, released when this is dropped.
    pub(super) fn new(shared: Arc<Shared>, seat: admission::Seat) -> Seat {
        Seat {
            shared,
            seat: Some(seat),
        }
    }

    /// The budget a viewer is served for `budget` (within the server's limits already): as
    /// far as its seat can grow within the server's memory limit
    /// ([`admission::Admission::grow`]).
    pub(super) fn grow(&mut self, budget: u32) -> u32 {
        match self.seat.as_mut() {
            Some(seat) => self.shared.gate().admission.grow(seat, budget),
            None => budget,
        }
    }
}

impl Drop for Seat {
    fn drop(&mut self) {
        if let Some(seat) = self.seat.take() {
            self.shared.gate().admission.left(seat);
        }
    }
}

/// A viewer's place in the world.
pub(super) struct Joined {
    pub vehicle: VehicleId,
    pub driver: bool,
    /// A driver's claim on its vehicle, for a reconnection.
    pub ticket: Option<Ticket>,
    pub resumed: bool,
    /// On an edge, the world's claim on a driver's vehicle for this connection (its leave
    /// or hold names it); 0 elsewhere.
    pub claim: u64,
    /// A driver's connection is told here that a reconnection with its ticket replaces it
    /// (the viewer came back before this server saw the old connection die): it ends,
    /// has its vehicle held, then answers on the sender it was given.
    pub replaced: Option<oneshot::Receiver<oneshot::Sender<()>>>,
    /// Watching a recording, this viewer presented the control token (`serve --control`).
    pub controller: bool,
}

impl Joined {
    /// A spectator following `vehicle`.
    pub(super) fn spectator(vehicle: VehicleId) -> Joined {
        Joined {
            vehicle,
            driver: false,
            ticket: None,
            resumed: false,
            claim: 0,
            replaced: None,
            controller: false,
        }
    }
}

/// The role as the logs name it.
pub(super) fn role_name(role: &Role) -> &'static str {
    match role {
        Role::Driver => "driver",
        Role::Spectator { .. } => "spectator",
    }
}
