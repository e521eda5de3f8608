//! From-scratch tessellators lent to the frame-coherent ones: the only map-sized state the
//! serving path has (a bit per grid vertex for the split set, two more for the ranks the
//! output pass builds), held once for the server rather than once per viewer.
//!
//! A viewer's cut lives in its [`super::Coherent`] as a hash set sized by the cut; it
//! borrows a [`Tessellator`] from the [`Scratch`] only for what needs a bitset over the
//! map: a rebuild (split-only ROAM from scratch), a key frame (the codec walks a bitset)
//! and, for tests and benchmarks, the mesh. Those run on the server's blocking frame
//! makers, at most one fewer than the cores (`net/makers.rs`), so the pool holds at most that many; measured at
//! 32769², a viewer carried its own (145 MB) before.
//!
//! A lent tessellator is left as [`Tessellator::cut`] expects it: its `active_list`
//! names every bit set, so the next user clears only those.

use std::sync::Mutex;

use roam_protocol::sync::lock;

use super::{Tessellator, unpack};

/// A pool of from-scratch tessellators for one map size.
pub struct Scratch {
    side: u32,
    pool: Mutex<Vec<Tessellator>>,
}

impl Scratch {
    /// An empty pool for maps of this `side` (`2^N + 1`); tessellators are made when
    /// first needed.
    pub fn new(side: u32) -> Scratch {
        Scratch {
            side,
            pool: Mutex::new(Vec::new()),
        }
    }

    /// Runs `f` with a tessellator of the pool (a new one when all are lent), and puts it
    /// back.
    pub(crate) fn with<R>(&self, f: impl FnOnce(&mut Tessellator) -> R) -> R {
        let taken = lock(&self.pool).pop();
        let mut t = taken.unwrap_or_else(|| Tessellator::new(self.side));
        let r = f(&mut t);
        lock(&self.pool).push(t);
        r
    }
}

impl Tessellator {
    /// Makes `split` (packed positions, a cut: closed under parent) this tessellator's
    /// split set, as if its last cut had made it with `triangles` triangles, for the
    /// codec's bitset and the output pass.
    pub(crate) fn load_cut(&mut self, split: impl IntoIterator<Item = u32>, triangles: u32) {
        self.reset();
        for p in split {
            let (x, z) = unpack(p);
            self.set_active(x, z);
            self.active_list.push(p);
        }
        self.triangles = triangles;
    }

    /// Calls `f` with the split set as the codec's row-major bitset over the map (the
    /// tessellator's own bitset, lent without a copy).
    pub(crate) fn with_split_set<R>(&mut self, f: impl FnOnce(&roam_protocol::BitSet) -> R) -> R {
        let set = roam_protocol::BitSet::from_words(std::mem::take(&mut self.active));
        let r = f(&set);
        self.active = set.into_words();
        r
    }
}
