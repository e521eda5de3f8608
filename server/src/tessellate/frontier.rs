//! Hash tables over packed diamond positions (`x | z << 16`), sized by what they hold: the
//! frame-coherent tessellator's split set ([`PosSet`]) and the index from a frontier
//! diamond to its record in a dense list ([`PosIndex`]), so what a viewer holds grows and
//! shrinks with its cut, not with the map.
//!
//! Both are open addressing with linear probing and backward-shift deletion (no
//! tombstones), over a table of any length (a slot is the hash's high bits scaled to it,
//! Lemire's multiply-shift), kept between 40 % and 80 % full: past 80 % the table grows,
//! below 40 % it shrinks, to 60 % full either way. So a member costs 5 to 10 bytes of
//! table, 6.7 at 60 %, where the first version (a list of positions beside a table of
//! `(position, index)` pairs of a power of two length, at most half full) cost 4 + 16 to
//! 32. At 80 % a miss probes 13 slots on average: 52 bytes of one table, one or two cache
//! lines. Deterministic: no random hasher, so the member order depends only on the
//! operations.
//!
//! [`PosSet`] keeps the positions themselves in its slots (0, the corner `(0, 0)`, never a
//! diamond, marks an empty one). [`PosIndex`] keeps a place in the caller's list (24
//! bits) with 4 bits of the position's hash and the slot's distance from its home beside
//! it: a probe compares those before it reads the caller's list, so a probe past other
//! members rarely leaves the table (bare places would read a scattered record per probe),
//! and a removal moves slots back without reading the list (see [`PosIndex`]).
//!
//! [`Chunks`] is the dense list beside a [`PosIndex`]: chunks of 1,024 records, so what
//! it reserves follows what it holds within a chunk and a half, and growing copies
//! nothing. (A `Vec` keeps what it reserved at its largest unless shrunk: grown by a
//! quarter at a time and shrunk below half full, the split frontier's 30,781 records at
//! the end of the bench's drive on `kossou` at 65,536 triangles sat in room for 43,301
//! (1.91 MB of 44-byte records); grown by an eighth and shrunk below three quarters, in
//! room for 39,809 (1.75 MB); in chunks, 31,744 (1.40 MB; 1.14 MB of 36-byte records).)

/// The mixer of MurmurHash3 (`fmix32`): every output bit depends on every input bit.
#[inline(always)]
fn hash(pos: u32) -> u32 {
    let mut h = pos;
    h ^= h >> 16;
    h = h.wrapping_mul(0x85eb_ca6b);
    h ^= h >> 13;
    h = h.wrapping_mul(0xc2b2_ae35);
    h ^ (h >> 16)
}

/// The home slot of hash `h` in a table of `len` slots.
#[inline(always)]
fn home(h: u32, len: usize) -> usize {
    ((u64::from(h) * len as u64) >> 32) as usize
}

/// Asks the processor to bring `r` into the cache (nothing for `None`): for look-ups of
/// scattered places known ahead, so that their cache misses overlap rather than wait one
/// for the other.
#[inline(always)]
fn prefetch<T>(r: Option<&T>) {
    #[cfg(target_arch = "x86_64")]
    if let Some(r) = r {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        // SAFETY: a prefetch reads nothing and cannot fault; the address is a live
        // reference's, and SSE is in every x86_64 processor.
        unsafe { _mm_prefetch::<_MM_HINT_T0>((r as *const T).cast()) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = r;
}

/// Asks for the home slot of `pos` in an open-addressed `table` ([`prefetch`]).
#[inline(always)]
fn prefetch_home(table: &[u32], pos: u32) {
    prefetch(table.get(home(hash(pos), table.len())));
}

/// Smallest table.
const MIN_SLOTS: usize = 64;

/// The table length for `members` after a resize: 60 % full.
fn slots_for(members: usize) -> usize {
    (members * 5 / 3).max(MIN_SLOTS)
}

/// Slots for a table about to hold `members`: three quarters full then, within
/// [`too_full`] (a table grown one member at a time ends between 60 and 80 % full).
fn reserved_slots(members: usize) -> usize {
    (members * 4 / 3 + 1).max(MIN_SLOTS)
}

/// Whether a table of `slots` is to grow to hold `members`: over 80 % full.
#[inline(always)]
fn too_full(members: usize, slots: usize) -> bool {
    5 * members > 4 * slots
}

/// Whether a table of `slots` left holding `members` is to shrink: under 40 % full (and
/// larger than the smallest). Asked on removals only: a table [`PosSet::reserve`] sized
/// for a cut about to be inserted is under 40 % until it is filled (asked on insertions
/// too, the first one shrank it again and the cut grew it a third at a time: 0.3 ms of a
/// viewer's first frame, `perf`, `data/kossou` at 32,768 triangles, 2026-12-07).
#[inline(always)]
fn too_empty(members: usize, slots: usize) -> bool {
    5 * members < 2 * slots && slots > MIN_SLOTS
}

/// Whether a reserve for `slots` gives back an empty table of `table` slots: one over
/// twice that size (a frontier cleared for a rebuild at a much lower budget would keep its
/// peak's table, since only removals shrink a table).
#[inline]
fn given_back(len: usize, table: usize, slots: usize) -> bool {
    len == 0 && table > 2 * slots
}

/// Records per chunk of a [`Chunks`].
const CHUNK: usize = 1024;

/// A dense list in chunks of [`CHUNK`] records: what it reserves follows its length
/// within a chunk and a half, and growing never copies it (a `Vec` doubles, so it reserves
/// a third more than it holds on average and up to twice, and keeps its peak).
pub(super) struct Chunks<T> {
    chunks: Vec<Vec<T>>,
    len: usize,
}

impl<T> Default for Chunks<T> {
    fn default() -> Self {
        Chunks {
            chunks: Vec::new(),
            len: 0,
        }
    }
}

impl<T: Copy> Chunks<T> {
    pub(super) fn len(&self) -> usize {
        self.len
    }

    /// Empties it (its chunks given back).
    pub(super) fn clear(&mut self) {
        self.chunks = Vec::new();
        self.len = 0;
    }

    pub(super) fn heap_bytes(&self) -> usize {
        self.chunks.capacity() * std::mem::size_of::<Vec<T>>()
            + self
                .chunks
                .iter()
                .map(|c| c.capacity() * std::mem::size_of::<T>())
                .sum::<usize>()
    }

    /// Appends `v`.
    pub(super) fn push(&mut self, v: T) {
        if self.len / CHUNK == self.chunks.len() {
            self.chunks.push(Vec::with_capacity(CHUNK));
        }
        self.chunks[self.len / CHUNK].push(v);
        self.len += 1;
    }

    /// Removes the record at `i`, the last one taking its place.
    pub(super) fn swap_remove(&mut self, i: usize) -> T {
        let last = self.chunks[(self.len - 1) / CHUNK]
            .pop()
            .expect("the last chunk holds the last record");
        self.len -= 1;
        let removed = if i == self.len {
            last
        } else {
            std::mem::replace(&mut self[i], last)
        };
        // No chunk past the last record's, but one while it is over half a chunk in (so a
        // length going back and forth across a chunk's end allocates nothing).
        let keep = if self.len == 0 {
            0
        } else {
            (self.len + CHUNK / 2).div_ceil(CHUNK)
        };
        if keep == 0 {
            self.chunks = Vec::new();
        } else if self.chunks.len() > keep {
            self.chunks.truncate(keep);
        }
        removed
    }

    pub(super) fn iter(&self) -> impl Iterator<Item = &T> + '_ {
        self.chunks.iter().flatten()
    }

    /// Asks for record `i` ahead (nothing if there is none: [`prefetch`]).
    #[inline(always)]
    pub(super) fn prefetch(&self, i: usize) {
        prefetch(self.chunks.get(i / CHUNK).and_then(|c| c.get(i % CHUNK)));
    }
}

impl<T> std::ops::Index<usize> for Chunks<T> {
    type Output = T;

    #[inline(always)]
    fn index(&self, i: usize) -> &T {
        &self.chunks[i / CHUNK][i % CHUNK]
    }
}

impl<T> std::ops::IndexMut<usize> for Chunks<T> {
    #[inline(always)]
    fn index_mut(&mut self, i: usize) -> &mut T {
        &mut self.chunks[i / CHUNK][i % CHUNK]
    }
}

/// Whether the element at `j` of a cyclic table may stay when slot `i` (before it in its
/// probe run) empties: its home lies cyclically in `(i, j]`.
#[inline(always)]
fn stays(i: usize, j: usize, home: usize) -> bool {
    if i <= j {
        i < home && home <= j
    } else {
        i < home || home <= j
    }
}

/// A set of diamonds by packed position (not 0).
#[derive(Default)]
pub(super) struct PosSet {
    /// Positions; 0 is an empty slot.
    table: Vec<u32>,
    len: usize,
}

impl PosSet {
    pub(super) fn len(&self) -> usize {
        self.len
    }

    /// The members, in table order (not sorted).
    pub(super) fn iter(&self) -> impl Iterator<Item = u32> + '_ {
        self.table.iter().copied().filter(|&p| p != 0)
    }

    pub(super) fn heap_bytes(&self) -> usize {
        self.table.capacity() * 4
    }

    /// The slot holding `pos`, or the empty slot where it would go.
    #[inline(always)]
    fn find(&self, pos: u32) -> usize {
        let n = self.table.len();
        let mut i = home(hash(pos), n);
        loop {
            let k = self.table[i];
            if k == pos || k == 0 {
                return i;
            }
            i += 1;
            if i == n {
                i = 0;
            }
        }
    }

    #[inline]
    pub(super) fn contains(&self, pos: u32) -> bool {
        !self.table.is_empty() && self.table[self.find(pos)] == pos
    }

    /// Asks for `pos`'s home slot ahead of a look-up ([`prefetch_home`]).
    #[inline(always)]
    pub(super) fn prefetch(&self, pos: u32) {
        prefetch_home(&self.table, pos);
    }

    /// Makes room for `members` without resizing on the way there (a table grows by a
    /// third at a time, so an empty one filled with a cut rehashes it four times over).
    pub(super) fn reserve(&mut self, members: usize) {
        let slots = reserved_slots(members);
        if slots > self.table.len() || given_back(self.len, self.table.len(), slots) {
            self.resize(slots);
        }
    }

    /// Adds `pos` (not 0); false when it was there already.
    pub(super) fn insert(&mut self, pos: u32) -> bool {
        debug_assert_ne!(pos, 0, "position 0 is a corner, not a diamond");
        if too_full(self.len + 1, self.table.len()) {
            self.resize(slots_for(self.len + 1));
        }
        let i = self.find(pos);
        if self.table[i] == pos {
            return false;
        }
        self.table[i] = pos;
        self.len += 1;
        true
    }

    /// Removes `pos`; false when it was not there.
    pub(super) fn remove(&mut self, pos: u32) -> bool {
        if !self.contains(pos) {
            return false;
        }
        let n = self.table.len();
        let mut i = self.find(pos);
        let mut j = i;
        loop {
            j = if j + 1 == n { 0 } else { j + 1 };
            let k = self.table[j];
            if k == 0 {
                break;
            }
            if !stays(i, j, home(hash(k), n)) {
                self.table[i] = k;
                i = j;
            }
        }
        self.table[i] = 0;
        self.len -= 1;
        if too_empty(self.len, n) {
            self.resize(slots_for(self.len));
        }
        true
    }

    fn resize(&mut self, slots: usize) {
        let old = std::mem::replace(&mut self.table, vec![0; slots]);
        for p in old.into_iter().filter(|&p| p != 0) {
            let i = self.find(p);
            self.table[i] = p;
        }
    }
}

/// An empty [`PosIndex`] slot.
const EMPTY: u32 = u32::MAX;
/// Bits of an index in a [`PosIndex`] slot (the rest hold its distance from its home slot
/// and 4 bits of the position's hash).
const INDEX_BITS: u32 = 24;
const INDEX_MASK: u32 = (1 << INDEX_BITS) - 1;
/// A slot's distance from its home slot: 0 to 14, or [`FAR`] for 15 or more.
const DIST_SHIFT: u32 = INDEX_BITS;
const FAR: u32 = 15;
/// The hash bits a slot keeps beside its index and distance.
const TAG_SHIFT: u32 = INDEX_BITS + 4;

/// The most members a [`PosIndex`] indexes (a frontier holds at most 4 diamonds per
/// split one, and a cut splits fewer diamonds than its budget, at most 2^20 triangles).
pub(super) const MAX_INDEXED: usize = INDEX_MASK as usize;

/// The hash bits a slot keeps beside its index (the low ones: its home comes from the
/// high ones).
#[inline(always)]
fn tag(h: u32) -> u32 {
    (h & 0xf) << TAG_SHIFT
}

/// The distance field of a slot `d` slots past its home.
#[inline(always)]
fn dist(d: usize) -> u32 {
    (d.min(FAR as usize) as u32) << DIST_SHIFT
}

/// `a - b` in a cyclic table of `n` slots (`a`, `b` < `n`): how far slot `a` lies past
/// slot `b`, or the slot `b` slots before `a`.
#[inline(always)]
fn cyclic_sub(a: usize, b: usize, n: usize) -> usize {
    if a >= b { a - b } else { a + n - b }
}

/// An index from packed positions to places in a list the caller keeps: the caller says
/// which position is at a place (`at`), and tells the index when a member moves.
///
/// A slot holds, beside the place, 4 bits of the position's hash and how far the slot lies
/// past the position's home (up to 14; [`FAR`]: further). A probe compares both before it
/// reads the caller's list, so it reads the list once for the member it finds and about
/// never for another; and a removal's backward shift knows the home of each slot it may
/// move without reading the list. With 8 bits of hash and no distance, the shift read the
/// record of every slot after the removed one in its run: scattered reads, 72 % of a
/// frontier removal's time with 50 driving viewers' cuts (a removal was 8 % of the
/// server's time).
#[derive(Default)]
pub(super) struct PosIndex {
    /// `tag | distance | index`; [`EMPTY`] is an empty slot.
    table: Vec<u32>,
    len: usize,
}

impl PosIndex {
    pub(super) fn len(&self) -> usize {
        self.len
    }

    pub(super) fn clear(&mut self) {
        self.table.iter_mut().for_each(|e| *e = EMPTY);
        self.len = 0;
    }

    pub(super) fn heap_bytes(&self) -> usize {
        self.table.capacity() * 4
    }

    /// The slot holding `pos` (`Ok`), or the empty slot where it would go (`Err`, with its
    /// distance from `pos`'s home).
    #[inline(always)]
    fn find(&self, pos: u32, at: impl Fn(u32) -> u32) -> Result<usize, (usize, usize)> {
        let n = self.table.len();
        let h = hash(pos);
        let t = tag(h);
        let home = home(h, n);
        let (mut i, mut d) = (home, 0);
        loop {
            let k = self.table[i];
            if k == EMPTY {
                return Err((i, d));
            }
            if k & !INDEX_MASK == t | dist(d) && at(k & INDEX_MASK) == pos {
                return Ok(i);
            }
            i += 1;
            if i == n {
                i = 0;
            }
            d += 1;
        }
    }

    /// Asks for `pos`'s home slot ahead of a look-up ([`prefetch_home`]).
    #[inline(always)]
    pub(super) fn prefetch(&self, pos: u32) {
        prefetch_home(&self.table, pos);
    }

    /// The place the first slot of `pos`'s run whose hash bits and distance match holds
    /// (most likely `pos`'s own), reading no record: what to prefetch of the caller's list
    /// once `pos`'s home slot is in the cache. `None` when none matches in the first
    /// [`FAR`] slots.
    #[inline(always)]
    pub(super) fn likely(&self, pos: u32) -> Option<u32> {
        let n = self.table.len();
        if n == 0 {
            return None;
        }
        let h = hash(pos);
        let (t, mut i) = (tag(h), home(h, n));
        for d in 0..FAR as usize {
            let k = self.table[i];
            if k == EMPTY {
                return None;
            }
            if k & !INDEX_MASK == t | dist(d) {
                return Some(k & INDEX_MASK);
            }
            i = if i + 1 == n { 0 } else { i + 1 };
        }
        None
    }

    /// The place of `pos` in the caller's list.
    #[inline]
    pub(super) fn get(&self, pos: u32, at: impl Fn(u32) -> u32) -> Option<u32> {
        if self.table.is_empty() {
            return None;
        }
        self.find(pos, at).ok().map(|i| self.table[i] & INDEX_MASK)
    }

    /// Makes room for `members` without resizing on the way there ([`PosSet::reserve`]).
    pub(super) fn reserve(&mut self, members: usize, at: impl Fn(u32) -> u32) {
        let slots = reserved_slots(members);
        if slots > self.table.len() || given_back(self.len, self.table.len(), slots) {
            self.resize(slots, &at);
        }
    }

    /// Records that `pos` (not a member) is at `index` of the caller's list.
    pub(super) fn insert(&mut self, pos: u32, index: u32, at: impl Fn(u32) -> u32) {
        assert!(
            (index as usize) < MAX_INDEXED,
            "a frontier is bounded by the largest budget"
        );
        if too_full(self.len + 1, self.table.len()) {
            self.resize(slots_for(self.len + 1), &at);
        }
        let (i, d) = match self.find(pos, &at) {
            Err(free) => free,
            Ok(_) => unreachable!("inserted positions are not members"),
        };
        self.table[i] = tag(hash(pos)) | dist(d) | index;
        self.len += 1;
    }

    /// Records that member `pos` moved to `index`.
    pub(super) fn moved(&mut self, pos: u32, index: u32, at: impl Fn(u32) -> u32) {
        let i = self
            .find(pos, at)
            .expect("a member that moved is indexed under its position");
        self.table[i] = (self.table[i] & !INDEX_MASK) | index;
    }

    /// Forgets member `pos` (while `at` still finds it at its place). The slots after it
    /// in its run move back where their homes allow; each one's home comes from its
    /// distance (the caller's list is read only for one [`FAR`] from home).
    pub(super) fn remove(&mut self, pos: u32, at: impl Fn(u32) -> u32) {
        let n = self.table.len();
        let mut i = self
            .find(pos, &at)
            .expect("a member removed is indexed under its position");
        let mut j = i;
        loop {
            j = if j + 1 == n { 0 } else { j + 1 };
            let k = self.table[j];
            if k == EMPTY {
                break;
            }
            let d = (k >> DIST_SHIFT) & FAR;
            let home = if d < FAR {
                cyclic_sub(j, d as usize, n)
            } else {
                home(hash(at(k & INDEX_MASK)), n)
            };
            if !stays(i, j, home) {
                self.table[i] = (k & !(FAR << DIST_SHIFT)) | dist(cyclic_sub(i, home, n));
                i = j;
            }
        }
        self.table[i] = EMPTY;
        self.len -= 1;
        if too_empty(self.len, n) {
            self.resize(slots_for(self.len), &at);
        }
    }

    fn resize(&mut self, slots: usize, at: impl Fn(u32) -> u32) {
        let old = std::mem::replace(&mut self.table, vec![EMPTY; slots]);
        for k in old.into_iter().filter(|&k| k != EMPTY) {
            let pos = at(k & INDEX_MASK);
            let (i, d) = match self.find(pos, &at) {
                Err(free) => free,
                Ok(_) => unreachable!("each member is indexed once"),
            };
            self.table[i] = tag(hash(pos)) | dist(d) | (k & INDEX_MASK);
        }
    }

    /// Every slot's distance field against a recount from the caller's list (for tests).
    #[cfg(test)]
    fn check(&self, at: impl Fn(u32) -> u32) {
        let n = self.table.len();
        for (i, &k) in self.table.iter().enumerate() {
            if k != EMPTY {
                let h = hash(at(k & INDEX_MASK));
                let want = tag(h) | dist(cyclic_sub(i, home(h, n), n));
                assert_eq!(k & !INDEX_MASK, want, "slot {i}");
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A tiny LCG keeps it deterministic.
    fn positions(seed: &mut u64) -> (u32, bool) {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (1 + ((*seed >> 33) % 700) as u32 * 97, *seed >> 63 == 0)
    }

    /// A table reserved for a cut keeps its slots while the cut goes in: the shrink test,
    /// asked on insertions too, once shrank it at the first and the rest grew it a third
    /// at a time. A cleared one reserved for far fewer gives its slots back.
    #[test]
    fn a_reserved_table_keeps_its_slots_while_it_fills() {
        let members: Vec<u32> = (1..=10_000).map(|p| p * 3).collect();
        let mut set = PosSet::default();
        set.reserve(members.len());
        let reserved = set.heap_bytes();
        for &p in &members {
            assert!(set.insert(p));
            assert_eq!(set.heap_bytes(), reserved, "after {p}");
        }
        let mut index = PosIndex::default();
        let at = |i: u32| members[i as usize];
        index.reserve(members.len(), at);
        let reserved = index.heap_bytes();
        for (i, &p) in members.iter().enumerate() {
            index.insert(p, i as u32, at);
            assert_eq!(index.heap_bytes(), reserved, "after {p}");
        }
        assert!(reserved >= members.len() * 4, "room for every member");
        // Cleared (a rebuild) and reserved for a tenth: the table is given back.
        index.clear();
        index.reserve(members.len() / 10, at);
        assert!(index.heap_bytes() < reserved / 4, "{}", index.heap_bytes());
    }

    /// Random inserts and removes against a sorted reference.
    #[test]
    fn set_matches_a_reference_set() {
        let mut set = PosSet::default();
        let mut reference = std::collections::BTreeSet::new();
        let mut seed = 12345u64;
        for _ in 0..20_000 {
            let (pos, insert) = positions(&mut seed);
            if insert {
                assert_eq!(set.insert(pos), reference.insert(pos));
            } else {
                assert_eq!(set.remove(pos), reference.remove(&pos));
            }
            assert_eq!(set.len(), reference.len());
            let slots = set.heap_bytes() / 4;
            assert!(
                slots <= MIN_SLOTS || 5 * set.len() >= 2 * slots,
                "40 % full"
            );
            assert!(5 * set.len() <= 4 * slots, "80 % full at most");
        }
        let mut got: Vec<u32> = set.iter().collect();
        got.sort_unstable();
        assert_eq!(got, reference.iter().copied().collect::<Vec<_>>());
        for p in 1..70_000 {
            assert_eq!(set.contains(p), reference.contains(&p), "{p}");
        }
        for p in got {
            assert!(set.remove(p));
        }
        assert!(
            set.len() == 0 && set.heap_bytes() <= MIN_SLOTS * 4,
            "shrunk"
        );
    }

    /// The same with an index over a swap-removed list, as the frontiers use it; then the
    /// tables shrink as the members go.
    #[test]
    fn index_matches_a_reference_map() {
        let mut index = PosIndex::default();
        let mut list: Chunks<u32> = Chunks::default();
        let mut reference = std::collections::BTreeSet::new();
        let mut seed = 777u64;
        for _ in 0..20_000 {
            let (pos, insert) = positions(&mut seed);
            let found = index.get(pos, |i| list[i as usize]);
            assert_eq!(found.is_some(), reference.contains(&pos));
            match (found, insert) {
                (None, true) => {
                    list.push(pos);
                    index.insert(pos, list.len() as u32 - 1, |i| list[i as usize]);
                    reference.insert(pos);
                }
                (Some(at), false) => {
                    index.remove(pos, |i| list[i as usize]);
                    let last = list.len() - 1;
                    if at as usize != last {
                        index.moved(list[last], at, |i| list[i as usize]);
                    }
                    list.swap_remove(at as usize);
                    reference.remove(&pos);
                }
                _ => {}
            }
            assert_eq!(index.len(), reference.len());
            index.check(|i| list[i as usize]);
            let chunks = list.heap_bytes() / (CHUNK * 4);
            assert!(chunks <= (list.len() + CHUNK / 2).div_ceil(CHUNK).max(1));
        }
        for (i, &p) in list.iter().enumerate() {
            assert_eq!(index.get(p, |i| list[i as usize]), Some(i as u32));
        }
        for p in 1..70_000 {
            let got = index.get(p, |i| list[i as usize]);
            assert_eq!(got.is_some(), reference.contains(&p), "{p}");
        }
        let peak = index.heap_bytes();
        while list.len() > 0 {
            let last = list.len() - 1;
            index.remove(list[last], |i| list[i as usize]);
            list.swap_remove(last);
        }
        assert!(index.heap_bytes() < peak && index.heap_bytes() <= MIN_SLOTS * 4);
        assert_eq!(list.heap_bytes(), 0, "every chunk given back");
    }

    /// One run of 20 members that share a home slot (distances 0 to 19: five [`FAR`]),
    /// removed from the middle out: every removal's shift keeps each slot's distance and
    /// finds every other member.
    #[test]
    fn index_keeps_distances_past_far() {
        let same_home: Vec<u32> = (1..)
            .filter(|&p| home(hash(p), MIN_SLOTS) == MIN_SLOTS - 3)
            .take(20)
            .collect();
        let mut index = PosIndex::default();
        let mut list: Chunks<u32> = Chunks::default();
        for &p in &same_home {
            list.push(p);
            index.insert(p, list.len() as u32 - 1, |i| list[i as usize]);
        }
        assert_eq!(
            index.heap_bytes(),
            MIN_SLOTS * 4,
            "one table, wrapping at its end"
        );
        let far = index
            .table
            .iter()
            .filter(|&&k| k != EMPTY && (k >> DIST_SHIFT) & FAR == FAR);
        assert_eq!(far.count(), 5);
        index.check(|i| list[i as usize]);
        for &gone in [10usize, 3, 17, 0, 19, 14, 1].iter() {
            index.remove(same_home[gone], |i| list[i as usize]);
            list[gone] = 0;
            index.check(|i| list[i as usize]);
            for (at, &p) in same_home.iter().enumerate() {
                let want = (list[at] != 0).then_some(at as u32);
                assert_eq!(index.get(p, |i| list[i as usize]), want, "{p}");
            }
        }
    }
}
