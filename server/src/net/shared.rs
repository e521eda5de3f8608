//! [`Shared`]: what every connection task of a server shares: the terrain and its
//! tiles, the world's inbox and snapshots, admission's gate, the drivers' tickets, the
//! frame makers and the counts.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, MutexGuard};

use roam_protocol::messages::Ticket;
use roam_protocol::sync::lock;
use tokio::sync::watch;

use super::stats::ServeStats;
use super::tickets::Claim;
use super::world_loop::{self, Inbound};
use super::{bus, color_budget, makers, replay};
use crate::Terrain;
use crate::sim::world_core::Snapshot;
use crate::terrain::color_pyramid::ColorPyramid;
use crate::terrain::normal_pyramid::NormalPyramid;
use crate::terrain::variance::VarianceTree;
use crate::viewer::admission::{Admission, PendingId};

/// What every connection task shares.
pub struct Shared {
    pub terrain: Arc<Terrain>,
    pub variance: Arc<VarianceTree>,
    pub token: String,
    pub limits: crate::viewer::ViewerLimits,
    /// The heights' common step, for the mesh coder (computed once).
    pub height_step: u16,
    /// The colour map's tiles, coded once ([`crate::terrain::color_pyramid`]).
    pub pyramid: Arc<ColorPyramid>,
    /// The normals' tiles, in the same layout ([`crate::terrain::normal_pyramid`]).
    pub normals: Arc<NormalPyramid>,
    /// The colour budget every viewer shares ([`super::Options::color_rate`] and
    /// [`super::Options::color_total`]), and [`super::Options::color_window`].
    pub color: color_budget::ColorBudget,
    pub color_window: u8,
    /// The world thread's one inbox: joins, leaves and key states.
    pub(super) world: std::sync::mpsc::Sender<Inbound>,
    pub(super) snapshots: watch::Receiver<Arc<Snapshot>>,
    pub(super) shutdown: watch::Receiver<bool>,
    pub(super) hello_timeout: std::time::Duration,
    /// The world thread's counts, and the held vehicles it freed at its limit.
    pub(super) world_stats: Arc<world_loop::WorldStats>,
    /// Admission, and how to evict each pending connection.
    pub(super) gate: Mutex<Gate>,
    /// Drivers' tickets: the vehicle each names (on an edge, the world's tickets of the
    /// drivers this edge serves).
    pub(super) tickets: Mutex<HashMap<Ticket, Claim>>,
    /// The world, when it is elsewhere ([`super::Options::remote`]).
    pub(super) remote: Option<Arc<bus::edge::Remote>>,
    /// The recording served instead of a world ([`super::Options::replay`]).
    pub(super) replay: Option<Arc<replay::ReplayShared>>,
    /// Blocking frame makers at once: one fewer than the cores (at least one), so the
    /// world thread always finds a core.
    /// Streaming viewers' frames before joining viewers' first ones ([`makers`]).
    pub(super) makers: Arc<makers::Makers>,
    /// The from-scratch tessellators the frame makers borrow (the one map-sized state of
    /// the serving path, at most one per blocking frame maker).
    pub(super) scratch: crate::tessellate::Scratch,
    /// Evicted connections being finished only to be closed with their reason, at most
    /// [`super::Options::max_pending`] at once (past that, one is dropped unfinished): the cap
    /// bounds the handshakes in flight at twice itself, whatever the rate of arrivals.
    pub(super) unfinished: Arc<tokio::sync::Semaphore>,
    pub(super) stats: Arc<ServeStats>,
    /// Every viewer's frames, made on one clock ([`super::frames`]).
    pub(super) clock: super::clock::FrameClock,
}

/// Admission's state and each pending connection's eviction notice.
pub(super) struct Gate {
    pub(super) admission: Admission,
    pub(super) evict: HashMap<PendingId, tokio::sync::oneshot::Sender<()>>,
}

impl Shared {
    pub(super) fn gate(&self) -> MutexGuard<'_, Gate> {
        lock(&self.gate)
    }

    /// The recording served now, if viewers watch one (`serve --replay`; on an edge,
    /// while its world serves one).
    pub(super) fn watching(&self) -> Option<&Arc<replay::ReplayShared>> {
        self.replay.as_ref().filter(|r| r.active())
    }

    pub(super) fn tickets(&self) -> MutexGuard<'_, HashMap<Ticket, Claim>> {
        lock(&self.tickets)
    }

    /// What a viewer's frames are made from: the terrain, its variance tree, and the
    /// tessellators a rebuild borrows.
    pub(super) fn scene(&self) -> crate::viewer::Scene<'_> {
        crate::viewer::Scene {
            terrain: &self.terrain,
            variance: &self.variance,
            scratch: &self.scratch,
        }
    }

    pub(super) async fn shutting_down(&self) {
        let mut rx = self.shutdown.clone();
        let _ = rx.wait_for(|&s| s).await;
    }
}
