//! The world as a process of its own (`roam-server world`): the 100 Hz world thread of
//! `serve` ([`super::super::world_loop`]), fed from NATS instead of viewer tasks, its
//! snapshots published to every edge, and the drivers' tickets kept here, so that a driver
//! may come back through any edge.
//!
//! Three tasks beside the thread: one answers the edges' requests ([`Ask`]: each in a task
//! of its own, at most [`MAX_ASKING`] at once, so forty joins at once wait one tick, not
//! forty), one hands the drivers' key states to the thread, one publishes each snapshot
//! (the latest: a publish that waits for a slow NATS skips the ticks made meanwhile, and
//! the world thread never waits for it).

use std::collections::HashMap;
use std::sync::mpsc::Sender;
use std::sync::{Arc, Mutex};

use futures_util::StreamExt;
use roam_protocol::bus::{Answer, Ask, Keys, MAX_EDGES, Subjects};
use roam_protocol::messages::{Ticket, decode};
use tokio::sync::{oneshot, watch};

use super::{BusError, BusOptions, Malformed, encode, to_wire};
use crate::Terrain;
use crate::net::world_loop::{self, Inbound, WorldStats};
use crate::sim::session::RecordOptions;
use crate::sim::world::{VehicleId, World};
use crate::sim::world_core::{Event, Snapshot};

/// Requests answered at once; past it, the next waits for one to finish.
const MAX_ASKING: usize = 256;

/// How the world runs.
pub struct WorldOptions {
    pub record: Option<RecordOptions>,
    /// How long a dropped driver's vehicle is held.
    pub hold: std::time::Duration,
    /// Vehicles at most, held ones included.
    pub max_vehicles: usize,
}

/// What the request tasks share.
struct State {
    /// The drivers' tickets: the vehicle each names.
    tickets: Mutex<HashMap<Ticket, VehicleId>>,
    /// The edges' addresses, as they said hello (the newest last, at most [`MAX_EDGES`]).
    edges: Mutex<Vec<String>>,
    data: [u8; 32],
    inbox: Sender<Inbound>,
    snapshots: watch::Receiver<Arc<Snapshot>>,
    stats: Arc<WorldStats>,
}

/// A running world.
pub struct WorldServer {
    thread: std::thread::JoinHandle<World>,
    inbox: Option<Sender<Inbound>>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
    snapshots: watch::Receiver<Arc<Snapshot>>,
    stats: Arc<WorldStats>,
    client: async_nats::Client,
}

impl WorldServer {
    /// Starts the world (on the current tokio runtime) serving data set `data` (its
    /// content hash) under `bus`'s name, and returns once it listens on NATS.
    pub async fn start(
        terrain: Arc<Terrain>,
        data: [u8; 32],
        options: WorldOptions,
        bus: &BusOptions,
    ) -> Result<WorldServer, BusError> {
        let subjects = bus.subjects()?;
        let client = bus.connect().await?;
        let nats = |what| {
            move |e: async_nats::SubscribeError| BusError::Nats {
                what,
                error: e.to_string(),
            }
        };
        let asks = client
            .subscribe(subjects.ask.clone())
            .await
            .map_err(nats("subscribing to the requests"))?;
        let keys = client
            .subscribe(subjects.keys.clone())
            .await
            .map_err(nats("subscribing to the key states"))?;
        let (inbox, inbox_rx) = std::sync::mpsc::channel();
        let (snap_tx, snapshots) = watch::channel(Arc::new(Snapshot::default()));
        let stats = Arc::new(WorldStats::default());
        let thread = world_loop::start(
            terrain,
            options.record,
            (options.hold, options.max_vehicles),
            inbox_rx,
            snap_tx,
            stats.clone(),
        )
        .map_err(BusError::World)?;
        let state = Arc::new(State {
            tickets: Mutex::new(HashMap::new()),
            edges: Mutex::new(Vec::new()),
            data,
            inbox: inbox.clone(),
            snapshots: snapshots.clone(),
            stats: stats.clone(),
        });
        let tasks = vec![
            tokio::spawn(answer_asks(asks, client.clone(), state.clone())),
            tokio::spawn(take_keys(keys, inbox.clone())),
            tokio::spawn(publish(client.clone(), subjects, snapshots.clone())),
        ];
        client.flush().await.map_err(|e| BusError::Nats {
            what: "flushing the subscriptions",
            error: e.to_string(),
        })?;
        Ok(WorldServer {
            thread,
            inbox: Some(inbox),
            tasks,
            snapshots,
            stats,
            client,
        })
    }

    /// The world after its latest tick.
    pub fn snapshot(&self) -> Arc<Snapshot> {
        self.snapshots.borrow().clone()
    }

    /// The snapshots as they come (latest wins).
    pub fn watch(&self) -> watch::Receiver<Arc<Snapshot>> {
        self.snapshots.clone()
    }

    /// How the world thread keeps time.
    pub fn world_stats(&self) -> Arc<WorldStats> {
        self.stats.clone()
    }

    /// Stops answering, stops the world and closes its recording; the final world.
    pub async fn shutdown(mut self) -> Result<World, BusError> {
        for t in &self.tasks {
            t.abort();
        }
        for t in self.tasks.drain(..) {
            let _ = t.await;
        }
        let _ = self.client.flush().await;
        drop(self.inbox.take());
        let thread = self.thread;
        tokio::task::spawn_blocking(move || thread.join())
            .await
            .ok()
            .and_then(Result::ok)
            .ok_or(BusError::WorldPanicked)
    }
}

/// Answers each request in a task of its own (at most [`MAX_ASKING`] at once).
async fn answer_asks(
    mut asks: async_nats::Subscriber,
    client: async_nats::Client,
    state: Arc<State>,
) {
    let permits = Arc::new(tokio::sync::Semaphore::new(MAX_ASKING));
    let mut malformed = Malformed::new("request");
    while let Some(msg) = asks.next().await {
        let Some(reply) = msg.reply else {
            continue; // a request nobody waits for the answer of: not one of ours
        };
        let ask = match decode::<Ask>(&msg.payload) {
            Ok(ask) => ask,
            Err(e) => {
                malformed.note(&e);
                let answer = Answer::Refused {
                    reason: format!("malformed request: {e}"),
                };
                let _ = client.publish(reply, encode(&answer)).await;
                continue;
            }
        };
        let Ok(permit) = permits.clone().acquire_owned().await else {
            return;
        };
        let (client, state) = (client.clone(), state.clone());
        tokio::spawn(async move {
            let answer = answer(&state, ask).await;
            let _ = client.publish(reply, encode(&answer)).await;
            drop(permit);
        });
    }
}

/// Hands the world an event that answers with a vehicle.
async fn ask_world(state: &State, event: Event) -> Option<VehicleId> {
    let (tx, rx) = oneshot::channel();
    state.inbox.send((event, Some(tx))).ok()?;
    rx.await.ok()
}

async fn answer(state: &State, ask: Ask) -> Answer {
    let refused = |reason: &str| Answer::Refused {
        reason: reason.into(),
    };
    match ask {
        Ask::Hello { data, addresses } => {
            if data == state.data {
                let mut edges = state.edges.lock().unwrap_or_else(|e| e.into_inner());
                for a in addresses {
                    edges.retain(|e| *e != a);
                    edges.push(a);
                }
                let extra = edges.len().saturating_sub(MAX_EDGES);
                edges.drain(..extra);
            }
            Answer::Hello {
                data: state.data,
                edges: state
                    .edges
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .clone(),
            }
        }
        Ask::Join => {
            // At the limit the world frees the oldest held vehicle first
            // ([`WorldCore::with_limit`]), in the order the joins reach it.
            let Some(vehicle) = ask_world(state, Event::Join).await else {
                return refused("no vehicle free");
            };
            let ticket = crate::net::handshake::random_ticket();
            let mut tickets = state.tickets.lock().unwrap_or_else(|e| e.into_inner());
            for freed in state.stats.take_evicted() {
                tickets.retain(|_, v| *v != freed);
            }
            // A ticket names one vehicle, and a vehicle has one ticket (ids are reused).
            tickets.retain(|_, v| *v != vehicle);
            tickets.insert(ticket, vehicle);
            Answer::Joined { vehicle, ticket }
        }
        Ask::Resume { ticket } => {
            let vehicle = state
                .tickets
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .get(&ticket)
                .copied();
            let Some(vehicle) = vehicle else {
                return refused("no vehicle has this ticket (its hold ran out)");
            };
            // Its old edge may not have seen the connection go (or be gone itself): the
            // ticket proves the driver, so a vehicle still driven is held and taken back.
            let held = state.snapshots.borrow().held.contains(&vehicle);
            if !held {
                let _ = state.inbox.send((Event::Hold { vehicle, silent: 0 }, None));
            }
            match ask_world(state, Event::Resume(vehicle)).await {
                Some(vehicle) => Answer::Resumed { vehicle },
                None => refused("the vehicle is not held any more"),
            }
        }
        Ask::Leave { vehicle } => {
            let _ = state.inbox.send((Event::Leave(vehicle), None));
            state
                .tickets
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .retain(|_, v| *v != vehicle);
            Answer::Done
        }
        Ask::Hold { vehicle, silent } => {
            let _ = state.inbox.send((Event::Hold { vehicle, silent }, None));
            Answer::Done
        }
    }
}

/// Hands the drivers' key states to the world thread.
async fn take_keys(mut keys: async_nats::Subscriber, inbox: Sender<Inbound>) {
    let mut malformed = Malformed::new("key states");
    while let Some(msg) = keys.next().await {
        match decode::<Keys>(&msg.payload) {
            Ok(k) => {
                let event = Event::Keys {
                    vehicle: k.vehicle,
                    states: k.states,
                };
                if inbox.send((event, None)).is_err() {
                    return; // the world has stopped
                }
            }
            Err(e) => malformed.note(&e),
        }
    }
}

/// Publishes each snapshot (the latest, when publishing falls behind).
async fn publish(
    client: async_nats::Client,
    subjects: Subjects,
    mut snapshots: watch::Receiver<Arc<Snapshot>>,
) {
    while snapshots.changed().await.is_ok() {
        let snap = snapshots.borrow_and_update().clone();
        if let Err(e) = client
            .publish(subjects.snapshots.clone(), encode(&to_wire(&snap)))
            .await
        {
            tracing::warn!(tick = snap.tick, "publishing the snapshot: {e}");
        }
    }
}
