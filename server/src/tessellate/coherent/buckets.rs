//! The frame-coherent tessellator's queues, kept from frame to frame: priority buckets
//! (the spec's queue) whose entries live as long as the evaluation they carry, and the
//! odometer schedules that say which kept evaluations are due.
//!
//! A frontier diamond is queued once per evaluation, its entry naming the evaluation by
//! a stamp ([`Stamped`]): when the diamond is evaluated again, leaves its frontier or is
//! popped, older entries go stale and are dropped when met (a check of the stamp kept
//! beside the diamond). So a frame pushes what it evaluated and pops what it splits or
//! merges, and nothing walks the frontiers: the fixed cost that made a one-change frame
//! cost 150 µs at 32,768 triangles on `kossou` (every one of some 26,000 frontier
//! diamonds checked and pushed again, each frame) is gone. Stale entries are counted, and
//! the owner compacts (re-queues the live entries alone) once they outnumber the live
//! ones, so memory stays proportional to the frontier.
//!
//! Within a bucket the order is first in, first out, as in the from-scratch queue. (Last
//! in, first out was tried: at the budget, split/merge swaps of diamonds in one bucket
//! then cycled until the update's bound, 9 rebuilds along the bench's drive, none with
//! this order.)

/// Number of buckets, and the one above every priority ([`crate::tessellate::queue`]).
use crate::tessellate::queue::BUCKETS;

/// A queued diamond: its packed position and the stamp of the evaluation it carries.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct Stamped {
    pub pos: u32,
    pub stamp: u32,
}

impl Stamped {
    fn pack(self) -> u64 {
        (u64::from(self.stamp) << 32) | u64::from(self.pos)
    }

    fn unpack(e: u64) -> Stamped {
        Stamped {
            pos: e as u32,
            stamp: (e >> 32) as u32,
        }
    }
}

/// Priority buckets kept across frames (entries pushed and popped, never rebuilt per
/// frame); a two-level bitmap finds the highest non-empty bucket.
pub(super) struct Buckets {
    /// Per bucket, `(entry, priority)`: the priority beside it lets the error bound scan a
    /// bucket without looking every entry up.
    lists: Vec<std::collections::VecDeque<(u64, f32)>>,
    nonempty: [u64; BUCKETS / 64],
    summary: u32,
    len: usize,
}

impl Default for Buckets {
    fn default() -> Self {
        Buckets {
            lists: vec![std::collections::VecDeque::new(); BUCKETS],
            nonempty: [0; BUCKETS / 64],
            summary: 0,
            len: 0,
        }
    }
}

impl Buckets {
    /// Entries queued, stale ones included.
    pub fn len(&self) -> usize {
        self.len
    }

    pub fn clear(&mut self) {
        while let Some(b) = self.top_bucket() {
            self.lists[b].clear();
            self.clear_bit(b);
        }
        self.len = 0;
    }

    /// Queues `e`, whose evaluation gave `prio`, in `bucket`.
    #[inline]
    pub fn push(&mut self, bucket: usize, e: Stamped, prio: f32) {
        let list = &mut self.lists[bucket];
        if list.is_empty() {
            self.nonempty[bucket >> 6] |= 1 << (bucket & 63);
            self.summary |= 1 << (bucket >> 6);
        }
        list.push_back((e.pack(), prio));
        self.len += 1;
    }

    /// The highest non-empty bucket.
    #[inline]
    pub fn top_bucket(&self) -> Option<usize> {
        if self.summary == 0 {
            return None;
        }
        let w = 31 - self.summary.leading_zeros() as usize;
        Some(w * 64 + 63 - self.nonempty[w].leading_zeros() as usize)
    }

    /// The entry the next pop returns, with its bucket.
    #[inline]
    pub fn peek(&self) -> Option<(usize, Stamped)> {
        let b = self.top_bucket()?;
        let (e, _) = *self.lists[b].front()?;
        Some((b, Stamped::unpack(e)))
    }

    /// Removes and returns the next entry of the highest non-empty bucket.
    #[inline]
    pub fn pop(&mut self) -> Option<(usize, Stamped)> {
        let b = self.top_bucket()?;
        let list = &mut self.lists[b];
        let (e, _) = list.pop_front()?;
        if list.is_empty() {
            self.clear_bit(b);
        }
        self.len -= 1;
        Some((b, Stamped::unpack(e)))
    }

    #[inline]
    fn clear_bit(&mut self, b: usize) {
        self.nonempty[b >> 6] &= !(1 << (b & 63));
        if self.nonempty[b >> 6] == 0 {
            self.summary &= !(1 << (b >> 6));
        }
    }

    /// Non-empty buckets, highest first.
    fn buckets_desc(&self) -> impl Iterator<Item = usize> + '_ {
        (0..BUCKETS)
            .rev()
            .filter(|&b| self.nonempty[b >> 6] >> (b & 63) & 1 != 0)
    }

    /// The highest priority of a live entry (`live` says which are), from the highest
    /// bucket holding one; `top` (ranked by position, not priority) is read whole and the
    /// search goes on below it. An entry is looked up only when it would raise the
    /// highest found so far: a few lookups a bucket, not one an entry.
    pub fn max_live(&self, top: usize, live: impl Fn(Stamped) -> bool) -> f32 {
        let mut best = 0f32;
        for b in self.buckets_desc() {
            let mut most: Option<f32> = None;
            for &(e, prio) in &self.lists[b] {
                if most.is_none_or(|m| prio > m) && live(Stamped::unpack(e)) {
                    most = Some(prio);
                }
            }
            if let Some(v) = most {
                best = best.max(v);
                if b != top {
                    break;
                }
            }
        }
        best
    }

    /// Every entry with its bucket, stale ones included (for the audit).
    pub fn entries(&self) -> impl Iterator<Item = (usize, Stamped)> + '_ {
        self.buckets_desc().flat_map(move |b| {
            self.lists[b]
                .iter()
                .map(move |&(e, _)| (b, Stamped::unpack(e)))
        })
    }

    pub fn heap_bytes(&self) -> usize {
        self.lists.capacity() * std::mem::size_of::<std::collections::VecDeque<(u64, f32)>>()
            + self.lists.iter().map(|l| l.capacity() * 16).sum::<usize>()
    }

    /// Frees what the buckets reserved beyond what they hold.
    pub fn shrink(&mut self) {
        for l in &mut self.lists {
            l.shrink_to_fit();
        }
    }
}

/// When kept evaluations fall due: `(odometer reading, diamond)` pairs in a radix heap
/// (Ahuja et al. 1990) over the readings' bits, stale entries dropped when popped.
///
/// Readings only grow, and every reading pushed is at least the odometer now, so a
/// monotone queue fits: an entry sits in the bucket of the highest bit in which its
/// reading differs from `last` (the newest reading taken), and is moved to a lower
/// bucket only when `last` catches up with its bucket; each bucket keeps its smallest
/// reading, so "anything due?" reads one word. Buckets are plain vectors walked in order,
/// so a frame touches a few cache lines: a binary heap of the same entries walked 16
/// levels of scattered memory per pop, 1–2 µs each with the caches cold (as they are
/// when a server serves many viewers in turn).
pub(super) struct Schedule {
    /// Bucket `i` holds readings whose highest bit differing from `last` is `i - 1`
    /// (bucket 0: equal to `last`); as `(reading bits, entry)`.
    buckets: Vec<Vec<(u64, u64)>>,
    /// Each bucket's smallest reading (bits).
    least: [u64; 65],
    /// Buckets not empty, a bit each.
    nonempty: u128,
    last: u64,
    len: usize,
}

/// Entries a schedule's emptied bucket keeps room for.
const KEEP_CAPACITY: usize = 256;

impl Default for Schedule {
    fn default() -> Self {
        Schedule {
            buckets: vec![Vec::new(); 65],
            least: [u64::MAX; 65],
            nonempty: 0,
            last: 0,
            len: 0,
        }
    }
}

impl Schedule {
    pub fn len(&self) -> usize {
        self.len
    }

    /// Empties the schedule (and forgets the readings taken: any may be pushed next).
    pub fn clear(&mut self) {
        for b in &mut self.buckets {
            b.clear();
        }
        self.least = [u64::MAX; 65];
        self.nonempty = 0;
        self.last = 0;
        self.len = 0;
    }

    #[inline]
    fn bucket(&self, at: u64) -> usize {
        (64 - (at ^ self.last).leading_zeros()) as usize
    }

    #[inline]
    fn put(&mut self, at: u64, e: u64) {
        let b = self.bucket(at);
        self.buckets[b].push((at, e));
        self.least[b] = self.least[b].min(at);
        self.nonempty |= 1 << b;
    }

    /// Schedules `e` at odometer reading `at` (an infinite one is never due and is not
    /// scheduled; one below a reading already taken counts as that one).
    #[inline]
    pub fn push(&mut self, at: f64, e: Stamped) {
        if at.is_finite() {
            // Non-negative floats order as their bits.
            let at = at.max(0.0).to_bits().max(self.last);
            self.put(at, e.pack());
            self.len += 1;
        }
    }

    /// The next entry due at odometer reading `now`, if any, with its reading.
    #[inline]
    pub fn pop_due(&mut self, now: f64) -> Option<(f64, Stamped)> {
        let now = now.max(0.0).to_bits();
        loop {
            if self.nonempty == 0 {
                return None;
            }
            let b = self.nonempty.trailing_zeros() as usize;
            if self.least[b] > now {
                return None;
            }
            if b == 0 {
                let (at, e) = self.buckets[0].pop().expect("a bucket marked non-empty");
                if self.buckets[0].is_empty() {
                    self.nonempty &= !1;
                    self.least[0] = u64::MAX;
                }
                self.len -= 1;
                return Some((f64::from_bits(at), Stamped::unpack(e)));
            }
            // The smallest reading is due: take it as `last`, and move its bucket's
            // entries down (each to a lower bucket: they share more bits with it).
            self.last = self.least[b];
            let moved = std::mem::take(&mut self.buckets[b]);
            self.least[b] = u64::MAX;
            self.nonempty &= !(1 << b);
            for &(at, e) in &moved {
                self.put(at, e);
            }
            // A small bucket keeps its memory for later; a large one gives it back (its
            // entries went to lower buckets: kept, every bucket's peak would stay held).
            if moved.capacity() <= KEEP_CAPACITY {
                let mut moved = moved;
                moved.clear();
                self.buckets[b] = moved;
            }
        }
    }

    /// Every entry with its reading, stale ones included (for the audit).
    pub fn entries(&self) -> impl Iterator<Item = (f64, Stamped)> + '_ {
        self.buckets
            .iter()
            .flatten()
            .map(|&(at, e)| (f64::from_bits(at), Stamped::unpack(e)))
    }

    pub fn heap_bytes(&self) -> usize {
        self.buckets
            .iter()
            .map(|b| b.capacity() * 16)
            .sum::<usize>()
            + 65 * 24
    }

    pub fn shrink(&mut self) {
        for b in &mut self.buckets {
            b.shrink_to_fit();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn s(pos: u32, stamp: u32) -> Stamped {
        Stamped { pos, stamp }
    }

    #[test]
    fn pops_highest_bucket_first_oldest_within() {
        let mut q = Buckets::default();
        for (b, e) in [(5, 1), (700, 2), (5, 3), (BUCKETS - 1, 4), (700, 5), (0, 6)] {
            q.push(b, s(e, e), 0.0);
        }
        assert_eq!(q.len(), 6);
        assert_eq!(q.peek(), Some((BUCKETS - 1, s(4, 4))));
        let order: Vec<u32> = std::iter::from_fn(|| q.pop()).map(|(_, e)| e.pos).collect();
        assert_eq!(order, [4, 2, 5, 1, 3, 6]);
        assert_eq!((q.top_bucket(), q.len()), (None, 0));
        q.push(9, s(7, 0), 0.0);
        q.clear();
        assert_eq!(q.pop(), None);
    }

    #[test]
    fn max_live_skips_stale_entries_and_reads_top_whole() {
        let mut q = Buckets::default();
        let top = BUCKETS - 1;
        q.push(top, s(1, 0), 1.0);
        q.push(top, s(2, 0), 2.0);
        q.push(100, s(3, 1), 3.0); // stale
        q.push(90, s(4, 0), 4.0);
        q.push(90, s(9, 1), 9.0); // stale
        q.push(90, s(5, 0), 5.0);
        q.push(80, s(8, 0), 8.0); // below the highest live bucket
        let live = |e: Stamped| e.stamp == 0;
        assert_eq!(q.max_live(top, live), 5.0);
        assert_eq!(Buckets::default().max_live(top, live), 0.0);
    }

    #[test]
    fn schedule_pops_what_is_due_in_order() {
        let mut d = Schedule::default();
        d.push(3.0, s(3, 0));
        d.push(1.0, s(1, 0));
        d.push(f64::INFINITY, s(9, 0));
        d.push(2.0, s(2, 0));
        assert_eq!(d.len(), 3, "an infinite reading is never due");
        assert_eq!(d.pop_due(0.5), None);
        let due: Vec<u32> = std::iter::from_fn(|| d.pop_due(2.0))
            .map(|(_, e)| e.pos)
            .collect();
        assert_eq!(due, [1, 2]);
        // Pushed after readings were taken: at least the last one.
        d.push(2.5, s(4, 0));
        d.push(0.0, s(5, 0));
        assert_eq!(d.pop_due(2.0), Some((2.0, s(5, 0))));
        assert_eq!(d.pop_due(2.9), Some((2.5, s(4, 0))));
        assert_eq!(d.pop_due(10.0), Some((3.0, s(3, 0))));
        assert_eq!((d.pop_due(10.0), d.len()), (None, 0));
        d.clear();
        assert_eq!(d.len(), 0);
    }

    /// Many readings, pushed as an odometer grows and popped as it passes them, come out
    /// exactly when due, against a sorted reference.
    #[test]
    fn schedule_matches_a_reference() {
        let mut d = Schedule::default();
        let mut reference: Vec<(f64, u32)> = Vec::new();
        let mut seed = 99u64;
        let mut rand = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut now = 0.0;
        for step in 0..2000u32 {
            now += rand() * 3.0;
            for k in 0..3 {
                let at = now + rand().powi(3) * 500.0;
                d.push(at, s(step * 4 + k, 0));
                reference.push((at, step * 4 + k));
            }
            let mut got: Vec<(f64, u32)> = std::iter::from_fn(|| d.pop_due(now))
                .map(|(at, e)| (at, e.pos))
                .collect();
            let (mut want, rest): (Vec<_>, Vec<_>) =
                reference.iter().partition(|&&(at, _)| at <= now);
            reference = rest;
            got.sort_by(|a, b| a.partial_cmp(b).expect("finite readings"));
            want.sort_by(|a, b| a.partial_cmp(b).expect("finite readings"));
            assert_eq!(got, want, "step {step}");
            assert_eq!(d.len(), reference.len());
        }
    }
}
