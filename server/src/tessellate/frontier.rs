//! A set of diamonds as a dense list plus an index, each member with a value beside it:
//! O(1) insert, remove and membership, and a sequential walk over the members and values. The frame-coherent tessellator keeps its two
//! frontiers (diamonds that may be split, diamonds that may be merged) in these, so what a
//! viewer holds grows with its cut, not with the map.
//!
//! The index is open addressing with linear probing over packed positions (`x | z << 16`;
//! 0 is the corner `(0, 0)`, never a diamond, so it marks an empty slot), kept at most half
//! full, with backward-shift deletion (no tombstones). Deterministic: no random hasher, so
//! the member order depends only on the operations.

/// Diamonds, by packed position, each with a `T`.
pub struct PosSet<T> {
    /// The members, in no particular order.
    list: Vec<u32>,
    /// Each member's value, beside it.
    data: Vec<T>,
    /// `(position, index in list)`; position 0 is empty.
    table: Vec<(u32, u32)>,
}

#[inline(always)]
fn hash(pos: u32) -> usize {
    (pos.wrapping_mul(0x9e37_79b1) ^ (pos >> 15)).wrapping_mul(0x85eb_ca6b) as usize
}

impl<T> Default for PosSet<T> {
    fn default() -> Self {
        PosSet {
            list: Vec::new(),
            data: Vec::new(),
            table: Vec::new(),
        }
    }
}

impl<T: Copy> PosSet<T> {
    /// The members, in no particular order.
    pub fn as_slice(&self) -> &[u32] {
        &self.list
    }

    /// The members' values, in the order of [`Self::as_slice`].
    pub fn values(&self) -> &[T] {
        &self.data
    }

    /// The same, to change.
    pub fn values_mut(&mut self) -> &mut [T] {
        &mut self.data
    }

    pub fn len(&self) -> usize {
        self.list.len()
    }

    pub fn clear(&mut self) {
        self.list.clear();
        self.data.clear();
        self.table.iter_mut().for_each(|e| *e = (0, 0));
    }

    pub fn heap_bytes(&self) -> usize {
        self.list.capacity() * 4
            + self.data.capacity() * std::mem::size_of::<T>()
            + self.table.capacity() * 8
    }

    #[inline(always)]
    fn mask(&self) -> usize {
        self.table.len() - 1
    }

    /// The table slot holding `pos`, or the empty slot where it would go.
    #[inline(always)]
    fn find(&self, pos: u32) -> usize {
        let mask = self.mask();
        let mut i = hash(pos) & mask;
        loop {
            let k = self.table[i].0;
            if k == pos || k == 0 {
                return i;
            }
            i = (i + 1) & mask;
        }
    }

    /// The value beside `pos`, if it is a member.
    #[inline]
    pub fn get(&self, pos: u32) -> Option<&T> {
        if self.table.is_empty() {
            return None;
        }
        let (k, at) = self.table[self.find(pos)];
        (k == pos).then(|| &self.data[at as usize])
    }

    /// The same, to change.
    pub fn get_mut(&mut self, pos: u32) -> Option<&mut T> {
        if self.table.is_empty() {
            return None;
        }
        let (k, at) = self.table[self.find(pos)];
        (k == pos).then(|| &mut self.data[at as usize])
    }

    pub fn contains(&self, pos: u32) -> bool {
        !self.table.is_empty() && self.table[self.find(pos)].0 == pos
    }

    /// Adds `pos` (not 0) with the value `make()`; false (and `make` not called) when it
    /// was there already.
    pub fn insert_with(&mut self, pos: u32, make: impl FnOnce() -> T) -> bool {
        debug_assert_ne!(pos, 0, "position 0 is a corner, not a diamond");
        if 2 * (self.list.len() + 1) > self.table.len() {
            self.grow();
        }
        let i = self.find(pos);
        if self.table[i].0 == pos {
            return false;
        }
        self.table[i] = (pos, self.list.len() as u32);
        self.list.push(pos);
        self.data.push(make());
        true
    }

    /// Removes `pos`; false when it was not there.
    pub fn remove(&mut self, pos: u32) -> bool {
        if self.table.is_empty() {
            return false;
        }
        let mut i = self.find(pos);
        if self.table[i].0 != pos {
            return false;
        }
        // The last member takes the removed one's place in the list.
        let at = self.table[i].1 as usize;
        let last = self
            .list
            .pop()
            .expect("a member was found, so the list is not empty");
        let value = self.data.pop().expect("values are beside members");
        if last != pos {
            self.list[at] = last;
            self.data[at] = value;
            let j = self.find(last);
            self.table[j].1 = at as u32;
        }
        // Backward-shift deletion: pull later members of the probe run into the hole.
        let mask = self.mask();
        let mut j = i;
        loop {
            j = (j + 1) & mask;
            let (k, v) = self.table[j];
            if k == 0 {
                break;
            }
            let home = hash(k) & mask;
            // Move k into the hole at i unless its home lies cyclically in (i, j].
            let stays = if i <= j {
                i < home && home <= j
            } else {
                i < home || home <= j
            };
            if !stays {
                self.table[i] = (k, v);
                i = j;
            }
        }
        self.table[i] = (0, 0);
        true
    }

    fn grow(&mut self) {
        let cap = (self.table.len() * 2).max(64);
        self.table = vec![(0, 0); cap];
        let mask = cap - 1;
        for (n, &pos) in self.list.iter().enumerate() {
            let mut i = hash(pos) & mask;
            while self.table[i].0 != 0 {
                i = (i + 1) & mask;
            }
            self.table[i] = (pos, n as u32);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Random inserts and removes against a sorted reference (a tiny LCG keeps it
    /// deterministic).
    #[test]
    fn matches_a_reference_set() {
        let mut set = PosSet::<u32>::default();
        let mut reference = std::collections::BTreeSet::new();
        let mut seed = 12345u64;
        for _ in 0..20_000 {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let pos = 1 + ((seed >> 33) % 700) as u32 * 97;
            if seed >> 63 == 0 {
                assert_eq!(set.insert_with(pos, || pos * 3), reference.insert(pos));
            } else {
                assert_eq!(set.remove(pos), reference.remove(&pos));
            }
            assert_eq!(set.len(), reference.len());
        }
        let mut got = set.as_slice().to_vec();
        got.sort_unstable();
        assert_eq!(got, reference.iter().copied().collect::<Vec<_>>());
        for (p, v) in set.as_slice().iter().zip(set.values()) {
            assert_eq!(*v, p * 3, "each value stays beside its member");
        }
        for p in 1..70_000 {
            assert_eq!(set.contains(p), reference.contains(&p), "{p}");
        }
        set.clear();
        assert!(set.len() == 0 && !set.contains(got.first().copied().unwrap_or(1)));
    }
}
