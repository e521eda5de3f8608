//! The split queue: priority buckets with constant-time insert and pop.
//!
//! A priority (a positive `f32`, pixels) falls in bucket `bits >> 20`: its exponent and top
//! three mantissa bits, eight buckets per octave, monotone in the priority. The last bucket
//! is reserved for diamonds under the eye. Each bucket is a first-in first-out chain of
//! chunks from one pool, and a two-level bitmap finds the highest non-empty bucket with two
//! leading-zero counts. Nothing is allocated during a frame once the pool is reserved.

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
const NIL: u32 = u32::MAX;

/// One bucket: a first-in first-out chain of chunks.
#[derive(Clone, Copy)]
struct Bucket {
    /// Chunk and position of the oldest entry.
    head: u32,
    read: u32,
    /// Chunk and position one past the newest entry.
    tail: u32,
    write: u32,
}

const EMPTY: Bucket = Bucket {
    head: NIL,
    read: 0,
    tail: NIL,
    write: 0,
};

/// First-in first-out lists of `u64` entries, one per bucket, in chunks taken from one
/// pool. Within a chunk, entries are read and written in order: the next pop neither
/// chases a pointer nor waits on the entry just computed. Chunks are handed out afresh
/// each frame; [`BucketQueue::reserve`] sizes the pool for a frame's worst case so that
/// nothing is allocated during a frame.
pub struct BucketQueue {
    buckets: Box<[Bucket; BUCKETS]>,
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
            buckets: Box::new([EMPTY; BUCKETS]),
            entries: Vec::new(),
            next: Vec::new(),
            used: 0,
            nonempty: [0; BUCKETS / 64],
            summary: 0,
        }
    }
}

impl BucketQueue {
    /// Makes room for `pushes` entries in a frame, whatever buckets they fall in.
    /// (Address space only: pages are touched as chunks are first used.)
    pub fn reserve(&mut self, pushes: usize) {
        let chunks = pushes.div_ceil(CHUNK) + BUCKETS;
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
        self.used = 0;
    }

    /// Appends `entry` to `bucket`.
    #[inline(always)]
    pub fn push(&mut self, bucket: usize, entry: u64) {
        // Fields are read and written one by one (no whole-struct copies), so a load is
        // always served by the store of the same field just before it: a wide load over
        // narrower stores would stall store forwarding on every push after a pop.
        let (tail, write) = (self.buckets[bucket].tail, self.buckets[bucket].write);
        if tail == NIL || write as usize == CHUNK {
            self.push_new_chunk(bucket, entry);
            return;
        }
        self.entries[tail as usize * CHUNK + write as usize] = entry;
        self.buckets[bucket].write = write + 1;
    }

    /// `push` when the bucket's last chunk is full or it has none.
    #[cold]
    fn push_new_chunk(&mut self, bucket: usize, entry: u64) {
        let c = self.new_chunk();
        let bk = self.buckets[bucket];
        if bk.tail == NIL {
            self.buckets[bucket].head = c;
            self.buckets[bucket].read = 0;
            self.nonempty[bucket >> 6] |= 1 << (bucket & 63);
            self.summary |= 1 << (bucket >> 6);
        } else {
            self.next[bk.tail as usize] = c;
        }
        self.buckets[bucket].tail = c;
        self.entries[c as usize * CHUNK] = entry;
        self.buckets[bucket].write = 1;
    }

    fn new_chunk(&mut self) -> u32 {
        if self.used == self.next.len() {
            // First use of this chunk (within the reserved capacity, unless a caller
            // under-reserved: then it grows rather than fails).
            self.next.push(NIL);
            self.entries.resize(self.entries.len() + CHUNK, 0);
        }
        let c = self.used;
        self.used += 1;
        self.next[c] = NIL;
        c as u32
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
        let (head, read) = (self.buckets[b].head, self.buckets[b].read);
        let entry = self.entries[head as usize * CHUNK + read as usize];
        let read = read + 1;
        if head == self.buckets[b].tail && read == self.buckets[b].write {
            self.buckets[b] = EMPTY;
            self.clear_bit(b);
        } else if read as usize == CHUNK {
            self.buckets[b].head = self.next[head as usize];
            self.buckets[b].read = 0;
        } else {
            self.buckets[b].read = read;
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
        let bk = self.buckets[bucket];
        let (mut c, mut i) = (bk.head, bk.read as usize);
        std::iter::from_fn(move || {
            if c == NIL || (c == bk.tail && i == bk.write as usize) {
                return None;
            }
            let e = self.entries[c as usize * CHUNK + i];
            i += 1;
            if i == CHUNK && c != bk.tail {
                c = self.next[c as usize];
                i = 0;
            }
            Some(e)
        })
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
