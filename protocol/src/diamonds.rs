//! [`DiamondMap`]: a map from diamonds (row-major grid indices) to small values, sized by
//! what it holds rather than by the grid: the viewer's split set with each diamond's
//! height, a frame's change list, the changes composed since a base.
//!
//! Open addressing with linear probing and backward-shift deletion (no tombstones, so a
//! map that sees every diamond of a long drive come and go stays as fast as a fresh one),
//! a power-of-two table at most half full, keys hashed by a Fibonacci multiply. Iteration
//! follows the table, so it depends only on the sequence of operations: deterministic.
//!
//! Why not a bitset over the grid: at 32769² one bit per vertex is 128 MiB, which a viewer
//! scanned (copied, counted, walked) every frame for a cut of 32k diamonds; the issue-22
//! measurements are in `crate::follow`. Why not `std`'s `HashMap`: its random seed makes
//! iteration order differ run to run, and its per-entry overhead is larger (this is 8
//! bytes a slot for a `u16` value, 16 at the half load bound).

/// No key: grid indices are below `2^31` (`MAX_LEVELS` = 15: `(2^15 + 1)^2`).
const EMPTY: u32 = u32::MAX;

/// A map from grid indices to `V`, sized by its contents.
#[derive(Clone, Debug)]
pub struct DiamondMap<V: Copy + Default> {
    keys: Vec<u32>,
    values: Vec<V>,
    len: usize,
    /// `64 − log2(table size)`.
    shift: u32,
}

impl<V: Copy + Default> Default for DiamondMap<V> {
    fn default() -> Self {
        DiamondMap::new()
    }
}

impl<V: Copy + Default> DiamondMap<V> {
    /// An empty map (no allocation until the first insert).
    pub fn new() -> DiamondMap<V> {
        DiamondMap {
            keys: Vec::new(),
            values: Vec::new(),
            len: 0,
            shift: 64,
        }
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Empties the map, keeping its table.
    pub fn clear(&mut self) {
        if self.len > 0 {
            self.keys.fill(EMPTY);
            self.len = 0;
        }
    }

    #[inline]
    fn slot(&self, key: u32) -> usize {
        (u64::from(key).wrapping_mul(0x9e37_79b9_7f4a_7c15) >> self.shift) as usize
    }

    #[inline]
    fn mask(&self) -> usize {
        self.keys.len().wrapping_sub(1)
    }

    /// The table position of `key`, if present.
    #[inline]
    fn find(&self, key: u32) -> Option<usize> {
        if self.len == 0 {
            return None;
        }
        let mask = self.mask();
        let mut s = self.slot(key);
        loop {
            match self.keys[s] {
                k if k == key => return Some(s),
                EMPTY => return None,
                _ => s = (s + 1) & mask,
            }
        }
    }

    #[inline]
    pub fn contains(&self, key: u32) -> bool {
        self.find(key).is_some()
    }

    #[inline]
    pub fn get(&self, key: u32) -> Option<V> {
        self.find(key).map(|s| self.values[s])
    }

    /// Sets `key` to `value`; whether it was absent.
    pub fn insert(&mut self, key: u32, value: V) -> bool {
        debug_assert_ne!(key, EMPTY);
        if 2 * (self.len + 1) > self.keys.len() {
            self.grow();
        }
        let mask = self.mask();
        let mut s = self.slot(key);
        loop {
            match self.keys[s] {
                k if k == key => {
                    self.values[s] = value;
                    return false;
                }
                EMPTY => {
                    self.keys[s] = key;
                    self.values[s] = value;
                    self.len += 1;
                    return true;
                }
                _ => s = (s + 1) & mask,
            }
        }
    }

    /// Removes `key`; its value if it was present. Later keys of its probe run shift back
    /// into the hole, so no tombstone is left.
    pub fn remove(&mut self, key: u32) -> Option<V> {
        let mut hole = self.find(key)?;
        let value = self.values[hole];
        let mask = self.mask();
        let mut s = hole;
        loop {
            s = (s + 1) & mask;
            let k = self.keys[s];
            if k == EMPTY {
                break;
            }
            // `k` may fill the hole if its home is not cyclically within (hole, s].
            let home = self.slot(k);
            if (s.wrapping_sub(home) & mask) >= (s.wrapping_sub(hole) & mask) {
                self.keys[hole] = k;
                self.values[hole] = self.values[s];
                hole = s;
            }
        }
        self.keys[hole] = EMPTY;
        self.len -= 1;
        Some(value)
    }

    /// Inserts `key` with `value` if absent, removes it if present: a toggle.
    pub fn toggle(&mut self, key: u32, value: V) {
        if self.remove(key).is_none() {
            self.insert(key, value);
        }
    }

    /// Keys and values, in table order.
    pub fn iter(&self) -> impl Iterator<Item = (u32, V)> + '_ {
        self.keys
            .iter()
            .zip(&self.values)
            .filter(|(k, _)| **k != EMPTY)
            .map(|(&k, &v)| (k, v))
    }

    /// Doubles the table (16 slots at first).
    fn grow(&mut self) {
        let size = (self.keys.len() * 2).max(16);
        let keys = std::mem::replace(&mut self.keys, vec![EMPTY; size]);
        let values = std::mem::replace(&mut self.values, vec![V::default(); size]);
        self.shift = 64 - size.trailing_zeros();
        self.len = 0;
        for (k, v) in keys.into_iter().zip(values) {
            if k != EMPTY {
                self.insert(k, v);
            }
        }
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.keys.capacity() * 4 + self.values.capacity() * std::mem::size_of::<V>()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;

    /// Runs `ops` (key, insert or remove) on a map and on a `BTreeMap`; they must agree
    /// throughout.
    fn check(ops: &[(u32, bool)]) {
        let mut map = DiamondMap::<u16>::new();
        let mut reference = BTreeMap::new();
        for (n, &(k, insert)) in ops.iter().enumerate() {
            if insert {
                assert_eq!(
                    map.insert(k, n as u16),
                    reference.insert(k, n as u16).is_none()
                );
            } else {
                assert_eq!(map.remove(k), reference.remove(&k));
            }
            assert_eq!(map.len(), reference.len());
        }
        let mut got: Vec<(u32, u16)> = map.iter().collect();
        got.sort_unstable();
        let want: Vec<(u32, u16)> = reference.into_iter().collect();
        assert_eq!(got, want);
        for &(k, _) in ops {
            assert_eq!(map.get(k), want.iter().find(|e| e.0 == k).map(|e| e.1));
        }
    }

    #[test]
    fn agrees_with_a_btree_map() {
        check(&[]);
        check(&[(5, true), (5, true), (5, false), (5, false)]);
        // Keys landing in one probe run, removed from its middle.
        let run: Vec<(u32, bool)> = (0..12).map(|k| (k * 16, true)).collect();
        let mut ops = run.clone();
        ops.extend([(32, false), (64, false), (0, false), (32, true)]);
        check(&ops);
        // Pseudo-random churn through several growths.
        let mut x = 0x1234_5678_u64;
        let churn: Vec<(u32, bool)> = (0..20_000)
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                ((x % 3000) as u32, x >> 40 & 3 != 0)
            })
            .collect();
        check(&churn);
    }

    #[test]
    fn toggling_twice_leaves_nothing_and_clear_keeps_the_table() {
        let mut map = DiamondMap::<u16>::new();
        for k in 0..100 {
            map.toggle(k, 1);
        }
        assert_eq!(map.len(), 100);
        for k in 0..100 {
            map.toggle(k, 2);
        }
        assert!(map.is_empty());
        let bytes = map.bytes();
        map.insert(7, 3);
        map.clear();
        assert!(map.is_empty() && !map.contains(7));
        assert_eq!(map.bytes(), bytes);
    }
}
