//! The cluster's bus attacked (issue 39): a real `nats-server` on loopback, a world, an edge
//! and a real driver on it over QUIC, and an attacker, a plain NATS client that may publish
//! and subscribe anything on that NATS server but holds no secret of the cluster. It speaks
//! the project's own bus encodings ([`roam_protocol::bus`]) on the world's subjects
//! (`roam.<world>.ask`, `.keys`, `.snap`): it steers, frees and holds another driver's
//! vehicle, kicks every driver with a made-up world restart, fills the world with joins,
//! snoops on tickets and claims, puts its own address in the edge list, and replays what it
//! captured. Each test asserts that the attack does NOT succeed (and that the world keeps its
//! 100 ticks a second and the real driver's drive stays exact).
//!
//! The world and the edge hold the cluster's secret ([`cluster::bus`]); the attacker does
//! not. Each test ends by asserting what the world ([`WorldServer::refused`]) and the edge
//! ([`Remote::refused`]) counted: every attacking message refused, none taken.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use futures_util::StreamExt;
use roam_client::headless::{self, ViewerOptions, ViewerStats};
use roam_protocol::bus::{self as wire, Answer, Ask, DriverKeys, Keys, Subjects};
use roam_protocol::messages::{KeyState, Role, decode, encode};
use roam_protocol::script;
use roam_protocol::sync::lock;
use roam_server::Terrain;
use roam_server::net::bus::edge::Remote;
use roam_server::net::bus::world::WorldServer;
use roam_server::sim::world_core::Snapshot;
use roam_tests::fixtures::{self, Running, flat};
use roam_tests::nats::Nats;
use roam_tests::nats::cluster::{self, bus, edge_and_remote, when};

use crate::turn;

/// How long the attacker waits for the world's answer to one request.
const ANSWER_WAIT: Duration = Duration::from_secs(1);

/// Requests the attacker has in flight at once.
const IN_FLIGHT: usize = 128;

/// The frames the real driver takes: [`fixtures::DRIVE`] (423 ticks) and its stop, at
/// 60 frames a second, about 8 s, over which each attack is made.
const FRAMES: u64 = 480;

/// A world, an edge of it serving viewers on loopback, and an attacker on the same NATS.
struct Cluster {
    _nats: Nats,
    terrain: Arc<Terrain>,
    world: WorldServer,
    edge: Running,
    remote: Arc<Remote>,
    attacker: Attacker,
}

impl Cluster {
    /// A world named `name` of at most `max_vehicles` vehicles, its edge, and the attacker.
    async fn start(name: &str, max_vehicles: usize) -> Cluster {
        let nats = Nats::start();
        let terrain = flat();
        // The cluster's secret, shared by the world and its edge (the attacker never has
        // it): `cluster::bus`.
        let bus = bus(&nats, name);
        let hold = Duration::from_secs(30);
        let world = cluster::start_world(&terrain, &bus, (hold, max_vehicles), None).await;
        let (edge, remote) = edge_and_remote(terrain.clone(), &bus).await;
        let attacker = Attacker::connect(&nats, name).await;
        Cluster {
            _nats: nats,
            terrain,
            world,
            edge,
            remote,
            attacker,
        }
    }

    /// A real driver on the edge driving [`fixtures::DRIVE`] for [`FRAMES`] frames (its
    /// task: `Err` if it could not join or its session ended early).
    fn driver(&self) -> tokio::task::JoinHandle<anyhow::Result<ViewerStats>> {
        let options = ViewerOptions {
            token: self.edge.token.clone(),
            role: Role::Driver,
            budget: 8_000,
            frames: FRAMES,
            inputs: Some(script::parse(fixtures::DRIVE).expect("DRIVE is a valid script")),
            ..ViewerOptions::default()
        };
        tokio::spawn(headless::run(
            self.edge.server.addr,
            self.edge.fingerprint,
            options,
        ))
    }

    /// The real driver's vehicle, once it is in the world.
    async fn driven(&self) -> u16 {
        let mut snaps = self.world.watch();
        when(&mut snaps, 10, "the driver's vehicle appears", |s| {
            !s.vehicles.is_empty()
        })
        .await
        .vehicles[0]
            .id
    }

    /// The world's tick now.
    fn tick(&self) -> u64 {
        self.world.snapshot().tick
    }

    /// Stops the edge and the world.
    async fn stop(self) {
        self.edge.server.shutdown().await.expect("the edge stops");
        self.world.shutdown().await.expect("the world stops");
    }
}

/// A NATS client without the cluster's secret: plain `async-nats`, no credentials.
struct Attacker {
    client: async_nats::Client,
    subjects: Subjects,
}

impl Attacker {
    async fn connect(nats: &Nats, world: &str) -> Attacker {
        let client = async_nats::connect(nats.url())
            .await
            .expect("the attacker reaches NATS (it lets anyone in)");
        Attacker {
            client,
            subjects: Subjects::of(world).expect("a valid world name"),
        }
    }

    /// Publishes `msg`, encoded as the bus encodes it, on `subject`.
    async fn publish<T: serde::Serialize>(&self, subject: &str, msg: &T) {
        self.publish_raw(subject, bytes(msg)).await;
    }

    /// Publishes `payload` as it is on `subject`.
    async fn publish_raw(&self, subject: &str, payload: bytes::Bytes) {
        self.client
            .publish(subject.to_owned(), payload)
            .await
            .expect("NATS takes the attacker's publish");
    }

    /// Waits until NATS has every publish so far.
    async fn flush(&self) {
        self.client
            .flush()
            .await
            .expect("NATS takes the attacker's messages");
    }

    /// Subscribes to `subject` (wildcards allowed), effective once this returns.
    async fn subscribe(&self, subject: &str) -> async_nats::Subscriber {
        let sub = self
            .client
            .subscribe(subject.to_owned())
            .await
            .expect("NATS lets anyone subscribe");
        self.flush().await;
        sub
    }

    /// Asks the world `payload` (a request with the attacker's own inbox for the reply):
    /// its answer if one that decodes comes within [`ANSWER_WAIT`].
    async fn ask_raw(&self, payload: bytes::Bytes) -> Option<Answer> {
        let reply = tokio::time::timeout(
            ANSWER_WAIT,
            self.client.request(self.subjects.ask.clone(), payload),
        )
        .await
        .ok()?
        .ok()?;
        decode::<Answer>(&reply.payload).ok()
    }

    /// Every request of `asks` asked, [`IN_FLIGHT`] at a time: the answers that came.
    async fn ask_all(&self, asks: Vec<bytes::Bytes>) -> Vec<Answer> {
        let mut answers = Vec::new();
        let mut flying = tokio::task::JoinSet::new();
        for payload in asks {
            if flying.len() >= IN_FLIGHT
                && let Some(done) = flying.join_next().await
            {
                answers.extend(done.expect("a request task runs"));
            }
            let (client, subject) = (self.client.clone(), self.subjects.ask.clone());
            flying.spawn(async move {
                let reply = tokio::time::timeout(ANSWER_WAIT, client.request(subject, payload))
                    .await
                    .ok()?
                    .ok()?;
                decode::<Answer>(&reply.payload).ok()
            });
        }
        while let Some(done) = flying.join_next().await {
            answers.extend(done.expect("a request task runs"));
        }
        answers
    }

    /// Everything published on `subject` from now on, kept (at most `cap` messages) until
    /// the returned [`Capture`] is taken.
    async fn capture(&self, subject: &str, cap: usize) -> Capture {
        let mut sub = self.subscribe(subject).await;
        let kept: Arc<Mutex<Vec<async_nats::Message>>> = Arc::default();
        let into = kept.clone();
        let task = tokio::spawn(async move {
            while let Some(msg) = sub.next().await {
                let mut kept = lock(&into);
                if kept.len() < cap {
                    kept.push(msg);
                }
            }
        });
        Capture { kept, task }
    }
}

/// Messages captured by [`Attacker::capture`].
struct Capture {
    kept: Arc<Mutex<Vec<async_nats::Message>>>,
    task: tokio::task::JoinHandle<()>,
}

impl Capture {
    /// Stops capturing: what was captured, in order.
    fn take(self) -> Vec<async_nats::Message> {
        self.task.abort();
        std::mem::take(&mut *lock(&self.kept))
    }
}

/// `msg` as the bus encodes it.
fn bytes<T: serde::Serialize>(msg: &T) -> bytes::Bytes {
    let mut out = Vec::new();
    encode(msg, &mut out).expect("a bus message encodes");
    out.into()
}

/// The world once 100 more ticks (1 s) have passed, or as soon as `gone` holds of it: what
/// an attack made takes effect within, as the world applies events at its next tick.
async fn a_second_on(
    world: &WorldServer,
    mut gone: impl FnMut(&Snapshot) -> bool,
) -> Arc<Snapshot> {
    let (mut snaps, stats) = (world.watch(), world.world_stats());
    let from = stats.ticks();
    when(&mut snaps, 10, "100 more world ticks", |s| {
        stats.ticks() >= from + 100 || gone(s)
    })
    .await
}

/// The world's pace, from [`Pace::start`] to [`Pace::check`].
struct Pace {
    stats: Arc<roam_server::net::world_loop::WorldStats>,
    ticks: u64,
    at: Instant,
}

impl Pace {
    fn start(world: &WorldServer) -> Pace {
        let stats = world.world_stats();
        Pace {
            ticks: stats.ticks(),
            at: Instant::now(),
            stats,
        }
    }

    /// The world kept 100 ticks a second (80 % of them at least: a liveness bound on 2
    /// cores) and dropped none, since [`Pace::start`].
    fn check(&self, during: &str) {
        let (ticks, elapsed) = (self.stats.ticks() - self.ticks, self.at.elapsed());
        let due = elapsed.as_secs_f64() * 100.0;
        assert!(
            ticks as f64 >= 0.8 * due,
            "the world made {ticks} ticks in {:.2} s {during} (100 a second due)",
            elapsed.as_secs_f64()
        );
        assert_eq!(self.stats.dropped(), 0, "no world tick dropped {during}");
    }
}

/// The driver's task awaited (bounded): its session went to its last frame, and its drive
/// ended exactly where [`fixtures::DRIVE`], simulated, ends.
async fn drove_exactly(
    terrain: &Arc<Terrain>,
    d: tokio::task::JoinHandle<anyhow::Result<ViewerStats>>,
) -> ViewerStats {
    let stats = fixtures::bounded("the driver's session", d)
        .await
        .expect("the driver's task runs")
        .expect("the driver joins and its session goes on to its last frame");
    assert_eq!(stats.frames, FRAMES, "every frame taken");
    fixtures::assert_drive_exact(terrain, stats.last, stats.last_tick);
    stats
}

/// Keys forged for another driver's vehicle: while the real driver drives
/// [`fixtures::DRIVE`], the attacker publishes `Keys` for its vehicle, Left held, with
/// sequence numbers near 4·10⁹ (which would outrank the real ones), 100 a second for 3 s.
/// Proves that they steer nothing (the drive ends exactly where the script, simulated, ends)
/// and that the world keeps its 100 ticks a second under them.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn forged_keys_do_not_steer_another_drivers_vehicle() {
    let _turn = turn().await;
    let c = Cluster::start("steer", 64).await;
    let d = c.driver();
    let vehicle = c.driven().await;
    let pace = Pace::start(&c.world);
    let mut rate = tokio::time::interval(Duration::from_millis(10));
    for i in 0..300u32 {
        rate.tick().await;
        let forged = Keys {
            drivers: vec![DriverKeys {
                vehicle,
                states: vec![KeyState {
                    seq: 4_000_000_000 + i,
                    held: roam_protocol::Keys::LEFT.bits(),
                    pressed: 0,
                }],
            }],
        };
        c.attacker.publish(&c.attacker.subjects.keys, &forged).await;
    }
    c.attacker.flush().await;
    pace.check("under 3 s of forged keys");
    drove_exactly(&c.terrain, d).await;
    // Every forged message refused as unsealed, and counted.
    let refused = c.world.refused();
    assert_eq!(refused.unsealed, 300, "{refused:?}");
    assert_eq!(refused.not_holder, 0, "{refused:?}");
    c.stop().await;
}

/// Leaves forged for another driver's vehicle: `Ask::Leave` with claims 1 to 199 (claims
/// are not to be guessed). Proves that the vehicle stays in the world, and its driver's
/// session goes on to its last frame, its drive exact.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn forged_leaves_do_not_free_another_drivers_vehicle() {
    let _turn = turn().await;
    let c = Cluster::start("leave", 64).await;
    let d = c.driver();
    let vehicle = c.driven().await;
    let leaves = (1..=199u64)
        .map(|claim| bytes(&Ask::Leave { vehicle, claim }))
        .collect();
    c.attacker.ask_all(leaves).await;
    let after = a_second_on(&c.world, |s| s.vehicles.iter().all(|v| v.id != vehicle)).await;
    assert!(
        after.vehicles.iter().any(|v| v.id == vehicle),
        "vehicle {vehicle} freed by forged leaves (the world at tick {}: {} vehicles)",
        after.tick,
        after.vehicles.len()
    );
    drove_exactly(&c.terrain, d).await;
    // Each leave refused as unsealed (no edge's proof), and counted.
    let refused = c.world.refused();
    assert_eq!(refused.unsealed, 199, "{refused:?}");
    c.stop().await;
}

/// Holds forged for another driver's vehicle: `Ask::Hold` with claims 1 to 199. Proves
/// that the vehicle is never held, and its driver's session goes on, its drive exact.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn forged_holds_do_not_hold_another_drivers_vehicle() {
    let _turn = turn().await;
    let c = Cluster::start("hold", 64).await;
    let d = c.driver();
    let vehicle = c.driven().await;
    let holds = (1..=199u64)
        .map(|claim| {
            bytes(&Ask::Hold {
                vehicle,
                claim,
                silent: 0,
            })
        })
        .collect();
    c.attacker.ask_all(holds).await;
    let after = a_second_on(&c.world, |s| s.held.contains(&vehicle)).await;
    assert!(
        !after.held.contains(&vehicle),
        "vehicle {vehicle} held by forged holds (the world at tick {}: held {:?})",
        after.tick,
        after.held
    );
    drove_exactly(&c.terrain, d).await;
    // Each hold refused as unsealed, and counted.
    let refused = c.world.refused();
    assert_eq!(refused.unsealed, 199, "{refused:?}");
    c.stop().await;
}

/// Snapshots forged from a "restarted" world: three `Snapshot`s on `roam.<world>.snap`
/// naming a new world process and no vehicles. Proves that the edge does not take them for
/// a world restart (it would tell every driver to join again): no restart counted, and the
/// driver's session goes on to its last frame, its drive exact.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn forged_snapshots_of_a_new_world_kick_no_driver() {
    let _turn = turn().await;
    let c = Cluster::start("kick", 64).await;
    let d = c.driver();
    c.driven().await;
    let tick = c.tick();
    for i in 1..=3 {
        let forged = wire::Snapshot {
            world: 0x0bad_0bad_0bad_0bad,
            tick: tick + i,
            ..wire::Snapshot::default()
        };
        c.attacker
            .publish(&c.attacker.subjects.snapshots, &forged)
            .await;
    }
    c.attacker.flush().await;
    // The driver's session, to its end, is the time the edge had to take the snapshots.
    let ended = fixtures::bounded("the driver's session", d).await;
    assert_eq!(
        c.remote.restarts(),
        0,
        "the edge took forged snapshots for a world restart"
    );
    let stats = ended
        .expect("the driver's task runs")
        .expect("the driver's session goes on to its last frame");
    fixtures::assert_drive_exact(&c.terrain, stats.last, stats.last_tick);
    // The three refused by the edge as unsealed, and counted.
    let refused = c.remote.refused();
    assert_eq!(refused.unsealed, 3, "{refused:?}");
    c.stop().await;
}

/// Joins forged by the thousand: 1,100 bare `Ask::Join` at a world of at most 1,024
/// vehicles (the command line's default). Proves that none is answered `Joined`, that the
/// world keeps its 100 ticks a second under them, and that a real driver then joins and
/// drives exactly.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn forged_joins_do_not_fill_the_world() {
    let _turn = turn().await;
    let c = Cluster::start("fill", 1024).await;
    let pace = Pace::start(&c.world);
    let joins = (0..1100).map(|_| bytes(&Ask::Join)).collect();
    let answers = c.attacker.ask_all(joins).await;
    let joined = answers
        .iter()
        .filter(|a| matches!(a, Answer::Joined { .. }))
        .count();
    assert_eq!(joined, 0, "forged joins answered Joined");
    pace.check("under 1,100 forged joins");
    let in_world = c.world.snapshot().vehicles.len();
    assert_eq!(in_world, 0, "vehicles nobody drives in the world");
    drove_exactly(&c.terrain, c.driver()).await;
    // Each join refused as unsealed, and counted.
    let refused = c.world.refused();
    assert_eq!(refused.unsealed, 1100, "{refused:?}");
    c.stop().await;
}

/// A snooper on every subject (`roam.>`) and every reply inbox (`_INBOX.>`) from before a
/// driver joins to after it leaves, and a fake edge's hello (a made-up edge, address
/// 203.0.113.9:4433). Proves that no captured message reads as a join's or a resume's
/// answer (its ticket and claim) nor as a request naming a claim (a hello's vehicles, a
/// leave, a hold), and that the fake address is given neither to the attacker nor to the
/// real edge in the world's list of edges (which its viewers are told).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_snooper_learns_no_ticket_or_claim_and_a_fake_edge_is_not_listed() {
    let _turn = turn().await;
    let c = Cluster::start("snoop", 64).await;
    let replies = c.attacker.capture("_INBOX.>", 100_000).await;
    let subjects = c.attacker.capture("roam.>", 100_000).await;
    let d = c.driver();
    c.driven().await;
    const FAKE: &str = "203.0.113.9:4433";
    let fake_hello = Ask::Hello {
        data: c.terrain.content_hash(),
        edge: 0x0bad_ed9e,
        addresses: vec![FAKE.into()],
        vehicles: vec![],
    };
    let answer = c.attacker.ask_raw(bytes(&fake_hello)).await;
    // The driver's session to its end (the edge's hellos every ½ s meanwhile), then its
    // vehicle gone: its edge's leave asked, and answered.
    drove_exactly(&c.terrain, d).await;
    let mut snaps = c.world.watch();
    when(&mut snaps, 10, "the driver's vehicle leaves", |s| {
        s.vehicles.is_empty()
    })
    .await;
    let (replies, subjects) = (replies.take(), subjects.take());
    assert!(
        subjects.len() > 100,
        "the snooper heard the world's snapshots: {} messages",
        subjects.len()
    );
    let leaked_answers: Vec<Answer> = replies
        .iter()
        .filter_map(|m| decode::<Answer>(&m.payload).ok())
        .filter(|a| matches!(a, Answer::Joined { .. } | Answer::Resumed { .. }))
        .collect();
    assert!(
        leaked_answers.is_empty(),
        "tickets and claims read on _INBOX.>: {leaked_answers:?}"
    );
    let leaked_asks: Vec<Ask> = subjects
        .iter()
        .filter(|m| m.subject.as_str() == c.attacker.subjects.ask)
        .filter_map(|m| decode::<Ask>(&m.payload).ok())
        .filter(|a| match a {
            Ask::Hello { vehicles, .. } => !vehicles.is_empty(),
            Ask::Leave { .. } | Ask::Hold { .. } => true,
            _ => false,
        })
        .collect();
    assert!(
        leaked_asks.is_empty(),
        "claims read on {}: {leaked_asks:?}",
        c.attacker.subjects.ask
    );
    if let Some(Answer::Hello { edges, .. }) = &answer {
        assert!(
            !edges.iter().any(|e| e == FAKE),
            "the fake edge's hello answered with its address listed: {edges:?}"
        );
    }
    let listed = c.remote.edges();
    assert!(
        !listed.iter().any(|e| e == FAKE),
        "the world lists the fake edge's address to the real edge (and its viewers): {listed:?}"
    );
    assert!(
        listed.contains(&c.edge.server.addr.to_string()),
        "the real edge is listed: {listed:?}"
    );
    // The fake hello refused as unsealed, and counted; the snooper's capture was all
    // sealed, and none of it decodes as a bus message.
    let refused = c.world.refused();
    assert_eq!(refused.unsealed, 1, "{refused:?}");
    assert!(answer.is_none(), "the fake hello was answered: {answer:?}");
    let own = bytes(&fake_hello);
    let plain = replies
        .iter()
        .chain(&subjects)
        .filter(|m| m.payload != own && !m.payload.starts_with(&roam_server::net::bus::seal::MAGIC))
        .count();
    assert_eq!(
        plain, 0,
        "every message on the bus but the attacker's is sealed"
    );
    c.stop().await;
}

/// Genuine messages replayed: the attacker captures the edge's key states
/// (`roam.<world>.keys`), its requests (`.ask`: its hellos and its driver's join) and the
/// world's snapshots (`.snap`) for the drive's first second, then publishes each again (100
/// of each kind, the requests with its own inbox for the reply). Proves that no replayed
/// join is answered `Joined`, that the world's vehicles stay the one driven, that the edge
/// takes no restart, and that the driver's session goes on, its drive exact. (Before the
/// fix, the replayed joins are what succeed: the replayed key states carry sequence numbers
/// already applied, and the replayed snapshots name the same world process.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replayed_messages_join_free_steer_and_kick_nothing() {
    let _turn = turn().await;
    let c = Cluster::start("replay", 64).await;
    let s = &c.attacker.subjects;
    let keys = c.attacker.capture(&s.keys, 1000).await;
    let asks = c.attacker.capture(&s.ask, 1000).await;
    let snaps = c.attacker.capture(&s.snapshots, 1000).await;
    let d = c.driver();
    let vehicle = c.driven().await;
    let mut watch = c.world.watch();
    let from = c.tick();
    when(&mut watch, 10, "a second of the drive", |w| {
        w.tick >= from + 100
    })
    .await;
    let (keys, asks, snaps) = (keys.take(), asks.take(), snaps.take());
    for (what, got) in [
        ("key states", &keys),
        ("requests", &asks),
        ("snapshots", &snaps),
    ] {
        assert!(!got.is_empty(), "captured the edge's {what}");
    }
    let again = |captured: &[async_nats::Message]| -> Vec<bytes::Bytes> {
        (0..100)
            .map(|i| captured[i % captured.len()].payload.clone())
            .collect()
    };
    for payload in again(&keys) {
        c.attacker.publish_raw(&s.keys, payload).await;
    }
    for payload in again(&snaps) {
        c.attacker.publish_raw(&s.snapshots, payload).await;
    }
    c.attacker.flush().await;
    let answers = c.attacker.ask_all(again(&asks)).await;
    let joined = answers
        .iter()
        .filter(|a| matches!(a, Answer::Joined { .. } | Answer::Resumed { .. }))
        .count();
    assert_eq!(joined, 0, "replayed joins answered with a vehicle");
    let after = a_second_on(&c.world, |w| w.vehicles.len() != 1).await;
    let ids: Vec<u16> = after.vehicles.iter().map(|v| v.id).collect();
    assert_eq!(ids, vec![vehicle], "the world's vehicles: the one driven");
    let ended = fixtures::bounded("the driver's session", d).await;
    assert_eq!(
        c.remote.restarts(),
        0,
        "the edge took replays for a restart"
    );
    let stats = ended
        .expect("the driver's task runs")
        .expect("the driver's session goes on to its last frame");
    fixtures::assert_drive_exact(&c.terrain, stats.last, stats.last_tick);
    // Every replay refused, and counted: the 100 key states by the world as replays; the
    // 100 requests as forged (each seal is bound to its reply subject, and the attacker
    // gave its own); the 100 snapshots by the edge as replays (none newer than its last).
    let (world, edge) = (c.world.refused(), c.remote.refused());
    assert_eq!(world.replayed, 100, "{world:?}");
    assert_eq!(world.forged, 100, "{world:?}");
    assert_eq!(world.unsealed, 0, "{world:?}");
    assert_eq!(edge.replayed, 100, "{edge:?}");
    c.stop().await;
}
