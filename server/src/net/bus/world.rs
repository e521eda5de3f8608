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
//!
//! **Trust** ([`super::seal`]): with the cluster's secret, a request or key states are
//! taken only if they open, are new from their sender, and are for this world process (a
//! hello for another is answered, so the edge learns this one, but changes nothing). The
//! edge that sealed a join or a resume holds the vehicle ([`super::drivers`]): only its key
//! states, leave and hold for it are taken, claims are random, and a vehicle no live edge
//! names [`EDGE_SILENCE`] after its claim is held, then freed with its hold (or given
//! back, should its edge name it after all). Answers and snapshots are sealed by this
//! process. What is refused is counted ([`WorldServer::refused`]) and logged.

use std::collections::HashMap;
use std::sync::mpsc::Sender;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use futures_util::StreamExt;
use roam_protocol::bus::{Answer, Ask, Keys, MAX_EDGES, Subjects};
use roam_protocol::sync::lock;
use tokio::sync::{oneshot, watch};

use super::drivers::Drivers;
use super::seal::{BusKey, Kind, Refused, RefusedCounts};
use super::voice::{Ear, Voice, count};
use super::{BusError, BusOptions};
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

/// An edge, as its hellos tell it.
struct Seen {
    heard: Instant,
    /// Its newest hello's counter (sealed; 0 on a plain bus): an older one, delivered late
    /// or played again, changes nothing.
    counter: u64,
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
    /// The world's key (`None`: a plain bus, `--insecure-bus`).
    key: Option<BusKey>,
    /// What the world says: its answers and snapshots, sealed as `id`.
    voice: Voice,
    /// Messages refused, by why.
    refused: Arc<RefusedCounts>,
    /// When the world started (the drivers' book counts from it).
    started: Instant,
}

/// A running world.
pub struct WorldServer {
    thread: std::thread::JoinHandle<World>,
    inbox: Option<Sender<Inbound>>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
    snapshots: watch::Receiver<Arc<Snapshot>>,
    stats: Arc<WorldStats>,
    client: async_nats::Client,
    refused: Arc<RefusedCounts>,
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
        let key = bus.key();
        let id = super::random_id();
        let refused = Arc::new(RefusedCounts::default());
        let state = Arc::new(State {
            drivers: Mutex::new(Drivers::default()),
            edges: Mutex::new(HashMap::new()),
            silenced: Mutex::new(HashMap::new()),
            data,
            id,
            inbox: inbox.clone(),
            snapshots: snapshots.clone(),
            stats: stats.clone(),
            replay: replay.clone(),
            voice: Voice::new(key.as_ref(), id),
            key,
            refused: refused.clone(),
            started: Instant::now(),
        });
        let tasks = vec![
            tokio::spawn(answer_asks(asks, client.clone(), state.clone())),
            tokio::spawn(take_keys(keys, state.clone())),
            tokio::spawn(publish(
                client.clone(),
                subjects,
                snapshots.clone(),
                state.clone(),
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
            refused,
        })
    }

    /// The bus messages refused so far, by why.
    pub fn refused(&self) -> Refused {
        self.refused.get()
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

/// Answers each request in a task of its own (at most [`MAX_ASKING`] at once). Sealed,
/// a request is taken only if it opens, is new from its sender, and is for this world
/// process (a hello for another is answered, to tell the edge which process this is, but
/// changes nothing).
async fn answer_asks(
    mut asks: async_nats::Subscriber,
    client: async_nats::Client,
    state: Arc<State>,
) {
    let permits = Arc::new(tokio::sync::Semaphore::new(MAX_ASKING));
    let mut ear = Ear::new(
        Kind::Ask,
        state.key.as_ref(),
        state.refused.clone(),
        "request",
    );
    while let Some(msg) = asks.next().await {
        let Some(reply) = msg.reply else {
            continue; // a request nobody waits for the answer of: not one of ours
        };
        // Bound to its reply subject: played again with another, it does not open.
        let Some((header, ask)) = ear.open::<Ask>(&msg.payload, reply.as_bytes()) else {
            continue;
        };
        let from = Requester {
            edge: header.map(|h| h.sender),
            counter: header.map_or(0, |h| h.counter),
            here: header.is_none_or(|h| h.to == state.id),
        };
        // Only what is for this process is remembered against replays: a hello for another
        // is answered and changes nothing, so the windows hold this world's edges only.
        if from.here
            && let Some(h) = &header
            && !ear.fresh(h)
        {
            continue;
        }
        if !from.here && !matches!(ask, Ask::Hello { .. }) {
            count(
                &state.refused.other_world,
                format_args!("a request for another world process (from before it restarted?)"),
            );
            let answer = Answer::Refused {
                reason: super::OTHER_WORLD.into(),
            };
            let (_, bytes) = state
                .voice
                .say(Kind::Answer, from.to(), from.counter, &answer);
            let _ = client.publish(reply, bytes).await;
            continue;
        }
        let Ok(permit) = permits.clone().acquire_owned().await else {
            return;
        };
        let (client, state) = (client.clone(), state.clone());
        tokio::spawn(async move {
            let answer = answer(&state, &from, ask).await;
            let (_, bytes) = state
                .voice
                .say(Kind::Answer, from.to(), from.counter, &answer);
            let _ = client.publish(reply, bytes).await;
            drop(permit);
        });
    }
}

/// Who asked: the edge that sealed the request (`None` on a plain bus), its request's
/// counter, and whether the request is for this world process.
struct Requester {
    edge: Option<u64>,
    counter: u64,
    here: bool,
}

impl Requester {
    /// Whom the answer is sealed for.
    fn to(&self) -> u64 {
        self.edge.unwrap_or(0)
    }
}

/// Hands the world an event that answers with a vehicle.
async fn ask_world(state: &State, event: Event) -> Option<VehicleId> {
    let (tx, rx) = oneshot::channel();
    state.inbox.send((event, Some(tx))).ok()?;
    rx.await.ok()
}

async fn answer(state: &State, from: &Requester, ask: Ask) -> Answer {
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
            // Sealed, the edge is the one that sealed it.
            let edge = from.edge.unwrap_or(edge);
            if data == state.data && from.here {
                heard(state, edge, (from.edge, from.counter), addresses, vehicles);
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
            let claim = super::random_id();
            let mut drivers = lock(&state.drivers);
            for freed in state.stats.take_evicted() {
                drivers.forget(freed);
            }
            // A ticket names one vehicle, and a vehicle has one ticket (ids are reused).
            drivers.forget(vehicle);
            drivers.tickets.insert(ticket, vehicle);
            drivers.claim(vehicle, from.edge, claim, state.started.elapsed());
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
                let claim = super::random_id();
                drivers.claim(vehicle, from.edge, claim, state.started.elapsed());
                (vehicle, claim)
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
            if drivers.holds(vehicle, from.edge, claim) {
                drivers.leave(vehicle, from.edge, state.started.elapsed());
                let _ = state.inbox.send((Event::Leave(vehicle), None));
            } else {
                not_holder(state, "a leave", vehicle, from.edge);
            }
            Answer::Done
        }
        Ask::Hold {
            vehicle,
            claim,
            silent,
        } => {
            if lock(&state.drivers).holds(vehicle, from.edge, claim) {
                let _ = state.inbox.send((Event::Hold { vehicle, silent }, None));
            } else {
                not_holder(state, "a hold", vehicle, from.edge);
            }
            Answer::Done
        }
    }
}

/// A leave or hold (`what`) for `vehicle` from an edge that does not hold it with that
/// claim: counted. (A late one from an edge whose driver has since moved, or a retry whose
/// answer was lost, counts here too; an edge without the secret cannot send one.)
fn not_holder(state: &State, what: &str, vehicle: VehicleId, edge: Option<u64>) {
    count(
        &state.refused.not_holder,
        format_args!("{what} for vehicle {vehicle} from edge {edge:?}, which does not hold it"),
    );
}

/// An edge said hello: it lives, with these addresses and vehicles. Those of its
/// vehicles held since it fell silent are given back to it. (`sealer`: the edge that
/// sealed the hello, `None` on a plain bus.)
fn heard(
    state: &State,
    edge: u64,
    (sealer, counter): (Option<u64>, u64),
    addresses: Vec<String>,
    vehicles: Vec<(VehicleId, u64)>,
) {
    // The edge's entry first: a vehicle given back below is named by it when the edges
    // are next watched ([`hold_unnamed`]).
    {
        let mut edges = lock(&state.edges);
        let full = edges.len() >= MAX_WATCHED;
        match edges.get_mut(&edge) {
            Some(seen) if sealer.is_some() && seen.counter > counter => return,
            Some(seen) => {
                seen.heard = Instant::now();
                seen.counter = counter;
                seen.addresses = addresses;
                seen.vehicles = vehicles.clone();
            }
            None if full => return,
            None => {
                let seen = Seen {
                    heard: Instant::now(),
                    counter,
                    addresses,
                    vehicles: vehicles.clone(),
                };
                edges.insert(edge, seen);
                tracing::info!(edge, edges = edges.len(), "an edge said hello");
            }
        }
    }
    {
        let drivers = lock(&state.drivers);
        let mut silenced = lock(&state.silenced);
        for &(v, claim) in &vehicles {
            if silenced.get(&v) == Some(&(edge, claim)) {
                silenced.remove(&v);
                if drivers.holds(v, sealer, claim) && state.snapshots.borrow().held.contains(&v) {
                    tracing::info!(edge, vehicle = v, "an edge heard again: its vehicle back");
                    let _ = state.inbox.send((Event::Resume(v), None));
                }
            }
        }
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
        let sealed = state.key.is_some();
        for (edge, silent, vehicles) in dead {
            let mut held = 0;
            for (vehicle, claim) in vehicles {
                // Not one its driver has since taken back through another edge.
                let driven = snap.vehicles.iter().any(|v| v.id == vehicle);
                let holds = drivers.holds(vehicle, sealed.then_some(edge), claim);
                if holds && driven && !snap.held.contains(&vehicle) {
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
        if state.replay.is_none() {
            hold_unnamed(&state, &snap, &drivers, &mut silenced);
        }
    }
}

/// Holds each driven vehicle that no live edge's latest hello names with its claim,
/// [`EDGE_SILENCE`] after its join or resume: a join whose edge never took it up (its
/// answer lost, the edge gone), or a vehicle its edge let go without a leave reaching the
/// world. The hold runs from its claim, so it is freed when the hold runs out unless its
/// driver comes back with its ticket, or (sealed) its edge names it after all (a hello
/// late under load): then, as for an edge heard again, it is given back.
fn hold_unnamed(
    state: &State,
    snap: &Snapshot,
    drivers: &super::drivers::Drivers,
    silenced: &mut HashMap<VehicleId, (u64, u64)>,
) {
    let edges = lock(&state.edges);
    let named = |v: VehicleId, edge: Option<u64>, claim: u64| {
        let names = |s: &Seen| s.vehicles.contains(&(v, claim));
        match edge {
            Some(e) => edges.get(&e).is_some_and(names),
            None => edges.values().any(names),
        }
    };
    let driven = snap
        .vehicles
        .iter()
        .map(|v| v.id)
        .filter(|v| !snap.held.contains(v) && !silenced.contains_key(v));
    let unnamed = drivers.unnamed(driven, state.started.elapsed(), EDGE_SILENCE, named);
    drop(edges);
    for (vehicle, age) in unnamed {
        let silent = world_loop::hold_ticks(age);
        let _ = state.inbox.send((Event::Hold { vehicle, silent }, None));
        if let Some(h) = drivers.holder(vehicle)
            && let Some(edge) = h.edge
        {
            silenced.insert(vehicle, (edge, h.claim));
        }
        count(
            &state.refused.unnamed,
            format_args!(
                "vehicle {vehicle}: no edge names it {:.1} s after its join: held",
                age.as_secs_f64()
            ),
        );
    }
}

/// Hands the drivers' key states to the world thread: sealed, only those of vehicles the
/// sending edge holds, in messages for this world process.
async fn take_keys(mut keys: async_nats::Subscriber, state: Arc<State>) {
    let mut ear = Ear::new(
        Kind::Keys,
        state.key.as_ref(),
        state.refused.clone(),
        "key states",
    );
    while let Some(msg) = keys.next().await {
        // Sealed, key states from an edge that holds no vehicle are dropped before any
        // cryptography (a flood of made-up senders costs a lookup each).
        if state.key.is_some()
            && let Some(h) = super::seal::Header::peek(&msg.payload)
            && let drivers = lock(&state.drivers)
            && !drivers.holds_any(h.sender)
        {
            if drivers.late(Some(h.sender), state.started.elapsed()) {
                continue;
            }
            count(
                &state.refused.not_holder,
                format_args!("key states from {:x}, which holds no vehicle", h.sender),
            );
            continue;
        }
        let Some((header, batch)) = ear.open::<Keys>(&msg.payload, b"") else {
            continue;
        };
        if header.is_some_and(|h| h.to != state.id) {
            count(
                &state.refused.other_world,
                format_args!("key states for another world process"),
            );
            continue;
        }
        if let Some(h) = &header
            && !ear.fresh(h)
        {
            continue;
        }
        let edge = header.map(|h| h.sender);
        let mut events = Vec::with_capacity(batch.drivers.len());
        {
            let drivers = lock(&state.drivers);
            for k in batch.drivers {
                if drivers.drives(k.vehicle, edge) {
                    events.push(Event::Keys {
                        vehicle: k.vehicle,
                        states: k.states,
                    });
                } else if !drivers.late(edge, state.started.elapsed()) {
                    count(
                        &state.refused.not_holder,
                        format_args!(
                            "key states for vehicle {} from edge {edge:?}, which does not hold it",
                            k.vehicle
                        ),
                    );
                }
            }
        }
        for event in events {
            if state.inbox.send((event, None)).is_err() {
                return; // the world has stopped
            }
        }
    }
}

/// Publishes each snapshot (the latest, when publishing falls behind).
async fn publish(
    client: async_nats::Client,
    subjects: Subjects,
    mut snapshots: watch::Receiver<Arc<Snapshot>>,
    state: Arc<State>,
) {
    while snapshots.changed().await.is_ok() {
        let snap = snapshots.borrow_and_update().clone();
        let clock = state.replay.as_ref().map(|r| r.wire_status());
        let wire = super::to_wire_watched(&snap, state.id, clock);
        let (_, bytes) = state.voice.say(Kind::Snapshot, 0, 0, &wire);
        if let Err(e) = client.publish(subjects.snapshots.clone(), bytes).await {
            tracing::warn!(tick = snap.tick, "publishing the snapshot: {e}");
        }
    }
}
