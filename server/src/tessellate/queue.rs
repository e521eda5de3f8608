//! The split queue: priority buckets with constant-time insert and pop.
//!
//! A priority (a positive `f32`, pixels) falls in bucket `bits >> 20`: its exponent and top
//! three mantissa bits, eight buckets per octave, monotone in the priority. The last bucket
//! is reserved for diamonds under the eye. Each bucket is a first-in first-out chain of
//! chunks from one pool, kept as a read and a write position, and a two-level bitmap finds
//! the highest non-empty bucket with two leading-zero counts. [`BucketQueue::push_if`]
//! sends an entry that is not wanted to a trash bucket, so a caller pushes a fixed number
//! of candidates with no branch on which are kept. Nothing is allocated during a frame
//! once the pool is reserved.

/// Number of buckets: every non-negative `f32` maps to one of the first `BUCKETS - 1`.
pub const BUCKETS: usize = 2048;
/// The bucket above every priority: diamonds under the eye.
pub const TOP: usize = BUCKETS - 1;

/// The bucket of a priority (non-negative, possibly infinite).
#[inline(always)]
pub fn bucket_of(prio: f32) -> usize {
    ((prio.to_bits() >> 20) as usize).min(TOP - 1)
}

/// Entries per chunk: a bucket is a chain of chunks, read and written in order.
const CHUNK: usize = 64;

/// One bucket: a first-in first-out chain of chunks, as two positions in the entry pool.
/// `write == 0` is an empty bucket (a written position is past an entry, so at least 1); a
/// `write` at a chunk boundary means the chunk it ends is full.
#[derive(Clone, Copy)]
struct Bucket {
    /// Position of the oldest entry.
    read: u32,
    /// Position one past the newest entry.
    write: u32,
}

const EMPTY: Bucket = Bucket { read: 0, write: 0 };

/// Index of the trash bucket, and its state: its writes go to slot 1 of chunk 0.
const TRASH: usize = BUCKETS;
const TRASH_BUCKET: Bucket = Bucket { read: 1, write: 1 };

/// First-in first-out lists of `u64` entries, one per bucket, in chunks taken from one
/// pool. Within a chunk, entries are read and written in order: the next pop neither
/// chases a pointer nor waits on the entry just computed. Chunks are handed out afresh
/// each frame; [`BucketQueue::reserve`] sizes the pool for a frame's worst case so that
/// nothing is allocated during a frame.
pub struct BucketQueue {
    /// The buckets, then the trash: a bucket that is never read, whose writes land in
    /// chunk 0 (reserved) and never advance.
    buckets: Box<[Bucket; BUCKETS + 1]>,
    /// Chunk `c` is `entries[c * CHUNK..][..CHUNK]`, followed by chunk `next[c]`.
    entries: Vec<u64>,
    next: Vec<u32>,
    /// Chunks handed out this frame.
    used: usize,
    nonempty: [u64; BUCKETS / 64],
    summary: u32,
}

impl Default for BucketQueue {
    fn default() -> Self {
        BucketQueue {
            buckets: Box::new(std::array::from_fn(|b| {
                if b == TRASH { TRASH_BUCKET } else { EMPTY }
            })),
            entries: vec![0; CHUNK],
            next: vec![0],
            used: 1,
            nonempty: [0; BUCKETS / 64],
            summary: 0,
        }
    }
}

impl BucketQueue {
    /// Makes room for `pushes` entries in a frame, whatever buckets they fall in.
    /// (Address space only: pages are touched as chunks are first used.)
    pub fn reserve(&mut self, pushes: usize) {
        let chunks = pushes.div_ceil(CHUNK) + BUCKETS + 1;
        self.next.reserve(chunks.saturating_sub(self.next.len()));
        self.entries
            .reserve((chunks * CHUNK).saturating_sub(self.entries.len()));
    }

    /// Empties the queue, keeping its memory.
    pub fn clear(&mut self) {
        while let Some(b) = self.top_bucket() {
            self.buckets[b] = EMPTY;
            self.clear_bit(b);
        }
        self.used = 1; // chunk 0 is the trash's
    }

    /// Appends `entry` to `bucket`.
    #[inline(always)]
    pub fn push(&mut self, bucket: usize, entry: u64) {
        let write = self.buckets[bucket].write as usize;
        if write.is_multiple_of(CHUNK) {
            self.push_new_chunk(bucket, entry);
            return;
        }
        self.entries[write] = entry;
        self.buckets[bucket].write = write as u32 + 1;
    }

    /// Appends `entry` to `bucket` when `keep`; otherwise writes it to the trash. Either
    /// way the same instructions run: no branch on `keep` to mispredict.
    #[inline(always)]
    pub fn push_if(&mut self, keep: bool, bucket: usize, entry: u64) {
        let b = if keep { bucket } else { TRASH };
        let write = self.buckets[b].write as usize;
        if write.is_multiple_of(CHUNK) {
            // Never the trash's: its write position stays at 1.
            self.push_new_chunk(b, entry);
            return;
        }
        self.entries[write] = entry;
        self.buckets[b].write = (write + usize::from(keep)) as u32;
    }

    /// `push` when the bucket's last chunk is full or it has none.
    #[cold]
    fn push_new_chunk(&mut self, bucket: usize, entry: u64) {
        let start = self.new_chunk() * CHUNK;
        let write = self.buckets[bucket].write as usize;
        if write == 0 {
            self.buckets[bucket].read = start as u32;
            self.nonempty[bucket >> 6] |= 1 << (bucket & 63);
            self.summary |= 1 << (bucket >> 6);
        } else {
            self.next[write / CHUNK - 1] = (start / CHUNK) as u32;
        }
        self.entries[start] = entry;
        self.buckets[bucket].write = start as u32 + 1;
    }

    fn new_chunk(&mut self) -> usize {
        if self.used == self.next.len() {
            // First use of this chunk (within the reserved capacity, unless a caller
            // under-reserved: then it grows rather than fails).
            self.next.push(0);
            self.entries.resize(self.entries.len() + CHUNK, 0);
        }
        self.used += 1;
        self.used - 1
    }

    /// The highest non-empty bucket.
    #[inline(always)]
    pub fn top_bucket(&self) -> Option<usize> {
        if self.summary == 0 {
            return None;
        }
        let w = 31 - self.summary.leading_zeros() as usize;
        Some(w * 64 + 63 - self.nonempty[w].leading_zeros() as usize)
    }

    /// Removes and returns the oldest entry of the highest non-empty bucket.
    #[inline(always)]
    pub fn pop(&mut self) -> Option<u64> {
        let b = self.top_bucket()?;
        let read = self.buckets[b].read as usize;
        let entry = self.entries[read];
        let read = read + 1;
        if read == self.buckets[b].write as usize {
            self.buckets[b] = EMPTY;
            self.clear_bit(b);
        } else if read.is_multiple_of(CHUNK) {
            self.buckets[b].read = self.next[read / CHUNK - 1] * CHUNK as u32;
        } else {
            self.buckets[b].read = read as u32;
        }
        Some(entry)
    }

    #[inline(always)]
    fn clear_bit(&mut self, b: usize) {
        self.nonempty[b >> 6] &= !(1 << (b & 63));
        if self.nonempty[b >> 6] == 0 {
            self.summary &= !(1 << (b >> 6));
        }
    }

    /// Non-empty buckets, highest first.
    pub fn buckets_desc(&self) -> impl Iterator<Item = usize> + '_ {
        (0..BUCKETS)
            .rev()
            .filter(|&b| self.nonempty[b >> 6] >> (b & 63) & 1 != 0)
    }

    /// The entries of one bucket still queued, oldest first.
    pub fn entries(&self, bucket: usize) -> impl Iterator<Item = u64> + '_ {
        let Bucket { read, write } = self.buckets[bucket];
        let (mut i, end) = (read as usize, write as usize);
        std::iter::from_fn(move || {
            if i == end {
                return None;
            }
            let e = self.entries[i];
            i += 1;
            if i.is_multiple_of(CHUNK) && i != end {
                i = self.next[i / CHUNK - 1] as usize * CHUNK;
            }
            Some(e)
        })
    }

    /// The highest priority (an entry's upper 32 bits, as `f32`) among the entries `live`
    /// accepts. The top bucket (under the eye) is ranked by position, not priority, so it
    /// is read whole and the search goes on to the first ordinary bucket holding a live
    /// entry.
    pub fn remaining_max(&self, live: impl Fn(u64) -> bool) -> f32 {
        let mut best = 0f32;
        for b in self.buckets_desc() {
            let most = self
                .entries(b)
                .filter(|&e| live(e))
                .map(|e| f32::from_bits((e >> 32) as u32))
                .reduce(f32::max);
            if let Some(v) = most {
                best = best.max(v);
                if b != TOP {
                    break;
                }
            }
        }
        best
    }

    pub fn heap_bytes(&self) -> usize {
        std::mem::size_of::<[Bucket; BUCKETS]>()
            + self.entries.capacity() * 8
            + self.next.capacity() * 4
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn buckets_are_monotone_in_priority() {
        let mut last = 0;
        for p in [
            0.0f32,
            1e-30,
            1e-3,
            0.5,
            0.51,
            0.6,
            1.0,
            1.1,
            2.0,
            1e6,
            3e38,
            f32::INFINITY,
        ] {
            let b = bucket_of(p);
            assert!(b >= last && b < TOP, "{p}");
            last = b;
        }
        assert!(
            bucket_of(1.0) < bucket_of(1.2),
            "several buckets per octave"
        );
    }

    #[test]
    fn pops_highest_bucket_first_and_fifo_within() {
        let mut q = BucketQueue::default();
        for (b, e) in [(5, 1), (700, 2), (5, 3), (TOP, 4), (700, 5), (0, 6)] {
            q.push(b, e);
        }
        let order: Vec<u64> = std::iter::from_fn(|| q.pop()).collect();
        assert_eq!(order, [4, 2, 5, 1, 3, 6]);
        assert_eq!(q.top_bucket(), None);
        q.push(9, 7);
        q.clear();
        assert_eq!(q.pop(), None);
        q.push(3, 8);
        assert_eq!(q.entries(3).collect::<Vec<_>>(), [8]);
        assert_eq!(q.buckets_desc().collect::<Vec<_>>(), [3]);
    }

    #[test]
    fn push_if_keeps_only_what_it_is_told() {
        let mut q = BucketQueue::default();
        q.reserve(500);
        for e in 0..200u64 {
            q.push_if(e % 3 == 0, 4 + (e % 2) as usize, e);
        }
        let order: Vec<u64> = std::iter::from_fn(|| q.pop()).collect();
        let mut want: Vec<u64> = (0..200).filter(|e| e % 3 == 0 && e % 2 == 1).collect();
        want.extend((0..200).filter(|e| e % 3 == 0 && e % 2 == 0));
        assert_eq!(order, want);
        assert_eq!(q.top_bucket(), None, "the trash is never popped");
    }

    #[test]
    fn long_buckets_span_chunks_in_order() {
        let mut q = BucketQueue::default();
        q.reserve(1000);
        let before = q.heap_bytes();
        for e in 0..300u64 {
            q.push(7 + (e as usize % 2) * 100, e);
        }
        let odd: Vec<u64> = q.entries(107).collect();
        assert_eq!(odd, (0..300).filter(|e| e % 2 == 1).collect::<Vec<_>>());
        let order: Vec<u64> = std::iter::from_fn(|| q.pop()).collect();
        let mut want: Vec<u64> = (0..300).filter(|e| e % 2 == 1).collect();
        want.extend((0..300).filter(|e| e % 2 == 0));
        assert_eq!(order, want);
        assert_eq!(q.heap_bytes(), before, "reserved: nothing grew");
        q.clear();
        assert_eq!(q.pop(), None);
    }
}
