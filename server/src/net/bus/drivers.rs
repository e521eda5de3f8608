//! The world's book of who drives what ([`Drivers`]): each driven vehicle's ticket (the
//! driver's, to come back with through any edge), its claim (a random number for one join
//! or resume: a leave or hold naming another is stale) and the edge holding it, the only
//! one whose keys, leave and hold for it are taken. Pure: the time is a parameter (the
//! time since the world started).
//!
//! With a plain bus (`--insecure-bus`) requests name no edge (`None`): any edge's keys
//! and claims are taken, as before the bus had proofs.
//!
//! Key states an edge sent before its leave can reach the world after it: keys and
//! requests are read by two tasks, so their order is not kept. For [`LATE_KEYS`] after an
//! edge's leave, its key states for vehicles it no longer holds are late, not refused
//! ([`Drivers::late`]): dropped without a refusal being counted or logged (every leave
//! would otherwise log one, and the tests saw it under load). A forger naming that edge
//! as sender is dropped all the same, uncounted for that second.

use std::collections::HashMap;
use std::time::Duration;

use roam_protocol::messages::Ticket;

use crate::sim::world::VehicleId;

/// How long after its leave an edge's key states for vehicles it no longer holds are late
/// rather than refused: a few of the edge's 10 ms key batches, with room for a loaded
/// machine.
pub(crate) const LATE_KEYS: Duration = Duration::from_secs(1);

/// Who holds a vehicle, by which claim, since when.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Holder {
    /// The edge (its name on the bus); `None` on a plain bus.
    pub edge: Option<u64>,
    pub claim: u64,
    /// When the claim was made (a vehicle no edge names by then is held, [`Drivers::unnamed`]).
    pub since: Duration,
}

/// Each driven vehicle's ticket and holder (at most one entry a vehicle id in each).
#[derive(Default)]
pub(crate) struct Drivers {
    pub tickets: HashMap<Ticket, VehicleId>,
    holders: HashMap<VehicleId, Holder>,
    /// Vehicles each edge holds (edges holding none are not here).
    held_by: HashMap<u64, usize>,
    /// When each edge last left a vehicle (`None`: a plain bus), for [`LATE_KEYS`]; entries
    /// older than that are dropped at the next leave.
    left: HashMap<Option<u64>, Duration>,
}

impl Drivers {
    /// `vehicle` is held by `edge` with `claim` (random, given) from `now`: older claims
    /// are stale from now on.
    pub(super) fn claim(
        &mut self,
        vehicle: VehicleId,
        edge: Option<u64>,
        claim: u64,
        now: Duration,
    ) {
        let before = self.holders.insert(
            vehicle,
            Holder {
                edge,
                claim,
                since: now,
            },
        );
        self.let_go(before);
        if let Some(e) = edge {
            *self.held_by.entry(e).or_default() += 1;
        }
    }

    /// A holder's vehicle is not its edge's any more.
    fn let_go(&mut self, holder: Option<Holder>) {
        if let Some(e) = holder.and_then(|h| h.edge)
            && let Some(n) = self.held_by.get_mut(&e)
        {
            *n -= 1;
            if *n == 0 {
                self.held_by.remove(&e);
            }
        }
    }

    /// Whether `edge` holds any vehicle (key states from an edge holding none are not
    /// worth opening).
    pub(super) fn holds_any(&self, edge: u64) -> bool {
        self.held_by.contains_key(&edge)
    }

    /// Whether `edge` holds `vehicle` with `claim` (its newest).
    pub(super) fn holds(&self, vehicle: VehicleId, edge: Option<u64>, claim: u64) -> bool {
        self.holders
            .get(&vehicle)
            .is_some_and(|h| h.claim == claim && same(h.edge, edge))
    }

    /// Whether `edge` holds `vehicle` (its keys are taken).
    pub(super) fn drives(&self, vehicle: VehicleId, edge: Option<u64>) -> bool {
        self.holders
            .get(&vehicle)
            .is_some_and(|h| same(h.edge, edge))
    }

    /// `edge` left `vehicle` at `now`: the vehicle is free ([`Drivers::forget`]), and the
    /// edge's key states sent before the leave are late for a while ([`Drivers::late`]).
    pub(super) fn leave(&mut self, vehicle: VehicleId, edge: Option<u64>, now: Duration) {
        self.forget(vehicle);
        self.left
            .retain(|_, at| now.saturating_sub(*at) < LATE_KEYS);
        self.left.insert(edge, now);
    }

    /// Whether key states from `edge` for a vehicle it does not hold are late (it left a
    /// vehicle less than [`LATE_KEYS`] before `now`), not refused.
    pub(super) fn late(&self, edge: Option<u64>, now: Duration) -> bool {
        self.left
            .get(&edge)
            .is_some_and(|at| now.saturating_sub(*at) < LATE_KEYS)
    }

    pub(super) fn holder(&self, vehicle: VehicleId) -> Option<Holder> {
        self.holders.get(&vehicle).copied()
    }

    /// `vehicle` is free: its ticket and claim name nothing.
    pub(super) fn forget(&mut self, vehicle: VehicleId) {
        self.tickets.retain(|_, v| *v != vehicle);
        let holder = self.holders.remove(&vehicle);
        self.let_go(holder);
    }

    /// Of `driven` (the vehicles driven now, not held), those whose claim is at least
    /// `grace` old and that no edge's latest hello names with it (`named(vehicle, edge,
    /// claim)`): a join whose edge never took it up, or a vehicle its edge dropped without a
    /// leave reaching the world. Each with how long ago its claim was made.
    pub(super) fn unnamed(
        &self,
        driven: impl IntoIterator<Item = VehicleId>,
        now: Duration,
        grace: Duration,
        named: impl Fn(VehicleId, Option<u64>, u64) -> bool,
    ) -> Vec<(VehicleId, Duration)> {
        driven
            .into_iter()
            .filter_map(|v| {
                let h = self.holders.get(&v)?;
                let age = now.saturating_sub(h.since);
                (age >= grace && !named(v, h.edge, h.claim)).then_some((v, age))
            })
            .collect()
    }
}

/// Whether a holder's edge and a sender are the same edge (either `None`: a plain bus).
fn same(holder: Option<u64>, sender: Option<u64>) -> bool {
    match (holder, sender) {
        (Some(h), Some(s)) => h == s,
        _ => true,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_the_holding_edge_with_the_newest_claim_is_taken() {
        let now = Duration::from_secs(100);
        let mut d = Drivers::default();
        d.claim(3, Some(10), 111, now);
        let check = |d: &Drivers, vehicle, edge, claim, expected: (bool, bool)| {
            assert_eq!(
                (d.holds(vehicle, edge, claim), d.drives(vehicle, edge)),
                expected,
                "vehicle {vehicle} edge {edge:?} claim {claim}"
            );
        };
        check(&d, 3, Some(10), 111, (true, true));
        check(&d, 3, Some(10), 112, (false, true));
        check(&d, 3, Some(11), 111, (false, false));
        check(&d, 4, Some(10), 111, (false, false));
        // A plain bus names no edge: the claim alone decides.
        check(&d, 3, None, 111, (true, true));
        assert!(d.holds_any(10) && !d.holds_any(11));
        // A resume through another edge moves the vehicle there.
        d.claim(3, Some(11), 222, now);
        check(&d, 3, Some(10), 111, (false, false));
        check(&d, 3, Some(11), 222, (true, true));
        assert!(!d.holds_any(10) && d.holds_any(11));
        d.claim(4, Some(11), 333, now);
        d.forget(3);
        check(&d, 3, Some(11), 222, (false, false));
        assert!(d.holds_any(11), "vehicle 4 still");
        d.forget(4);
        assert!(!d.holds_any(11));
    }

    #[test]
    fn key_states_after_a_leave_are_late_for_a_while_and_only_from_that_edge() {
        let t0 = Duration::from_secs(100);
        let mut d = Drivers::default();
        d.claim(3, Some(10), 111, t0);
        d.claim(4, Some(20), 222, t0);
        assert!(!d.late(Some(10), t0), "no leave yet");
        d.leave(3, Some(10), t0);
        assert!(
            !d.drives(3, Some(10)) && !d.holds_any(10),
            "the vehicle is free"
        );
        let check = |d: &Drivers, edge, after: Duration, expected: bool| {
            assert_eq!(
                d.late(edge, t0 + after),
                expected,
                "edge {edge:?} after {after:?}"
            );
        };
        check(&d, Some(10), Duration::ZERO, true);
        check(&d, Some(10), LATE_KEYS - Duration::from_millis(1), true);
        check(&d, Some(10), LATE_KEYS, false);
        check(&d, Some(20), Duration::ZERO, false);
        check(&d, None, Duration::ZERO, false);
        // The next leave drops the window that has run out.
        d.leave(4, Some(20), t0 + 2 * LATE_KEYS);
        assert_eq!(d.left.len(), 1, "{:?}", d.left);
        check(&d, Some(20), 2 * LATE_KEYS, true);
    }

    #[test]
    fn vehicles_no_edge_names_after_the_grace_are_found() {
        let t0 = Duration::from_secs(100);
        let mut d = Drivers::default();
        d.claim(1, Some(10), 5, t0);
        d.claim(2, Some(10), 6, t0);
        d.claim(3, Some(20), 7, t0 + Duration::from_secs(2));
        let grace = Duration::from_secs(3);
        let named =
            |v: VehicleId, edge: Option<u64>, claim: u64| (v, edge, claim) == (1, Some(10), 5);
        let at = |secs| t0 + Duration::from_secs(secs);
        assert_eq!(d.unnamed([1, 2, 3], at(1), grace, named), vec![]);
        assert_eq!(
            d.unnamed([1, 2, 3], at(4), grace, named),
            vec![(2, Duration::from_secs(4))]
        );
        assert_eq!(
            d.unnamed([1, 2, 3, 9], at(6), grace, named),
            vec![(2, Duration::from_secs(6)), (3, Duration::from_secs(4))],
            "a vehicle with no holder (9) is not this book's"
        );
    }
}
