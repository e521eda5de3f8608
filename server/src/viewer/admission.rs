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
//!   lock everyone out for the deadline (`tests/tests/flood.rs` joins through one).
//!
//! Every pending connection also has one deadline for handshake and hello together (the
//! shell's timer): what the cap does not close, the deadline does.
//!
//! **After the hello.** At most [`Admission::max_viewers`] viewers (drivers and spectators)
//! are served; the next hello is refused with a reason ([`Full`]).

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

/// The admission state: pending connections (oldest first) and the viewers served.
#[derive(Debug)]
pub struct Admission {
    max_pending: usize,
    max_viewers: usize,
    /// Oldest first, and whether each has finished its handshake.
    pending: VecDeque<(PendingId, bool)>,
    next: PendingId,
    viewers: usize,
}

impl Admission {
    /// At most `max_pending` (at least 1) connections pending and `max_viewers` served.
    pub fn new(max_pending: usize, max_viewers: usize) -> Admission {
        Admission {
            max_pending: max_pending.max(1),
            max_viewers,
            pending: VecDeque::new(),
            next: 0,
            viewers: 0,
        }
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

    /// Pending connection `id` said hello: it becomes a viewer, or is refused when the
    /// server is full. Either way it is no longer pending.
    pub fn hello(&mut self, id: PendingId) -> Result<(), Full> {
        self.gone(id);
        self.seat(false)
    }

    /// A viewer whose hello was accepted takes a seat, or is refused when the server is
    /// full; `replacing` (a driver coming back whose old connection still holds a seat,
    /// about to be closed) takes one regardless.
    pub fn seat(&mut self, replacing: bool) -> Result<(), Full> {
        if self.viewers >= self.max_viewers && !replacing {
            return Err(Full {
                max: self.max_viewers,
            });
        }
        self.viewers += 1;
        Ok(())
    }

    /// Pending connection `id` ended before its hello (deadline, eviction, error); an id
    /// no longer pending changes nothing.
    pub fn gone(&mut self, id: PendingId) {
        if let Some(k) = self.pending.iter().position(|&(p, _)| p == id) {
            self.pending.remove(k);
        }
    }

    /// A viewer's connection ended.
    pub fn left(&mut self) {
        self.viewers = self.viewers.saturating_sub(1);
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
        Hello(PendingId, Result<(), Full>),
        Handshaken(PendingId),
        Gone(PendingId),
        Left,
    }

    fn check(max_pending: usize, max_viewers: usize, steps: Vec<Step>, pending: usize) {
        let mut a = Admission::new(max_pending, max_viewers);
        for (k, step) in steps.into_iter().enumerate() {
            match step {
                Step::Arrive {
                    validated,
                    may_retry,
                    expect,
                } => assert_eq!(a.arrive(validated, may_retry), expect, "step {k}"),
                Step::Hello(id, expect) => assert_eq!(a.hello(id), expect, "step {k}"),
                Step::Handshaken(id) => a.handshaken(id),
                Step::Gone(id) => a.gone(id),
                Step::Left => a.left(),
            }
        }
        assert_eq!(a.pending(), pending);
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
        assert_eq!(a.seat(false), Ok(()));
        assert_eq!(a.seat(false), Err(Full { max: 1 }));
        assert_eq!(a.seat(true), Ok(()));
        a.left();
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
                Step::Hello(2, Err(Full { max: 2 })),
                Step::Left,
                arrive(false, true, Admit(3)),
                Step::Hello(3, Ok(())),
            ],
            0,
        );
    }
}
