//! From-scratch tessellators lent to the frame-coherent ones: the only map-sized state the
//! serving path has (a bit per grid vertex for the split set, two more for the ranks the
//! output pass builds), held once for the server rather than once per viewer.
//!
//! A viewer's cut lives in its [`super::Coherent`] as a hash set sized by the cut; it
//! borrows a [`Tessellator`] from the [`Scratch`] only for what needs a bitset over the
//! map: a rebuild (split-only ROAM from scratch, and its frontiers' members found on the
//! bitset), a key frame (the codec walks a bitset) and, for tests and benchmarks, the
//! mesh. Those run on the server's blocking frame makers, at most one fewer than the cores
//! (`net/makers.rs`), and a joining viewer's first frame on the frame clock; measured at
//! 32769², a viewer carried its own (145 MB) before.
//!
//! **Bounded by the makers.** The pool is given the number of users that borrow at once
//! (the server's frame makers; 1 for a single-threaded test or bench) and never makes more
//! tessellators than that: a borrower beyond it waits for one to come back rather than
//! making another. The makers' permits keep the makers within it; the frame clock's first
//! frames borrow beside them and may wait for one to come back (`net/frames.rs`,
//! `INLINE_FIRST_BUDGET`). The bound is what keeps any other caller (a new path that
//! borrows off the makers, a test with many threads) from growing the pool one map-sized
//! tessellator per concurrent borrower, as a pool that made one whenever all were lent
//! did. A borrower that panics drops its tessellator (its state may be torn) and frees
//! its place for a new one. Borrowers do not nest (nothing lent calls back into the pool),
//! so a bound of 1 cannot deadlock.
//!
//! A lent tessellator is left as [`Tessellator::cut`] expects it: its `active_list`
//! names every bit set, so the next user clears only those.

use std::sync::{Condvar, Mutex, MutexGuard};

use roam_protocol::sync::{lock, wait};

use super::{Tessellator, unpack};

/// A pool of from-scratch tessellators for one map size, at most `most` of them.
pub struct Scratch {
    side: u32,
    /// The most tessellators made: the users that borrow at once.
    most: usize,
    pool: Mutex<Pool>,
    /// Signalled when a tessellator comes back (or a place frees up).
    returned: Condvar,
}

/// The tessellators not lent, how many exist (lent or not), and the borrowers waiting.
struct Pool {
    free: Vec<Tessellator>,
    made: usize,
    waiting: usize,
}

impl Scratch {
    /// An empty pool for maps of this `side` (`2^N + 1`) shared by `most` users at once
    /// (at least 1); tessellators are made when first needed.
    pub fn new(side: u32, most: usize) -> Scratch {
        Scratch {
            side,
            most: most.max(1),
            pool: Mutex::new(Pool {
                free: Vec::new(),
                made: 0,
                waiting: 0,
            }),
            returned: Condvar::new(),
        }
    }

    fn lock(&self) -> MutexGuard<'_, Pool> {
        lock(&self.pool)
    }

    /// Tessellators made (lent or in the pool): never more than the bound.
    pub fn made(&self) -> usize {
        self.lock().made
    }

    /// Borrowers waiting for a tessellator to come back.
    pub fn waiting(&self) -> usize {
        self.lock().waiting
    }

    /// Runs `f` with a tessellator of the pool (a new one when all are lent and fewer than
    /// the bound exist; else it waits for one), and puts it back.
    pub(crate) fn with<R>(&self, f: impl FnOnce(&mut Tessellator) -> R) -> R {
        let mut pool = self.lock();
        let taken = loop {
            if let Some(t) = pool.free.pop() {
                break Some(t);
            }
            if pool.made < self.most {
                pool.made += 1;
                break None;
            }
            pool.waiting += 1;
            pool = wait(&self.returned, pool);
            pool.waiting -= 1;
        };
        drop(pool);
        let mut lent = Lent {
            scratch: self,
            t: Some(taken.unwrap_or_else(|| Tessellator::new(self.side))),
        };
        f(lent.t.as_mut().expect("set above, taken only when dropped"))
    }
}

/// A lent tessellator, put back when its borrower is done (dropped if it panicked).
struct Lent<'a> {
    scratch: &'a Scratch,
    t: Option<Tessellator>,
}

impl Drop for Lent<'_> {
    fn drop(&mut self) {
        let mut pool = self.scratch.lock();
        match self.t.take() {
            Some(t) if !std::thread::panicking() => pool.free.push(t),
            _ => pool.made -= 1,
        }
        drop(pool);
        self.scratch.returned.notify_one();
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

#[cfg(test)]
mod tests {
    use std::sync::Barrier;
    use std::sync::atomic::{AtomicUsize, Ordering};

    use super::Scratch;

    /// Three borrowers hold the three tessellators of a pool bounded at three; four more
    /// come: they wait (none is served, none is made) until the three give theirs back,
    /// then all are served by the same three.
    #[test]
    fn borrowers_beyond_the_bound_wait_rather_than_make_more() {
        let (bound, extra) = (3, 4);
        let scratch = Scratch::new(65, bound);
        let (held, release) = (Barrier::new(bound + 1), Barrier::new(bound + 1));
        let served = AtomicUsize::new(0);
        let (mut made_held, mut served_early) = (0, 0);
        std::thread::scope(|s| {
            for _ in 0..bound {
                s.spawn(|| {
                    scratch.with(|_| {
                        held.wait();
                        release.wait();
                    })
                });
            }
            held.wait();
            made_held = scratch.made();
            for _ in 0..extra {
                s.spawn(|| scratch.with(|_| served.fetch_add(1, Ordering::SeqCst)));
            }
            // Until each has come: waiting, or (from a pool that made more) served.
            while scratch.waiting() + served.load(Ordering::SeqCst) < extra {
                std::thread::yield_now();
            }
            served_early = served.load(Ordering::SeqCst);
            release.wait();
        });
        assert_eq!(made_held, bound, "three lent at once");
        assert_eq!(served_early, 0, "served beyond the bound");
        assert_eq!(served.into_inner(), extra, "served once some came back");
        assert_eq!(scratch.made(), bound);
        assert_eq!(scratch.waiting(), 0);
    }

    /// A borrower that panics gives up its tessellator and its place: the pool still lends
    /// up to its bound.
    #[test]
    fn a_panicking_borrower_frees_its_place() {
        let scratch = Scratch::new(65, 2);
        let panicked = std::thread::scope(|s| {
            s.spawn(|| scratch.with(|_| panic!("a borrower's bug (this test's)")))
                .join()
                .is_err()
        });
        assert!(panicked);
        assert_eq!(scratch.made(), 0, "the torn tessellator is not kept");
        let together = Barrier::new(2);
        std::thread::scope(|s| {
            for _ in 0..2 {
                s.spawn(|| scratch.with(|_| together.wait()));
            }
        });
        assert_eq!(scratch.made(), 2);
    }
}
