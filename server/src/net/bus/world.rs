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
//!
//! The edges' hellos come every half second ([`super::edge::BEAT`]), each naming the
//! vehicles its drivers drive. A fourth task ([`watch_edges`]) holds the vehicles of an
//! edge silent for [`EDGE_SILENCE`] (killed, cut off from NATS), counting the hold from
//! its last hello, so they are freed when the hold runs out unless their drivers come
//! back through another edge with their tickets. An edge heard again names its vehicles
//! again: those still held since its silence are given back to it. While the world's own
//! NATS connection is down it judges no edge, and gives each a fresh [`EDGE_SILENCE`]
//! once it is back (a NATS restart silences everyone at once).

use std::collections::HashMap;
use std::sync::mpsc::Sender;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use futures_util::StreamExt;
use roam_protocol::bus::{Answer, Ask, Keys, MAX_EDGES, Subjects};
use roam_protocol::messages::{Ticket, decode};
use tokio::sync::{oneshot, watch};

use super::{BusError, BusOptions, Malformed, encode};
use crate::Terrain;
use crate::net::world_loop::{self, Inbound, WorldStats};
use crate::sim::session::RecordOptions;
use crate::sim::world::{VehicleId, World};
use crate::sim::world_core::{Event, Snapshot};

/// Requests answered at once; past it, the next waits for one to finish.
const MAX_ASKING: usize = 256;

/// An edge not heard for this long is taken for dead: its vehicles are held.
pub const EDGE_SILENCE: Duration = Duration::from_secs(3);

/// The most edges the world keeps track of; a hello from one more is answered, but its
/// vehicles are not watched.
const MAX_WATCHED: usize = 4096;

/// What names a driver's vehicle: its ticket (the driver's, to come back with through any
/// edge) and its claim (the edge's, for one join or resume: a leave or hold with an older
/// claim is stale). Each map holds at most one entry a vehicle id.
#[derive(Default)]
struct Drivers {
    tickets: HashMap<Ticket, VehicleId>,
    claims: HashMap<VehicleId, u64>,
    next_claim: u64,
}

impl Drivers {
    /// A new claim on `vehicle`: older ones are stale from now on.
    fn claim(&mut self, vehicle: VehicleId) -> u64 {
        self.next_claim += 1;
        self.claims.insert(vehicle, self.next_claim);
        self.next_claim
    }

    /// Whether `claim` is `vehicle`'s newest.
    fn holds(&self, vehicle: VehicleId, claim: u64) -> bool {
        self.claims.get(&vehicle) == Some(&claim)
    }

    /// `vehicle` is free: its ticket and claim name nothing.
    fn forget(&mut self, vehicle: VehicleId) {
        self.tickets.retain(|_, v| *v != vehicle);
        self.claims.remove(&vehicle);
    }
}

/// An edge, as its hellos tell it.
struct Seen {
    heard: Instant,
    addresses: Vec<String>,
    /// Its drivers' vehicles and their claims.
    vehicles: Vec<(VehicleId, u64)>,
}

/// How the world runs.
pub struct WorldOptions {
    pub record: Option<RecordOptions>,
    /// How long a dropped driver's vehicle is held.
    pub hold: std::time::Duration,
    /// Vehicles at most, held ones included.
    pub max_vehicles: usize,
    /// A recording to serve instead of a live world (`world --replay`): its clock goes
    /// with every snapshot, the edges' controls come as [`Ask::Replay`], and joins are
    /// refused (the edges serve every viewer as a spectator). `record` is not used.
    pub replay: Option<crate::net::replay::Replaying>,
}

/// What the request tasks share.
struct State {
    /// The drivers' tickets and claims.
    drivers: Mutex<Drivers>,
    /// The edges heard from, by their names.
    edges: Mutex<HashMap<u64, Seen>>,
    /// Vehicles held because their edge fell silent: which edge, and the claim it named.
    /// (Locked after `drivers` where both are.)
    silenced: Mutex<HashMap<VehicleId, (u64, u64)>>,
    data: [u8; 32],
    /// This world process's name (random): a new one tells edges the world restarted.
    id: u64,
    inbox: Sender<Inbound>,
    snapshots: watch::Receiver<Arc<Snapshot>>,
    stats: Arc<WorldStats>,
    /// The recording served (`world --replay`).
    replay: Option<Arc<crate::net::replay::ReplayShared>>,
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
        let (thread, replay) = match options.replay {
            Some(r) => {
                let (thread, shared) =
                    crate::net::replay::start(r, inbox_rx, snap_tx, stats.clone())
                        .map_err(BusError::World)?;
                (thread, Some(shared))
            }
            None => (
                world_loop::start(
                    terrain,
                    options.record,
                    (options.hold, options.max_vehicles, true),
                    inbox_rx,
                    snap_tx,
                    stats.clone(),
                )
                .map_err(BusError::World)?,
                None,
            ),
        };
        let state = Arc::new(State {
            drivers: Mutex::new(Drivers::default()),
            edges: Mutex::new(HashMap::new()),
            silenced: Mutex::new(HashMap::new()),
            data,
            id: super::random_id(),
            inbox: inbox.clone(),
            snapshots: snapshots.clone(),
            stats: stats.clone(),
            replay: replay.clone(),
        });
        let tasks = vec![
            tokio::spawn(answer_asks(asks, client.clone(), state.clone())),
            tokio::spawn(take_keys(keys, inbox.clone())),
            tokio::spawn(publish(
                client.clone(),
                subjects,
                snapshots.clone(),
                (state.id, replay),
            )),
            tokio::spawn(watch_edges(client.clone(), state.clone())),
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
        // Bounded: with the NATS server gone, a flush waits for a reconnection that may
        // never come, and SIGINT would never end the process (issue 39). What is not
        // flushed by then is lost with the connection anyway.
        const FLUSH_WAIT: Duration = Duration::from_millis(500);
        let _ = tokio::time::timeout(FLUSH_WAIT, self.client.flush()).await;
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
        Ask::Hello {
            data,
            edge,
            addresses,
            vehicles,
        } => {
            if data == state.data {
                heard(state, edge, addresses, vehicles);
            }
            Answer::Hello {
                data: state.data,
                world: state.id,
                edges: live_addresses(state),
            }
        }
        Ask::Join | Ask::Resume { .. } if state.replay.is_some() => {
            refused("the world serves a recording: its viewers watch it as spectators")
        }
        Ask::Replay(c) => match &state.replay {
            Some(r) if r.control_here(c) => Answer::Done,
            Some(_) => refused("the recording has stopped"),
            None => refused("the world is live, not a recording"),
        },
        Ask::Join => {
            // At the limit the world frees the oldest held vehicle first
            // ([`WorldCore::with_limit`]), in the order the joins reach it.
            let Some(vehicle) = ask_world(state, Event::Join).await else {
                return refused("the world is full (--max-vehicles), none held to free");
            };
            let ticket = crate::net::tickets::random_ticket();
            let mut drivers = lock(&state.drivers);
            for freed in state.stats.take_evicted() {
                drivers.forget(freed);
            }
            // A ticket names one vehicle, and a vehicle has one ticket (ids are reused).
            drivers.forget(vehicle);
            drivers.tickets.insert(ticket, vehicle);
            let claim = drivers.claim(vehicle);
            Answer::Joined {
                vehicle,
                ticket,
                claim,
            }
        }
        Ask::Resume { ticket } => {
            // Claimed before the world is asked: a leave or hold from the driver's old
            // connection, arriving meanwhile, is stale.
            let (vehicle, claim) = {
                let mut drivers = lock(&state.drivers);
                let Some(vehicle) = drivers.tickets.get(&ticket).copied() else {
                    return refused("no vehicle has this ticket (its hold ran out)");
                };
                (vehicle, drivers.claim(vehicle))
            };
            lock(&state.silenced).remove(&vehicle);
            // Its old edge may not have seen the connection go (or be gone itself): the
            // ticket proves the driver, so a vehicle still driven is held and taken back.
            let held = state.snapshots.borrow().held.contains(&vehicle);
            if !held {
                let _ = state.inbox.send((Event::Hold { vehicle, silent: 0 }, None));
            }
            match ask_world(state, Event::Resume(vehicle)).await {
                Some(vehicle) => Answer::Resumed { vehicle, claim },
                None => refused("the vehicle is not held any more"),
            }
        }
        Ask::Leave { vehicle, claim } => {
            let mut drivers = lock(&state.drivers);
            if drivers.holds(vehicle, claim) {
                drivers.forget(vehicle);
                let _ = state.inbox.send((Event::Leave(vehicle), None));
            }
            Answer::Done
        }
        Ask::Hold {
            vehicle,
            claim,
            silent,
        } => {
            if lock(&state.drivers).holds(vehicle, claim) {
                let _ = state.inbox.send((Event::Hold { vehicle, silent }, None));
            }
            Answer::Done
        }
    }
}

/// An edge said hello: it lives, with these addresses and vehicles. Those of its
/// vehicles held since it fell silent are given back to it.
fn heard(state: &State, edge: u64, addresses: Vec<String>, vehicles: Vec<(VehicleId, u64)>) {
    {
        let drivers = lock(&state.drivers);
        let mut silenced = lock(&state.silenced);
        for &(v, claim) in &vehicles {
            if silenced.get(&v) == Some(&(edge, claim)) {
                silenced.remove(&v);
                if drivers.holds(v, claim) && state.snapshots.borrow().held.contains(&v) {
                    tracing::info!(edge, vehicle = v, "an edge heard again: its vehicle back");
                    let _ = state.inbox.send((Event::Resume(v), None));
                }
            }
        }
    }
    let mut edges = lock(&state.edges);
    if edges.len() >= MAX_WATCHED && !edges.contains_key(&edge) {
        return;
    }
    let seen = Seen {
        heard: Instant::now(),
        addresses,
        vehicles,
    };
    if edges.insert(edge, seen).is_none() {
        tracing::info!(edge, edges = edges.len(), "an edge said hello");
    }
}

/// The addresses of the edges heard from lately, at most [`MAX_EDGES`].
fn live_addresses(state: &State) -> Vec<String> {
    let edges = lock(&state.edges);
    let mut all: Vec<&Seen> = edges.values().collect();
    all.sort_by_key(|s| std::cmp::Reverse(s.heard));
    let mut out: Vec<String> = Vec::new();
    for a in all.into_iter().flat_map(|s| &s.addresses) {
        if out.len() < MAX_EDGES && !out.contains(a) {
            out.push(a.clone());
        }
    }
    out
}

/// Holds the vehicles of each edge silent for [`EDGE_SILENCE`] (judging none while this
/// world's own NATS connection is down, and giving each a fresh start once it is back).
async fn watch_edges(client: async_nats::Client, state: Arc<State>) {
    let mut tick = tokio::time::interval(EDGE_SILENCE / 8);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut was_down = false;
    loop {
        tick.tick().await;
        let down = client.connection_state() != async_nats::connection::State::Connected;
        if down || was_down {
            let now = Instant::now();
            for seen in lock(&state.edges).values_mut() {
                seen.heard = now;
            }
            was_down = down;
            continue;
        }
        let snap = state.snapshots.borrow().clone();
        let mut dead = Vec::new();
        lock(&state.edges).retain(|edge, seen| {
            let silent = seen.heard.elapsed();
            if silent < EDGE_SILENCE {
                return true;
            }
            dead.push((*edge, silent, std::mem::take(&mut seen.vehicles)));
            false
        });
        let drivers = lock(&state.drivers);
        let mut silenced = lock(&state.silenced);
        // Forgotten once not held any more (taken back, freed).
        silenced.retain(|v, _| snap.held.contains(v));
        for (edge, silent, vehicles) in dead {
            let mut held = 0;
            for (vehicle, claim) in vehicles {
                // Not one its driver has since taken back through another edge.
                let driven = snap.vehicles.iter().any(|v| v.id == vehicle);
                if drivers.holds(vehicle, claim) && driven && !snap.held.contains(&vehicle) {
                    let silent = world_loop::hold_ticks(silent);
                    let _ = state.inbox.send((Event::Hold { vehicle, silent }, None));
                    silenced.insert(vehicle, (edge, claim));
                    held += 1;
                }
            }
            tracing::warn!(
                edge,
                held,
                "an edge silent for {:.1} s: its vehicles held",
                silent.as_secs_f64()
            );
        }
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Hands the drivers' key states to the world thread.
async fn take_keys(mut keys: async_nats::Subscriber, inbox: Sender<Inbound>) {
    let mut malformed = Malformed::new("key states");
    while let Some(msg) = keys.next().await {
        match decode::<Keys>(&msg.payload) {
            Ok(batch) => {
                for k in batch.drivers {
                    let event = Event::Keys {
                        vehicle: k.vehicle,
                        states: k.states,
                    };
                    if inbox.send((event, None)).is_err() {
                        return; // the world has stopped
                    }
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
    (world, replay): (u64, Option<Arc<crate::net::replay::ReplayShared>>),
) {
    while snapshots.changed().await.is_ok() {
        let snap = snapshots.borrow_and_update().clone();
        let clock = replay.as_ref().map(|r| r.wire_status());
        if let Err(e) = client
            .publish(
                subjects.snapshots.clone(),
                encode(&super::to_wire_watched(&snap, world, clock)),
            )
            .await
        {
            tracing::warn!(tick = snap.tick, "publishing the snapshot: {e}");
        }
    }
}
