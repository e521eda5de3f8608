//! Who gets in: the server's decisions about connections before and after their hello,
//! with no clock, socket or lock (the network shell holds it under a mutex and acts on its
//! verdicts).
//!
//! **Before the hello.** A connection costs the server a TLS handshake and some memory
//! until it shows the token; an unauthenticated peer can open them as fast as it can send
//! packets. At most [`Admission::max_pending`] are *pending* (handshaking or in their hello)
//! at once. Past the cap:
//!
//! - a peer whose address is not yet validated is sent a QUIC Retry ([`Verdict::Retry`]):
//!   it must prove it receives at the address it claims before the server spends a
//!   handshake on it (a spoofed flood ends there, for the price of one stateless packet);
//! - a validated peer is admitted and **the oldest pending connection is evicted**
//!   ([`Verdict::AdmitEvicting`]), the oldest of those that finished their handshake and
//!   still say nothing if there is one: memory stays bounded by the cap, and a flood of
//!   peers that handshake and then stall cannot keep a real viewer out, because a real
//!   viewer says hello within a round trip of its handshake, and is never the one evicted
//!   while a silent one is pending (and a handshake slowed by a flood that saturates the
//!   CPU is not counted against it). Refusing instead would let a flood that holds the cap
//!   lock everyone out for the deadline (`tests/tests/it/flood.rs` joins through one).
//!
//! Every pending connection also has one deadline for handshake and hello together (the
//! shell's timer): what the cap does not close, the deadline does.
//!
//! **After the hello.** At most [`Admission::max_viewers`] viewers (drivers and spectators)
//! are served, and their state together holds at most [`Admission::max_memory`] bytes; the
//! next hello past either is refused with a reason ([`NoSeat`]).
//!
//! **What a viewer's state is.** A seat reserves [`viewer_bytes`] of its budget (clamped as
//! it is served): [`CUT_BYTES_PER_TRIANGLE`] a triangle for its cut (the split set, both
//! frontiers, their queues and schedules, what the allocator keeps around them: measured,
//! see the constant) plus [`CONNECTION_BYTES`], what its connection holds at most whatever
//! the budget (quinn's send window and receive buffers, the core's encoders and change
//! logs, its tasks). An estimate, not the bytes held now: it is known before the viewer
//! costs anything, it bounds what the viewer can come to hold (a cut grows with the camera,
//! in a frame), and it does not wait for the allocator. A viewer that asks for more
//! triangles later grows its reservation while the limit has room, and is served the most
//! triangles that fit otherwise ([`Admission::grow`]); a reservation never shrinks while
//! the viewer stays (a cut keeps its capacity), and is given back whole when it leaves.

use std::collections::VecDeque;

/// A pending connection's number (rises by one per admitted connection).
pub type PendingId = u64;

/// What to do with a new connection.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Verdict {
    /// Handshake it: it is pending as this id.
    Admit(PendingId),
    /// Handshake it, and close the oldest pending connection, `evict`, to make room.
    AdmitEvicting { id: PendingId, evict: PendingId },
    /// Send a QUIC Retry: the peer must show it owns its address first.
    Retry,
    /// Refuse without a handshake (full, and the peer cannot be asked to retry).
    Refuse,
}

/// The server serves its most viewers already: `max` of them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("the server is full: {max} viewers")]
pub struct Full {
    pub max: usize,
}

/// Viewers' state may hold at most `limit` bytes, `held` are reserved, and a viewer at
/// `budget` triangles would need `wanted` more.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error(
    "the server's memory for viewers is full (--max-memory {}): {} held, {} more needed for \
     {budget} triangles; ask for fewer triangles or try later",
    mib(*limit),
    mib(*held),
    mib(*wanted)
)]
pub struct OutOfMemory {
    pub limit: u64,
    pub held: u64,
    pub wanted: u64,
    pub budget: u32,
}

/// Why a viewer gets no seat.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum NoSeat {
    #[error(transparent)]
    Full(#[from] Full),
    #[error(transparent)]
    Memory(#[from] OutOfMemory),
}

/// Bytes in MiB, as the refusals say them.
fn mib(bytes: u64) -> String {
    format!("{:.1} MiB", bytes as f64 / f64::from(1u32 << 20))
}

/// What one triangle of a viewer's budget costs its cut at most, bytes: the split set,
/// both frontiers, their queues and schedules, with what the allocator holds around them.
/// Measured (issue 22) on `kossou` at 65,536 triangles, driving: the cut's `heap_bytes`
/// (capacities) 2.48 MB, 2.73 MB at its peak along the bench's drive (`roam-server bench
/// --json`'s `serve_viewer_heap_bytes` and `_peak`): 38 to 42 bytes a triangle (221
/// before its frontiers became small records). The records grow by chunks, the indexes
/// and vectors by doubling: 64 leaves room for that at every budget.
/// `server/tests/it/viewer_core.rs` checks that a driving viewer's cut stays within it, and
/// that it is not so loose as to reserve four times what a viewer holds.
pub const CUT_BYTES_PER_TRIANGLE: u64 = 64;

/// What a viewer holds besides its cut and its transport's buffers, at most, bytes: the
/// core's encoders, change logs and scratch, the viewer's tasks, quinn's state for the
/// connection (about 0.2 MB measured with heaptrack at 65,536 triangles).
pub const CORE_BYTES: u64 = 512 << 10;

/// What a viewer's connection holds at most besides its cut, bytes: quinn's send window
/// (everything sent and not yet acknowledged: colour tiles, a key frame on a slow path),
/// its receive windows and datagram buffers ([`roam_link::tls::server_transport`]), and
/// [`CORE_BYTES`].
pub const CONNECTION_BYTES: u64 = roam_link::tls::SERVER_SEND_WINDOW
    + roam_link::tls::SERVER_RECEIVE_WINDOW
    + roam_link::tls::SERVER_DATAGRAM_RECEIVE
    + roam_link::tls::SERVER_DATAGRAM_SEND
    + CORE_BYTES;

/// The bytes a seat reserves for a viewer served `budget` triangles a frame.
pub fn viewer_bytes(budget: u32) -> u64 {
    CONNECTION_BYTES + u64::from(budget) * CUT_BYTES_PER_TRIANGLE
}

/// The most triangles whose seat fits in `bytes` (0 when not even the connection does).
pub fn budget_within(bytes: u64) -> u32 {
    let triangles = bytes.saturating_sub(CONNECTION_BYTES) / CUT_BYTES_PER_TRIANGLE;
    u32::try_from(triangles).unwrap_or(u32::MAX)
}

/// The default [`Admission::max_memory`]: half the memory available when the server
/// starts (`MemAvailable` in `meminfo`, the text of `/proc/meminfo`), `None` when it does
/// not say. Available, not total: it is what the machine can give without swapping, with
/// what other programs and this server's own start (tiles, caches) hold already taken out;
/// half of it, because the data set's mapped files (heights, variance tree, colour tiles)
/// are served from the page cache that the other half keeps, and a viewer's frame that
/// faults its heights in from disk is late.
pub fn default_max_memory(meminfo: &str) -> Option<u64> {
    let line = meminfo.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let mut words = line.split_whitespace().skip(1);
    let kib: u64 = words.next()?.parse().ok()?;
    (words.next() == Some("kB")).then_some(kib.saturating_mul(1024) / 2)
}

/// The admission state: pending connections (oldest first), the viewers served and the
/// bytes their seats reserve.
#[derive(Debug)]
pub struct Admission {
    max_pending: usize,
    max_viewers: usize,
    max_memory: u64,
    /// Oldest first, and whether each has finished its handshake.
    pending: VecDeque<(PendingId, bool)>,
    next: PendingId,
    viewers: usize,
    /// What the seats reserve together ([`viewer_bytes`]).
    memory: u64,
}

impl Admission {
    /// At most `max_pending` (at least 1) connections pending and `max_viewers` served, with
    /// no limit on their memory ([`Self::with_max_memory`]).
    pub fn new(max_pending: usize, max_viewers: usize) -> Admission {
        Admission {
            max_pending: max_pending.max(1),
            max_viewers,
            max_memory: u64::MAX,
            pending: VecDeque::new(),
            next: 0,
            viewers: 0,
            memory: 0,
        }
    }

    /// The viewers' seats reserve at most `bytes` together.
    pub fn with_max_memory(self, bytes: u64) -> Admission {
        Admission {
            max_memory: bytes,
            ..self
        }
    }

    pub fn max_memory(&self) -> u64 {
        self.max_memory
    }

    /// Bytes the seats reserve now.
    pub fn memory(&self) -> u64 {
        self.memory
    }

    pub fn max_pending(&self) -> usize {
        self.max_pending
    }

    pub fn max_viewers(&self) -> usize {
        self.max_viewers
    }

    /// Connections handshaking or in their hello now.
    pub fn pending(&self) -> usize {
        self.pending.len()
    }

    /// Viewers served now.
    pub fn viewers(&self) -> usize {
        self.viewers
    }

    /// A new connection arrives: `validated` if its address is proven (a Retry token came
    /// back), `may_retry` if it can still be asked to (it has not been already).
    pub fn arrive(&mut self, validated: bool, may_retry: bool) -> Verdict {
        if self.pending.len() < self.max_pending {
            return Verdict::Admit(self.push());
        }
        if !validated {
            return if may_retry {
                Verdict::Retry
            } else {
                Verdict::Refuse
            };
        }
        let k = self.pending.iter().position(|&(_, done)| done).unwrap_or(0);
        let (evict, _) = self
            .pending
            .remove(k)
            .expect("the cap is at least 1, and reached");
        Verdict::AdmitEvicting {
            id: self.push(),
            evict,
        }
    }

    fn push(&mut self) -> PendingId {
        let id = self.next;
        self.next += 1;
        self.pending.push_back((id, false));
        id
    }

    /// Pending connection `id` finished its TLS handshake (and waits for its hello).
    pub fn handshaken(&mut self, id: PendingId) {
        if let Some(p) = self.pending.iter_mut().find(|(p, _)| *p == id) {
            p.1 = true;
        }
    }

    /// Pending connection `id` said hello, asking to be served `budget` triangles (as
    /// clamped by the server): it becomes a viewer holding a [`Seat`], or is refused when
    /// the server is full. Either way it is no longer pending.
    pub fn hello(&mut self, id: PendingId, budget: u32) -> Result<Seat, NoSeat> {
        self.gone(id);
        self.seat(budget, false)
    }

    /// A viewer whose hello was accepted takes a seat for `budget` triangles (as clamped by
    /// the server), or is refused when the viewers or their memory are at the limit;
    /// `replacing` (a driver coming back whose old connection still holds a seat, about to
    /// be closed) takes one regardless: the old one's seat is about to be given back.
    pub fn seat(&mut self, budget: u32, replacing: bool) -> Result<Seat, NoSeat> {
        if self.viewers >= self.max_viewers && !replacing {
            return Err(Full {
                max: self.max_viewers,
            }
            .into());
        }
        let bytes = viewer_bytes(budget);
        if self.memory.saturating_add(bytes) > self.max_memory && !replacing {
            return Err(OutOfMemory {
                limit: self.max_memory,
                held: self.memory,
                wanted: bytes,
                budget,
            }
            .into());
        }
        self.viewers += 1;
        self.memory = self.memory.saturating_add(bytes);
        Ok(Seat { bytes })
    }

    /// A seated viewer asks for `budget` triangles (as clamped by the server): the seat
    /// grows to hold them if the limit has room, or as far as it has; returns the
    /// triangles the viewer is served, at most `budget`. A smaller budget keeps the seat
    /// as it is (the cut keeps what it reserved).
    pub fn grow(&mut self, seat: &mut Seat, budget: u32) -> u32 {
        let wanted = viewer_bytes(budget);
        if wanted > seat.bytes {
            let free = self.max_memory.saturating_sub(self.memory);
            let more = (wanted - seat.bytes).min(free);
            seat.bytes += more;
            self.memory = self.memory.saturating_add(more);
        }
        budget.min(budget_within(seat.bytes))
    }

    /// Pending connection `id` ended before its hello (deadline, eviction, error); an id
    /// no longer pending changes nothing.
    pub fn gone(&mut self, id: PendingId) {
        if let Some(k) = self.pending.iter().position(|&(p, _)| p == id) {
            self.pending.remove(k);
        }
    }

    /// A viewer's connection ended: its seat is given back.
    pub fn left(&mut self, seat: Seat) {
        self.viewers = self.viewers.saturating_sub(1);
        self.memory = self.memory.saturating_sub(seat.bytes);
    }
}

/// What one viewer's seat reserves ([`Admission::seat`]); given back with
/// [`Admission::left`].
#[derive(Debug, PartialEq, Eq)]
#[must_use = "a seat is given back with Admission::left"]
pub struct Seat {
    bytes: u64,
}

impl Seat {
    /// The bytes this seat reserves.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A step and what it must give.
    enum Step {
        Arrive {
            validated: bool,
            may_retry: bool,
            expect: Verdict,
        },
        /// A hello at the fewest triangles, and whether it is seated or why not.
        Hello(PendingId, Result<(), NoSeat>),
        Handshaken(PendingId),
        Gone(PendingId),
        /// The oldest seated viewer leaves.
        Left,
    }

    const MIN: u32 = roam_protocol::messages::MIN_BUDGET;

    fn check(max_pending: usize, max_viewers: usize, steps: Vec<Step>, pending: usize) {
        let mut a = Admission::new(max_pending, max_viewers);
        let mut seats = VecDeque::new();
        for (k, step) in steps.into_iter().enumerate() {
            match step {
                Step::Arrive {
                    validated,
                    may_retry,
                    expect,
                } => assert_eq!(a.arrive(validated, may_retry), expect, "step {k}"),
                Step::Hello(id, expect) => {
                    let got = a.hello(id, MIN);
                    assert_eq!(got.as_ref().map(|_| ()).map_err(|e| *e), expect, "step {k}");
                    seats.extend(got.ok());
                }
                Step::Handshaken(id) => a.handshaken(id),
                Step::Gone(id) => a.gone(id),
                Step::Left => a.left(seats.pop_front().expect("a viewer to leave")),
            }
        }
        assert_eq!(a.pending(), pending);
        assert_eq!(a.viewers(), seats.len());
        assert_eq!(a.memory(), seats.len() as u64 * viewer_bytes(MIN));
    }

    fn arrive(validated: bool, may_retry: bool, expect: Verdict) -> Step {
        Step::Arrive {
            validated,
            may_retry,
            expect,
        }
    }

    #[test]
    fn under_the_cap_everyone_is_handshaken() {
        use Verdict::Admit;
        check(
            3,
            64,
            vec![
                arrive(false, true, Admit(0)),
                arrive(false, true, Admit(1)),
                Step::Gone(0),
                arrive(false, false, Admit(2)),
            ],
            2,
        );
    }

    #[test]
    fn past_the_cap_unproven_addresses_retry_and_proven_ones_evict_the_oldest() {
        use Verdict::*;
        check(
            2,
            64,
            vec![
                arrive(false, true, Admit(0)),
                arrive(false, true, Admit(1)),
                arrive(false, true, Retry),
                arrive(false, false, Refuse),
                arrive(true, false, AdmitEvicting { id: 2, evict: 0 }),
                arrive(true, false, AdmitEvicting { id: 3, evict: 1 }),
                // An evicted connection's end changes nothing.
                Step::Gone(0),
                arrive(false, true, Retry),
            ],
            2,
        );
    }

    #[test]
    fn a_silent_handshaken_connection_is_evicted_before_one_still_handshaking() {
        use Verdict::*;
        check(
            3,
            64,
            vec![
                arrive(false, true, Admit(0)),
                arrive(false, true, Admit(1)),
                arrive(false, true, Admit(2)),
                Step::Handshaken(1),
                Step::Handshaken(2),
                arrive(true, false, AdmitEvicting { id: 3, evict: 1 }),
                arrive(true, false, AdmitEvicting { id: 4, evict: 2 }),
                // None handshaken: the oldest.
                arrive(true, false, AdmitEvicting { id: 5, evict: 0 }),
            ],
            3,
        );
    }

    #[test]
    fn a_driver_replacing_its_old_connection_is_seated_past_the_limit() {
        let mut a = Admission::new(8, 1);
        let first = a.seat(MIN, false).expect("room for one");
        assert_eq!(a.seat(MIN, false), Err(Full { max: 1 }.into()));
        let _second = a.seat(MIN, true).expect("a replacement is seated");
        a.left(first);
        assert_eq!(a.viewers(), 1);
    }

    #[test]
    fn viewers_past_the_limit_are_refused_and_a_leave_makes_room() {
        use Verdict::Admit;
        check(
            8,
            2,
            vec![
                arrive(false, true, Admit(0)),
                arrive(false, true, Admit(1)),
                arrive(false, true, Admit(2)),
                Step::Hello(0, Ok(())),
                Step::Hello(1, Ok(())),
                Step::Hello(2, Err(Full { max: 2 }.into())),
                Step::Left,
                arrive(false, true, Admit(3)),
                Step::Hello(3, Ok(())),
            ],
            0,
        );
    }

    #[test]
    fn a_viewer_whose_state_would_not_fit_is_refused_naming_the_limit() {
        let budget = 65_536;
        let each = viewer_bytes(budget);
        // Room for two at 65,536 triangles and a bit.
        let mut a = Admission::new(8, 64).with_max_memory(each * 5 / 2);
        let first = a.seat(budget, false).expect("the first fits");
        let _second = a.seat(budget, false).expect("the second fits");
        let refused = a.seat(budget, false);
        let expected = OutOfMemory {
            limit: each * 5 / 2,
            held: 2 * each,
            wanted: each,
            budget,
        };
        assert_eq!(refused, Err(NoSeat::Memory(expected)));
        let text = refused.expect_err("refused").to_string();
        assert!(text.contains("--max-memory"), "{text}");
        assert!(text.contains(&format!("{budget} triangles")), "{text}");
        assert!(text.len() <= roam_protocol::messages::MAX_REASON, "{text}");
        // Refused, it reserves nothing: a cheaper viewer still fits in what is left.
        assert_eq!(a.viewers(), 2);
        assert_eq!(a.memory(), 2 * each);
        let cheap = a.seat(MIN, false).expect("a small budget fits");
        assert_eq!(a.memory(), 2 * each + viewer_bytes(MIN));
        // A leave gives its seat back whole.
        a.left(first);
        a.left(cheap);
        assert_eq!(a.memory(), each);
        let _again = a.seat(budget, false).expect("room again after a leave");
        assert_eq!(a.viewers(), 2);
    }

    #[test]
    fn a_driver_replacing_its_connection_is_seated_past_the_memory_limit() {
        let each = viewer_bytes(10_000);
        let mut a = Admission::new(8, 64).with_max_memory(each);
        let old = a.seat(10_000, false).expect("fits");
        assert!(matches!(a.seat(10_000, false), Err(NoSeat::Memory(_))));
        let new = a.seat(10_000, true).expect("a replacement is seated");
        a.left(old);
        assert_eq!(a.memory(), new.bytes());
    }

    #[test]
    fn a_larger_budget_is_served_as_far_as_the_limit_has_room() {
        let limit = viewer_bytes(50_000);
        let mut a = Admission::new(8, 64).with_max_memory(limit);
        let mut seat = a.seat(10_000, false).expect("fits");
        // Within the limit: granted whole.
        assert_eq!(a.grow(&mut seat, 30_000), 30_000);
        assert_eq!(seat.bytes(), viewer_bytes(30_000));
        // Smaller again: served, the seat kept.
        assert_eq!(a.grow(&mut seat, 5_000), 5_000);
        assert_eq!(seat.bytes(), viewer_bytes(30_000));
        // Past the limit: the most that fits.
        assert_eq!(a.grow(&mut seat, 80_000), 50_000);
        assert_eq!(a.memory(), limit);
        // Another viewer now finds no room, until this one leaves.
        assert!(matches!(a.seat(MIN, false), Err(NoSeat::Memory(_))));
        a.left(seat);
        assert_eq!(a.memory(), 0);
        let _seat = a.seat(MIN, false).expect("room after the leave");
    }

    #[test]
    fn the_estimate_and_its_inverse_agree() {
        for budget in [MIN, 1_000, 65_536, roam_protocol::messages::MAX_BUDGET] {
            assert_eq!(budget_within(viewer_bytes(budget)), budget);
            assert_eq!(budget_within(viewer_bytes(budget) - 1), budget - 1);
        }
        assert_eq!(budget_within(CONNECTION_BYTES - 1), 0);
        // 65,536 triangles: about 19 MB with the connection.
        assert_eq!(viewer_bytes(65_536), CONNECTION_BYTES + (4 << 20));
    }

    #[test]
    fn the_default_is_half_the_memory_available() {
        let meminfo = "MemTotal:       24528300 kB\nMemFree:         1234567 kB\n\
                       MemAvailable:   20000000 kB\nBuffers:          100 kB\n";
        assert_eq!(default_max_memory(meminfo), Some(20_000_000 * 1024 / 2));
        // On a 24 GiB machine, far more than the default 64 viewers at 65,536 triangles.
        let seats = default_max_memory(meminfo).expect("said") / viewer_bytes(65_536);
        assert!(seats > 400, "{seats}");
        assert_eq!(default_max_memory("MemTotal: 1 kB\n"), None);
        assert_eq!(default_max_memory("MemAvailable: lots kB\n"), None);
        assert_eq!(default_max_memory("MemAvailable: 12 MB\n"), None);
    }
}
