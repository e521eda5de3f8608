//! The simulated network's paths: one direction of a viewer's path ([`Direction`]: delay,
//! jitter, loss, a bandwidth cap and its queue) and the packets on it ([`Wire`]: queued, on
//! the way, awaiting retransmission), the control stream's in-order delivery
//! ([`InOrder`]), and the seeded generator every random choice comes from
//! ([`SplitMix64`]). The model itself is described in the [module docs](super).

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::time::Duration;

pub use crate::fixtures::SplitMix64;

/// Header bytes per packet, counted against a direction's rate and queue.
pub const OVERHEAD: usize = 40;

/// One direction of a viewer's path.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Direction {
    /// One-way delay.
    pub delay: Duration,
    /// Extra delay, uniform in `[0, jitter]`, per packet (packets overtake each other).
    pub jitter: Duration,
    /// Probability that a packet is lost.
    pub loss: f64,
    /// The bandwidth: a packet leaves when the direction is free. `None`: no limit.
    pub rate_bytes_per_s: Option<u64>,
    /// The serialisation queue's limit, bytes: a packet that finds it fuller is dropped.
    pub queue_bytes: usize,
}

impl Default for Direction {
    /// 10 ms, no jitter, no loss, no bandwidth limit.
    fn default() -> Direction {
        Direction {
            delay: Duration::from_millis(10),
            jitter: Duration::ZERO,
            loss: 0.0,
            rate_bytes_per_s: None,
            queue_bytes: 256 << 10,
        }
    }
}

impl Direction {
    /// A direction with this delay, jitter and loss, and no bandwidth limit.
    pub fn lossy(delay_ms: u64, jitter_ms: u64, loss: f64) -> Direction {
        Direction {
            delay: Duration::from_millis(delay_ms),
            jitter: Duration::from_millis(jitter_ms),
            loss,
            ..Direction::default()
        }
    }

    /// The same direction at `bytes_per_s`.
    pub fn with_rate(self, bytes_per_s: u64) -> Direction {
        Direction {
            rate_bytes_per_s: Some(bytes_per_s),
            ..self
        }
    }
}

/// A viewer's path: the direction to the server and the direction back.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Path {
    pub up: Direction,
    pub down: Direction,
}

impl Path {
    /// The same settings both ways.
    pub fn symmetric(direction: Direction) -> Path {
        Path {
            up: direction,
            down: direction,
        }
    }
}

/// When a sender learns that a packet on `direction` was lost and sends it again: 2 × the
/// one-way delay + 10 ms after it left.
pub fn rto(direction: &Direction) -> Duration {
    2 * direction.delay + Duration::from_millis(10)
}

/// What a packet carries.
#[derive(Clone, Debug)]
pub(super) enum Payload {
    Datagram(Vec<u8>),
    Control {
        seq: u64,
        bytes: Vec<u8>,
    },
    Chunk {
        stream: u64,
        index: u32,
        count: u32,
        bytes: Vec<u8>,
    },
    /// The sender closed the connection.
    Close,
}

impl Payload {
    pub(super) fn size(&self) -> usize {
        OVERHEAD
            + match self {
                Payload::Datagram(b)
                | Payload::Control { bytes: b, .. }
                | Payload::Chunk { bytes: b, .. } => b.len(),
                Payload::Close => 0,
            }
    }

    pub(super) fn stream(&self) -> Option<u64> {
        match self {
            Payload::Chunk { stream, .. } => Some(*stream),
            _ => None,
        }
    }

    /// Whether a loss is repaired (control and stream packets).
    fn reliable(&self) -> bool {
        matches!(self, Payload::Control { .. } | Payload::Chunk { .. })
    }
}

/// Packets through one direction of a path.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct WireStats {
    /// Packets that left (retransmissions included).
    pub packets: u64,
    /// Bytes that left, headers included.
    pub bytes: u64,
    /// Packets lost on the way (or to a cut path).
    pub lost: u64,
    /// Packets dropped at a full queue.
    pub dropped: u64,
    /// Packets sent again after a loss.
    pub retransmitted: u64,
}

struct Flying {
    left: Duration,
    arrive: Duration,
    order: u64,
    payload: Payload,
}

/// One direction of a viewer's path, with its packets queued, on the way and awaiting
/// retransmission.
pub(super) struct Wire {
    pub(super) direction: Direction,
    rng: SplitMix64,
    /// `(enqueued at, packet)`, first out first.
    queue: VecDeque<(Duration, Payload)>,
    queued_bytes: usize,
    /// When the direction has finished sending what left so far.
    free_at: Duration,
    flying: Vec<Flying>,
    /// `(due, packet)`: lost packets to send again.
    retransmit: Vec<(Duration, Payload)>,
    /// The direction carries nothing before this time (`Duration::MAX`: never again).
    pub(super) down_until: Duration,
    order: u64,
    /// Streams the sender reset: nothing of theirs is sent again.
    reset: BTreeSet<u64>,
    /// The sender closed: nothing lost is sent again.
    closed: bool,
    pub(super) stats: WireStats,
}

impl Wire {
    pub(super) fn new(direction: Direction, seed: u64) -> Wire {
        Wire {
            direction,
            rng: SplitMix64::new(seed),
            queue: VecDeque::new(),
            queued_bytes: 0,
            free_at: Duration::ZERO,
            flying: Vec::new(),
            retransmit: Vec::new(),
            down_until: Duration::ZERO,
            order: 0,
            reset: BTreeSet::new(),
            closed: false,
            stats: WireStats::default(),
        }
    }

    fn is_down(&self, at: Duration) -> bool {
        at < self.down_until
    }

    fn lose(&mut self, at: Duration, payload: Payload) {
        self.stats.lost += 1;
        self.repair(at, payload);
    }

    /// A lost packet is sent again, `rto` after `at`, if it is to be.
    fn repair(&mut self, at: Duration, payload: Payload) {
        let reset = payload.stream().is_some_and(|s| self.reset.contains(&s));
        if payload.reliable() && !self.closed && !reset {
            self.retransmit.push((at + rto(&self.direction), payload));
        }
    }

    /// Queues a packet at `now` (it leaves at the next [`Self::pump`]).
    pub(super) fn send(&mut self, now: Duration, payload: Payload) {
        let size = payload.size();
        if self.direction.rate_bytes_per_s.is_some()
            && self.queued_bytes + size > self.direction.queue_bytes
        {
            self.stats.dropped += 1;
            self.repair(now, payload);
            return;
        }
        self.queued_bytes += size;
        self.queue.push_back((now, payload));
    }

    /// Queues control message `bytes` at `now` as the next of the control stream whose
    /// next sequence number is `seq`.
    pub(super) fn send_control(&mut self, now: Duration, seq: &mut u64, bytes: Vec<u8>) {
        let this = *seq;
        *seq += 1;
        self.send(now, Payload::Control { seq: this, bytes });
    }

    /// Retransmissions due by `now` are queued, and what the direction can send by `now` leaves.
    pub(super) fn pump(&mut self, now: Duration) {
        let mut due = Vec::new();
        self.retransmit.retain(|(at, p)| {
            if *at <= now {
                due.push((*at, p.clone()));
                false
            } else {
                true
            }
        });
        due.sort_by_key(|(at, _)| *at);
        for (_, p) in due {
            self.stats.retransmitted += 1;
            self.send(now, p);
        }
        while let Some((enqueued, _)) = self.queue.front() {
            let start = self.free_at.max(*enqueued);
            if start > now {
                break;
            }
            let (_, payload) = self.queue.pop_front().expect("front checked");
            let size = payload.size();
            self.queued_bytes -= size;
            let busy = match self.direction.rate_bytes_per_s {
                Some(rate) => {
                    Duration::from_nanos((size as u64 * 1_000_000_000).div_ceil(rate.max(1)))
                }
                None => Duration::ZERO,
            };
            let left = start + busy;
            self.free_at = left;
            self.stats.packets += 1;
            self.stats.bytes += size as u64;
            if self.is_down(left) || self.rng.chance(self.direction.loss) {
                self.lose(left, payload);
                continue;
            }
            let jitter = Duration::from_nanos(
                (self.rng.unit() * self.direction.jitter.as_nanos() as f64) as u64,
            );
            self.order += 1;
            self.flying.push(Flying {
                left,
                arrive: left + self.direction.delay + jitter,
                order: self.order,
                payload,
            });
        }
    }

    /// The packets that have arrived by `now`, in the order they arrived.
    pub(super) fn arrived(&mut self, now: Duration) -> Vec<(Duration, Payload)> {
        let mut due: Vec<Flying> = Vec::new();
        let mut i = 0;
        while i < self.flying.len() {
            if self.flying[i].arrive <= now {
                due.push(self.flying.swap_remove(i));
            } else {
                i += 1;
            }
        }
        due.sort_by_key(|f| (f.arrive, f.order));
        let mut out = Vec::new();
        for f in due {
            if self.is_down(f.arrive) {
                self.lose(f.left, f.payload);
            } else {
                out.push((f.arrive, f.payload));
            }
        }
        out
    }

    /// The sender resets `stream`: its queued packets go, and none is sent again.
    pub(super) fn reset(&mut self, stream: u64) {
        let mut freed = 0;
        self.queue.retain(|(_, p)| {
            let keep = p.stream() != Some(stream);
            if !keep {
                freed += p.size();
            }
            keep
        });
        self.queued_bytes -= freed;
        self.retransmit.retain(|(_, p)| p.stream() != Some(stream));
        self.reset.insert(stream);
    }

    /// Whether `stream` was reset and none of its packets is on the way: it will never
    /// complete (what arrived of it is all that will).
    pub(super) fn abandoned(&self, stream: u64) -> bool {
        self.reset.contains(&stream)
            && !self
                .flying
                .iter()
                .any(|f| f.payload.stream() == Some(stream))
    }

    /// The sender closed: what waits to leave goes, and nothing lost is sent again (what
    /// is on the way still arrives, and a last word may still be sent).
    pub(super) fn close(&mut self) {
        self.closed = true;
        self.queue.clear();
        self.queued_bytes = 0;
        self.retransmit.clear();
    }
}

/// A control stream's receiving end: messages handed on in order.
#[derive(Default)]
pub(super) struct InOrder {
    next: u64,
    held: BTreeMap<u64, Vec<u8>>,
}

impl InOrder {
    pub(super) fn accept(&mut self, seq: u64, bytes: Vec<u8>) -> Vec<Vec<u8>> {
        if seq >= self.next {
            self.held.insert(seq, bytes);
        }
        let mut out = Vec::new();
        while let Some(b) = self.held.remove(&self.next) {
            out.push(b);
            self.next += 1;
        }
        out
    }
}
