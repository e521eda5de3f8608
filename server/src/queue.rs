//! The split queue: priority buckets with constant-time insert and pop.
//!
//! A priority (a positive `f32`, pixels) falls in bucket `bits >> 20`: its exponent and top
//! three mantissa bits, eight buckets per octave, monotone in the priority. The last bucket
//! is reserved for diamonds under the eye. Each bucket is a first-in first-out array, and a two-level bitmap finds the highest non-empty bucket with two
//! leading-zero counts. Nothing is allocated once the pool has grown to a frame's size.

/// Number of buckets: every non-negative `f32` maps to one of the first `BUCKETS - 1`.
pub const BUCKETS: usize = 2048;
/// The bucket above every priority: diamonds under the eye.
pub const TOP: usize = BUCKETS - 1;

/// The bucket of a priority (non-negative, possibly infinite).
#[inline(always)]
pub fn bucket_of(prio: f32) -> usize {
    ((prio.to_bits() >> 20) as usize).min(TOP - 1)
}

/// First-in first-out lists of `u64` entries, one per bucket.
pub struct BucketQueue {
    /// Each bucket's entries; `read[b]` of them have been popped.
    lists: Vec<Vec<u64>>,
    read: Vec<u32>,
    nonempty: [u64; BUCKETS / 64],
    summary: u32,
}

impl Default for BucketQueue {
    fn default() -> Self {
        BucketQueue {
            lists: (0..BUCKETS).map(|_| Vec::new()).collect(),
            read: vec![0; BUCKETS],
            nonempty: [0; BUCKETS / 64],
            summary: 0,
        }
    }
}

impl BucketQueue {
    /// Empties the queue, keeping its memory. Buckets emptied by `pop` were cleared then.
    pub fn clear(&mut self) {
        while let Some(b) = self.top_bucket() {
            self.lists[b].clear();
            self.read[b] = 0;
            self.clear_bit(b);
        }
    }

    /// Appends `entry` to `bucket`. Within a bucket the oldest entry pops first, read from
    /// a contiguous array: the next pop neither chases a pointer nor waits on the entry
    /// just computed, so successive splits overlap in the CPU.
    #[inline(always)]
    pub fn push(&mut self, bucket: usize, entry: u64) {
        self.lists[bucket].push(entry);
        self.nonempty[bucket >> 6] |= 1 << (bucket & 63);
        self.summary |= 1 << (bucket >> 6);
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
        let list = &mut self.lists[b];
        let r = self.read[b] as usize;
        let entry = list[r];
        if r + 1 == list.len() {
            list.clear();
            self.read[b] = 0;
            self.clear_bit(b);
        } else {
            self.read[b] = r as u32 + 1;
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
        self.lists[bucket][self.read[bucket] as usize..]
            .iter()
            .copied()
    }

    pub fn heap_bytes(&self) -> usize {
        self.lists
            .iter()
            .map(|l| l.capacity() * 8 + 24)
            .sum::<usize>()
            + self.read.capacity() * 4
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
}
