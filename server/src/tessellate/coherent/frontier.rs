//! One frontier of the cut (split candidates, or merge candidates): its members in a dense
//! list of small records ([`Member`], in [`Chunks`]) with an index by position
//! ([`PosIndex`]), the priority queue they sit in (threaded through the records) and the
//! two schedules that say when each is due (bucket vectors of places, each member knowing
//! its index), in [`super::buckets`].
//!
//! A member keeps only what the next frame needs of its last evaluation: its priority,
//! its verdicts, when it falls due (an odometer key each), and its links: 32 bytes, where
//! the first version kept a 64-byte entry beside a list of positions and a table of
//! `(position, index)` pairs, plus 16-byte queue and schedule entries pushed per
//! evaluation. Two decisions, measured on `kossou` at 65,536 triangles:
//!
//! - What an evaluation needs that does not depend on the camera (centre, error, corner
//!   heights, size) is gathered from the map again at each evaluation
//!   ([`super::eval::fixed`]): a frame evaluates 10 to 14 diamonds and a rebuild gathers
//!   every member anyway, where keeping it cost 28 bytes a member (1.1 MB).
//! - Links are places of 24 bits (a frontier holds fewer than 2^24 members:
//!   [`crate::tessellate::frontier::MAX_INDEXED`]): as `u32`s the record was 44 bytes
//!   (1.72 MB for the split frontier's records at the drive's end, now 1.14 MB).

use super::audit_error::ListError;
use super::buckets::{Link, NIL, Nodes, Queue, Schedule};
use crate::tessellate::frontier::{Chunks, PosIndex};
use crate::tessellate::queue::{TOP, bucket_of};

/// [`Member`] flags: worth splitting (error, in view or under the eye, at or above the
/// threshold); under the eye; in view with error but below the threshold.
pub(super) const WANTED: u8 = 1;
pub(super) const UNDER: u8 = 2;
pub(super) const DROPPED: u8 = 4;

/// The position of a free place's record (no diamond's: positions are at most
/// `32768 | 32768 << 16`).
const FREE: u32 = u32::MAX;

/// Free places at most before [`Frontier::remove`] compacts the records, and the share of
/// the places they may be: a frontier that shrank for good (a lower budget) gives its
/// memory back; one that breathes, as a driving cut's does, refills its holes.
const FREE_MIN: usize = 256;
const FREE_SHARE: usize = 16;

/// A [`Member`]'s link to no member: places are below 2^24 - 1
/// ([`crate::tessellate::frontier::MAX_INDEXED`]).
const NIL24: u32 = 0xff_ffff;

/// Where list `w`'s 24-bit link starts in [`Member::links`]: the queue's previous and
/// next (0 and 3), then each schedule's index in its bucket (6 and 9; a schedule has no
/// next: its `Link::next` reads 0).
#[inline(always)]
fn prev_at(w: usize) -> usize {
    if w == 0 { 0 } else { 3 + 3 * w }
}

/// A frontier diamond and its last evaluation: 32 bytes.
#[derive(Clone, Copy, Debug)]
pub(super) struct Member {
    /// Packed position.
    pub pos: u32,
    /// Priority at its last evaluation (0 before the first).
    pub prio: f32,
    /// When it is due again, per odometer (while scheduled on it).
    keys: [u32; 2],
    /// Its links in the queue (previous then next) and the two schedules (its index in its
    /// bucket's vector, then 0): places of
    /// 24 bits, little-endian ([`NIL24`]: none). (As `u32`s the record was 44 bytes.)
    links: [u8; 12],
    /// Per schedule, the bucket its entry sits in (while scheduled): its key may have
    /// grown since ([`Schedule::reschedule`]). Within the padding the record had.
    at: [u8; 2],
    /// [`WANTED`], [`UNDER`], [`DROPPED`].
    pub flags: u8,
}

impl Member {
    #[inline(always)]
    fn get24(&self, at: usize) -> u32 {
        let b = &self.links[at..at + 3];
        let v = u32::from_le_bytes([b[0], b[1], b[2], 0]);
        if v == NIL24 { NIL } else { v }
    }

    #[inline(always)]
    fn set24(&mut self, at: usize, v: u32) {
        debug_assert!(v == NIL || v < NIL24, "places fit in 24 bits");
        self.links[at..at + 3].copy_from_slice(&(v & NIL24).to_le_bytes()[..3]);
    }

    #[inline(always)]
    fn link(&self, w: usize) -> Link {
        Link {
            prev: self.get24(prev_at(w)),
            next: if w == 0 { self.get24(3) } else { 0 },
        }
    }

    pub(super) fn queued(&self) -> bool {
        self.link(0).linked()
    }

    /// Whether it is scheduled on odometer `k`, and at which key.
    pub(super) fn due(&self, k: usize) -> Option<u32> {
        self.link(1 + k).linked().then_some(self.keys[k])
    }

    /// A free place's record ([`Frontier::remove`]).
    pub(super) fn is_free(&self) -> bool {
        self.pos == FREE
    }

    /// A diamond's record, not evaluated (neither queued nor scheduled).
    fn fresh(pos: u32) -> Member {
        Member {
            pos,
            prio: 0.0,
            keys: [0; 2],
            links: [0xff; 12],
            at: [0; 2],
            flags: 0,
        }
    }
}

impl Nodes for Chunks<Member> {
    #[inline(always)]
    fn len(&self) -> usize {
        Chunks::len(self)
    }
    #[inline(always)]
    fn link(&self, i: u32, w: usize) -> Link {
        self[i as usize].link(w)
    }
    #[inline(always)]
    fn set_link(&mut self, i: u32, w: usize, l: Link) {
        let m = &mut self[i as usize];
        m.set24(prev_at(w), l.prev);
        if w == 0 {
            m.set24(3, l.next);
        }
    }
    #[inline(always)]
    fn set_prev(&mut self, i: u32, w: usize, prev: u32) {
        self[i as usize].set24(prev_at(w), prev);
    }
    #[inline(always)]
    fn set_next(&mut self, i: u32, w: usize, next: u32) {
        debug_assert_eq!(w, 0, "only the queue's lists have a next");
        self[i as usize].set24(3, next);
    }
    #[inline(always)]
    fn key(&self, i: u32, k: usize) -> u32 {
        self[i as usize].keys[k]
    }
    #[inline(always)]
    fn set_key(&mut self, i: u32, k: usize, key: u32) {
        self[i as usize].keys[k] = key;
    }
    #[inline(always)]
    fn entry_bucket(&self, i: u32, k: usize) -> usize {
        usize::from(self[i as usize].at[k])
    }
    #[inline(always)]
    fn set_entry_bucket(&mut self, i: u32, k: usize, b: usize) {
        debug_assert!(b < 256, "a schedule has 121 buckets");
        self[i as usize].at[k] = b as u8;
    }
    #[inline(always)]
    fn prefetch(&self, i: u32) {
        Chunks::prefetch(self, i as usize);
    }
    #[inline(always)]
    fn prio(&self, i: u32) -> f32 {
        self[i as usize].prio
    }
}

/// A frontier: its members, the queue and the schedules.
pub(super) struct Frontier {
    /// Merge candidates (else split candidates): which bucket a member is queued in.
    merges: bool,
    /// By place; a removed member's place is left free ([`FREE`]) for the next inserted.
    members: Chunks<Member>,
    /// The free places, the latest freed last.
    free: Vec<u32>,
    index: PosIndex,
    queue: Queue,
    due: [Schedule; 2],
}

impl Frontier {
    pub(super) fn new(merges: bool) -> Frontier {
        Frontier {
            merges,
            members: Chunks::default(),
            free: Vec::new(),
            index: PosIndex::default(),
            // The split queue's highest priority is the error bound.
            queue: Queue::new(!merges),
            due: [Schedule::new(0), Schedule::new(1)],
        }
    }

    /// Members.
    pub(super) fn len(&self) -> usize {
        self.members.len() - self.free.len()
    }

    pub(super) fn members(&self) -> impl Iterator<Item = &Member> + '_ {
        self.members.iter().filter(|m| !m.is_free())
    }

    /// Every place's record, free ones included ([`Member::is_free`]), by place.
    pub(super) fn records(&self) -> impl Iterator<Item = &Member> + '_ {
        self.members.iter()
    }

    /// The members' places.
    pub(super) fn places(&self) -> impl Iterator<Item = u32> + '_ {
        (0..self.members.len() as u32).filter(|&i| !self.members[i as usize].is_free())
    }

    pub(super) fn clear(&mut self) {
        self.members.clear();
        self.free = Vec::new();
        self.index.clear();
        self.queue.clear();
        self.due.iter_mut().for_each(Schedule::clear);
    }

    pub(super) fn members_bytes(&self) -> usize {
        self.members.heap_bytes() + self.free.capacity() * 4
    }

    pub(super) fn index_bytes(&self) -> usize {
        self.index.heap_bytes()
    }

    pub(super) fn queue_bytes(&self) -> usize {
        self.queue.heap_bytes()
    }

    /// The schedule of odometer `k`'s bucket vectors.
    pub(super) fn schedule_bytes(&self, k: usize) -> usize {
        self.due[k].heap_bytes()
    }

    /// Members queued, and scheduled on each odometer.
    pub(super) fn counts(&self) -> (usize, usize, usize) {
        (self.queue.len(), self.due[0].len(), self.due[1].len())
    }

    #[inline]
    fn find(&self, pos: u32) -> Option<u32> {
        let m = &self.members;
        self.index.get(pos, |i| m[i as usize].pos)
    }

    /// Makes room for `members` in the index without resizing on the way there.
    pub(super) fn reserve(&mut self, members: usize) {
        let m = &self.members;
        self.index.reserve(members, |i| m[i as usize].pos);
    }

    #[inline]
    pub(super) fn contains(&self, pos: u32) -> bool {
        self.find(pos).is_some()
    }

    /// Asks for the index slot of `pos` ahead of a look-up, so that a change's look-ups
    /// (its children, its parents) wait for their cache misses together.
    #[inline(always)]
    pub(super) fn prefetch(&self, pos: u32) {
        self.index.prefetch(pos);
    }

    /// Then asks for the record of member `pos`, if it likely is one (its index slot read:
    /// best after [`Self::prefetch`]).
    #[inline(always)]
    pub(super) fn prefetch_member(&self, pos: u32) {
        if let Some(i) = self.index.likely(pos) {
            self.members.prefetch(i as usize);
        }
    }

    /// The bucket a member's evaluation queues it in, if any. A split candidate goes in its
    /// priority's bucket (under the eye: the top one) when it is worth splitting; otherwise
    /// in none. A merge candidate goes first (the top bucket) when unwanted, else lowest
    /// priority first; one under the eye in none (the ground under the eye stays refined).
    #[inline]
    fn bucket(&self, m: &Member) -> Option<usize> {
        let (wanted, under) = (m.flags & WANTED != 0, m.flags & UNDER != 0);
        if self.merges {
            match (under, wanted) {
                (true, _) => None,
                (false, false) => Some(TOP),
                (false, true) => Some(TOP - 1 - bucket_of(m.prio)),
            }
        } else {
            wanted.then(|| if under { TOP } else { bucket_of(m.prio) })
        }
    }

    /// The bucket `m` is queued in by its evaluation (for the audit).
    pub(super) fn queue_bucket(&self, m: &Member) -> Option<usize> {
        self.bucket(m)
    }

    /// Member `i`'s position.
    #[inline]
    pub(super) fn pos(&self, i: u32) -> u32 {
        self.members[i as usize].pos
    }

    /// The place of member `pos`, if it is one (valid until a member is removed).
    #[inline]
    pub(super) fn place(&self, pos: u32) -> Option<u32> {
        self.find(pos)
    }

    /// Adds `pos` as a member not yet evaluated (neither queued nor scheduled): its place,
    /// or `None` when it was one already.
    pub(super) fn insert(&mut self, pos: u32) -> Option<u32> {
        if self.contains(pos) {
            return None;
        }
        let i = match self.free.pop() {
            Some(i) => {
                self.members[i as usize] = Member::fresh(pos);
                i
            }
            None => {
                self.members.push(Member::fresh(pos));
                self.members.len() as u32 - 1
            }
        };
        let m = &self.members;
        self.index.insert(pos, i, |i| m[i as usize].pos);
        Some(i)
    }

    /// Takes member `i` out of the queue and the schedules it is in.
    fn unlink(&mut self, i: u32) {
        let m = self.members[i as usize];
        if m.queued() {
            let b = self.bucket(&m).expect("a queued member has a bucket");
            self.queue.remove(&mut self.members, b, i);
        }
        for (k, due) in self.due.iter_mut().enumerate() {
            if m.due(k).is_some() {
                due.remove(&mut self.members, i);
            }
        }
    }

    /// Removes `pos`; false when it was not a member. Its place is left free for the next
    /// member inserted: moving the last member into it, as this did first, told the
    /// moved member's queue neighbours, schedule slots and index slot where it went, four
    /// or five cache misses a removal (two or three removals a split or merge) when a
    /// server serves many viewers in turn. Free places are compacted away only once they
    /// are many ([`FREE_MIN`], [`FREE_SHARE`]).
    pub(super) fn remove(&mut self, pos: u32) -> bool {
        let Some(i) = self.find(pos) else {
            return false;
        };
        self.unlink(i);
        let m = &self.members;
        self.index.remove(pos, |j| m[j as usize].pos);
        if i as usize + 1 == self.members.len() {
            self.members.swap_remove(i as usize);
        } else {
            self.members[i as usize] = Member::fresh(FREE);
            self.free.push(i);
        }
        if self.free.len() > FREE_MIN && self.free.len() * FREE_SHARE > self.members.len() {
            self.compact();
        }
        true
    }

    /// Fills the free places with the last members, and drops the free places at the end.
    fn compact(&mut self) {
        self.free.sort_unstable();
        let mut holes = std::mem::take(&mut self.free).into_iter();
        while let Some(hole) = holes.next() {
            // Free records at the end go first (the highest free places, in order).
            while self.members.len() > 0 && self.members[self.members.len() - 1].is_free() {
                self.members.swap_remove(self.members.len() - 1);
                holes.next_back();
            }
            if hole as usize >= self.members.len() {
                break;
            }
            self.move_last_to(hole);
        }
    }

    /// Moves the last member (not free) into the free place `i`, telling the index, its
    /// queue neighbours and its schedule slots.
    fn move_last_to(&mut self, i: u32) {
        let m = &self.members;
        let from = m.len() as u32 - 1;
        self.index
            .moved(m[from as usize].pos, i, |j| m[j as usize].pos);
        self.members.swap_remove(i as usize);
        let moved = self.members[i as usize];
        if moved.queued() {
            let b = self.bucket(&moved).expect("a queued member has a bucket");
            self.queue.relocate(&mut self.members, b, from, i);
        }
        for (k, due) in self.due.iter_mut().enumerate() {
            if moved.due(k).is_some() {
                due.relocate(&mut self.members, from, i);
            }
        }
    }

    /// Keeps an evaluation of member `i` (by place: priority, flags, and per odometer the
    /// key it is due at, `None`: never), and queues and schedules it by it. By place, not
    /// position: the callers know it (a due member's, a member just inserted), and looking
    /// it up again in the index was 12 % of a loaded server's time (cache misses, with
    /// 50 viewers' cuts).
    pub(super) fn keep(&mut self, i: u32, prio: f32, flags: u8, keys: [Option<u32>; 2]) {
        let old = self.members[i as usize];
        let new = Member { prio, flags, ..old };
        let was = if old.queued() {
            Some(self.bucket(&old).expect("a queued member has a bucket"))
        } else {
            None
        };
        let will = self.bucket(&new);
        if let Some(b) = was
            && was == will
        {
            // It stays where it is (most evaluations of a driving frame: the priority moved
            // by a few per cent, its bucket spans 9 %); only its bucket's highest follows.
            let m = &mut self.members[i as usize];
            (m.prio, m.flags) = (prio, flags);
            self.queue.repriced(b, old.prio, prio);
        } else {
            if let Some(b) = was {
                self.queue.remove(&mut self.members, b, i);
            }
            let m = &mut self.members[i as usize];
            (m.prio, m.flags) = (prio, flags);
            if let Some(b) = will {
                self.queue.push(&mut self.members, b, i);
            }
        }
        for (k, key) in keys.into_iter().enumerate() {
            self.due[k].reschedule(&mut self.members, i, key);
        }
    }

    /// The first member of the highest bucket, taken out of the queue (it stays a
    /// member): its bucket, position and priority.
    pub(super) fn pop(&mut self) -> Option<(usize, u32, f32)> {
        let (b, i) = self.queue.pop(&mut self.members)?;
        let m = &self.members[i as usize];
        Some((b, m.pos, m.prio))
    }

    /// The bucket and member the next pop returns.
    pub(super) fn peek(&self) -> Option<(usize, &Member)> {
        let (b, i) = self.queue.peek()?;
        Some((b, &self.members[i as usize]))
    }

    /// Queues member `pos` again by its kept evaluation, after a pop (nothing if it left
    /// the frontier since, or is queued).
    pub(super) fn requeue(&mut self, pos: u32) {
        if let Some(i) = self.find(pos)
            && !self.members[i as usize].queued()
        {
            let m = self.members[i as usize];
            let b = self.bucket(&m).expect("a popped member had a bucket");
            self.queue.push(&mut self.members, b, i);
        }
    }

    /// Takes every member due on odometer `k` at the keys `now` out of its schedule into
    /// `out` (places), and out of the other schedule those due there too (so one due on
    /// both is taken once). One not due on the other stays scheduled there, its entry
    /// kept for [`Self::keep`] (taking it out touched the member that filled its place: a
    /// cache miss, in a server serving many viewers, for most evaluations of a turning
    /// frame).
    pub(super) fn take_due(&mut self, k: usize, now: [u32; 2], out: &mut Vec<u32>) {
        let from = out.len();
        self.due[k].take_due(&mut self.members, now[k], out);
        for &i in &out[from..] {
            if self.members[i as usize]
                .due(1 - k)
                .is_some_and(|key| key <= now[1 - k])
            {
                self.due[1 - k].remove(&mut self.members, i);
            }
        }
    }

    /// Shifts odometer `k`'s keys down by `shift` (those below it to 0), the schedule
    /// made again in member order.
    pub(super) fn rebase(&mut self, k: usize, shift: u32) {
        let keys: Vec<Option<u32>> = self
            .members
            .iter()
            .map(|m| m.due(k).map(|key| key.saturating_sub(shift)))
            .collect();
        self.due[k].clear();
        for (i, key) in keys.into_iter().enumerate() {
            self.members.set_link(i as u32, 1 + k, Link::OUT);
            if let Some(key) = key {
                self.due[k].push(&mut self.members, i as u32, key);
            }
        }
    }

    /// The highest priority queued: the top bucket (ranked by position, not priority) is
    /// read whole, and the search goes on to the next bucket below it.
    pub(super) fn max_queued(&mut self) -> f32 {
        let mut best = 0f32;
        let mut bucket = self.queue.top_bucket();
        while let Some(b) = bucket {
            best = best.max(self.queue.most(&self.members, b));
            if b != TOP {
                break;
            }
            bucket = self.queue.below(b);
        }
        best
    }

    /// The queue's buckets and the schedules, each member where its evaluation puts it,
    /// checked (for the audit): `(bucket, member)` queued, and each odometer's members.
    #[allow(clippy::type_complexity)]
    pub(super) fn lists(&self) -> Result<(Vec<(usize, u32)>, [Vec<u32>; 2]), ListError> {
        let queued = self
            .queue
            .lists(&self.members)?
            .into_iter()
            .flat_map(|(b, l)| l.into_iter().map(move |i| (b, i)))
            .collect();
        Ok((
            queued,
            [
                self.due[0].lists(&self.members)?,
                self.due[1].lists(&self.members)?,
            ],
        ))
    }

    /// Whether `i` is the place the index gives member `i`'s position (for the audit).
    pub(super) fn indexed(&self, i: usize) -> bool {
        self.find(self.members[i].pos) == Some(i as u32) && self.index.len() == self.len()
    }

    /// Whether the free places are the free records, each once (for the audit).
    pub(super) fn free_listed(&self) -> bool {
        let mut free = self.free.clone();
        free.sort_unstable();
        free.dedup();
        free.len() == self.free.len()
            && free.iter().all(|&i| self.members[i as usize].is_free())
            && self.members.iter().filter(|m| m.is_free()).count() == free.len()
    }
}
