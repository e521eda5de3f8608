//! `roam-server bus-load` (hidden from `--help`): a load generator for a world on NATS
//! that stands in for E edges, for the snapshot fan-out figures of issue 23
//! (`scripts/cluster.sh fanout`, README "One world, several machines").
//!
//! ```text
//! roam-server bus-load --nats URL [--world NAME] --vehicles N [--edges E] [--seconds S]
//!     [--warmup W] [--history K] [--data DIR] [--cpu-pid NAME=PID ...]
//! ```
//!
//! Each fake edge is what a real edge is to the world, minus its viewers: a NATS
//! connection of its own that
//!
//! - joins its share of the N vehicles by request-reply (`Ask::Join`; vehicle `j` goes to
//!   fake edge `j % E`), at most [`JOINING`] joins in flight in all;
//! - says hello every [`BEAT`] (the edge's beat) with the world's data hash and the
//!   vehicles it drives, so the world treats it as a live edge (an edge silent for 3 s
//!   has its vehicles held);
//! - publishes every 10 ms one `Keys` batch (split at `MAX_BATCH` drivers) holding, per
//!   vehicle, the newest K key states newest first (K = `--history`, default the viewer's
//!   `KEY_HISTORY`, 8: a real edge forwards each viewer's datagram, which repeats its last
//!   eight states), seq rising by one per state. Every vehicle drives: Up held, turning
//!   left then right for 1.5 s each with straight runs between, each vehicle at its own
//!   phase. A load figure must drive its vehicles, never park them: `vehicles_moved`
//!   counts those whose position changed over the window;
//! - subscribes to the world's snapshots (`roam.<world>.snap`) and counts their payload
//!   bytes and messages, decoding each (a malformed one is counted).
//!
//! Then: wait until a snapshot lists every vehicle (at most [`SEEN_WAIT`]), warm up for
//! `--warmup` seconds, measure `--seconds` seconds, leave every vehicle (`Ask::Leave`),
//! and print one JSON line (keys in [`report`]'s docs).
//!
//! Decisions:
//!
//! - The world's data hash is learnt from the world's answer to a first hello (the world
//!   answers any hello with its hash, and takes an edge's vehicles only from a hello with
//!   the right one); `--data DIR` instead computes it as `serve`, `world` and `edge` do
//!   (`super::served::data_hash`) and refuses a world whose hash differs.
//! - `--cpu-pid NAME=PID` reads `/proc/PID/stat` (utime + stime, the process's every
//!   thread) at the window's two ends here, so the CPU time and the ticks seen (the
//!   snapshots' `tick` field) cover the same window exactly; `scripts/cluster.sh` reads
//!   the world's and nats-server's so. The resolution is a clock tick (10 ms): at 10
//!   vehicles and 10 s the world's figure is good to about ±2 µs a tick.
//! - `keys_to_snapshot_ms_*` is the bus's round trip with the tick's wait in it: from
//!   publishing a key state to the first snapshot showing it applied, for each fake
//!   edge's first vehicle (one a tick, so the world's key queue must hold one state: a
//!   backlog shows here as a growing latency).
//!
//! Measured on 2026-11-26, evening (`PROFILE=measure scripts/cluster.sh fanout`, 4 fake
//! edges, 10 s windows, two runs; the 2 cores shared with other sessions, load average
//! 0.4–1.7: provisional): a snapshot is about 40 bytes a vehicle (376 / 3,706 / 40,446
//! bytes at 10 / 100 / 1,000 vehicles), so each edge gets 37.6 KB / 371 KB / 4.04 MB a
//! second, every snapshot (100.0 a second, none missed); the world's CPU per tick
//! 100–180 / 170–230 / 560–700 µs (issue 23: ≤ 2,000 at 1,000 vehicles and 4 edges, aim
//! ≤ 500); nats-server 2–4.4 % of a core; this generator 1–5 %; a key state to the first
//! snapshot showing it 18–21 ms (median; the world's key queue holds one to two states).

use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::Args;
use futures_util::StreamExt;
use roam_protocol::bus::{Answer, Ask, DriverKeys, Keys, MAX_BATCH, Snapshot, Subjects};
use roam_protocol::keys::Keys as Held;
use roam_protocol::messages::{KEY_HISTORY, KeyState};
use roam_protocol::stats::quantile;
use roam_protocol::sync::lock;
use roam_server::net::bus::asker::Asker;
use roam_server::net::bus::seal::{Kind, RefusedCounts};
use roam_server::net::bus::voice::Ear;

use super::cluster::BusArgs;

/// Joins in flight at once (the world answers 256 at once; a join waits one tick).
const JOINING: usize = 64;

/// How often a fake edge says hello: a real edge's beat.
const BEAT: Duration = Duration::from_millis(500);

/// How often a fake edge publishes its drivers' key states: one state a tick.
const KEYS_EVERY: Duration = Duration::from_millis(10);

/// Tries per join or leave before giving up.
const TRIES: u32 = 5;

/// How long to wait for a snapshot listing every vehicle joined.
const SEEN_WAIT: Duration = Duration::from_secs(20);

/// Publish times kept per fake edge, for the key→snapshot latency (seconds of them).
const SENT_KEPT: usize = 512;

#[derive(Args)]
pub(crate) struct BusLoadArgs {
    #[command(flatten)]
    pub bus: BusArgs,
    /// Vehicles to join and drive, spread over the fake edges (at most the world's
    /// --max-vehicles).
    #[arg(long, value_parser = clap::value_parser!(u16).range(1..=16384))]
    pub vehicles: u16,
    /// Fake edges: NATS connections, each joining, driving and subscribing.
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u16).range(1..=256))]
    pub edges: u16,
    /// Seconds measured.
    #[arg(long, default_value_t = 10.0, value_parser = seconds)]
    pub seconds: f64,
    /// Seconds of driving before the measured window.
    #[arg(long, default_value_t = 3.0, value_parser = seconds)]
    pub warmup: f64,
    /// Key states a driver's entry carries, newest first (a viewer's datagram: 8).
    #[arg(long, default_value_t = KEY_HISTORY as u8,
          value_parser = clap::value_parser!(u8).range(1..=KEY_HISTORY as i64))]
    pub history: u8,
    /// The world's data set, to compute its hash here (else the world's answer says it).
    #[arg(long, value_name = "DIR")]
    pub data: Option<PathBuf>,
    /// A process whose CPU time over the window to report (`/proc/PID/stat`), by name.
    #[arg(long = "cpu-pid", value_name = "NAME=PID", value_parser = name_pid)]
    pub cpu_pid: Vec<(String, u32)>,
}

fn seconds(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(s) if s.is_finite() && (0.0..=3600.0).contains(&s) => Ok(s),
        _ => Err(format!("expected 0 to 3600 seconds, got {text:?}")),
    }
}

fn name_pid(text: &str) -> Result<(String, u32), String> {
    let (name, pid) = text
        .split_once('=')
        .ok_or_else(|| format!("expected NAME=PID, got {text:?}"))?;
    let pid = pid
        .parse::<u32>()
        .map_err(|e| format!("{text:?}: the pid: {e}"))?;
    if name.is_empty() || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
        return Err(format!("{text:?}: a name is letters, digits and '_'"));
    }
    Ok((name.to_owned(), pid))
}

/// One fake edge: its connection, its vehicles and what it counted.
struct FakeEdge {
    id: u64,
    client: async_nats::Client,
    /// Its requests, sealed as a real edge's are (`--bus-secret`), or plain.
    asker: Asker,
    /// Its hearing of the snapshots.
    key: Option<roam_server::net::bus::seal::BusKey>,
    /// Its vehicles, each with the claim the world gave it (named in hellos and leaves).
    vehicles: Mutex<Vec<(u16, u64)>>,
    /// Snapshots received: payload bytes, messages, malformed ones.
    bytes: AtomicU64,
    messages: AtomicU64,
    malformed: AtomicU64,
    /// The newest snapshot received.
    latest: Mutex<Option<Arc<Snapshot>>>,
    /// Key states published: their seq and when, newest last (at most [`SENT_KEPT`]).
    sent: Mutex<VecDeque<(u32, Instant)>>,
    /// Key state published → first snapshot showing it applied, ms (while measuring).
    latencies: Mutex<Vec<f64>>,
    keys_bytes: AtomicU64,
    keys_messages: AtomicU64,
    hellos: AtomicU64,
    hello_failures: AtomicU64,
    /// The slowest hello's answer, µs.
    hello_us_max: AtomicU64,
}

impl FakeEdge {
    /// One request and its answer.
    async fn ask(&self, _subjects: &Subjects, ask: &Ask) -> Result<Answer> {
        Ok(self.asker.ask(ask).await?)
    }

    fn hello(&self, data: [u8; 32]) -> Ask {
        Ask::Hello {
            data,
            edge: self.id,
            addresses: Vec::new(),
            vehicles: lock(&self.vehicles).clone(),
        }
    }
}

/// The keys vehicle `v` holds at state `seq`: Up, and a turn left or right for 1.5 s of
/// every 6 (each vehicle at its own phase).
fn held(v: u16, seq: u32) -> Held {
    let phase = (seq.wrapping_add(u32::from(v).wrapping_mul(97)) / 150) % 4;
    match phase {
        1 => Held::UP.union(Held::LEFT),
        3 => Held::UP.union(Held::RIGHT),
        _ => Held::UP,
    }
}

/// Vehicle `v`'s newest `history` states up to `seq`, newest first (as a viewer sends).
fn states(v: u16, seq: u32, history: u8) -> Vec<KeyState> {
    (0..u32::from(history))
        .map_while(|k| seq.checked_sub(k).filter(|s| *s >= 1))
        .map(|s| {
            let now = held(v, s);
            let before = if s > 1 { held(v, s - 1) } else { Held::NONE };
            KeyState {
                seq: s,
                held: now.bits(),
                pressed: now.without(before).bits(),
            }
        })
        .collect()
}

/// Publishes one `Keys` batch (or several, past `MAX_BATCH` drivers) every 10 ms.
async fn drive(edge: Arc<FakeEdge>, subjects: Subjects, history: u8) {
    let mut tick = tokio::time::interval(KEYS_EVERY);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut seq = 0u32;
    loop {
        tick.tick().await;
        seq += 1;
        let vehicles = lock(&edge.vehicles).clone();
        for chunk in vehicles.chunks(MAX_BATCH) {
            let batch = Keys {
                drivers: chunk
                    .iter()
                    .map(|&(vehicle, _)| DriverKeys {
                        vehicle,
                        states: states(vehicle, seq, history),
                    })
                    .collect(),
            };
            let voice = edge.asker.voice();
            let (_, payload) = voice.say(Kind::Keys, edge.asker.world(), 0, &batch);
            edge.keys_bytes
                .fetch_add(payload.len() as u64, Ordering::Relaxed);
            edge.keys_messages.fetch_add(1, Ordering::Relaxed);
            if let Err(e) = edge.client.publish(subjects.keys.clone(), payload).await {
                tracing::warn!("publishing key states: {e}");
            }
        }
        let mut sent = lock(&edge.sent);
        sent.push_back((seq, Instant::now()));
        while sent.len() > SENT_KEPT {
            sent.pop_front();
        }
    }
}

/// Says hello every [`BEAT`], counting failures and the slowest answer.
async fn beat(edge: Arc<FakeEdge>, subjects: Subjects, data: [u8; 32]) {
    let mut tick = tokio::time::interval(BEAT);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tick.tick().await;
        let started = Instant::now();
        let ok = matches!(
            edge.ask(&subjects, &edge.hello(data)).await,
            Ok(Answer::Hello { data: d, .. }) if d == data
        );
        let us = started.elapsed().as_micros().try_into().unwrap_or(u64::MAX);
        edge.hellos.fetch_add(1, Ordering::Relaxed);
        edge.hello_us_max.fetch_max(us, Ordering::Relaxed);
        if !ok {
            edge.hello_failures.fetch_add(1, Ordering::Relaxed);
        }
    }
}

/// Counts (and decodes) the world's snapshots; while `measuring`, notes when the first
/// vehicle's newest key states show applied.
async fn watch(mut sub: async_nats::Subscriber, edge: Arc<FakeEdge>, measuring: Arc<AtomicBool>) {
    let mut applied_before = 0u32;
    let counts = Arc::new(RefusedCounts::default());
    let mut ear = Ear::new(Kind::Snapshot, edge.key.as_ref(), counts, "snapshot");
    while let Some(msg) = sub.next().await {
        edge.bytes
            .fetch_add(msg.payload.len() as u64, Ordering::Relaxed);
        edge.messages.fetch_add(1, Ordering::Relaxed);
        let Some((_, snap)) = ear.hear::<Snapshot>(&msg.payload) else {
            edge.malformed.fetch_add(1, Ordering::Relaxed);
            continue;
        };
        let snap = Arc::new(snap);
        let probe = lock(&edge.vehicles).first().map(|v| v.0);
        let applied = probe.and_then(|p| snap.applied.iter().find(|(v, _)| *v == p));
        if let Some(&(_, seq)) = applied
            && seq > applied_before
        {
            if measuring.load(Ordering::Relaxed) {
                let now = Instant::now();
                let sent = lock(&edge.sent);
                let newly = sent
                    .iter()
                    .filter(|(s, _)| *s > applied_before && *s <= seq);
                let ms: Vec<f64> = newly
                    .map(|(_, at)| now.duration_since(*at).as_secs_f64() * 1e3)
                    .collect();
                lock(&edge.latencies).extend(ms);
            }
            applied_before = seq;
        }
        *lock(&edge.latest) = Some(snap);
    }
}

/// CPU seconds (user + system, every thread) process `pid` has used.
fn cpu_seconds(pid: u32) -> Result<f64> {
    let path = format!("/proc/{pid}/stat");
    let text = std::fs::read_to_string(&path).with_context(|| format!("reading {path}"))?;
    // After the command's closing parenthesis: state is field 3, utime 14, stime 15.
    let fields: Vec<&str> = text
        .rsplit_once(')')
        .map(|(_, rest)| rest.split_whitespace().collect())
        .with_context(|| format!("{path}: no command name"))?;
    let field = |i: usize| -> Result<u64> {
        fields
            .get(i)
            .with_context(|| format!("{path}: field {} missing", i + 3))?
            .parse::<u64>()
            .with_context(|| format!("{path}: field {}", i + 3))
    };
    Ok((field(11)? + field(12)?) as f64 / clock_ticks())
}

/// Clock ticks a second, the unit of `/proc/PID/stat`'s times (`getconf CLK_TCK`).
fn clock_ticks() -> f64 {
    // SAFETY: sysconf reads a constant of the C library; it has no preconditions.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    if hz > 0 { hz as f64 } else { 100.0 }
}

/// What the window starts or ends with.
struct Mark {
    at: Instant,
    bytes: Vec<u64>,
    messages: Vec<u64>,
    tick: u64,
    /// Positions of the generator's vehicles in the newest snapshot.
    positions: Vec<(u16, f64, f64)>,
    cpu: Vec<f64>,
    own_cpu: f64,
}

fn mark(edges: &[Arc<FakeEdge>], pids: &[(String, u32)]) -> Result<Mark> {
    let at = Instant::now();
    let latest = lock(&edges[0].latest).clone();
    let ours: Vec<u16> = edges.iter().flat_map(|e| ids(e)).collect();
    let positions = latest.as_ref().map_or_else(Vec::new, |s| {
        s.vehicles
            .iter()
            .filter(|v| ours.contains(&v.id))
            .map(|v| (v.id, v.x, v.z))
            .collect()
    });
    Ok(Mark {
        at,
        bytes: edges
            .iter()
            .map(|e| e.bytes.load(Ordering::Relaxed))
            .collect(),
        messages: edges
            .iter()
            .map(|e| e.messages.load(Ordering::Relaxed))
            .collect(),
        tick: latest.map_or(0, |s| s.tick),
        positions,
        cpu: pids
            .iter()
            .map(|(_, pid)| cpu_seconds(*pid))
            .collect::<Result<_>>()?,
        own_cpu: cpu_seconds(std::process::id())?,
    })
}

pub(crate) fn bus_load(args: BusLoadArgs) -> Result<()> {
    let subjects = Subjects::of(&args.bus.world).context("--world")?;
    let expected = match &args.data {
        Some(dir) => {
            let served = super::served::open_served(dir)?;
            Some(super::served::data_hash(
                dir,
                &served.terrain,
                &served.report,
            )?)
        }
        None => None,
    };
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    runtime.block_on(run(args, subjects, expected))
}

async fn run(args: BusLoadArgs, subjects: Subjects, expected: Option<[u8; 32]>) -> Result<()> {
    let mut edges = Vec::new();
    let mut tasks = Vec::new();
    let measuring = Arc::new(AtomicBool::new(false));
    for i in 0..args.edges {
        let bus = args.bus.options(&format!("roam-server bus-load {i}"))?;
        let client = bus.connect().await?;
        let id = roam_server::net::bus::random_id();
        let key = bus.key();
        let counts = Arc::new(RefusedCounts::default());
        let asker = Asker::start(client.clone(), &subjects, key.as_ref(), id, counts).await?;
        let edge = Arc::new(FakeEdge {
            id,
            client,
            asker,
            key,
            vehicles: Mutex::new(Vec::new()),
            bytes: AtomicU64::new(0),
            messages: AtomicU64::new(0),
            malformed: AtomicU64::new(0),
            latest: Mutex::new(None),
            sent: Mutex::new(VecDeque::new()),
            latencies: Mutex::new(Vec::new()),
            keys_bytes: AtomicU64::new(0),
            keys_messages: AtomicU64::new(0),
            hellos: AtomicU64::new(0),
            hello_failures: AtomicU64::new(0),
            hello_us_max: AtomicU64::new(0),
        });
        let sub = edge
            .client
            .subscribe(subjects.snapshots.clone())
            .await
            .context("subscribing to the snapshots")?;
        tasks.push(tokio::spawn(watch(sub, edge.clone(), measuring.clone())));
        edges.push(edge);
    }
    let (data, world) = world_data(&edges[0], &subjects, expected).await?;
    // Their requests and key states are for this world process from now on.
    for e in &edges {
        e.asker.set_world(world);
    }
    let beats: Vec<_> = edges
        .iter()
        .map(|e| tokio::spawn(beat(e.clone(), subjects.clone(), data)))
        .collect();

    let joining = Instant::now();
    join_all(&edges, &subjects, args.vehicles).await?;
    let join_s = joining.elapsed().as_secs_f64();
    for e in &edges {
        tasks.push(tokio::spawn(drive(
            e.clone(),
            subjects.clone(),
            args.history,
        )));
    }
    wait_seen(&edges, usize::from(args.vehicles)).await?;
    tokio::time::sleep(Duration::from_secs_f64(args.warmup)).await;

    let start = mark(&edges, &args.cpu_pid)?;
    let keys_before: (u64, u64) = keys_sent(&edges);
    measuring.store(true, Ordering::Relaxed);
    tokio::time::sleep(Duration::from_secs_f64(args.seconds)).await;
    measuring.store(false, Ordering::Relaxed);
    let end = mark(&edges, &args.cpu_pid)?;
    let keys_after = keys_sent(&edges);

    for t in &tasks {
        t.abort();
    }
    let leaves_failed = leave_all(&edges, &subjects).await;
    for b in &beats {
        b.abort();
    }
    for e in &edges {
        let _ = e.client.flush().await;
    }
    let out = report(
        &args,
        &edges,
        &start,
        &end,
        (keys_before, keys_after),
        join_s,
        leaves_failed,
    );
    say!("{out}");
    Ok(())
}

/// A fake edge's vehicle ids.
fn ids(e: &FakeEdge) -> Vec<u16> {
    lock(&e.vehicles).iter().map(|v| v.0).collect()
}

/// The world's data hash, from its answer to a hello (checked against `expected`).
async fn world_data(
    edge: &FakeEdge,
    subjects: &Subjects,
    expected: Option<[u8; 32]>,
) -> Result<([u8; 32], u64)> {
    let deadline = Instant::now() + Duration::from_secs(30);
    let hello = Ask::Hello {
        data: expected.unwrap_or([0; 32]),
        edge: edge.id,
        addresses: Vec::new(),
        vehicles: Vec::new(),
    };
    let (data, world) = loop {
        match edge.ask(subjects, &hello).await {
            Ok(Answer::Hello { data, world, .. }) => break (data, world),
            Ok(other) => bail!("the world answered a hello with {other:?}"),
            Err(e) if Instant::now() >= deadline => {
                return Err(e.context("no world answered on NATS in 30 s"));
            }
            Err(_) => tokio::time::sleep(Duration::from_millis(200)).await,
        }
    };
    if let Some(ours) = expected
        && ours != data
    {
        bail!(
            "the world serves the data set {}, --data is {}",
            roam_link::tls::hex(&data),
            roam_link::tls::hex(&ours)
        );
    }
    Ok((data, world))
}

/// Joins `n` vehicles, vehicle `j` through fake edge `j % E`.
async fn join_all(edges: &[Arc<FakeEdge>], subjects: &Subjects, n: u16) -> Result<()> {
    let permits = Arc::new(tokio::sync::Semaphore::new(JOINING));
    let mut set = tokio::task::JoinSet::new();
    for j in 0..usize::from(n) {
        let edge = edges[j % edges.len()].clone();
        let (subjects, permits) = (subjects.clone(), permits.clone());
        set.spawn(async move {
            let _permit = permits.acquire_owned().await?;
            let mut last = anyhow::anyhow!("not asked");
            for _ in 0..TRIES {
                match edge.ask(&subjects, &Ask::Join).await {
                    Ok(Answer::Joined { vehicle, claim, .. }) => {
                        lock(&edge.vehicles).push((vehicle, claim));
                        return Ok(());
                    }
                    Ok(Answer::Refused { reason }) => bail!("a join refused: {reason}"),
                    Ok(other) => bail!("the world answered a join with {other:?}"),
                    Err(e) => last = e,
                }
            }
            Err(last.context(format!("a join, asked {TRIES} times")))
        });
    }
    while let Some(joined) = set.join_next().await {
        joined.context("a join task")??;
    }
    for e in edges {
        lock(&e.vehicles).sort_unstable();
    }
    Ok(())
}

/// Waits until a snapshot lists every vehicle joined.
async fn wait_seen(edges: &[Arc<FakeEdge>], n: usize) -> Result<()> {
    let ours: Vec<u16> = edges.iter().flat_map(|e| ids(e)).collect();
    let deadline = Instant::now() + SEEN_WAIT;
    loop {
        let seen = lock(&edges[0].latest).as_ref().map_or(0, |s| {
            s.vehicles.iter().filter(|v| ours.contains(&v.id)).count()
        });
        if seen == n {
            return Ok(());
        }
        if Instant::now() >= deadline {
            bail!("after {SEEN_WAIT:?} the snapshots list {seen} of the {n} vehicles joined");
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Key-state bytes and messages published so far, every fake edge's.
fn keys_sent(edges: &[Arc<FakeEdge>]) -> (u64, u64) {
    edges.iter().fold((0, 0), |(b, m), e| {
        (
            b + e.keys_bytes.load(Ordering::Relaxed),
            m + e.keys_messages.load(Ordering::Relaxed),
        )
    })
}

/// Leaves every vehicle; the leaves not answered.
async fn leave_all(edges: &[Arc<FakeEdge>], subjects: &Subjects) -> usize {
    let permits = Arc::new(tokio::sync::Semaphore::new(JOINING));
    let mut set = tokio::task::JoinSet::new();
    for edge in edges {
        for (vehicle, claim) in lock(&edge.vehicles).clone() {
            let (edge, subjects, permits) = (edge.clone(), subjects.clone(), permits.clone());
            set.spawn(async move {
                let Ok(_permit) = permits.acquire_owned().await else {
                    return false;
                };
                for _ in 0..TRIES {
                    if let Ok(Answer::Done) =
                        edge.ask(&subjects, &Ask::Leave { vehicle, claim }).await
                    {
                        return true;
                    }
                }
                false
            });
        }
    }
    let mut failed = 0;
    while let Some(left) = set.join_next().await {
        if !matches!(left, Ok(true)) {
            failed += 1;
        }
    }
    failed
}

/// The JSON line: `vehicles`, `edges`, `history`, `seconds` (the window, measured);
/// `ticks` (world ticks made in the window, from the snapshots' `tick`: `tick_first` to
/// `tick_last`) and `ticks_per_s`; `snapshots_per_s` (received, mean over the fake
/// edges), `snapshots_received_min` (the fewest any fake edge got in the window, against
/// `ticks`); `snapshot_bytes_per_s_per_edge` (payload bytes, mean over the fake edges),
/// `snapshot_bytes_mean` (per snapshot), `snapshots_malformed`; `keys_bytes_per_s` and
/// `keys_messages_per_s` (published, all fake edges); `vehicles_seen` (the generator's
/// vehicles in the last snapshot), `vehicles_moved` (of them, those more than 1 m from
/// where they were at the window's start), `speed_mean`; `keys_to_snapshot_ms_median`
/// and `_p99`; `join_s` (all joins), `leaves_failed`, `hellos`, `hello_failures`,
/// `hello_ms_max`; per `--cpu-pid` name: `cpu_s` (CPU seconds over the window),
/// `cpu_us_per_tick` and `cpu_share` (÷ the window's seconds); `generator_cpu_share`.
fn report(
    args: &BusLoadArgs,
    edges: &[Arc<FakeEdge>],
    start: &Mark,
    end: &Mark,
    keys: ((u64, u64), (u64, u64)),
    join_s: f64,
    leaves_failed: usize,
) -> serde_json::Value {
    let wall = end.at.duration_since(start.at).as_secs_f64().max(1e-9);
    let ticks = end.tick.saturating_sub(start.tick);
    let n = edges.len() as f64;
    let got: Vec<u64> = (0..edges.len())
        .map(|i| end.messages[i] - start.messages[i])
        .collect();
    let bytes: u64 = (0..edges.len())
        .map(|i| end.bytes[i] - start.bytes[i])
        .sum();
    let messages: u64 = got.iter().sum();
    let moved = end
        .positions
        .iter()
        .filter(|(id, x, z)| {
            start
                .positions
                .iter()
                .find(|(s, ..)| s == id)
                .is_some_and(|(_, x0, z0)| (x - x0).hypot(z - z0) > 1.0)
        })
        .count();
    let latest = lock(&edges[0].latest).clone();
    let ours: Vec<u16> = edges.iter().flat_map(|e| ids(e)).collect();
    let speeds: Vec<f64> = latest.as_ref().map_or_else(Vec::new, |s| {
        s.vehicles
            .iter()
            .filter(|v| ours.contains(&v.id))
            .map(|v| v.speed)
            .collect()
    });
    let latencies: Vec<f64> = edges
        .iter()
        .flat_map(|e| lock(&e.latencies).clone())
        .collect();
    let sum = |f: &dyn Fn(&FakeEdge) -> u64| edges.iter().map(|e| f(e)).sum::<u64>();
    let hello_us_max = edges
        .iter()
        .map(|e| e.hello_us_max.load(Ordering::Relaxed))
        .max()
        .unwrap_or(0);
    let round = |x: f64, places: i32| {
        let k = 10f64.powi(places);
        (x * k).round() / k
    };
    let mut cpu_s = serde_json::Map::new();
    let mut per_tick = serde_json::Map::new();
    let mut share = serde_json::Map::new();
    for (i, (name, _)) in args.cpu_pid.iter().enumerate() {
        let s = end.cpu[i] - start.cpu[i];
        cpu_s.insert(name.clone(), round(s, 3).into());
        per_tick.insert(name.clone(), round(s * 1e6 / ticks.max(1) as f64, 1).into());
        share.insert(name.clone(), round(s / wall, 3).into());
    }
    serde_json::json!({
        "vehicles": args.vehicles,
        "edges": args.edges,
        "history": args.history,
        "seconds": round(wall, 3),
        "ticks": ticks,
        "tick_first": start.tick,
        "tick_last": end.tick,
        "ticks_per_s": round(ticks as f64 / wall, 2),
        "snapshots_per_s": round(messages as f64 / n / wall, 2),
        "snapshots_received_min": got.iter().min().copied().unwrap_or(0),
        "snapshot_bytes_per_s_per_edge": round(bytes as f64 / n / wall, 0),
        "snapshot_bytes_mean": round(bytes as f64 / messages.max(1) as f64, 1),
        "snapshots_malformed": sum(&|e| e.malformed.load(Ordering::Relaxed)),
        "keys_bytes_per_s": round((keys.1.0 - keys.0.0) as f64 / wall, 0),
        "keys_messages_per_s": round((keys.1.1 - keys.0.1) as f64 / wall, 2),
        "vehicles_seen": speeds.len(),
        "vehicles_moved": moved,
        "speed_mean": round(speeds.iter().sum::<f64>() / speeds.len().max(1) as f64, 2),
        "keys_to_snapshot_ms_median": round(quantile(&latencies, 0.5), 2),
        "keys_to_snapshot_ms_p99": round(quantile(&latencies, 0.99), 2),
        "keys_to_snapshot_samples": latencies.len(),
        "join_s": round(join_s, 3),
        "leaves_failed": leaves_failed,
        "hellos": sum(&|e| e.hellos.load(Ordering::Relaxed)),
        "hello_failures": sum(&|e| e.hello_failures.load(Ordering::Relaxed)),
        "hello_ms_max": round(hello_us_max as f64 / 1e3, 2),
        "cpu_s": cpu_s,
        "cpu_us_per_tick": per_tick,
        "cpu_share": share,
        "generator_cpu_share": round((end.own_cpu - start.own_cpu) / wall, 3),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A driver's entry is a viewer's datagram: newest first, seq falling by one, never
    /// below 1; a key counts as pressed only in the state it goes down in; Up always.
    #[test]
    fn states_are_a_viewers_datagram() {
        let s = states(5, 10, 8);
        let seqs: Vec<u32> = s.iter().map(|k| k.seq).collect();
        assert_eq!(seqs, (3..=10).rev().collect::<Vec<u32>>());
        assert_eq!(states(5, 3, 8).len(), 3);
        for seq in 2..2000 {
            let [now] = states(7, seq, 1)[..] else {
                panic!("one state asked, one given")
            };
            let before = held(7, seq - 1);
            assert!(held(7, seq).contains(Held::UP));
            assert_eq!(now.pressed, held(7, seq).without(before).bits());
        }
    }

    #[test]
    fn cpu_pids_are_named() {
        assert_eq!(name_pid("world=42"), Ok(("world".into(), 42)));
        assert!(name_pid("world").is_err());
        assert!(name_pid("=42").is_err());
        assert!(name_pid("a b=42").is_err());
        assert!(name_pid("world=-1").is_err());
    }
}
