//! A seeded, lossy UDP relay on loopback: it stands between QUIC viewers and a server and
//! delays, reorders (jitter), rate-limits and drops datagrams, each direction by its own
//! [`Direction`] settings, deterministically for a given seed and datagram order.
//!
//! ```text
//! viewer ──► relay.addr() ──(to_server: loss, delay, jitter)──► upstream socket per viewer ──► server
//! viewer ◄── relay.addr() ◄─(to_client: loss, delay, jitter)─── upstream socket per viewer ◄── server
//! ```
//!
//! [`Relay::cut`] black-holes every datagram both ways (as a dropped Wi-Fi connection does) until
//! [`Relay::restore`]; datagrams already in a delay line still arrive. The flows and their
//! sockets stay, so a viewer that sends again after the cut reaches the server from the
//! same address.
//!
//! Every client source address gets an upstream socket of its own, so the server sees
//! several viewers as several peers. Queues are bounded ([`MAX_QUEUED`] datagrams per
//! direction, more are dropped and counted), flows idle for [`FLOW_IDLE`] are forgotten,
//! and dropping the [`Relay`] stops every task it started.

use crate::fixtures::SplitMix64;
use std::collections::{BinaryHeap, HashMap};
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

use anyhow::{Context, Result};
use roam_protocol::sync::lock;
use tokio::net::UdpSocket;
use tokio::sync::mpsc;
use tokio::task::{JoinHandle, JoinSet};
use tokio::time::Instant;

/// Datagrams that may wait in one direction's delay line; more are dropped.
pub const MAX_QUEUED: usize = 4096;
/// Client flows (source addresses) relayed at once; datagrams from more are dropped.
pub const MAX_FLOWS: usize = 1024;
/// A flow with no datagram either way for this long is forgotten (its socket closed).
pub const FLOW_IDLE: Duration = Duration::from_secs(60);
/// The largest datagram relayed (a UDP payload's limit).
const MAX_DATAGRAM: usize = 65_535;

/// What happens to datagrams going one way.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Direction {
    /// Every datagram is delivered this much later...
    pub delay: Duration,
    /// ...plus a uniform random amount in `[0, jitter)` (so datagrams may be reordered).
    pub jitter: Duration,
    /// The probability that a datagram is dropped (`0.0..=1.0`).
    pub loss: f64,
    /// A bottleneck: datagrams leave one after another at this many bytes a second (queued
    /// behind each other, before the delay). `None`: no limit.
    pub rate_bytes_per_s: Option<u64>,
}

impl Direction {
    /// A perfect direction: no delay, jitter or loss.
    pub const NONE: Direction = Direction {
        delay: Duration::ZERO,
        jitter: Duration::ZERO,
        loss: 0.0,
        rate_bytes_per_s: None,
    };
}

/// Both directions' settings and the seed of the drops and jitter.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RelayConfig {
    /// Viewer → server.
    pub to_server: Direction,
    /// Server → viewer.
    pub to_client: Direction,
    pub seed: u64,
}

impl RelayConfig {
    /// The same settings both ways.
    pub fn symmetric(direction: Direction, seed: u64) -> RelayConfig {
        RelayConfig {
            to_server: direction,
            to_client: direction,
            seed,
        }
    }
}

/// What one direction has done so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DirectionStats {
    /// Datagrams delivered.
    pub forwarded: u64,
    /// Datagrams dropped by the loss setting.
    pub lost: u64,
    /// Datagrams dropped because the delay line was full ([`MAX_QUEUED`]), there were too
    /// many flows, or the send failed.
    pub overflowed: u64,
    /// Datagrams dropped while the relay was cut ([`Relay::cut`]).
    pub cut: u64,
    /// Bytes delivered.
    pub bytes: u64,
}

impl DirectionStats {
    /// Every datagram dropped, for whatever reason.
    pub fn dropped(&self) -> u64 {
        self.lost + self.overflowed + self.cut
    }
}

/// Both directions' counters.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RelayStats {
    pub to_server: DirectionStats,
    pub to_client: DirectionStats,
}

impl std::fmt::Display for RelayStats {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let one = |d: &DirectionStats| {
            format!(
                "{} forwarded ({} bytes), {} lost, {} overflowed, {} cut",
                d.forwarded, d.bytes, d.lost, d.overflowed, d.cut
            )
        };
        write!(
            f,
            "to server: {}; to client: {}",
            one(&self.to_server),
            one(&self.to_client)
        )
    }
}

#[derive(Default)]
struct Counters {
    forwarded: AtomicU64,
    lost: AtomicU64,
    overflowed: AtomicU64,
    cut: AtomicU64,
    bytes: AtomicU64,
}

impl Counters {
    fn snapshot(&self) -> DirectionStats {
        DirectionStats {
            forwarded: self.forwarded.load(Ordering::Relaxed),
            lost: self.lost.load(Ordering::Relaxed),
            overflowed: self.overflowed.load(Ordering::Relaxed),
            cut: self.cut.load(Ordering::Relaxed),
            bytes: self.bytes.load(Ordering::Relaxed),
        }
    }

    fn overflow(&self) {
        self.overflowed.fetch_add(1, Ordering::Relaxed);
    }
}

/// One direction's decisions: which datagrams are dropped, and when the others leave.
struct Shaper {
    direction: Direction,
    rng: SplitMix64,
    /// With a rate limit: when the bottleneck is free again.
    free_at: Option<Instant>,
}

impl Shaper {
    fn new(direction: Direction, seed: u64) -> Shaper {
        Shaper {
            direction,
            rng: SplitMix64::new(seed),
            free_at: None,
        }
    }

    /// When a datagram of `len` bytes offered at `now` is delivered, or `None` if it is
    /// lost. Exactly two draws per datagram, so the drops of a seed do not depend on the
    /// delay settings.
    fn schedule(&mut self, now: Instant, len: usize) -> Option<Instant> {
        let lose = self.rng.unit() < self.direction.loss;
        let jitter = self.direction.jitter.mul_f64(self.rng.unit());
        if lose {
            return None;
        }
        let mut leaves = now;
        if let Some(rate) = self.direction.rate_bytes_per_s.filter(|&r| r > 0) {
            let start = self.free_at.map_or(now, |f| f.max(now));
            leaves = start + Duration::from_secs_f64(len as f64 / rate as f64);
            self.free_at = Some(leaves);
        }
        Some(leaves + self.direction.delay + jitter)
    }
}

/// A datagram in a delay line.
struct Pending {
    due: Instant,
    /// Arrival order: equal due times leave in the order they came.
    order: u64,
    bytes: Vec<u8>,
    socket: Arc<UdpSocket>,
    to: SocketAddr,
}

impl PartialEq for Pending {
    fn eq(&self, other: &Self) -> bool {
        (self.due, self.order) == (other.due, other.order)
    }
}
impl Eq for Pending {}
impl PartialOrd for Pending {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Pending {
    /// Reversed: the max-heap pops the earliest.
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        (other.due, other.order).cmp(&(self.due, self.order))
    }
}

/// The sending side of one direction's delay line: shapes each datagram and queues it.
#[derive(Clone)]
struct Line {
    shaper: Arc<std::sync::Mutex<Shaper>>,
    queue: mpsc::Sender<Pending>,
    counters: Arc<Counters>,
    order: Arc<AtomicU64>,
    /// Set while the relay is cut: every datagram is dropped.
    cut: Arc<AtomicBool>,
}

impl Line {
    fn offer(&self, bytes: &[u8], socket: &Arc<UdpSocket>, to: SocketAddr) {
        if self.cut.load(Ordering::Acquire) {
            self.counters.cut.fetch_add(1, Ordering::Relaxed);
            return;
        }
        let now = Instant::now();
        let due = lock(&self.shaper).schedule(now, bytes.len());
        let Some(due) = due else {
            self.counters.lost.fetch_add(1, Ordering::Relaxed);
            return;
        };
        let pending = Pending {
            due,
            order: self.order.fetch_add(1, Ordering::Relaxed),
            bytes: bytes.to_vec(),
            socket: socket.clone(),
            to,
        };
        if self.queue.try_send(pending).is_err() {
            self.counters.overflow();
        }
    }
}

/// Sends each queued datagram when it is due, until every [`Line`] is gone.
async fn deliver(mut queue: mpsc::Receiver<Pending>, counters: Arc<Counters>) {
    let mut heap: BinaryHeap<Pending> = BinaryHeap::new();
    loop {
        let next_due = heap.peek().map(|p| p.due);
        tokio::select! {
            got = queue.recv() => match got {
                Some(p) if heap.len() < MAX_QUEUED => heap.push(p),
                Some(_) => counters.overflow(),
                None => return,
            },
            () = sleep_until(next_due) => {
                let now = Instant::now();
                while heap.peek().is_some_and(|p| p.due <= now) {
                    let Some(p) = heap.pop() else { break };
                    match p.socket.send_to(&p.bytes, p.to).await {
                        Ok(_) => {
                            counters.forwarded.fetch_add(1, Ordering::Relaxed);
                            counters.bytes.fetch_add(p.bytes.len() as u64, Ordering::Relaxed);
                        }
                        Err(_) => counters.overflow(),
                    }
                }
            }
        }
    }
}

async fn sleep_until(due: Option<Instant>) {
    match due {
        Some(due) => tokio::time::sleep_until(due).await,
        None => std::future::pending().await,
    }
}

/// A running relay; dropping it stops it.
pub struct Relay {
    addr: SocketAddr,
    upstream: SocketAddr,
    to_server: Arc<Counters>,
    to_client: Arc<Counters>,
    cut: Arc<AtomicBool>,
    tasks: Vec<JoinHandle<()>>,
}

impl Relay {
    /// Starts relaying datagrams between clients that send to [`Relay::addr`] (on
    /// `127.0.0.1`, an ephemeral port) and `upstream`.
    pub async fn start(upstream: SocketAddr, config: RelayConfig) -> Result<Relay> {
        Relay::start_on(
            "127.0.0.1:0".parse().context("a loopback address")?,
            upstream,
            config,
        )
        .await
    }

    /// As [`Relay::start`], listening on `listen`.
    pub async fn start_on(
        listen: SocketAddr,
        upstream: SocketAddr,
        config: RelayConfig,
    ) -> Result<Relay> {
        for (name, d) in [
            ("to_server", config.to_server),
            ("to_client", config.to_client),
        ] {
            anyhow::ensure!(
                (0.0..=1.0).contains(&d.loss),
                "{name}: loss {} is not a probability",
                d.loss
            );
        }
        let socket = UdpSocket::bind(listen)
            .await
            .with_context(|| format!("listening on {listen}"))?;
        let addr = socket
            .local_addr()
            .with_context(|| format!("the address bound for {listen}"))?;
        let socket = Arc::new(socket);
        let (to_server, to_client) = (Arc::new(Counters::default()), Arc::new(Counters::default()));
        let cut = Arc::new(AtomicBool::new(false));
        let line = |direction: Direction, seed: u64, counters: &Arc<Counters>| {
            let (tx, rx) = mpsc::channel(MAX_QUEUED);
            let line = Line {
                shaper: Arc::new(std::sync::Mutex::new(Shaper::new(direction, seed))),
                queue: tx,
                counters: counters.clone(),
                order: Arc::new(AtomicU64::new(0)),
                cut: cut.clone(),
            };
            (line, tokio::spawn(deliver(rx, counters.clone())))
        };
        // Each direction draws from its own stream, so one's traffic does not shift the
        // other's drops.
        let (up, up_task) = line(config.to_server, config.seed, &to_server);
        let (down, down_task) = line(
            config.to_client,
            config.seed ^ 0x5851_f42d_4c95_7f2d,
            &to_client,
        );
        let accept = tokio::spawn(accept(socket, upstream, up, down));
        Ok(Relay {
            addr,
            upstream,
            to_server,
            to_client,
            cut,
            tasks: vec![accept, up_task, down_task],
        })
    }

    /// Where clients send.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Where datagrams go.
    pub fn upstream(&self) -> SocketAddr {
        self.upstream
    }

    /// From now on, every datagram either way is dropped (counted in
    /// [`DirectionStats::cut`]), until [`Relay::restore`].
    pub fn cut(&self) {
        self.cut.store(true, Ordering::Release);
    }

    /// Datagrams go through again.
    pub fn restore(&self) {
        self.cut.store(false, Ordering::Release);
    }

    /// Whether the relay is cut.
    pub fn is_cut(&self) -> bool {
        self.cut.load(Ordering::Acquire)
    }

    /// The counters so far.
    pub fn stats(&self) -> RelayStats {
        RelayStats {
            to_server: self.to_server.snapshot(),
            to_client: self.to_client.snapshot(),
        }
    }
}

impl Relay {
    /// Stops relaying and returns once every task has ended and its sockets are closed.
    pub async fn stop(mut self) {
        for t in std::mem::take(&mut self.tasks) {
            t.abort();
            let _ = t.await;
        }
    }
}

impl Drop for Relay {
    fn drop(&mut self) {
        // The accept task owns the flows' tasks (a JoinSet): aborting it aborts them.
        for t in &self.tasks {
            t.abort();
        }
    }
}

/// A client's flow: its upstream socket, and when it last saw a datagram.
struct Flow {
    socket: Arc<UdpSocket>,
    last: Arc<std::sync::Mutex<Instant>>,
    task: tokio::task::AbortHandle,
}

/// Reads from clients, opening an upstream socket per client, and forgets idle flows.
async fn accept(listen: Arc<UdpSocket>, upstream: SocketAddr, up: Line, down: Line) {
    let mut flows: HashMap<SocketAddr, Flow> = HashMap::new();
    let mut tasks = JoinSet::new();
    let mut buf = vec![0u8; MAX_DATAGRAM];
    let mut sweep = tokio::time::interval(FLOW_IDLE / 4);
    sweep.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        let (len, from) = tokio::select! {
            r = listen.recv_from(&mut buf) => match r {
                Ok(r) => r,
                // A port unreachable from an earlier send (ICMP), or a short buffer: the
                // socket itself still works (a pause, so a lasting error cannot spin).
                Err(_) => {
                    tokio::time::sleep(Duration::from_millis(1)).await;
                    continue;
                }
            },
            _ = sweep.tick() => {
                let now = Instant::now();
                flows.retain(|_, f| {
                    let idle = now - *lock(&f.last) > FLOW_IDLE;
                    if idle {
                        f.task.abort();
                    }
                    !idle
                });
                while tasks.try_join_next().is_some() {}
                continue;
            }
        };
        if !flows.contains_key(&from) {
            if flows.len() >= MAX_FLOWS {
                up.counters.overflow();
                continue;
            }
            let bind: SocketAddr = if upstream.is_ipv4() {
                SocketAddr::from(([127, 0, 0, 1], 0))
            } else {
                SocketAddr::from((std::net::Ipv6Addr::LOCALHOST, 0))
            };
            let Ok(socket) = UdpSocket::bind(bind).await else {
                up.counters.overflow();
                continue;
            };
            let socket = Arc::new(socket);
            let last = Arc::new(std::sync::Mutex::new(Instant::now()));
            let task = tasks.spawn(back(
                socket.clone(),
                upstream,
                listen.clone(),
                from,
                down.clone(),
                last.clone(),
            ));
            flows.insert(from, Flow { socket, last, task });
        }
        let Some(flow) = flows.get(&from) else {
            continue;
        };
        *lock(&flow.last) = Instant::now();
        up.offer(&buf[..len], &flow.socket, upstream);
    }
}

/// A flow's way back: what the server sends to the flow's upstream socket goes to the
/// client (anything from elsewhere is ignored).
async fn back(
    socket: Arc<UdpSocket>,
    upstream: SocketAddr,
    listen: Arc<UdpSocket>,
    client: SocketAddr,
    down: Line,
    last: Arc<std::sync::Mutex<Instant>>,
) {
    let mut buf = vec![0u8; MAX_DATAGRAM];
    loop {
        let Ok((len, from)) = socket.recv_from(&mut buf).await else {
            // As in `accept`: the socket still works; a pause so a lasting error cannot spin.
            tokio::time::sleep(Duration::from_millis(1)).await;
            continue;
        };
        if from != upstream {
            continue;
        }
        *lock(&last) = Instant::now();
        down.offer(&buf[..len], &listen, client);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn splitmix_is_seeded_and_uniform() {
        let draws = |seed| {
            let mut r = SplitMix64::new(seed);
            (0..4).map(|_| r.next_u64()).collect::<Vec<_>>()
        };
        assert_eq!(draws(1), draws(1));
        assert_ne!(draws(1), draws(2));
        let mut r = SplitMix64::new(7);
        let n = 100_000;
        let mean = (0..n).map(|_| r.unit()).sum::<f64>() / f64::from(n);
        assert!((mean - 0.5).abs() < 0.01, "{mean}");
    }

    #[test]
    fn shaper_drops_about_the_loss_and_is_deterministic() {
        let d = Direction {
            delay: Duration::from_millis(40),
            jitter: Duration::from_millis(10),
            loss: 0.05,
            rate_bytes_per_s: None,
        };
        let now = Instant::now();
        let run = |seed| {
            let mut s = Shaper::new(d, seed);
            (0..20_000)
                .map(|_| s.schedule(now, 100))
                .collect::<Vec<_>>()
        };
        let a = run(3);
        assert_eq!(a, run(3));
        let lost = a.iter().filter(|t| t.is_none()).count();
        assert!((800..1200).contains(&lost), "{lost} of 20,000 lost");
        for t in a.into_iter().flatten() {
            let late = t - now;
            assert!(late >= d.delay && late < d.delay + d.jitter, "{late:?}");
        }
    }

    #[test]
    fn shaper_queues_behind_a_rate_limit() {
        let d = Direction {
            rate_bytes_per_s: Some(1000),
            ..Direction::NONE
        };
        let now = Instant::now();
        let mut s = Shaper::new(d, 1);
        let first = s.schedule(now, 100).map(|t| t - now);
        let second = s.schedule(now, 100).map(|t| t - now);
        assert_eq!(first, Some(Duration::from_millis(100)));
        assert_eq!(second, Some(Duration::from_millis(200)));
    }
}
