//! An edge's end of the bus (`roam-server edge`): a server exactly as `serve` is, whose
//! world is somewhere else. [`Remote`] is the world as the edge reaches it: the hello
//! (which checks that both serve one data set), joins and resumes by request-reply
//! (answered with the world's tickets, so any edge can resume a driver). [`run`] stands
//! where `serve`'s world thread stands: it takes the viewer tasks' events (key states are
//! published, leaves and holds asked until answered) and puts each snapshot from the bus
//! in the viewer tasks' `watch`.

use std::sync::mpsc::Receiver;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use futures_util::StreamExt;
use roam_protocol::bus::{self as wire, Answer, Ask, Keys, Subjects};
use roam_protocol::messages::{Ticket, decode};
use tokio::sync::{mpsc, watch};

use super::{BusError, BusOptions, Malformed, encode, from_wire};
use crate::Terrain;
use crate::net::world_loop::Inbound;
use crate::sim::world::{VehicleId, World};
use crate::sim::world_core::{Event, Snapshot};

/// How long one request waits for the world's answer.
const ASK_TIMEOUT: Duration = Duration::from_secs(2);

/// How many times a leave or a hold is asked before it is given up (logged): the world
/// holds a vehicle whose edge went silent anyway, and frees it when the hold runs out.
const ASK_TRIES: u32 = 15;

/// Key-state messages waiting to be published at most; past it (NATS away), the newest
/// are dropped: each message carries a driver's last few states, and a driver's keys
/// are sent again 100 times a second.
const KEYS_QUEUED: usize = 4096;

/// The world as an edge reaches it.
pub struct Remote {
    client: async_nats::Client,
    subjects: Subjects,
    world: String,
    /// The world's edges (addresses viewers reach them at), as its last hello said.
    edges: Mutex<Vec<String>>,
}

impl Remote {
    /// Connects to the world named in `bus` and says hello with this edge's data set
    /// (`data`, its content hash, read from `dir`) and addresses. Refuses a world whose
    /// data set differs; waits up to `wait` for a world to answer.
    pub async fn connect(
        bus: &BusOptions,
        data: [u8; 32],
        dir: &str,
        addresses: Vec<String>,
        wait: Duration,
    ) -> Result<Arc<Remote>, BusError> {
        let subjects = bus.subjects()?;
        let client = bus.connect().await?;
        let remote = Remote {
            client,
            subjects,
            world: bus.world.clone(),
            edges: Mutex::new(Vec::new()),
        };
        let hello = Ask::Hello { data, addresses };
        let deadline = tokio::time::Instant::now() + wait;
        let answer = loop {
            match remote.ask(&hello).await {
                Ok(answer) => break answer,
                Err(e) if tokio::time::Instant::now() >= deadline => {
                    tracing::warn!("no answer from the world: {e}");
                    return Err(BusError::NoWorld {
                        world: bus.world.clone(),
                        url: bus.url.clone(),
                    });
                }
                // No responders yet (the world not started): asked again at once would
                // spin; the request's own timeout paces a world that is slow.
                Err(_) => tokio::time::sleep(Duration::from_millis(200)).await,
            }
        };
        match answer {
            Answer::Hello {
                data: world_data,
                edges,
            } => {
                if world_data != data {
                    return Err(BusError::DataSet {
                        world: bus.world.clone(),
                        world_data: roam_link::tls::hex(&world_data),
                        edge_data: roam_link::tls::hex(&data),
                        dir: dir.to_owned(),
                    });
                }
                *remote.edges.lock().unwrap_or_else(|e| e.into_inner()) = edges;
            }
            other => return Err(BusError::Answer(format!("to hello: {other:?}"))),
        }
        Ok(Arc::new(remote))
    }

    /// The world's name.
    pub fn world(&self) -> &str {
        &self.world
    }

    /// The world's edges, as its last hello said.
    pub fn edges(&self) -> Vec<String> {
        self.edges.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }

    /// One request, and the world's answer.
    async fn ask(&self, ask: &Ask) -> Result<Answer, BusError> {
        let nats = |e: String| BusError::Nats {
            what: "asking the world",
            error: e,
        };
        let reply = tokio::time::timeout(
            ASK_TIMEOUT,
            self.client.request(self.subjects.ask.clone(), encode(ask)),
        )
        .await
        .map_err(|_| nats("no answer in 2 s".into()))?
        .map_err(|e| nats(e.to_string()))?;
        decode::<Answer>(&reply.payload).map_err(|e| BusError::Answer(e.to_string()))
    }

    /// A new vehicle for a driver, and its ticket; `Err` says why not.
    pub async fn join(&self) -> Result<(VehicleId, Ticket), String> {
        match self.ask(&Ask::Join).await {
            Ok(Answer::Joined { vehicle, ticket }) => Ok((vehicle, ticket)),
            Ok(Answer::Refused { reason }) => Err(reason),
            Ok(other) => Err(format!("the world answered a join with {other:?}")),
            Err(e) => Err(e.to_string()),
        }
    }

    /// The held vehicle `ticket` names, given back; `Err` says why not.
    pub async fn resume(&self, ticket: Ticket) -> Result<VehicleId, String> {
        match self.ask(&Ask::Resume { ticket }).await {
            Ok(Answer::Resumed { vehicle }) => Ok(vehicle),
            Ok(Answer::Refused { reason }) => Err(reason),
            Ok(other) => Err(format!("the world answered a resume with {other:?}")),
            Err(e) => Err(e.to_string()),
        }
    }

    /// Asks until answered (at most [`ASK_TRIES`] times).
    async fn tell(&self, ask: Ask) {
        for _ in 0..ASK_TRIES {
            match self.ask(&ask).await {
                Ok(_) => return,
                Err(e) => tracing::debug!("{ask:?}: {e}; asking again"),
            }
        }
        tracing::warn!("{ask:?}: the world did not answer; its hold frees the vehicle");
    }
}

/// The edge's stand-in for the world thread: until `inbox` closes, publishes key states,
/// asks leaves and holds, and puts the world's snapshots in `snapshots`. Returns the
/// world as last seen (its tick; the vehicles are the world's).
pub fn run(
    remote: Arc<Remote>,
    terrain: Arc<Terrain>,
    runtime: tokio::runtime::Handle,
    inbox: Receiver<Inbound>,
    snapshots: watch::Sender<Arc<Snapshot>>,
) -> World {
    let snapshots = Arc::new(snapshots);
    let subscriber = runtime.spawn(take_snapshots(remote.clone(), snapshots.clone()));
    let (keys, keys_rx) = mpsc::channel(KEYS_QUEUED);
    let publisher = runtime.spawn(publish_keys(remote.clone(), keys_rx));
    let mut dropped = 0u64;
    // A blocking receive: this thread is the channel's reader, not a runtime worker.
    while let Ok((event, reply)) = inbox.recv() {
        match event {
            Event::Keys { vehicle, states } => {
                if keys.try_send(Keys { vehicle, states }).is_err() {
                    dropped += 1;
                    if dropped.is_power_of_two() {
                        tracing::warn!(dropped, "key states dropped: NATS is not keeping up");
                    }
                }
            }
            Event::Leave(vehicle) => {
                let remote = remote.clone();
                runtime.spawn(async move { remote.tell(Ask::Leave { vehicle }).await });
            }
            Event::Hold { vehicle, silent } => {
                let remote = remote.clone();
                runtime.spawn(async move { remote.tell(Ask::Hold { vehicle, silent }).await });
            }
            // Joins and resumes go by [`Remote::join`] and [`Remote::resume`], with the
            // world's tickets; one sent here is refused (its reply dropped).
            Event::Join | Event::Resume(_) => drop(reply),
        }
    }
    subscriber.abort();
    publisher.abort();
    let tick = snapshots.borrow().tick;
    World::at_tick(terrain, tick)
}

async fn publish_keys(remote: Arc<Remote>, mut keys: mpsc::Receiver<Keys>) {
    while let Some(k) = keys.recv().await {
        if let Err(e) = remote
            .client
            .publish(remote.subjects.keys.clone(), encode(&k))
            .await
        {
            tracing::warn!("publishing key states: {e}");
        }
    }
}

/// Each snapshot from the bus into the viewer tasks' `watch` (an older one than the
/// latest, from a world restarted behind it, is taken too: the world is what it says).
async fn take_snapshots(remote: Arc<Remote>, snapshots: Arc<watch::Sender<Arc<Snapshot>>>) {
    let mut sub = match remote
        .client
        .subscribe(remote.subjects.snapshots.clone())
        .await
    {
        Ok(sub) => sub,
        Err(e) => {
            tracing::error!("subscribing to the world's snapshots: {e}");
            return;
        }
    };
    let mut malformed = Malformed::new("snapshot");
    while let Some(msg) = sub.next().await {
        match decode::<wire::Snapshot>(&msg.payload) {
            Ok(s) => {
                snapshots.send_replace(from_wire(s));
            }
            Err(e) => malformed.note(&e),
        }
    }
}
