//! An edge's end of the bus (`roam-server edge`): a server exactly as `serve` is, whose
//! world is somewhere else. [`Remote`] is the world as the edge reaches it: the hello
//! (which checks that both serve one data set), joins and resumes by request-reply
//! (answered with the world's tickets, so any edge can resume a driver). [`run`] stands
//! where `serve`'s world thread stands: it takes the viewer tasks' events (key states are
//! published, leaves and holds asked until answered) and puts each snapshot from the bus
//! in the viewer tasks' `watch`.
//!
//! Beside it, the **beat** ([`beat`]): a hello every [`BEAT`], naming the vehicles this
//! edge's drivers drive, so the world holds them if the edge goes silent (killed, cut
//! off). Its answers are the edge's news of the world ([`News`], told to every viewer by
//! [`super::super::viewer`]): the world's edges (where a viewer may go), the world gone
//! (no answer for [`GONE_AFTER`]) and back, and a world restarted (another process, which
//! knows none of the old vehicles: the drivers are told to join again).
//!
//! **Trust** ([`super::seal`]): requests go through an [`Asker`] (sealed for the world
//! process this edge confirmed last, answered only by it), key states are sealed, and
//! snapshots are taken only from the world process confirmed by a hello's answer. A
//! snapshot of another process, however well sealed, makes the beat ask at once (at most
//! every [`CONFIRM_SPACING`]); only that answer can tell the edge the world restarted, so
//! an old world's snapshots played again kick nobody. What is refused is counted
//! ([`Remote::refused`]).

use std::collections::HashMap;
use std::sync::atomic::Ordering;
use std::sync::mpsc::Receiver;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use futures_util::StreamExt;
use roam_protocol::bus::{self as wire, Answer, Ask, DriverKeys, Keys, MAX_BATCH, Subjects};
use roam_protocol::messages::Ticket;
use roam_protocol::sync::lock;
use tokio::sync::{mpsc, oneshot, watch};

use super::asker::Asker;
use super::seal::{BusKey, Header, Kind, Refusal, Refused, RefusedCounts};
use super::voice::{Ear, count};
use super::{BusError, BusOptions, from_wire};
use crate::Terrain;
use crate::net::world_loop::Inbound;
use crate::sim::world::{VehicleId, World};
use crate::sim::world_core::{Event, Snapshot};

/// How many times a leave or a hold is asked before it is given up (logged): a vehicle
/// whose leave is lost stays driven while this edge names it, and is held once it does
/// not.
const ASK_TRIES: u32 = 15;

/// Key-state messages waiting to be published at most; past it (NATS away), the newest
/// are dropped: each message carries a driver's last few states, and a driver's keys
/// are sent again 100 times a second.
const KEYS_QUEUED: usize = 4096;

/// The least time between hellos asked early, to confirm a snapshot's world process.
const CONFIRM_SPACING: Duration = Duration::from_millis(100);

/// How often an edge says hello to its world.
pub const BEAT: Duration = Duration::from_millis(500);

/// No answer to the hellos for this long: the world is gone (news for the viewers).
pub const GONE_AFTER: Duration = Duration::from_millis(1500);

/// What an edge knows of its world, for its viewers.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct News {
    /// The world does not answer: why.
    pub gone: Option<String>,
    /// The world's edges, as its last answer listed them.
    pub edges: Vec<String>,
    /// Times the world was found restarted (another process answering).
    pub restarts: u32,
}

/// Why the world did not do what an edge asked of it (a join, a resume, a replay control).
#[derive(Debug, thiserror::Error)]
pub enum AskError {
    /// The world refused, in its own words.
    #[error("{0}")]
    Refused(String),
    /// The world answered with another answer than the request's (`asked`: `join`,
    /// `resume`, `replay control`).
    #[error("the world answered a {asked} with {answer:?}")]
    Unexpected {
        asked: &'static str,
        answer: Box<Answer>,
    },
    /// The bus failed before an answer came.
    #[error(transparent)]
    Bus(#[from] BusError),
    /// The queue of requests to the world is full.
    #[error("the world has stopped answering (too many requests queued)")]
    Busy,
    #[error("the edge is stopping")]
    Stopping,
}

/// What the world answered a request (`asked`, as [`AskError::Unexpected`] names it) with:
/// what `take` finds in the answer the request expects, or why there is none.
fn answer_of<T>(
    asked: &'static str,
    answer: Result<Answer, BusError>,
    take: impl FnOnce(&Answer) -> Option<T>,
) -> Result<T, AskError> {
    match answer? {
        Answer::Refused { reason } => Err(AskError::Refused(reason)),
        other => take(&other).ok_or_else(|| AskError::Unexpected {
            asked,
            answer: Box::new(other),
        }),
    }
}

/// The world as an edge reaches it.
pub struct Remote {
    client: async_nats::Client,
    subjects: Subjects,
    /// Its requests and their answers, sealed for the world process confirmed last.
    asker: Arc<Asker>,
    /// The world's key (`None`: a plain bus).
    key: Option<BusKey>,
    /// Messages refused, by why.
    refused: Arc<RefusedCounts>,
    /// Asks the beat to say hello now (a snapshot from a world process not confirmed).
    confirm: tokio::sync::Notify,
    world: String,
    url: String,
    data: [u8; 32],
    /// This edge's name for itself in its hellos (random, per process).
    edge: u64,
    /// The addresses viewers reach this edge at (set once it listens).
    addresses: Mutex<Vec<String>>,
    /// The vehicles this edge's drivers drive, each with its newest claim here.
    driven: Mutex<HashMap<VehicleId, u64>>,
    /// Leaves, holds and resumes, asked in the order they were told ([`tell_in_order`]):
    /// a driver's old connection's hold goes before its reconnection's resume.
    tells: mpsc::Sender<Tell>,
    /// Tells queued or being asked, and a wake-up for each one done.
    telling: Arc<(std::sync::atomic::AtomicUsize, tokio::sync::Notify)>,
    /// When the world was last heard (an answer, a snapshot).
    heard: Mutex<tokio::time::Instant>,
    /// The world's last answer named another data set (a world restarted on other data):
    /// gone, whatever its snapshots say.
    mismatch: std::sync::atomic::AtomicBool,
    news: watch::Sender<News>,
    /// The world serves a recording (`world --replay`): its clock, from its snapshots.
    replay: watch::Sender<Option<wire::Replay>>,
}

/// What [`tell_in_order`] asks.
enum Tell {
    /// Asked until answered (at most [`ASK_TRIES`] times).
    Ask(Ask),
    /// Asked once, answered on the sender.
    Resume(Ticket, oneshot::Sender<Result<Answer, BusError>>),
}

/// Leaves, holds and resumes waiting to be asked, at most: one or two for each viewer an
/// edge admits, so a full queue is a world that has stopped answering (a leave or hold
/// past it is dropped, logged: the world holds the vehicles of an edge it stops hearing
/// from, or frees them with its hold).
const TELLS_QUEUED: usize = 4096;

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
        let (tells, tells_rx) = mpsc::channel(TELLS_QUEUED);
        let key = bus.key();
        let edge = super::random_id();
        let refused = Arc::new(RefusedCounts::default());
        let asker = Asker::start(
            client.clone(),
            &subjects,
            key.as_ref(),
            edge,
            refused.clone(),
        )
        .await?;
        let remote = Remote {
            client,
            subjects,
            asker: Arc::new(asker),
            key,
            refused,
            confirm: tokio::sync::Notify::new(),
            world: bus.world.clone(),
            url: bus.url.clone(),
            data,
            edge,
            addresses: Mutex::new(addresses),
            driven: Mutex::new(HashMap::new()),
            tells,
            telling: Arc::default(),
            heard: Mutex::new(tokio::time::Instant::now()),
            mismatch: Default::default(),
            news: watch::Sender::new(News::default()),
            replay: watch::Sender::new(None),
        };
        let hello = remote.hello();
        let deadline = tokio::time::Instant::now() + wait;
        let answer = loop {
            match remote.asker.ask(&hello).await {
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
                world,
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
                remote.asker.set_world(world);
                remote.news.send_modify(|n| n.edges = edges);
            }
            other => return Err(BusError::Answer(format!("to hello: {other:?}"))),
        }
        tokio::spawn(tell_in_order(
            remote.asker.clone(),
            tells_rx,
            remote.telling.clone(),
        ));
        Ok(Arc::new(remote))
    }

    /// The world's name.
    pub fn world(&self) -> &str {
        &self.world
    }

    /// The world's edges, as its last hello said.
    pub fn edges(&self) -> Vec<String> {
        self.news.borrow().edges.clone()
    }

    /// The news of the world as it changes.
    pub fn news(&self) -> watch::Receiver<News> {
        self.news.subscribe()
    }

    /// The addresses viewers reach this edge at, said in every hello from now on.
    pub fn set_addresses(&self, addresses: Vec<String>) {
        *lock(&self.addresses) = addresses;
    }

    /// The bus messages refused so far, by why.
    pub fn refused(&self) -> Refused {
        self.refused.get()
    }

    /// The world was heard (a snapshot of the world process confirmed last).
    fn heard_now(&self) {
        *lock(&self.heard) = tokio::time::Instant::now();
        self.news.send_if_modified(|n| {
            let back = !self.mismatch.load(Ordering::Acquire) && n.gone.take().is_some();
            if back {
                tracing::info!(world = self.world, "the world answers again");
            }
            back
        });
    }

    /// World process `world` answered a hello (an answer to this edge's own request,
    /// which only the world can seal): if it is not the one heard before, the world
    /// restarted (said once, its drivers let go: their vehicles are not the new world's).
    /// Nothing else makes an edge believe the world restarted.
    fn heard_world(&self, world: u64) {
        self.heard_now();
        let before = self.asker.world();
        self.asker.set_world(world);
        if before == world {
            return;
        }
        lock(&self.driven).clear();
        tracing::warn!(
            world = self.world,
            "the world restarted: its vehicles are new; drivers are told to join again"
        );
        self.news.send_modify(|n| n.restarts += 1);
    }

    /// Times the world was found restarted.
    pub fn restarts(&self) -> u32 {
        self.news.borrow().restarts
    }

    /// This edge's hello.
    fn hello(&self) -> Ask {
        let mut vehicles: Vec<(u16, u64)> =
            lock(&self.driven).iter().map(|(v, c)| (*v, *c)).collect();
        vehicles.sort_unstable();
        Ask::Hello {
            data: self.data,
            edge: self.edge,
            addresses: lock(&self.addresses).clone(),
            vehicles,
        }
    }

    /// Whether the world serves a recording, and its clock, as its snapshots say.
    pub fn replay_clock(&self) -> watch::Receiver<Option<wire::Replay>> {
        self.replay.subscribe()
    }

    /// Steers the world's recording (the viewer holding this edge's controls asked);
    /// `Err` says why not.
    pub async fn replay_control(
        &self,
        c: roam_protocol::messages::ReplayControl,
    ) -> Result<(), AskError> {
        let answer = self.asker.ask(&Ask::Replay(c)).await;
        answer_of("replay control", answer, |a| {
            (*a == Answer::Done).then_some(())
        })
    }

    /// A new vehicle for a driver, its ticket and its claim; `Err` says why not.
    pub async fn join(&self) -> Result<(VehicleId, Ticket, u64), AskError> {
        let mut asked = self.asker.ask(&Ask::Join).await;
        // Asked of a world process gone (restarted, not yet confirmed by a hello): the
        // world now is asked who it is, and the join asked of it once more.
        if matches!(&asked, Ok(Answer::Refused { reason }) if reason == super::OTHER_WORLD) {
            say_hello(self).await;
            asked = self.asker.ask(&Ask::Join).await;
        }
        let (vehicle, ticket, claim) = answer_of("join", asked, |a| match *a {
            Answer::Joined {
                vehicle,
                ticket,
                claim,
            } => Some((vehicle, ticket, claim)),
            _ => None,
        })?;
        lock(&self.driven).insert(vehicle, claim);
        Ok((vehicle, ticket, claim))
    }

    /// The held vehicle `ticket` names, given back, and its new claim; `Err` says why
    /// not. Asked after every leave and hold told before it.
    pub async fn resume(&self, ticket: Ticket) -> Result<(VehicleId, u64), AskError> {
        let (tx, rx) = oneshot::channel();
        self.tells
            .try_send(Tell::Resume(ticket, tx))
            .map_err(|_| AskError::Busy)?;
        let answer = rx.await.map_err(|_| AskError::Stopping)?;
        let (vehicle, claim) = answer_of("resume", answer, |a| match *a {
            Answer::Resumed { vehicle, claim } => Some((vehicle, claim)),
            _ => None,
        })?;
        lock(&self.driven).insert(vehicle, claim);
        Ok((vehicle, claim))
    }

    /// A driver here is gone from `vehicle` (its claim `claim`): held, counted from
    /// `hold` ticks ago, or (`None`) left. Told to the world in order, until answered.
    pub fn ended(&self, vehicle: VehicleId, claim: u64, hold: Option<u64>) {
        {
            let mut driven = lock(&self.driven);
            if driven.get(&vehicle) == Some(&claim) {
                driven.remove(&vehicle);
            }
        }
        let ask = match hold {
            Some(silent) => Ask::Hold {
                vehicle,
                claim,
                silent,
            },
            None => Ask::Leave { vehicle, claim },
        };
        if self.queue(Tell::Ask(ask)).is_err() {
            tracing::warn!(vehicle, "too many requests queued for the world: not told");
        }
    }

    fn queue(&self, tell: Tell) -> Result<(), ()> {
        self.telling.0.fetch_add(1, Ordering::AcqRel);
        self.tells.try_send(tell).map_err(|_| {
            self.telling.0.fetch_sub(1, Ordering::AcqRel);
        })
    }

    /// Waits (at most `within`) until every leave and hold told so far has been asked: an
    /// edge stopping tells its world that its drivers left before it goes.
    pub async fn settle(&self, within: Duration) {
        let deadline = tokio::time::Instant::now() + within;
        loop {
            let done = self.telling.1.notified();
            if self.telling.0.load(Ordering::Acquire) == 0 {
                return;
            }
            if tokio::time::timeout_at(deadline, done).await.is_err() {
                tracing::warn!("stopping with leaves or holds the world has not answered");
                return;
            }
        }
    }
}

/// Asks what is told, one at a time, in order: a leave or a hold until answered (at most
/// [`ASK_TRIES`] times), a resume once.
async fn tell_in_order(
    asker: Arc<Asker>,
    mut tells: mpsc::Receiver<Tell>,
    telling: Arc<(std::sync::atomic::AtomicUsize, tokio::sync::Notify)>,
) {
    while let Some(tell) = tells.recv().await {
        tell_one(&asker, tell).await;
        telling.0.fetch_sub(1, Ordering::AcqRel);
        telling.1.notify_waiters();
    }
}

async fn tell_one(asker: &Asker, tell: Tell) {
    match tell {
        Tell::Resume(ticket, reply) => {
            let _ = reply.send(asker.ask(&Ask::Resume { ticket }).await);
        }
        Tell::Ask(a) => {
            for tries in 1..=ASK_TRIES {
                match asker.ask(&a).await {
                    Ok(_) => return,
                    Err(e) if tries < ASK_TRIES => tracing::debug!("{a:?}: {e}; asking again"),
                    Err(e) => tracing::warn!(
                        "{a:?}: {e}; the world did not answer (a vehicle this edge no longer \
                         names is held once the world notices)"
                    ),
                }
            }
        }
    }
}

/// The edge's stand-in for the world thread: until `inbox` closes, publishes key states,
/// says hello, and puts the world's snapshots in `snapshots`. Returns the
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
    let beating = runtime.spawn(beat(remote.clone()));
    let mut dropped = 0u64;
    // A blocking receive: this thread is the channel's reader, not a runtime worker.
    while let Ok((event, reply)) = inbox.recv() {
        match event {
            Event::Keys { vehicle, states } => {
                if keys.try_send(DriverKeys { vehicle, states }).is_err() {
                    dropped += 1;
                    if dropped.is_power_of_two() {
                        tracing::warn!(dropped, "key states dropped: NATS is not keeping up");
                    }
                }
            }
            // Joins and resumes go by [`Remote::join`] and [`Remote::resume`], with the
            // world's tickets, leaves and holds by [`Remote::ended`] with their claims;
            // one sent here is refused (its reply dropped).
            Event::Join | Event::Resume(_) | Event::Leave(_) | Event::Hold { .. } => drop(reply),
        }
    }
    subscriber.abort();
    publisher.abort();
    beating.abort();
    let tick = snapshots.borrow().tick;
    World::at_tick(terrain, tick)
}

/// Publishes the drivers' key states: each message all that was queued (at most
/// [`MAX_BATCH`]), so a tick's worth of drivers goes as one message.
async fn publish_keys(remote: Arc<Remote>, mut keys: mpsc::Receiver<DriverKeys>) {
    let mut batch = Keys::default();
    while let Some(k) = keys.recv().await {
        batch.drivers.push(k);
        while batch.drivers.len() < MAX_BATCH {
            match keys.try_recv() {
                Ok(k) => batch.drivers.push(k),
                Err(_) => break,
            }
        }
        let world = remote.asker.world();
        let (_, bytes) = remote.asker.voice().say(Kind::Keys, world, 0, &batch);
        if let Err(e) = remote
            .client
            .publish(remote.subjects.keys.clone(), bytes)
            .await
        {
            tracing::warn!("publishing key states: {e}");
        }
        batch.drivers.clear();
    }
}

/// Says hello every [`BEAT`] and keeps the news: the world's edges, the world gone (no
/// answer for [`GONE_AFTER`]) and back, a world restarted.
async fn beat(remote: Arc<Remote>) {
    let mut tick = tokio::time::interval(BEAT);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            // A snapshot of another world process: asked now whether it is the world's.
            _ = remote.confirm.notified() => {
                tokio::time::sleep(CONFIRM_SPACING).await;
            }
        }
        say_hello(&remote).await;
    }
}

/// One hello, and what its answer tells: the world's process (a restart), its edges, its
/// data set, or that it is gone.
async fn say_hello(remote: &Remote) {
    let why = match remote.asker.ask(&remote.hello()).await {
        Ok(Answer::Hello { data, world, edges }) if data == remote.data => {
            remote.mismatch.store(false, Ordering::Release);
            remote.heard_world(world);
            remote.news.send_if_modified(|n| {
                let changed = n.edges != edges;
                n.edges = edges;
                changed
            });
            return;
        }
        Ok(Answer::Hello { data, .. }) => {
            remote.mismatch.store(true, Ordering::Release);
            let why = format!(
                "the world {:?} now serves another data set ({}, this edge has {}): \
                 serve the same data set on both",
                remote.world,
                roam_link::tls::hex(&data),
                roam_link::tls::hex(&remote.data)
            );
            remote.news.send_if_modified(|n| {
                let first = n.gone.as_ref() != Some(&why);
                if first {
                    tracing::error!("{why}");
                }
                n.gone = Some(why);
                first
            });
            return;
        }
        Ok(other) => format!("the world answered a hello with {other:?}"),
        Err(e) => e.to_string(),
    };
    let silent = lock(&remote.heard).elapsed();
    if silent >= GONE_AFTER {
        let why = format!(
            "the world {:?} has not answered for {:.0} s (NATS at {}): {why}; \
             still trying",
            remote.world,
            silent.as_secs_f64(),
            remote.url
        );
        remote.news.send_if_modified(|n| {
            let first = n.gone.is_none();
            if first {
                tracing::warn!("{why}");
            }
            n.gone = Some(why);
            first
        });
    }
}

/// Each snapshot from the bus into the viewer tasks' `watch`: only the world process's
/// this edge confirmed last by a hello (a snapshot of another, however well sealed, may
/// be one recorded before a restart and played again: it asks the beat to confirm, and is
/// dropped meanwhile). Replays of the world's own are refused by its counter.
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
    let mut ear = Ear::new(
        Kind::Snapshot,
        remote.key.as_ref(),
        remote.refused.clone(),
        "snapshot",
    );
    // The newest snapshot taken: its world process and counter.
    let mut last: Option<(u64, u64)> = None;
    let unconfirmed = |world: u64| {
        count(
            &remote.refused.unconfirmed,
            format_args!(
                "a snapshot of world process {world:x}, not the one confirmed: asking the world"
            ),
        );
        remote.confirm.notify_one();
    };
    while let Some(msg) = sub.next().await {
        let confirmed = remote.asker.world();
        // Sealed, a snapshot of another process is not even opened (a flood of made-up
        // ones costs a look each); the beat asks the world who it is.
        if remote.key.is_some()
            && let Some(h) = Header::peek(&msg.payload)
            && h.sender != confirmed
        {
            unconfirmed(h.sender);
            continue;
        }
        let Some((header, s)) = ear.open::<wire::Snapshot>(&msg.payload, b"") else {
            continue;
        };
        if let Some(h) = header {
            if h.sender != s.world {
                ear.refuse(Refusal::Forged, Some(h.sender));
                continue;
            }
            // Snapshots supersede each other: only one newer than the last taken is, so a
            // genuine one played again (one this edge never saw, say) cannot take the
            // world back in time, nor a vehicle away from its driver.
            if last.is_some_and(|(w, c)| w == h.sender && h.counter <= c) {
                ear.refuse(Refusal::Replayed, Some(h.sender));
                continue;
            }
            last = Some((h.sender, h.counter));
        }
        if s.world != confirmed {
            unconfirmed(s.world);
            continue;
        }
        // Before the snapshot: a viewer task missing its vehicle in it knows why.
        remote.heard_now();
        remote
            .replay
            .send_if_modified(|r| std::mem::replace(r, s.replay) != s.replay);
        snapshots.send_replace(from_wire(s));
    }
}

#[cfg(test)]
mod tests {
    use roam_protocol::bus::Answer;

    use super::{AskError, BusError, answer_of};

    /// An error's kind, by name.
    fn kind(e: &AskError) -> &'static str {
        match e {
            AskError::Refused(_) => "refused",
            AskError::Unexpected { .. } => "unexpected",
            AskError::Bus(_) => "bus",
            AskError::Busy => "busy",
            AskError::Stopping => "stopping",
        }
    }

    /// A join's answer: the vehicle the world gave, or why not, in the words a refused
    /// viewer reads.
    #[test]
    fn an_answer_is_taken_or_says_why_not() {
        let joined = |a: &Answer| match *a {
            Answer::Joined { vehicle, .. } => Some(vehicle),
            _ => None,
        };
        let refused = Answer::Refused {
            reason: "no vehicle free".into(),
        };
        let lost = BusError::Nats {
            what: "a request",
            error: "no responders".into(),
        };
        let joined_7 = Answer::Joined {
            vehicle: 7,
            ticket: [1; 16],
            claim: 9,
        };
        for (answer, want) in [
            (Ok(joined_7), Ok(7)),
            (Ok(refused), Err(("no vehicle free", "refused"))),
            (
                Ok(Answer::Done),
                Err(("the world answered a join with Done", "unexpected")),
            ),
            (Err(lost), Err(("NATS (a request): no responders", "bus"))),
        ] {
            let got = answer_of("join", answer, joined).map_err(|e| (e.to_string(), kind(&e)));
            assert_eq!(got, want.map_err(|(words, kind)| (words.to_owned(), kind)));
        }
    }
}
