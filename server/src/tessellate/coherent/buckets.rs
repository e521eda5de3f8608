//! The frame-coherent tessellator's queues, kept from frame to frame: priority buckets
//! (the spec's queue) as lists threaded through the frontier's own member records (ROAM's
//! doubly linked bucket lists, Duchaineau et al. 1997 §6), reached through [`Nodes`], and
//! the odometer schedules that say which kept evaluations are due, as bucket vectors of
//! member places ([`Schedule`]).
//!
//! A member sits in at most one bucket of its frontier's [`Queue`] and in at most one
//! bucket of each [`Schedule`], by a [`Link`] of its own for each (in the queue its
//! previous and next member; in a schedule its index in the bucket's vector): evaluated
//! again, it is taken out of where its old evaluation put it and put where the new one
//! does; leaving its frontier, it is taken out; moved in the dense list (a removal fills
//! the hole with the last member), its neighbours, bucket head or bucket slot are told. So
//! a frame touches what it evaluated, splits or merges, nothing walks the frontiers, and
//! nothing goes stale. Each queue list is circular (the head's previous member is its
//! tail), so a bucket costs one head.
//!
//! Within a bucket the order is first in, first out, as in the from-scratch queue. (Last
//! in, first out was tried: at the budget, split/merge swaps of diamonds in one bucket
//! then cycled until the update's bound, 9 rebuilds along the bench's drive, none with
//! this order.)
//!
//! **Memory** (issue 22). The first version pushed a new entry per evaluation into
//! per-bucket `VecDeque`s (`(position, stamp, priority)`, 16 bytes) and per-schedule-bucket
//! vectors (`(reading, position and stamp)`, 16 bytes), each naming its evaluation by a
//! stamp and dropped when met stale, and re-filled everything from the live evaluations
//! once stale entries outnumbered them twice: at the end of the bench's drive on `kossou`
//! at 65,536 triangles the split side held 63,687 queue entries and 108,874 schedule
//! entries for 30,935 members (4.27 MB), the merge side 1.6 MB more, and each queue 2,048
//! `VecDeque` headers (64 KB). Threaded through the members, the three lists cost a
//! member 18 bytes of links (24-bit places, [`super::frontier::Member`]) and a queue 8 KB
//! of heads (the schedules, since, 4 bytes a scheduled member: see [`Schedule`]); none
//! is stale. Compacting lazily kept entries harder (in place, at a lower threshold) could
//! not go below 8 bytes an entry for a schedule alone, stale ones on top.
//!
//! **Time.** A radix heap moves a member down a bucket at a time as the odometer nears its
//! key: the schedules' buckets go by digits of 4 bits, not bits, to move members half as
//! often, and are vectors, not lists ([`Schedule`]); a frame takes every due member at
//! once, the heap's last key jumping to the odometer's ([`Schedule::take_due`]). The queue keeps each split bucket's
//! highest priority ([`Queue::most`]): the error bound read the bucket that holds it whole
//! every frame, 540 scattered records
//! at the median (20 µs), where the vector of `(entry, priority)` had been read in order.
//! Along the bench's drive at 32,768 triangles (six runs of each in turn on a busy
//! machine) the median frame went from 17–41 µs to 13–21 µs, the p99 (frames of 100–240
//! changes) from 708–1,972 µs to 871–4,576 µs (medians of the six: 870 and 990).

/// Number of buckets, and the one above every priority ([`crate::tessellate::queue`]).
use super::audit_error::ListError;
use crate::tessellate::queue::BUCKETS;

/// No member: an empty bucket's head, and an unlinked member's previous.
pub(super) const NIL: u32 = u32::MAX;

/// A member's place in one circular list: its previous and next members.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct Link {
    pub prev: u32,
    pub next: u32,
}

impl Link {
    /// In no list.
    pub(super) const OUT: Link = Link {
        prev: NIL,
        next: NIL,
    };

    pub(super) fn linked(self) -> bool {
        self.prev != NIL
    }
}

/// The members the lists are threaded through, by place: their links (list `w`: 0 the
/// queue, 1 + `k` the schedule of odometer `k`), their schedule keys and priorities.
pub(super) trait Nodes {
    fn len(&self) -> usize;
    fn link(&self, i: u32, w: usize) -> Link;
    fn set_link(&mut self, i: u32, w: usize, l: Link);
    fn key(&self, i: u32, k: usize) -> u32;
    fn set_key(&mut self, i: u32, k: usize, key: u32);
    /// The bucket its entry sits in, in the schedule of odometer `k` (while scheduled).
    fn entry_bucket(&self, i: u32, k: usize) -> usize;
    fn set_entry_bucket(&mut self, i: u32, k: usize, b: usize);
    /// Brings its record into the cache ahead of use (see [`Schedule::take_due`]).
    fn prefetch(&self, _i: u32) {}
    /// Its priority, by which it is queued.
    fn prio(&self, i: u32) -> f32;

    #[inline(always)]
    fn set_prev(&mut self, i: u32, w: usize, prev: u32) {
        let l = self.link(i, w);
        self.set_link(i, w, Link { prev, ..l });
    }

    #[inline(always)]
    fn set_next(&mut self, i: u32, w: usize, next: u32) {
        let l = self.link(i, w);
        self.set_link(i, w, Link { next, ..l });
    }
}

/// Appends member `i` to the circular list at `head` (list `w`).
#[inline]
fn push_back(nodes: &mut impl Nodes, w: usize, head: &mut u32, i: u32) {
    if *head == NIL {
        *head = i;
        nodes.set_link(i, w, Link { prev: i, next: i });
    } else {
        let h = *head;
        let tail = nodes.link(h, w).prev;
        nodes.set_link(
            i,
            w,
            Link {
                prev: tail,
                next: h,
            },
        );
        nodes.set_next(tail, w, i);
        nodes.set_prev(h, w, i);
    }
}

/// Unlinks member `i` from the circular list at `head` (list `w`); true when it empties.
#[inline]
fn unlink(nodes: &mut impl Nodes, w: usize, head: &mut u32, i: u32) -> bool {
    let Link { prev, next } = nodes.link(i, w);
    debug_assert!(prev != NIL, "only a linked member is unlinked");
    nodes.set_link(i, w, Link::OUT);
    if next == i {
        *head = NIL;
        return true;
    }
    nodes.set_next(prev, w, next);
    nodes.set_prev(next, w, prev);
    if *head == i {
        *head = next;
    }
    false
}

/// Member `from`, linked in the list at `head` (list `w`), now lives at `to` (its record
/// copied there): its neighbours and the head follow.
#[inline]
fn relocate(nodes: &mut impl Nodes, w: usize, head: &mut u32, from: u32, to: u32) {
    let Link { prev, next } = nodes.link(to, w);
    if next == from {
        // Alone in its list.
        nodes.set_link(to, w, Link { prev: to, next: to });
    } else {
        nodes.set_next(prev, w, to);
        nodes.set_prev(next, w, to);
    }
    if *head == from {
        *head = to;
    }
}

/// The members of the circular list at `head` (list `w`), first to last, checked: each
/// one's previous names the one before it. For the audit.
pub(super) fn walk(nodes: &impl Nodes, w: usize, head: u32) -> Result<Vec<u32>, ListError> {
    let mut out = Vec::new();
    if head == NIL {
        return Ok(out);
    }
    let mut i = head;
    loop {
        if i as usize >= nodes.len() {
            return Err(ListError::PastMembers { list: w, member: i });
        }
        let l = nodes.link(i, w);
        let prev = out.last().copied().unwrap_or(nodes.link(head, w).prev);
        if l.prev != prev {
            return Err(ListError::Previous {
                list: w,
                member: i,
                prev: l.prev,
                want: prev,
            });
        }
        out.push(i);
        if out.len() > nodes.len() {
            return Err(ListError::Endless { list: w });
        }
        i = l.next;
        if i == head {
            return Ok(out);
        }
    }
}

/// Priority buckets kept across frames, each a first-in first-out list of members; a
/// two-level bitmap finds the highest non-empty bucket.
///
/// A queue may keep each bucket's highest priority ([`Queue::most`]: the split queue, for
/// the error bound): known while nothing that could be it left the bucket, found again by a
/// walk of the bucket (its members' records: scattered reads) only when it is asked for
/// after such a change. Walked every frame, the bucket holding the bound (on `kossou` at
/// 32,768 triangles a median of 540 members, up to 2,345) cost 20 µs a frame.
pub(super) struct Queue {
    heads: Vec<u32>,
    /// Per bucket, its highest priority, NaN when not known (empty when not kept).
    most: Vec<f32>,
    nonempty: [u64; BUCKETS / 64],
    summary: u32,
    len: usize,
}

impl Queue {
    /// An empty queue, keeping each bucket's highest priority or not.
    pub(super) fn new(keep_most: bool) -> Queue {
        Queue {
            heads: vec![NIL; BUCKETS],
            most: if keep_most {
                vec![f32::NAN; BUCKETS]
            } else {
                Vec::new()
            },
            nonempty: [0; BUCKETS / 64],
            summary: 0,
            len: 0,
        }
    }

    /// Members queued.
    pub(super) fn len(&self) -> usize {
        self.len
    }

    /// Empties the queue (the members' links are the caller's to forget).
    pub(super) fn clear(&mut self) {
        while let Some(b) = self.top_bucket() {
            self.heads[b] = NIL;
            self.clear_bit(b);
        }
        self.len = 0;
    }

    /// Queues member `i` (not queued) last in `bucket`.
    #[inline]
    pub(super) fn push(&mut self, nodes: &mut impl Nodes, bucket: usize, i: u32) {
        let empty = self.heads[bucket] == NIL;
        if empty {
            self.nonempty[bucket >> 6] |= 1 << (bucket & 63);
            self.summary |= 1 << (bucket >> 6);
        }
        if let Some(most) = self.most.get_mut(bucket) {
            let prio = nodes.prio(i);
            *most = if empty {
                prio
            } else if most.is_nan() {
                // Not known: stays so.
                f32::NAN
            } else {
                most.max(prio)
            };
        }
        push_back(nodes, 0, &mut self.heads[bucket], i);
        self.len += 1;
    }

    /// Takes member `i` out of `bucket`, where it is queued.
    #[inline]
    pub(super) fn remove(&mut self, nodes: &mut impl Nodes, bucket: usize, i: u32) {
        if unlink(nodes, 0, &mut self.heads[bucket], i) {
            self.clear_bit(bucket);
        }
        if let Some(most) = self.most.get_mut(bucket)
            && (most.is_nan() || nodes.prio(i) >= *most)
        {
            // It may have been the highest (or the bucket's highest is not known).
            *most = f32::NAN;
        }
        self.len -= 1;
    }

    /// A member queued in `bucket` and staying there had priority `old` and has `new`: the
    /// bucket's highest follows.
    #[inline]
    pub(super) fn repriced(&mut self, bucket: usize, old: f32, new: f32) {
        if let Some(most) = self.most.get_mut(bucket)
            && !most.is_nan()
        {
            if new >= *most {
                *most = new;
            } else if old >= *most {
                // It was the highest and is lower now: not known.
                *most = f32::NAN;
            }
        }
    }

    /// Member `from`, queued in `bucket`, now lives at `to`.
    pub(super) fn relocate(&mut self, nodes: &mut impl Nodes, bucket: usize, from: u32, to: u32) {
        relocate(nodes, 0, &mut self.heads[bucket], from, to);
    }

    /// The highest non-empty bucket.
    #[inline]
    pub(super) fn top_bucket(&self) -> Option<usize> {
        if self.summary == 0 {
            return None;
        }
        let w = 31 - self.summary.leading_zeros() as usize;
        Some(w * 64 + 63 - self.nonempty[w].leading_zeros() as usize)
    }

    /// The member the next pop returns, with its bucket.
    #[inline]
    pub(super) fn peek(&self) -> Option<(usize, u32)> {
        let b = self.top_bucket()?;
        Some((b, self.heads[b]))
    }

    /// Removes and returns the first member of the highest non-empty bucket.
    #[inline]
    pub(super) fn pop(&mut self, nodes: &mut impl Nodes) -> Option<(usize, u32)> {
        let (b, i) = self.peek()?;
        self.remove(nodes, b, i);
        Some((b, i))
    }

    #[inline]
    fn clear_bit(&mut self, b: usize) {
        self.nonempty[b >> 6] &= !(1 << (b & 63));
        if self.nonempty[b >> 6] == 0 {
            self.summary &= !(1 << (b >> 6));
        }
    }

    /// The highest non-empty bucket below `bucket`.
    pub(super) fn below(&self, bucket: usize) -> Option<usize> {
        let mut w = bucket >> 6;
        // Bits below `bucket` in its word, then whole words below.
        let mut bits = self.nonempty[w] & ((1u64 << (bucket & 63)) - 1);
        loop {
            if bits != 0 {
                return Some(w * 64 + 63 - bits.leading_zeros() as usize);
            }
            if w == 0 {
                return None;
            }
            w -= 1;
            bits = self.nonempty[w];
        }
    }

    /// The highest priority in `bucket` (non-empty), walking it when not known; needs a
    /// queue that keeps it.
    pub(super) fn most(&mut self, nodes: &impl Nodes, bucket: usize) -> f32 {
        let known = self.most[bucket];
        if !known.is_nan() {
            return known;
        }
        let most = self
            .members(nodes, bucket)
            .map(|i| nodes.prio(i))
            .fold(0f32, f32::max);
        self.most[bucket] = most;
        most
    }

    /// The members of `bucket`, first to last.
    pub(super) fn members<'a>(
        &self,
        nodes: &'a impl Nodes,
        bucket: usize,
    ) -> impl Iterator<Item = u32> + 'a {
        let head = self.heads[bucket];
        let mut at = head;
        std::iter::from_fn(move || {
            if at == NIL {
                return None;
            }
            let i = at;
            at = nodes.link(i, 0).next;
            if at == head {
                at = NIL;
            }
            Some(i)
        })
    }

    /// The members of each non-empty bucket, checked (for the audit).
    pub(super) fn lists(&self, nodes: &impl Nodes) -> Result<Vec<(usize, Vec<u32>)>, ListError> {
        let mut out = Vec::new();
        for b in 0..BUCKETS {
            let list = walk(nodes, 0, self.heads[b])?;
            let marked = self.nonempty[b >> 6] >> (b & 63) & 1 != 0;
            if marked == list.is_empty() {
                return Err(ListError::QueueMarked {
                    bucket: b,
                    marked,
                    len: list.len(),
                });
            }
            let most = list.iter().map(|&i| nodes.prio(i)).fold(0f32, f32::max);
            if let Some(&known) = self.most.get(b)
                && !list.is_empty()
                && !known.is_nan()
                && known != most
            {
                return Err(ListError::Highest {
                    bucket: b,
                    most,
                    known,
                });
            }
            if !list.is_empty() {
                out.push((b, list));
            }
        }
        Ok(out)
    }

    pub(super) fn heap_bytes(&self) -> usize {
        (self.heads.capacity() + self.most.capacity()) * 4
    }
}

/// Bits of a schedule key's digit: a member moves down at most once per digit (8).
const DIGIT: u32 = 4;
const RADIX: usize = 1 << DIGIT;

/// Buckets of a schedule: keys equal to the last taken, then per digit (the highest that
/// differs from the last key taken) one per value it may take above the last key's.
const SLOTS: usize = 1 + (32 / DIGIT as usize) * (RADIX - 1);

/// When kept evaluations fall due: members by odometer key (a reading in fixed point,
/// rounded down: see [`super::Odometer`]) in a radix heap (Ahuja et al. 1990) over the
/// keys' digits of 4 bits, each bucket a vector of member places; a member keeps its
/// index in its bucket's vector (in its link for the schedule: `prev` the index, `next`
/// 0), so it is taken out in O(1) (the bucket's last member fills its place).
///
/// Keys only grow, and every key pushed is at least the odometer's now, so a monotone
/// queue fits: a member sits in the bucket of the highest digit in which its key differs
/// from `last` (the newest key taken) and that digit's value, and is moved to a lower
/// bucket only when `last` catches up with its bucket; each bucket keeps a lower bound of
/// its keys (exact when it was filled; a removal may leave it low, which only makes the
/// bucket's members move down a frame early), so "anything due?" reads one word. (A binary
/// heap of the same entries walked 16 levels of scattered memory per pop, 1–2 µs each with
/// the caches cold, as they are when a server serves many viewers in turn.)
///
/// **Vectors, not lists.** A bucket was first a list threaded through the members: moving
/// a bucket down walked it member by member, each step a cache miss that waited for the
/// one before (the next member's place is in the member), and in a server serving 50
/// driving viewers that walk and the relinking around it took a third of the server's
/// CPU (`perf`: the schedules' list walk, `push_back` and `unlink`). Now a move reads the
/// bucket's places in order and touches each member once, misses that overlap; it costs
/// 4 bytes a scheduled member (two schedules: about 0.3 MB at 65,536 triangles). 50
/// driving viewers on one core (`scripts/capacity.sh 50`): 289–322 µs of server CPU per
/// frame with the lists (three runs), 276 with vectors. (Keeping each key beside its
/// place, so that a move reads no member, measured the same, 273, for 4 bytes more.) With a
/// bucket per differing bit (33), a member moved 2.6 times per push along the bench's
/// drive at 32,768 triangles; with digits of 4 bits (121 buckets), 1.4 times.
///
/// **Keys that grow keep their entry** ([`Schedule::reschedule`]): a member evaluated again
/// (due on the other odometer) whose key here is no earlier than before only has its key
/// raised; its entry stays in the bucket it was put in (the member records which), and is
/// put again by its key when that bucket is moved down or taken. Taking it out and putting
/// it back touched the member that filled its place, a cache miss per evaluation. With
/// that, evaluating members by place rather than looking them up by position, and
/// leaving a re-evaluated member in its queue bucket when its bucket did not change
/// ([`super::frontier::Frontier::keep`]), 50 driving viewers went from 276 to 218 µs of
/// server CPU per frame (`scripts/capacity.sh 50`, quiet machine), and the bench's
/// `serve_many_frame_us_mean` along `scripts/capacity-drive.txt` from 187 to 141–146.
pub(super) struct Schedule {
    /// The odometer: the member's key `k`, its link `1 + k`.
    k: usize,
    buckets: Vec<Vec<u32>>,
    least: [u32; SLOTS],
    /// Buckets not empty, a bit each.
    nonempty: u128,
    last: u32,
    len: usize,
    /// Scratch for [`Self::take_due`]: the members of the buckets it empties.
    taken: Vec<u32>,
}

/// How many members ahead [`Schedule::take_due`] asks for their records ([`Nodes::prefetch`]):
/// each member's record is a cache miss when a server serves many viewers in turn, and a
/// walk's members are known ahead, in its bucket's vector.
const PREFETCH: usize = 8;

/// Places an emptied bucket keeps room for when it is moved down (a larger one gives its
/// memory back: kept, every bucket's peak would stay held).
const KEEP_CAPACITY: usize = 64;

impl Schedule {
    pub(super) fn new(k: usize) -> Schedule {
        Schedule {
            k,
            buckets: vec![Vec::new(); SLOTS],
            least: [u32::MAX; SLOTS],
            nonempty: 0,
            last: 0,
            len: 0,
            taken: Vec::new(),
        }
    }

    pub(super) fn len(&self) -> usize {
        self.len
    }

    /// Empties the schedule (and forgets the keys taken: any may be pushed next).
    pub(super) fn clear(&mut self) {
        for b in &mut self.buckets {
            b.clear();
            if b.capacity() > KEEP_CAPACITY {
                b.shrink_to(KEEP_CAPACITY);
            }
        }
        self.least = [u32::MAX; SLOTS];
        self.nonempty = 0;
        self.last = 0;
        self.len = 0;
    }

    pub(super) fn heap_bytes(&self) -> usize {
        self.buckets.capacity() * std::mem::size_of::<Vec<u32>>()
            + self.buckets.iter().map(|b| b.capacity() * 4).sum::<usize>()
            + self.taken.capacity() * 4
    }

    #[inline]
    fn bucket(&self, key: u32) -> usize {
        let x = key ^ self.last;
        if x == 0 {
            return 0;
        }
        let j = (31 - x.leading_zeros()) / DIGIT;
        // Above the last key's digit there, so at least 1.
        let v = (key >> (j * DIGIT)) as usize & (RADIX - 1);
        j as usize * (RADIX - 1) + v
    }

    #[inline]
    fn put(&mut self, nodes: &mut impl Nodes, i: u32, key: u32) {
        let b = self.bucket(key);
        let list = &mut self.buckets[b];
        nodes.set_link(
            i,
            1 + self.k,
            Link {
                prev: list.len() as u32,
                next: 0,
            },
        );
        nodes.set_entry_bucket(i, self.k, b);
        if list.len() == list.capacity() {
            // Grown by a quarter, not doubled: the schedules' vectors were half slack
            // (issue 22's memory per viewer); the copies are sequential and rare.
            list.reserve_exact(list.len() / 4 + 16);
        }
        list.push(i);
        self.least[b] = self.least[b].min(key);
        self.nonempty |= 1 << b;
    }

    /// Schedules member `i` (not scheduled) at `key` (one below a key already taken counts
    /// as that one).
    #[inline]
    pub(super) fn push(&mut self, nodes: &mut impl Nodes, i: u32, key: u32) {
        let key = key.max(self.last);
        nodes.set_key(i, self.k, key);
        self.put(nodes, i, key);
        self.len += 1;
    }

    /// Schedules member `i` at `key` (`None`: never), scheduled or not. A member already
    /// scheduled no later than `key` keeps its entry, only its key grows (see the type's
    /// docs: it is put again by its key when its entry comes up); so does one whose earlier
    /// key falls in its entry's bucket (taking it out touched the member that filled its
    /// place: 3 % of a server's time with 50 driving viewers).
    #[inline]
    pub(super) fn reschedule(&mut self, nodes: &mut impl Nodes, i: u32, key: Option<u32>) {
        let scheduled = nodes.link(i, 1 + self.k).linked();
        match key {
            Some(key) if scheduled && key >= nodes.key(i, self.k) => {
                nodes.set_key(i, self.k, key);
            }
            Some(key)
                if scheduled
                    && key >= self.last
                    && self.bucket(key) == nodes.entry_bucket(i, self.k) =>
            {
                nodes.set_key(i, self.k, key);
                let b = nodes.entry_bucket(i, self.k);
                self.least[b] = self.least[b].min(key);
            }
            _ => {
                if scheduled {
                    self.remove(nodes, i);
                }
                if let Some(key) = key {
                    self.push(nodes, i, key);
                }
            }
        }
    }

    /// Takes member `i`, scheduled, out.
    #[inline]
    pub(super) fn remove(&mut self, nodes: &mut impl Nodes, i: u32) {
        let b = nodes.entry_bucket(i, self.k);
        let at = nodes.link(i, 1 + self.k).prev;
        debug_assert!(at != NIL, "only a scheduled member is taken out");
        nodes.set_link(i, 1 + self.k, Link::OUT);
        let list = &mut self.buckets[b];
        list.swap_remove(at as usize);
        if let Some(&moved) = list.get(at as usize) {
            nodes.set_link(moved, 1 + self.k, Link { prev: at, next: 0 });
        }
        if list.is_empty() {
            self.nonempty &= !(1 << b);
            self.least[b] = u32::MAX;
        }
        // A bucket that emptied out by removals gives its memory back, as one that is
        // taken is cut to `KEEP_CAPACITY`: a bound on a bucket of distant keys, which is
        // rarely taken (along the bench's drive it changed nothing measurable).
        if list.capacity() > KEEP_CAPACITY && list.len() * 4 < list.capacity() {
            list.shrink_to(list.len() * 2);
        }
        self.len -= 1;
    }

    /// Member `from`, scheduled, now lives at `to` (its link and key moved with it).
    pub(super) fn relocate(&mut self, nodes: &mut impl Nodes, from: u32, to: u32) {
        let b = nodes.entry_bucket(to, self.k);
        let at = nodes.link(to, 1 + self.k).prev as usize;
        debug_assert_eq!(self.buckets[b][at], from, "the moved member's place");
        self.buckets[b][at] = to;
    }

    /// Takes out every member due at odometer key `now` (its key at most `now`) into
    /// `out`, and makes `now` the last key taken.
    ///
    /// All at once, as a radix heap whose `last` jumps to `now`: the buckets at or below
    /// `now`'s (relative to the old `last`) are emptied, their members either due or put
    /// again relative to `now`; every bucket above stays right as it is, since `now`
    /// agrees with the old `last` on the digits that place them. Taken one at a time, as
    /// this was first, `last` went from one bucket's lower bound to the next, and a member
    /// due this frame was moved down digit by digit before it was taken: along the
    /// capacity drive the turn schedule moved a member 2.6 times per push, each move a
    /// cache miss on its record.
    pub(super) fn take_due(&mut self, nodes: &mut impl Nodes, now: u32, out: &mut Vec<u32>) {
        if now < self.last {
            return; // every key is at least `last`
        }
        let upto = self.bucket(now);
        let mask = self.nonempty & (u128::MAX >> (127 - upto));
        let mut bits = mask;
        let mut taken = std::mem::take(&mut self.taken);
        taken.clear();
        while bits != 0 {
            let b = bits.trailing_zeros() as usize;
            bits &= bits - 1;
            let list = &mut self.buckets[b];
            taken.extend_from_slice(list);
            list.clear();
            if list.capacity() > KEEP_CAPACITY {
                list.shrink_to(KEEP_CAPACITY);
            }
            self.least[b] = u32::MAX;
        }
        self.nonempty &= !mask;
        self.last = now;
        for (j, &i) in taken.iter().enumerate() {
            if let Some(&ahead) = taken.get(j + PREFETCH) {
                nodes.prefetch(ahead);
            }
            // A key may have grown since its entry was put ([`Self::reschedule`]).
            let key = nodes.key(i, self.k);
            if key <= now {
                nodes.set_link(i, 1 + self.k, Link::OUT);
                self.len -= 1;
                out.push(i);
            } else {
                self.put(nodes, i, key);
            }
        }
        if taken.capacity() > KEEP_CAPACITY * 16 {
            taken = Vec::new();
        }
        self.taken = taken;
    }

    /// Every member scheduled, checked: each in the bucket its key says, at or above the
    /// bucket's bound, its link naming its index (for the audit).
    pub(super) fn lists(&self, nodes: &impl Nodes) -> Result<Vec<u32>, ListError> {
        let mut out = Vec::new();
        for (b, list) in self.buckets.iter().enumerate() {
            if (self.nonempty >> b & 1 != 0) == list.is_empty() {
                return Err(ListError::ScheduleMarked { bucket: b });
            }
            for (at, &i) in list.iter().enumerate() {
                if i as usize >= nodes.len() {
                    return Err(ListError::SchedulePast {
                        bucket: b,
                        member: i,
                    });
                }
                let l = nodes.link(i, 1 + self.k);
                if l.prev != at as u32 || l.next != 0 || nodes.entry_bucket(i, self.k) != b {
                    return Err(ListError::ScheduleLink {
                        member: i,
                        at,
                        bucket: b,
                        prev: l.prev,
                        next: l.next,
                        entry: nodes.entry_bucket(i, self.k),
                    });
                }
                // A key may have grown since its entry was put: at or above the bucket.
                let key = nodes.key(i, self.k);
                if self.bucket(key) < b || key < self.least[b] {
                    return Err(ListError::ScheduleKey {
                        key,
                        bucket: b,
                        bound: self.least[b],
                        last: self.last,
                    });
                }
            }
            out.extend_from_slice(list);
        }
        if out.len() != self.len {
            return Err(ListError::ScheduleCount {
                listed: out.len(),
                counted: self.len,
            });
        }
        Ok(out)
    }
}

#[cfg(test)]
#[path = "buckets_tests.rs"]
mod tests;
